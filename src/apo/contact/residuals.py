"""Residuals ``f_i(X_EG)`` of contact elements and their Jacobians (paper 4.3.1)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from apo.contact._arrays import _plane_basis
from apo.contact.elements import ContactElement, ContactKind
from apo.contact.model_data import _model_data, _ModelData
from apo.geometry import Polyhedron
from apo.spatial import check_pose as _check_pose
from apo.typing import FloatArray, IntArray

_N_RESIDUALS = {
    ContactKind.VF: 1,
    ContactKind.FV: 1,
    ContactKind.EE: 1,
    ContactKind.VE: 2,
    ContactKind.EV: 2,
    ContactKind.VV: 3,
}


def residual_counts(elements: Sequence[ContactElement]) -> IntArray:
    """Return the number of residual rows of each element (VF, FV, EE: 1; VE, EV: 2; VV: 3)."""
    return np.array([_N_RESIDUALS[el.kind] for el in elements], dtype=np.int64)


def _perp_basis(u: FloatArray) -> FloatArray:
    """Deterministic orthonormal basis (2, 3) of the plane perpendicular to unit ``u``."""
    return _plane_basis(u / np.linalg.norm(u))


def _element_rows(
    g: _ModelData, e: _ModelData, R: FloatArray, t: FloatArray, el: ContactElement
) -> tuple[list[float], list[FloatArray]]:
    """Residual rows of one element and their Jacobian rows (see :func:`element_residuals`)."""
    rows_r: list[float] = []
    rows_J: list[FloatArray] = []
    ga, eb = el.grasped[1], el.environment[1]
    k = el.kind
    if k is ContactKind.VF:
        p = R @ g.V[ga] + t
        n = e.poly.face_normals[eb]
        rows_r.append(float(n @ p - e.poly.face_offsets[eb]))
        rows_J.append(np.concatenate([np.cross(p, n), n]))
    elif k is ContactKind.FV:
        q = e.V[eb]
        w = R @ g.poly.face_normals[ga]
        p0 = R @ (g.poly.face_offsets[ga] * g.poly.face_normals[ga]) + t
        rows_r.append(float(w @ (q - p0)))
        rows_J.append(np.concatenate([np.cross(w, q), -w]))
    elif k is ContactKind.EE:
        a = R @ g.E0[ga] + t
        u = R @ g.edge_dir[ga]
        b = e.E0[eb]
        ed = e.edge_dir[eb]
        cr = np.cross(u, ed)
        nc = float(np.linalg.norm(cr))
        m = cr / nc
        ref = el.normals[0] if len(el.normals) else a - b
        if float(m @ ref) < 0:
            m = -m
        diff = a - b
        c = (diff - (m @ diff) * m) / nc
        sign = 1.0 if float(np.cross(u, ed) @ m) > 0 else -1.0
        jw = np.cross(a, m) + sign * (ed * float(u @ c) - c * float(u @ ed))
        rows_r.append(float(m @ diff))
        rows_J.append(np.concatenate([jw, m]))
    elif k is ContactKind.VE:
        p = R @ g.V[ga] + t
        b = e.E0[eb]
        for kj in _perp_basis(e.edge_dir[eb]):
            rows_r.append(float(kj @ (p - b)))
            rows_J.append(np.concatenate([np.cross(p, kj), kj]))
    elif k is ContactKind.EV:
        q = e.V[eb]
        a = R @ g.E0[ga] + t
        for kj0 in _perp_basis(g.edge_dir[ga]):
            kj = R @ kj0
            rows_r.append(float(kj @ (q - a)))
            rows_J.append(np.concatenate([np.cross(kj, q), -kj]))
    else:
        p = R @ g.V[ga] + t
        q = e.V[eb]
        for j in range(3):
            unit = np.zeros(3)
            unit[j] = 1.0
            rows_r.append(float(p[j] - q[j]))
            rows_J.append(np.concatenate([np.cross(p, unit), unit]))
    return rows_r, rows_J


def element_residuals(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG: npt.ArrayLike,
    elements: Sequence[ContactElement],
) -> tuple[FloatArray, FloatArray]:
    """Residuals ``f_i(X_EG)`` of contact elements and their Jacobians (paper 4.3.1).

    Parameters
    ----------
    grasped, environment : Polyhedron
        The models (frames G and E, metres).
    X_EG : array_like, shape (4, 4)
        Pose of G in E, metres.
    elements : sequence of ContactElement
        Elements whose feature ids refer to these models (e.g. from :func:`find_contacts`).

    Returns
    -------
    r : ndarray, shape (K,)
        Residuals, metres, concatenated in element order; element i contributes
        ``residual_counts(elements)[i]`` rows. All zero iff every contact holds exactly.
    J : ndarray, shape (K, 6)
        ``dr / dxi`` for a twist ``xi = [omega; v]`` (rotation first, environment frame)
        applied on the left: ``X_EG_new = exp(xi) @ X_EG`` (``apo.spatial.pose_from_twist``).

    Notes
    -----
    With ``p`` a vertex of G in E, ``q`` a vertex of E (all in E):

    - VF: ``n_f . p - d_f`` (E's face plane, positive outside E); row ``[p x n, n]``.
    - FV: ``w . (q - p_0)`` with ``w`` G's face normal and ``p_0`` a point of G's face
      plane, in E (positive outside G); row ``[w x q, -w]``.
    - EE: ``m . (a - b)``, ``a``, ``b`` points of G's and E's edge lines, ``m`` the unit
      common normal of the lines, signed from E to G (the element's normal); row
      ``[a x m + e (u . c) - c (u . e), m]`` with ``u``, ``e`` the edge directions and
      ``c = (I - m m^T)(a - b) / |u x e|``.
    - VE: the two components ``k_j . (p - b)`` of p's offset from E's edge line, ``k_1, k_2``
      a fixed orthonormal basis perpendicular to the edge; rows ``[p x k_j, k_j]``.
    - EV: ``k_j . (q - a)``, ``k_j`` perpendicular to G's edge (moving with G); rows
      ``[k_j x q, -k_j]``.
    - VV: ``p - q`` (3 rows); rows ``[-[p]_x, I]``.
    """
    X = _check_pose(X_EG)
    R, t = X[:3, :3], X[:3, 3]
    g, e = _model_data(grasped), _model_data(environment)
    rows_r: list[float] = []
    rows_J: list[FloatArray] = []
    for el in elements:
        r, J = _element_rows(g, e, R, t, el)
        rows_r += r
        rows_J += J
    if not rows_r:
        return np.zeros(0), np.zeros((0, 6))
    return np.asarray(rows_r, dtype=np.float64), np.asarray(rows_J, dtype=np.float64)
