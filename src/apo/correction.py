"""Pose correction from contact constraints (paper 4.3.1).

An observed pose ``X_EG`` of the grasped object G in the environment frame E is noisy, so the
contact elements found near it do not hold exactly. :func:`correct_pose` moves the pose the
least it can so that they do: it solves ``f_i(q) = 0`` for the residuals ``f_i`` of the
elements (VF, FV, EE, VE, EV, VV; ``apo.contact.element_residuals`` gives the same rows) by
repeated linearisation and an SVD least-squares step (paper 4.3.1 steps (1)-(5)).

:class:`ContactConstraints` compiles one element set into arrays once, so that the residuals
and Jacobians of many poses are evaluated together (``(n, K)`` and ``(n, K, 6)``, no Python
loop over frames or elements); :func:`correct_poses` groups the frames of a sequence by
their element set and corrects each group in one batch. ``docs/correction.md`` describes the
solver.

Everything is in the environment frame E, in metres and radians; twists are
``[omega; v]`` applied on the left, ``X_new = pose_from_twist(xi) @ X`` (``docs/conventions.md``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from apo.constants import tol
from apo.contact import ContactElement, ContactKind
from apo.geometry import Polyhedron
from apo.spatial import check_poses, perpendicular_basis
from apo.typing import BoolArray, FloatArray, IntArray

__all__ = [
    "DEFAULT_MAX_ITER",
    "DEFAULT_MAX_ROTATION",
    "DEFAULT_RCOND",
    "DEFAULT_TOL",
    "DISPLACEMENT_FACTOR",
    "RESIDUAL_FACTOR",
    "BatchCorrection",
    "ContactConstraints",
    "CorrectionResult",
    "correct_pose",
    "correct_poses",
]

DEFAULT_MAX_ITER = 20
"""Gauss-Newton iterations at most."""

DEFAULT_TOL = tol.correction
"""Convergence: every element distance at most this (metres); Gauss-Newton converges
quadratically, so this costs at most one step more than 1e-9."""

DEFAULT_RCOND = tol.correction_rcond
"""Rank cut of the SVD step: singular values below ``rcond * s_max`` of the scaled Jacobian
are treated as zero (the scaled Jacobian is dimensionless, O(1) entries)."""

DEFAULT_MAX_ROTATION = math.radians(5.0)
"""A correction that turns the object by more than this (rad) is flagged as implausible."""

DISPLACEMENT_FACTOR = 4.0
"""A correction that moves some vertex of G by more than this many contact thresholds is
flagged as implausible."""

RESIDUAL_FACTOR = 10.0
"""Without a threshold: a correction that moves some vertex of G by more than this many times
the initial residual is flagged (turning G back by a small angle moves its far vertices a few
times more than the contact points)."""

_MAX_HALVINGS = 8
_STALL = tol.correction_stall


# --------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CorrectionResult:
    """Result of correcting one pose (:func:`correct_pose`).

    Attributes
    ----------
    X_EG : ndarray, shape (4, 4)
        Corrected pose of G in E, metres.
    residual_before, residual_after : float
        ``max_i |f_i|`` at the observed and the corrected pose, metres; ``|f_i|`` is the
        distance of element i (the norm of its residual rows: 1 for VF, FV, EE, 2 for VE, EV,
        3 for VV).
    iterations : int
        Gauss-Newton steps taken (0 when the observed pose already met the tolerance).
    converged : bool
        ``residual_after <= tol``.
    rotation_change : float
        Angle (rad) of the rotation applied, ``angle(R_new R_obs^T)``.
    translation_change : float
        Distance (metres) the centroid of G's vertices moved.
    displacement : float
        Largest distance (metres) any vertex of G moved.
    flagged : bool
        True when the correction failed: not converged, or it turned G by more than
        ``max_rotation`` or moved a vertex further than ``max_displacement``.
    """

    X_EG: FloatArray
    residual_before: float
    residual_after: float
    iterations: int
    converged: bool
    rotation_change: float
    translation_change: float
    displacement: float
    flagged: bool


@dataclass(frozen=True)
class BatchCorrection:
    """Result of correcting many poses (:meth:`ContactConstraints.correct`, :func:`correct_poses`).

    Attributes
    ----------
    X_EG : ndarray, shape (n, 4, 4)
        Corrected poses of G in E, metres.
    residual_before, residual_after : ndarray, shape (n,)
        ``max_i |f_i|`` per frame at the observed and the corrected poses, metres.
    iterations : ndarray of int, shape (n,)
        Gauss-Newton steps taken per frame.
    converged : ndarray of bool, shape (n,)
        ``residual_after <= tol``.
    rotation_change : ndarray, shape (n,)
        Rotation applied per frame, rad.
    translation_change : ndarray, shape (n,)
        Movement of the centroid of G's vertices per frame, metres.
    displacement : ndarray, shape (n,)
        Largest vertex movement per frame, metres.
    flagged : ndarray of bool, shape (n,)
        Failed frames: not converged or moved implausibly far (see :class:`CorrectionResult`).
    """

    X_EG: FloatArray
    residual_before: FloatArray
    residual_after: FloatArray
    iterations: IntArray
    converged: BoolArray
    rotation_change: FloatArray
    translation_change: FloatArray
    displacement: FloatArray
    flagged: BoolArray

    def __len__(self) -> int:
        return int(self.X_EG.shape[0])

    def __getitem__(self, i: int) -> CorrectionResult:
        """Return frame ``i`` as a :class:`CorrectionResult`."""
        return CorrectionResult(
            X_EG=self.X_EG[i].copy(),
            residual_before=float(self.residual_before[i]),
            residual_after=float(self.residual_after[i]),
            iterations=int(self.iterations[i]),
            converged=bool(self.converged[i]),
            rotation_change=float(self.rotation_change[i]),
            translation_change=float(self.translation_change[i]),
            displacement=float(self.displacement[i]),
            flagged=bool(self.flagged[i]),
        )


# --------------------------------------------------------------------------------------------
# Small batched helpers
# --------------------------------------------------------------------------------------------


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Cross product of broadcast (..., 3) arrays (cheaper than ``np.cross`` for small ones)."""
    out: FloatArray = np.empty(np.broadcast_shapes(a.shape, b.shape))
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def _poses_from_twists(xi: FloatArray) -> FloatArray:
    """Batched ``apo.spatial.pose_from_twist``: twists (n, 6) ``[omega; v]`` -> poses (n, 4, 4)."""
    n = xi.shape[0]
    A, B, C, W, W2 = _twist_terms(xi[:, :3], rotation_only=False)
    eye = np.eye(3)
    out = np.zeros((n, 4, 4))
    out[:, 3, 3] = 1.0
    out[:, :3, :3] = eye + A[:, None, None] * W + B[:, None, None] * W2
    V = eye + B[:, None, None] * W + C[:, None, None] * W2
    out[:, :3, 3] = np.einsum("nij,nj->ni", V, xi[:, 3:])
    return out


