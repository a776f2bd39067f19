"""Rigid symmetries of a triangle mesh, and the symmetric twin of a pose nearest a reference.

A symmetry of a model ``M`` is a proper rigid motion ``S`` (a 4x4 pose, model frame) that
maps its surface onto itself: the pose ``X_CM @ S`` shows the same object as ``X_CM``. A
tracker that sees only the surface cannot tell these *twins* apart, so it must choose among
them consistently (:func:`nearest_twin`); contact states compared up to the symmetries do not
depend on that choice.

Method (:func:`symmetries`): every symmetry fixes the area-weighted centroid ``c`` of the
surface and permutes the vertices of a polyhedron. Two anchor vertices ``a`` and ``b`` (not
collinear with ``c``; ``a`` the farthest from ``c``, ``b`` the one whose distance to ``c``
is shared by the fewest vertices) can only go to vertices ``a'``, ``b'`` at the same
distances from ``c`` and at the same angle; each such pair gives one candidate rotation
about ``c``. A candidate is a symmetry when it keeps the inertia tensor of the surface and
maps every vertex and a dense sample of the surface to within ``tolerance`` (plus the
sampling spacing, for the samples) of the surface's own vertices and samples. Only proper
rotations are returned (mirror images are different objects). The set is a finite group: it
contains the identity (first) and is closed under composition and inversion.

Pure numpy/scipy; no I/O. Lengths in the units of the input (apo uses metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from apo.typing import FloatArray

__all__ = [
    "Symmetry",
    "describe_symmetries",
    "nearest_twin",
    "pose_distance",
    "symmetries",
    "twin_poses",
]

#: Candidate rotations beyond this count are not checked (a finely tessellated body of
#: revolution has as many as its tessellation; the check would dominate the run time).
MAX_CANDIDATES = 20000


@dataclass(frozen=True)
class Symmetry:
    """One rigid symmetry of a model, about its surface centroid.

    Attributes
    ----------
    S : ndarray, shape (4, 4)
        The motion in the model frame: ``X_CM @ S`` is a twin of ``X_CM``.
    axis : ndarray, shape (3,)
        Unit rotation axis, model frame (``[0, 0, 1]`` for the identity).
    angle : float
        Rotation angle about ``axis``, radians in [0, pi].
    """

    S: FloatArray
    axis: FloatArray
    angle: float


def _surface_moments(V: FloatArray, F: npt.NDArray[np.int64]) -> tuple[FloatArray, FloatArray]:
    """Area-weighted centroid and second-moment tensor of the surface (about the centroid)."""
    tri = V[F]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    total = float(area.sum())
    if not total > 0:
        raise ValueError("mesh has no area (all triangles degenerate)")
    c = (area[:, None] * tri.mean(axis=1)).sum(axis=0) / total
    # Second moment of each triangle (exact for a uniform density over the triangle).
    d = tri - c
    s = d.sum(axis=1)
    M = np.einsum("t,ti,tj->ij", area, s, s) + np.einsum("t,tki,tkj->ij", area, d, d)
    return c, M / (12.0 * total)


def _surface_samples(V: FloatArray, F: npt.NDArray[np.int64], spacing: float) -> FloatArray:
    """Points on every triangle on a barycentric grid whose steps are at most ``spacing``."""
    tri = V[F]
    longest = np.max(
        np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2),
        axis=1,
    )
    out = [V]
    steps = np.maximum(1, np.ceil(longest / spacing)).astype(int)
    for n in np.unique(steps):
        if n < 2:
            continue
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = i + j <= n
        b = np.stack([i[keep], j[keep]], axis=1) / n
        w = np.column_stack([1.0 - b.sum(axis=1), b])  # (K, 3) barycentric weights
        sel = tri[steps == n]
        out.append(np.einsum("kv,tvd->tkd", w, sel).reshape(-1, 3))
    return np.unique(np.round(np.vstack(out) / (spacing * 1e-3)), axis=0) * (spacing * 1e-3)


def _frame(a: FloatArray, b: FloatArray) -> FloatArray:
    """Orthonormal frame (columns) from two non-parallel vectors."""
    e1 = a / np.linalg.norm(a)
    e2 = b - (b @ e1) * e1
    e2 /= np.linalg.norm(e2)
    return np.column_stack([e1, e2, np.cross(e1, e2)])


def _anchors(P: FloatArray, r: FloatArray, tol: float) -> tuple[int, int]:
    """Two vertex indices not collinear with the centroid, with few look-alikes each."""
    a = int(np.argmax(r))
    ua = P[a] / r[a]
    sin = np.linalg.norm(np.cross(P, ua), axis=1)
    ok = sin > max(0.2 * r.max(), 10 * tol)
    if not ok.any():
        ok = sin > 10 * tol
    if not ok.any():
        raise ValueError("mesh vertices are collinear: no finite symmetry group")
    # The distance to c shared by the fewest vertices.
    rs = np.sort(r)
    counts = np.searchsorted(rs, r[ok] + tol, "right") - np.searchsorted(rs, r[ok] - tol, "left")
    b = int(np.flatnonzero(ok)[int(np.argmin(counts))])
    return a, b


def _candidates(P: FloatArray, r: FloatArray, a: int, b: int, tol: float) -> list[FloatArray]:
    """Rotations taking the anchors to vertices at the same distances and angle."""
    A = np.flatnonzero(np.abs(r - r[a]) <= tol)
    B = np.flatnonzero(np.abs(r - r[b]) <= tol)
    dot = P[a] @ P[b]
    F0 = _frame(P[a], P[b])
    out: list[FloatArray] = []
    for i in A:
        d = P[B] @ P[i]
        # |a||b| (cos) within the tolerance of the chord: |a' . b' - a . b| <~ tol (|a|+|b|)
        match = B[np.abs(d - dot) <= tol * (r[a] + r[b])]
        for j in match:
            if np.linalg.norm(np.cross(P[i], P[j])) <= 1e-12:
                continue
            out.append(_frame(P[i], P[j]) @ F0.T)
            if len(out) >= MAX_CANDIDATES:
                return out
    return out


def _dedupe(rotations: list[FloatArray], angle_tol: float) -> list[FloatArray]:
    """Distinct rotations (Frobenius distance above the angle tolerance), identity first."""
    out: list[FloatArray] = [np.eye(3)]
    for R in rotations:
        if all(np.linalg.norm(R - Q) > angle_tol for Q in out):
            out.append(R)
    return out


def symmetries(
    vertices: npt.ArrayLike,
    triangles: npt.ArrayLike,
    *,
    tolerance: float | None = None,
) -> list[Symmetry]:
    """Return the proper rigid motions that map a triangle mesh onto itself within a tolerance.

    Parameters
    ----------
    vertices : ndarray, shape (V, 3)
        Vertex positions, model frame (any length unit; apo uses metres).
    triangles : ndarray of int, shape (T, 3)
        Vertex indices of each triangle.
    tolerance : float, optional
        Largest distance (units of ``vertices``) between the moved surface and the surface;
        default 0.1 % of the mesh's diameter.

    Returns
    -------
    list of Symmetry
        The identity first, then the others by increasing angle. Each ``S`` is a rotation
        about the surface centroid (``S[:3, 3] = c - R c``).

    Raises
    ------
    ValueError
        Bad shapes, a mesh without area, or vertices all on one line.

    Examples
    --------
    A box with three different side lengths has the 4 symmetries of a brick (the identity
    and a half-turn about each axis):

    >>> import numpy as np
    >>> from apo.perception.render import box_triangles
    >>> V, F = box_triangles((0.03, 0.02, 0.01))
    >>> [round(float(np.degrees(s.angle))) for s in symmetries(V, F)]
    [0, 180, 180, 180]
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(triangles, dtype=np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) < 3:
        raise ValueError(f"vertices must have shape (V >= 3, 3), got {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise ValueError(f"triangles must have shape (T >= 1, 3), got {F.shape}")
    if F.min() < 0 or F.max() >= len(V):
        raise ValueError(f"triangle indices must be in [0, {len(V)}), got {F.min()}..{F.max()}")
    c, M = _surface_moments(V, F)
    used = np.unique(F)
    diameter = float(np.linalg.norm(V[used].max(0) - V[used].min(0)))
    tol = 1e-3 * diameter if tolerance is None else float(tolerance)
    if not tol > 0:
        raise ValueError(f"tolerance must be positive, got {tolerance}")
    P = V[used] - c
    r = np.linalg.norm(P, axis=1)
    a, b = _anchors(P, r, tol)
    rotations = _dedupe(_candidates(P, r, a, b, tol), angle_tol=tol / max(r.max(), 1e-300))
    spacing = max(diameter / 60.0, tol)
    S = _surface_samples(V, F, spacing) - c
    tree_v, tree_s = cKDTree(P), cKDTree(S)
    scale_M = max(float(np.abs(M).max()), 1e-300)
    found: list[FloatArray] = []
    for R in rotations:
        if np.abs(R @ M @ R.T - M).max() > 4.0 * tol * r.max() + 1e-9 * scale_M:
            continue
        if np.max(tree_v.query(P @ R.T, distance_upper_bound=2 * tol)[0]) > tol:
            continue
        if np.max(tree_s.query(S @ R.T, distance_upper_bound=4 * spacing)[0]) > tol + spacing:
            continue
        found.append(R)
    return sorted((_symmetry(R, c) for R in found), key=lambda s: s.angle)


def _symmetry(R: FloatArray, c: FloatArray) -> Symmetry:
    from scipy.spatial.transform import Rotation

    R = np.asarray(R)
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt
    rv = Rotation.from_matrix(R).as_rotvec()
    angle = float(np.linalg.norm(rv))
    axis = rv / angle if angle > 1e-12 else np.array([0.0, 0.0, 1.0])
    if angle > 1e-12 and abs(angle - np.pi) < 1e-9:
        # Half-turn: +axis and -axis are the same motion; choose a canonical sign.
        k = int(np.argmax(np.abs(axis)))
        axis = axis if axis[k] > 0 else -axis
    S = np.eye(4)
    S[:3, :3] = R
    S[:3, 3] = c - R @ c
    return Symmetry(S, axis, angle)


def twin_poses(X: npt.ArrayLike, syms: list[Symmetry]) -> FloatArray:
    """All twins ``X @ S`` of a pose (shape (K, 4, 4); the identity's first)."""
    M = np.asarray(X, dtype=np.float64)
    if not syms:
        return np.asarray(M[None].copy())
    return np.asarray(np.einsum("ij,kjl->kil", M, np.stack([s.S for s in syms])), np.float64)


def pose_distance(X_a: npt.ArrayLike, X_b: npt.ArrayLike, length: float) -> FloatArray:
    """Distance between poses: ``sqrt(|dp|^2 + (length * angle)^2)`` (units of ``length``).

    ``X_a`` may be a stack (K, 4, 4); ``length`` converts the rotation angle (radians) to a
    length (a model's radius makes it the displacement of its far points).
    """
    A = np.asarray(X_a, dtype=np.float64)
    B = np.asarray(X_b, dtype=np.float64)
    dp = np.linalg.norm(A[..., :3, 3] - B[:3, 3], axis=-1)
    cos = (np.einsum("...ij,ij->...", A[..., :3, :3], B[:3, :3]) - 1.0) / 2.0
    ang = np.arccos(np.clip(cos, -1.0, 1.0))
    return np.asarray(np.hypot(dp, length * ang))


def nearest_twin(
    X: npt.ArrayLike, X_ref: npt.ArrayLike, syms: list[Symmetry], *, length: float
) -> tuple[FloatArray, int]:
    """Return the twin ``X @ S_k`` of ``X`` nearest ``X_ref`` (:func:`pose_distance`), and ``k``.

    Ties (equally near twins) go to the lowest ``k``, i.e. the identity when it is among them.

    Examples
    --------
    >>> import numpy as np
    >>> from apo.spatial import matrix_from_axis_angle
    >>> def turn(angle):
    ...     X = np.eye(4)
    ...     X[:3, :3] = matrix_from_axis_angle([0, 0, 1], angle)
    ...     return X
    >>> half = Symmetry(turn(np.pi), np.array([0.0, 0.0, 1.0]), float(np.pi))
    >>> ident = Symmetry(np.eye(4), np.array([0.0, 0.0, 1.0]), 0.0)
    >>> X = turn(3.0)
    >>> _, k = nearest_twin(X, np.eye(4), [ident, half], length=0.05)
    >>> k
    1
    """
    T = twin_poses(X, syms)
    d = pose_distance(T, X_ref, length)
    k = int(np.argmin(d))
    return T[k], k


def describe_symmetries(syms: list[Symmetry]) -> str:
    """One-line description, e.g. ``"2 (identity; 180 deg about z)"``.

    Axes along a model axis are named (``x``, ``-y``); others are written as vectors.
    """
    if len(syms) <= 1:
        return "1 (identity only)"
    parts = []
    for s in syms[1:]:
        k = int(np.argmax(np.abs(s.axis)))
        if abs(abs(s.axis[k]) - 1.0) < 1e-6:
            name = ("" if s.axis[k] > 0 else "-") + "xyz"[k]
        else:
            name = "[" + ", ".join(f"{v:.2f}" for v in s.axis) + "]"
        parts.append(f"{np.degrees(s.angle):.0f} deg about {name}")
    if len(parts) > 6:
        parts = [*parts[:5], f"... {len(parts) - 5} more"]
    return f"{len(syms)} (identity; " + "; ".join(parts) + ")"