def _twist_terms(
    w: FloatArray, *, rotation_only: bool
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Return the series ``A, B, C`` of rotation vectors ``w`` (n, 3), ``W = [w]x``, ``W @ W``.

    ``C`` (the translation's series) is left empty when ``rotation_only``.
    """
    th = np.sqrt(np.einsum("ni,ni->n", w, w))
    small = th < tol.twist_series_angle
    ths = np.where(small, 1.0, th)
    A = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    B = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    C = _EMPTY if rotation_only else np.where(small, 1.0 / 6.0 - th**2 / 120.0, (1.0 - A) / ths**2)
    W = np.zeros((w.shape[0], 3, 3))
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    W[:, 1, 0], W[:, 2, 0], W[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    return A, B, C, W, W @ W


_EMPTY = np.zeros(0)


def _damped_svd_step(J: FloatArray, r: FloatArray, lam: FloatArray, rcond: float) -> FloatArray:
    """Levenberg-Marquardt step ``-(J^T J + lam I)^-1 J^T r`` by SVD, per frame.

    ``J`` (n, K, 6), ``r`` (n, K), ``lam`` (n,). Singular values below ``rcond * s_max``
    are dropped (treated as exact zeros); the others are damped as ``s / (s^2 + lam)``.
    """
    n = J.shape[0]
    if J.shape[1] == 0:
        return np.zeros((n, 6))
    with np.errstate(all="ignore"):
        U, sv, Vt = np.linalg.svd(J, full_matrices=False)
        keep = sv > rcond * sv[:, :1]
        gain = np.where(keep, sv / (sv * sv + lam[:, None]), 0.0)
        coef = np.einsum("nki,nk->ni", U, r) * gain
        y = -np.einsum("ni,nij->nj", coef, Vt)
    out: FloatArray = np.where(np.isfinite(y), y, 0.0)
    return out


def _step_poses(omega: FloatArray, v_c: FloatArray, c: FloatArray) -> FloatArray:
    """Left displacements (n, 4, 4): rotate by ``omega`` about ``c``, then move ``c`` by ``v_c``.

    The result is ``pose_from_twist(xi)`` for the twist ``xi`` of that screw motion; built
    directly so that the centroid moves by exactly ``v_c`` (metres; ``omega`` in rad).
    """
    # the rotation block of _poses_from_twists([omega; 0]), the same numbers (the rotation
    # vector read from a 6-column row, as there)
    w = np.concatenate([omega, np.zeros_like(omega)], axis=1)[:, :3]
    A, B, _C, W, W2 = _twist_terms(w, rotation_only=True)
    out = np.zeros((len(omega), 4, 4))
    out[:, 3, 3] = 1.0
    R = out[:, :3, :3]
    R[...] = np.eye(3) + A[:, None, None] * W + B[:, None, None] * W2
    out[:, :3, 3] = c + v_c - np.einsum("nij,nj->ni", R, c)
    return out


#: Take the trial arrays as they are when every frame's whole step is accepted (the usual
#: case), instead of copying them row by row: the same numbers (a switch for the tests).
_WHOLE_STEPS_AT_ONCE = True


def _check_poses(X_EG_seq: npt.ArrayLike) -> FloatArray:
    """Poses (n, 4, 4) or one (4, 4) as (n, 4, 4), checked by :func:`apo.spatial.check_poses`."""
    X = np.array(X_EG_seq, dtype=np.float64)
    return check_poses(X[None] if X.ndim == 2 else X)


def _rotation_angles(R: FloatArray) -> FloatArray:
    """Rotation angles (rad) of stacked rotation matrices (n, 3, 3)."""
    c = 0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0)
    s = 0.5 * np.linalg.norm(
        np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1),
        axis=1,
    )
    out: FloatArray = np.arctan2(s, c)
    return out


# --------------------------------------------------------------------------------------------
# Compiled constraints
# --------------------------------------------------------------------------------------------


class _Rows:
    """Residual rows of a set of elements, gathered by form (see :class:`ContactConstraints`).

    Point rows ``k . (R g + t) - d`` (``pg``, ``pk``, ``pd``), direction rows
    ``(R u) . (q - t) - c`` (``du``, ``dq``, ``dc``), edge rows (``ea``, ``eu``: a point and
    direction of G's edge; ``eb``, ``ee``: of E's; ``eref``: the sign reference), and the
    element index of each row (``p_el``, ``d_el``, ``e_el``). Each starts empty. (A plain
    class, not a dataclass: a dataclass's methods are compiled at every import.)
    """

    def __init__(self) -> None:
        self.pg: list[FloatArray] = []
        self.pk: list[FloatArray] = []
        self.pd: list[float] = []
        self.p_el: list[int] = []
        self.du: list[FloatArray] = []
        self.dq: list[FloatArray] = []
        self.dc: list[float] = []
        self.d_el: list[int] = []
        self.ea: list[FloatArray] = []
        self.eu: list[FloatArray] = []
        self.eb: list[FloatArray] = []
        self.ee: list[FloatArray] = []
        self.eref: list[FloatArray] = []
        self.e_el: list[int] = []


def _feature(poly: Polyhedron, feat: tuple[str, int], want: str, i: int) -> int:
    """Index of feature ``feat`` of ``poly``, checked to be a valid ``want`` (v, e or f)."""
    kind, idx = feat
    n = {"v": len(poly.vertices), "e": len(poly.edges), "f": len(poly.faces)}[want]
    if kind != want or not 0 <= idx < n:
        raise ValueError(f"element {i}: feature {feat!r} is not a valid {want!r} of {poly.name!r}")
    return int(idx)


def _add_point_rows(rows: _Rows, G: Polyhedron, E: Polyhedron, el: ContactElement, i: int) -> None:
    """Add the point rows of a VF (1 row), VE (2) or VV (3) element ``i``."""
    g = G.vertices[_feature(G, el.grasped, "v", i)]
    if el.kind is ContactKind.VF:
        f = _feature(E, el.environment, "f", i)
        dirs, offsets = [E.face_normals[f]], [float(E.face_offsets[f])]
    elif el.kind is ContactKind.VE:
        e = _feature(E, el.environment, "e", i)
        b0 = E.vertices[E.edges[e, 0]]
        dirs = list(perpendicular_basis(E.edge_directions[e]))
        offsets = [float(kj @ b0) for kj in dirs]
    else:  # VV
        q = E.vertices[_feature(E, el.environment, "v", i)]
        dirs = list(np.eye(3))
        offsets = [float(q[j]) for j in range(3)]
    for kj, d in zip(dirs, offsets, strict=True):
        rows.pg.append(g)
        rows.pk.append(kj)
        rows.pd.append(d)
        rows.p_el.append(i)


def _add_direction_rows(
    rows: _Rows, G: Polyhedron, E: Polyhedron, el: ContactElement, i: int
) -> None:
    """Add the direction rows of an FV (1 row) or EV (2) element ``i``."""
    if el.kind is ContactKind.FV:
        f = _feature(G, el.grasped, "f", i)
        dirs, offsets = [G.face_normals[f]], [float(G.face_offsets[f])]
    else:  # EV
        e = _feature(G, el.grasped, "e", i)
        a0 = G.vertices[G.edges[e, 0]]
        dirs = list(perpendicular_basis(G.edge_directions[e]))
        offsets = [float(kj @ a0) for kj in dirs]
    q = E.vertices[_feature(E, el.environment, "v", i)]
    for u, c in zip(dirs, offsets, strict=True):
        rows.du.append(u)
        rows.dq.append(q)
        rows.dc.append(c)
        rows.d_el.append(i)


def _add_edge_rows(rows: _Rows, G: Polyhedron, E: Polyhedron, el: ContactElement, i: int) -> None:
    """Add the edge row of an EE element ``i``.

    The edges' directions live in different frames (G's and E's), so whether they are
    parallel depends on the pose: an EE element found with the edges a degree apart may have
    exactly parallel model directions (a peg turned by noise about an axis-aligned slot). The
    rows guard the common normal at evaluation time, pose by pose.
    """
    eg = _feature(G, el.grasped, "e", i)
    ev = _feature(E, el.environment, "e", i)
    rows.ea.append(G.vertices[G.edges[eg, 0]])
    rows.eu.append(G.edge_directions[eg])
    rows.eb.append(E.vertices[E.edges[ev, 0]])
    rows.ee.append(E.edge_directions[ev])
    ref = el.normals[0] if len(el.normals) else np.zeros(3)
    rows.eref.append(np.asarray(ref, dtype=np.float64))
    rows.e_el.append(i)


class ContactConstraints:
    """The residuals ``f_i`` of one set of contact elements, compiled for many poses.

    Rows of the same form are gathered into arrays once, so :meth:`residuals` evaluates every
    row at every pose with a handful of numpy operations (no Python loop over frames or
    elements). Rows and signs are those of :func:`apo.contact.element_residuals`:

    - *point rows* (VF; VE and VV component rows): ``k . (R g + t) - d`` for a point ``g``
      of G (model frame) and a fixed direction ``k`` and offset ``d`` in E;
    - *direction rows* (FV; EV component rows): ``(R u) . (q - t) - c`` for a direction ``u``
      of G, a point ``q`` of E and ``c = u . g0`` with ``g0`` on G's face or edge;
    - *edge rows* (EE): ``m . (a - b)``, ``m`` the unit common normal of the two edge lines,
      signed like the element's separating normal.

    Parameters
    ----------
    grasped : Polyhedron
        Grasped object G (model frame G, metres).
    environment : Polyhedron
        Environment object E (model frame E, metres).
    elements : sequence of ContactElement
        Elements whose feature ids refer to these models (e.g. from
        :func:`apo.contact.find_contacts`).

    Attributes
    ----------
    n_rows : int
        Number of residual rows K.
    element_of_row : ndarray of int, shape (K,)
        Index into ``elements`` of each row (rows are ordered by kind, not by element).

    Raises
    ------
    ValueError
        An element's feature id is out of range for its model.

    Examples
    --------
    >>> import numpy as np
    >>> from apo.contact import find_contacts
    >>> from apo.shapes import box
    >>> table = box([1.0, 1.0, 0.1], center=[0.0, 0.0, -0.05])
    >>> cube = box([0.1, 0.1, 0.1], center=[0.0, 0.0, 0.05])
    >>> cc = ContactConstraints(cube, table, find_contacts(cube, table, np.eye(4)).elements)
    >>> X = np.eye(4)
    >>> X[2, 3] = 0.002  # 2 mm above the table
    >>> res = cc.correct(X[None])
    >>> bool(res.converged[0]), round(float(res.X_EG[0, 2, 3]), 12)
    (True, 0.0)
    """

    def __init__(
        self, grasped: Polyhedron, environment: Polyhedron, elements: Sequence[ContactElement]
    ) -> None:
        self.grasped = grasped
        self.environment = environment
        self.elements = tuple(elements)
        G, E = grasped, environment
        rows = _Rows()
        for i, el in enumerate(self.elements):
            if el.kind in (ContactKind.VF, ContactKind.VE, ContactKind.VV):
                _add_point_rows(rows, G, E, el, i)
            elif el.kind in (ContactKind.FV, ContactKind.EV):
                _add_direction_rows(rows, G, E, el, i)
            else:
                _add_edge_rows(rows, G, E, el, i)

        def arr(r: list[FloatArray]) -> FloatArray:
            return np.asarray(r, dtype=np.float64).reshape(-1, 3)

        self._pg, self._pk = arr(rows.pg), arr(rows.pk)
        self._pd = np.asarray(rows.pd, dtype=np.float64)
        self._du, self._dq = arr(rows.du), arr(rows.dq)
        self._dc = np.asarray(rows.dc, dtype=np.float64)
        self._ea, self._eu, self._eb = arr(rows.ea), arr(rows.eu), arr(rows.eb)
        self._ee, self._eref = arr(rows.ee), arr(rows.eref)
        self.element_of_row: IntArray = np.asarray(
            rows.p_el + rows.d_el + rows.e_el, dtype=np.int64
        )
        self.n_rows = len(self.element_of_row)
        # Per-element distance = norm of its rows: a (K, n_el) 0/1 grouping.
        n_el = len(self.elements)
        self._group = np.zeros((self.n_rows, max(n_el, 1)))
        self._group[np.arange(self.n_rows), self.element_of_row] = 1.0
        # Scaling of the step: rotation about the centroid of G's vertices, in units of
        # the RMS vertex radius (so the minimum-norm step is the one that moves G least).
        V = np.asarray(G.vertices, dtype=np.float64)
        self._centroid_G = V.mean(axis=0)
        self._length = float(np.sqrt(((V - self._centroid_G) ** 2).sum(axis=1).mean())) or 1.0
        self._vertices_G = V

    # ----------------------------------------------------------------------------------------
    def residuals(self, X_EG_seq: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Residual rows and their Jacobians at each pose.

        Parameters
        ----------
        X_EG_seq : array_like, shape (n, 4, 4)
            Poses of G in E, metres.

        Returns
        -------
        r : ndarray, shape (n, K)
            Residual rows, metres (order: point rows, direction rows, edge rows; see
            ``element_of_row``).
        J : ndarray, shape (n, K, 6)
            ``dr / dxi`` for a twist ``xi = [omega; v]`` (environment frame) applied on the
            left, ``X_new = pose_from_twist(xi) @ X``.
        """
        X = np.asarray(X_EG_seq, dtype=np.float64)
        return self._residuals(X[:, :3, :3], X[:, :3, 3])

    def _residuals(self, R: FloatArray, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        n = R.shape[0]
        rs: list[FloatArray] = []
        Js: list[FloatArray] = []
        if len(self._pg):
            p = np.swapaxes(R @ self._pg.T, 1, 2) + t[:, None, :]  # (n, k, 3)
            k = self._pk[None]
            rs.append((p * k).sum(axis=2) - self._pd)
            Js.append(np.concatenate([_cross(p, k), np.broadcast_to(k, p.shape)], axis=2))
        if len(self._du):
            w = np.swapaxes(R @ self._du.T, 1, 2)
            q = self._dq[None]
            rs.append((w * (q - t[:, None, :])).sum(axis=2) - self._dc)
            Js.append(np.concatenate([_cross(w, np.broadcast_to(q, w.shape)), -w], axis=2))
        if len(self._ea):
            a = np.swapaxes(R @ self._ea.T, 1, 2) + t[:, None, :]
            u = np.swapaxes(R @ self._eu.T, 1, 2)
            e = np.broadcast_to(self._ee[None], u.shape)
            cr = _cross(u, e)
            nc = np.sqrt(np.einsum("nki,nki->nk", cr, cr))
            nc = np.maximum(nc, tol.zero_norm)
            m = cr / nc[..., None]
            sign = np.where(np.einsum("nki,ki->nk", m, self._eref) < 0.0, -1.0, 1.0)
            m = m * sign[..., None]
            diff = a - self._eb[None]
            md = np.einsum("nki,nki->nk", m, diff)
            c = (diff - md[..., None] * m) / nc[..., None]
            uc = np.einsum("nki,nki->nk", u, c)
            ue = np.einsum("nki,nki->nk", u, e)
            jw = _cross(a, m) + sign[..., None] * (e * uc[..., None] - c * ue[..., None])
            rs.append(md)
            Js.append(np.concatenate([jw, m], axis=2))
        if not rs:
            return np.zeros((n, 0)), np.zeros((n, 0, 6))
        return np.concatenate(rs, axis=1), np.concatenate(Js, axis=1)

    def distances(self, r: FloatArray) -> FloatArray:
        """Per-element distances (n, n_elements), metres, from residual rows (n, K)."""
        out: FloatArray = np.sqrt((r * r) @ self._group)
        return out

    def _max_distance(self, r: FloatArray) -> FloatArray:
        if r.shape[1] == 0:
            return np.zeros(r.shape[0])
        out: FloatArray = self.distances(r).max(axis=1)
        return out

    # ----------------------------------------------------------------------------------------
    def correct(
        self,
        X_EG_seq: npt.ArrayLike,
        *,
        max_iter: int = DEFAULT_MAX_ITER,
        tol: float = DEFAULT_TOL,
        rcond: float = DEFAULT_RCOND,
        threshold: float | None = None,
        max_rotation: float = DEFAULT_MAX_ROTATION,
        max_displacement: float | None = None,
    ) -> BatchCorrection:
        """Correct every pose so that these contact elements hold exactly.

        Parameters
        ----------
        X_EG_seq : array_like, shape (n, 4, 4) or (4, 4)
            Observed poses of G in E, metres.
        max_iter : int
            Gauss-Newton steps at most.
        tol : float
            Convergence tolerance on ``max_i |f_i|``, metres.
        rcond : float
            Rank cut of the SVD step, relative to the largest singular value of the scaled
            Jacobian.
        threshold : float, optional
            Contact-finding threshold the elements were found with, metres; sets the default
            ``max_displacement`` to ``DISPLACEMENT_FACTOR * threshold``.
        max_rotation : float
            Flag frames whose correction turns G by more than this, rad.
        max_displacement : float, optional
            Flag frames whose correction moves a vertex of G by more than this, metres.
            Default ``DISPLACEMENT_FACTOR * threshold``, or without a threshold
            ``RESIDUAL_FACTOR * residual_before`` per frame.

        Returns
        -------
        BatchCorrection

        Raises
        ------
        ValueError
            Poses of the wrong shape, non-finite, or not rigid; bad ``max_iter``/``tol``.

        Notes
        -----
        See ``docs/correction.md``. Per iteration, for the frames not yet converged: the
        Jacobian is rescaled to the twist ``y = [L omega; v_c]`` (rotation about G's vertex
        centroid c, in units of G's RMS radius L), the minimum-norm least-squares step
        ``y = -J_s^+ r`` is taken with the pseudo-inverse cut at ``rcond``, and the step is
        halved (up to 8 times) while it does not lower ``sum r^2``. A frame whose step cannot
        lower the cost stops (stalled: an inconsistent element set).
        """
        if max_iter < 0:
            raise ValueError(f"max_iter must be >= 0, got {max_iter}")
        if not (math.isfinite(tol) and tol > 0):
            raise ValueError(f"tol must be a positive length in metres, got {tol}")
        X0 = _check_poses(X_EG_seq)
        X = X0.copy()
        n = X.shape[0]
        r, J = self._residuals(X[:, :3, :3], X[:, :3, 3])
        before = self._max_distance(r)
        after = before.copy()
        iters = np.zeros(n, dtype=np.int64)
        active = after > tol
        L = self._length
        for _ in range(max_iter):
            idx = np.flatnonzero(active)
            if len(idx) == 0:
                break
            Xi, ri, Ji = X[idx], r[idx], J[idx]
            c = np.einsum("nij,j->ni", Xi[:, :3, :3], self._centroid_G) + Xi[:, :3, 3]
            Jw, Jv = Ji[..., :3], Ji[..., 3:]
            # J_w omega + J_v (v_c + c x omega) with omega = theta / L.
            Js = np.concatenate([(Jw + _cross(Jv, c[:, None, :])) / L, Jv], axis=2)
            cost = np.einsum("nk,nk->n", ri, ri)
            y = _damped_svd_step(Js, ri, cost / L**2, rcond)
            omega = y[:, :3] / L
            alpha = np.ones(len(idx))
            accepted = np.zeros(len(idx), dtype=bool)
            # the gathered copies take the accepted rows (a row left to halve is only read)
            Xn, rn, Jn = Xi, ri, Ji
            todo = np.arange(len(idx))
            for _h in range(_MAX_HALVINGS + 1):
                a = alpha[todo, None]
                Xt = _step_poses(a * omega[todo], a * y[todo, 3:], c[todo]) @ Xi[todo]
                rt, Jt = self._residuals(Xt[:, :3, :3], Xt[:, :3, 3])
                ok = np.einsum("nk,nk->n", rt, rt) < _STALL * cost[todo]
                if _WHOLE_STEPS_AT_ONCE and _h == 0 and ok.all():  # the usual case
                    Xn, rn, Jn = Xt, rt, Jt
                    accepted[:] = True
                    break
                good = todo[ok]
                Xn[good], rn[good], Jn[good] = Xt[ok], rt[ok], Jt[ok]
                accepted[good] = True
                todo = todo[~ok]
                if len(todo) == 0:
                    break
                alpha[todo] *= 0.5
            X[idx], r[idx], J[idx] = Xn, rn, Jn
            iters[idx[accepted]] += 1
            after[idx] = self._max_distance(rn)
            active[idx] = accepted & (after[idx] > tol)
        converged = after <= tol
        return self._summarise(X0, X, before, after, iters, converged, threshold,
                               max_rotation, max_displacement)  # fmt: skip

    def _summarise(
        self,
        X0: FloatArray,
        X: FloatArray,
        before: FloatArray,
        after: FloatArray,
        iters: IntArray,
        converged: BoolArray,
        threshold: float | None,
        max_rotation: float,
        max_displacement: float | None,
    ) -> BatchCorrection:
        R0, R1 = X0[:, :3, :3], X[:, :3, :3]
        dR = R1 @ np.swapaxes(R0, 1, 2)
        rot = _rotation_angles(dR)
        cg = self._centroid_G
        c0 = np.einsum("nij,j->ni", R0, cg) + X0[:, :3, 3]
        c1 = np.einsum("nij,j->ni", R1, cg) + X[:, :3, 3]
        trans = np.linalg.norm(c1 - c0, axis=1)
        # Largest vertex movement, exactly, in chunks of frames to bound memory.
        Vg = self._vertices_G
        disp = np.empty(len(X))
        step = max(1, 200_000 // max(len(Vg), 1))
        for s in range(0, len(X), step):
            sl = slice(s, s + step)
            A = R1[sl] - R0[sl]
            b = X[sl, :3, 3] - X0[sl, :3, 3]
            d = np.einsum("nij,vj->nvi", A, Vg) + b[:, None, :]
            disp[sl] = np.sqrt(np.einsum("nvi,nvi->nv", d, d).max(axis=1))
        if max_displacement is not None:
            limit = np.full(len(X), float(max_displacement))
        elif threshold is not None:
            limit = np.full(len(X), DISPLACEMENT_FACTOR * float(threshold))
        else:
            limit = RESIDUAL_FACTOR * before
        moved = iters > 0
        implausible = moved & ((rot > max_rotation) | (disp > limit))
        return BatchCorrection(
            X_EG=X,
            residual_before=before,
            residual_after=after,
            iterations=iters,
            converged=converged,
            rotation_change=rot,
            translation_change=trans,
            displacement=disp,
            flagged=~converged | implausible,
        )


# --------------------------------------------------------------------------------------------
# Functions
# --------------------------------------------------------------------------------------------


def correct_pose(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG_observed: npt.ArrayLike,
    elements: Sequence[ContactElement],
    *,
    max_iter: int = DEFAULT_MAX_ITER,
    tol: float = DEFAULT_TOL,
    rcond: float = DEFAULT_RCOND,
    threshold: float | None = None,
    max_rotation: float = DEFAULT_MAX_ROTATION,
    max_displacement: float | None = None,
) -> CorrectionResult:
    """Correct one observed pose so that the contact elements hold exactly (paper 4.3.1).

    Parameters
    ----------
    grasped : Polyhedron
        Grasped object G (model frame G, metres).
    environment : Polyhedron
        Environment object E (model frame E, metres).
    X_EG_observed : array_like, shape (4, 4)
        Observed pose of G in E, metres; the initial solution ``q_0``.
    elements : sequence of ContactElement
        The contact elements to impose (e.g. found at the observed pose with a threshold of a
        few millimetres by :func:`apo.contact.find_contacts`).
    max_iter, tol, rcond, threshold, max_rotation, max_displacement
        As in :meth:`ContactConstraints.correct`: iterations, convergence tolerance
        (metres), SVD rank cut, contact threshold (metres), and the limits (rad, metres)
        beyond which a correction is flagged.

    Returns
    -------
    CorrectionResult
        The corrected pose, residuals before and after (metres), iterations, convergence,
        the change applied and the failure flag.

    See Also
    --------
    correct_poses : many frames, batched by element set.
    ContactConstraints : compiled residuals of one element set.

    Notes
    -----
    Paper 4.3.1: (1) ``q_c = q_0``; (2) stop if ``max_i |f_i(q_c)|`` is small enough;
    (3) linearise ``f_i`` at ``q_c``; (4) take the SVD least-squares solution of the
    linearised equations and update ``q_c``; (5) repeat. Here the update is the left twist
    ``X <- pose_from_twist(xi) @ X``, ``xi`` the minimum-norm step (``docs/correction.md``).

    Examples
    --------
    >>> import numpy as np
    >>> from apo.contact import find_contacts
    >>> from apo.shapes import box
    >>> from apo.spatial import matrix_from_axis_angle
    >>> table = box([1.0, 1.0, 0.1], center=[0.0, 0.0, -0.05])
    >>> cube = box([0.1, 0.1, 0.1], center=[0.0, 0.0, 0.05])
    >>> X = np.eye(4)
    >>> X[:3, :3] = matrix_from_axis_angle([1, 0, 0], 0.01)  # tilted, 0.5 mm in the table
    >>> X[2, 3] = 0.001
    >>> elements = find_contacts(cube, table, X, threshold=0.003).elements
    >>> res = correct_pose(cube, table, X, elements)
    >>> res.converged, res.residual_after < 1e-10, bool(abs(res.X_EG[2, 1]) < 1e-12)
    (True, True, True)
    """
    X = np.asarray(X_EG_observed, dtype=np.float64)
    if X.shape != (4, 4):
        raise ValueError(f"X_EG_observed must have shape (4, 4), got {X.shape}")
    res = ContactConstraints(grasped, environment, elements).correct(
        X[None],
        max_iter=max_iter,
        tol=tol,
        rcond=rcond,
        threshold=threshold,
        max_rotation=max_rotation,
        max_displacement=max_displacement,
    )
    return res[0]


def _group_key(elements: Sequence[ContactElement]) -> tuple[object, ...]:
    """Hashable identity of an element set, with each EE element's normal sign."""
    out: list[object] = []
    for el in elements:
        sign: tuple[float, ...] = ()
        if el.kind is ContactKind.EE and len(el.normals):
            sign = tuple(np.round(el.normals[0], 3).tolist())
        out.append((el.key, sign))
    return tuple(out)


def correct_poses(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG_seq: npt.ArrayLike,
    elements_seq: Sequence[Sequence[ContactElement]],
    *,
    max_iter: int = DEFAULT_MAX_ITER,
    tol: float = DEFAULT_TOL,
    rcond: float = DEFAULT_RCOND,
    threshold: float | None = None,
    max_rotation: float = DEFAULT_MAX_ROTATION,
    max_displacement: float | None = None,
) -> BatchCorrection:
    """Correct a sequence of poses, each under its own contact elements (paper 4.3.1).

    Frames with the same element set (same kinds, feature ids and EE normal signs) are
    corrected together in one batch by one :class:`ContactConstraints`; a demonstration
    usually has a few states over many frames, so this costs a few numpy calls per state
    and iteration rather than per frame.

    Parameters
    ----------
    grasped : Polyhedron
        Grasped object G (model frame G, metres).
    environment : Polyhedron
        Environment object E (model frame E, metres).
    X_EG_seq : array_like, shape (n, 4, 4)
        Observed poses of G in E, metres.
    elements_seq : sequence of sequence of ContactElement, length n
        The elements to impose at each frame (e.g. ``state.elements`` of each frame's
        contact state). A frame with no elements is returned unchanged (converged).
    max_iter, tol, rcond, threshold, max_rotation, max_displacement
        As in :meth:`ContactConstraints.correct`.

    Returns
    -------
    BatchCorrection
        Per frame, in the order of ``X_EG_seq``.

    Raises
    ------
    ValueError
        ``elements_seq`` does not have one entry per pose, or bad poses or options.
    """
    X = _check_poses(X_EG_seq)
    n = X.shape[0]
    if len(elements_seq) != n:
        raise ValueError(f"elements_seq has {len(elements_seq)} entries for {n} poses")
    groups: dict[tuple[object, ...], list[int]] = {}
    first: dict[tuple[object, ...], Sequence[ContactElement]] = {}
    for i, els in enumerate(elements_seq):
        key = _group_key(els)
        groups.setdefault(key, []).append(i)
        first.setdefault(key, els)
    out_X = X.copy()
    fields = {
        name: np.zeros(n)
        for name in ("before", "after", "rot", "trans", "disp")
    }  # fmt: skip
    iters = np.zeros(n, dtype=np.int64)
    conv = np.ones(n, dtype=bool)
    flagged = np.zeros(n, dtype=bool)
    for key, frames in groups.items():
        idx = np.asarray(frames, dtype=np.int64)
        res = ContactConstraints(grasped, environment, first[key]).correct(
            X[idx],
            max_iter=max_iter,
            tol=tol,
            rcond=rcond,
            threshold=threshold,
            max_rotation=max_rotation,
            max_displacement=max_displacement,
        )
        out_X[idx] = res.X_EG
        fields["before"][idx] = res.residual_before
        fields["after"][idx] = res.residual_after
        fields["rot"][idx] = res.rotation_change
        fields["trans"][idx] = res.translation_change
        fields["disp"][idx] = res.displacement
        iters[idx] = res.iterations
        conv[idx] = res.converged
        flagged[idx] = res.flagged
    return BatchCorrection(
        X_EG=out_X,
        residual_before=fields["before"],
        residual_after=fields["after"],
        iterations=iters,
        converged=conv,
        rotation_change=fields["rot"],
        translation_change=fields["trans"],
        displacement=fields["disp"],
        flagged=flagged,
    )
