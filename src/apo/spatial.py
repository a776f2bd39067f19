"""Rigid transforms, quaternions and twists (no I/O).

Conventions (``docs/conventions.md``): poses are 4x4 homogeneous matrices ``X_AB`` (frame B in
frame A, ``p_A = X_AB @ p_B``); quaternions are ``(qw, qx, qy, qz)``; poses on disk are
``x y z qw qx qy qz``; twists are ``[S0; S1]`` = ``[omega; v]``, rotation first, with ``v`` the
velocity of the point at the origin of the frame the twist is expressed in.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from apo.constants import tol
from apo.errors import InputFormatError
from apo.typing import FloatArray


def check_quaternion(q: npt.ArrayLike) -> FloatArray:
    """Return ``q`` as a unit quaternion ``(qw, qx, qy, qz)``.

    Raises
    ------
    ValueError
        If ``q`` is not 4 finite numbers or has (near) zero norm.
    """
    arr = np.asarray(q, dtype=float)
    if arr.shape != (4,):
        raise ValueError(f"expected a quaternion of shape (4,), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"quaternion has non-finite entries: {arr.tolist()}")
    n = float(np.linalg.norm(arr))
    if n < tol.quaternion_zero_norm:
        raise ValueError("quaternion has zero norm")
    return arr / n


def skew(v: npt.ArrayLike) -> FloatArray:
    """Return the 3x3 cross-product matrix of ``v`` (``skew(a) @ b == cross(a, b)``)."""
    x, y, z = np.asarray(v, dtype=float)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def matrix_from_quaternion(q: npt.ArrayLike) -> FloatArray:
    """Return the rotation matrix of a quaternion ``(qw, qx, qy, qz)``."""
    out: FloatArray = matrices_from_quaternions(check_quaternion(q)[None])[0]
    return out


def matrices_from_quaternions(q: npt.ArrayLike) -> FloatArray:
    """Return the rotation matrices (N, 3, 3) of quaternions ``(qw, qx, qy, qz)`` (N, 4).

    Each quaternion is normalised first. Numpy only, the same numbers as
    ``scipy.spatial.transform.Rotation.from_quat(...).as_matrix()`` bit for bit.

    Examples
    --------
    >>> matrices_from_quaternions([[2.0, 0.0, 0.0, 0.0]])[0].tolist()
    [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    """
    a = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    w, x, y, z = a[:, 0], a[:, 1], a[:, 2], a[:, 3]
    n = np.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    M = np.empty((len(a), 3, 3))
    M[:, 0, 0] = x2 - y2 - z2 + w2
    M[:, 1, 0] = 2 * (xy + zw)
    M[:, 2, 0] = 2 * (xz - yw)
    M[:, 0, 1] = 2 * (xy - zw)
    M[:, 1, 1] = -x2 + y2 - z2 + w2
    M[:, 2, 1] = 2 * (yz + xw)
    M[:, 0, 2] = 2 * (xz + yw)
    M[:, 1, 2] = 2 * (yz - xw)
    M[:, 2, 2] = -x2 - y2 + z2 + w2
    return M


def quaternion_from_matrix(R: npt.ArrayLike) -> FloatArray:
    """Return the quaternion ``(qw, qx, qy, qz)`` of a rotation matrix, with ``qw >= 0``."""
    out: FloatArray = quaternions_from_matrices(np.asarray(R, dtype=float)[None])[0]
    return out


def quaternions_from_matrices(R: npt.ArrayLike) -> FloatArray:
    """Return the quaternions ``(qw, qx, qy, qz)``, ``qw >= 0``, of rotation matrices (N, 3, 3).

    Numpy only, the same numbers as ``scipy.spatial.transform.Rotation.from_matrix`` bit
    for bit (Shepperd's method on the largest of the trace and the diagonal; a matrix whose
    Gram matrix is not the identity within 1e-12 is first replaced by its nearest rotation
    ``U @ Vt``), without importing scipy.

    Examples
    --------
    >>> quaternions_from_matrices(np.eye(3)[None]).tolist()
    [[1.0, 0.0, 0.0, 0.0]]
    """
    M = np.array(R, dtype=np.float64).reshape(-1, 3, 3)
    gram = M @ M.transpose(0, 2, 1)
    rtol, atol = tol.orthogonal_rtol, tol.orthogonal_atol
    ortho = np.all(np.isclose(gram, np.eye(3), rtol=rtol, atol=atol), axis=(1, 2))
    if not ortho.all():
        U, _, Vt = np.linalg.svd(M[~ortho], full_matrices=False)
        M[~ortho] = U @ Vt
    tr = M[:, 0, 0] + M[:, 1, 1] + M[:, 2, 2]
    choice = np.argmax(np.stack([M[:, 0, 0], M[:, 1, 1], M[:, 2, 2], tr], axis=1), axis=1)
    q = np.empty((len(M), 4))  # x, y, z, w as scipy computes them
    for c in range(3):
        m = choice == c
        i, j, k, S = c, (c + 1) % 3, (c + 2) % 3, M[m]
        q[m, i] = 1 - tr[m] + 2 * S[:, i, i]
        q[m, j] = S[:, j, i] + S[:, i, j]
        q[m, k] = S[:, k, i] + S[:, i, k]
        q[m, 3] = S[:, k, j] - S[:, j, k]
    m = choice == 3
    S = M[m]
    q[m, 0] = S[:, 2, 1] - S[:, 1, 2]
    q[m, 1] = S[:, 0, 2] - S[:, 2, 0]
    q[m, 2] = S[:, 1, 0] - S[:, 0, 1]
    q[m, 3] = 1 + tr[m]
    n = np.sqrt(q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2] + q[:, 3] * q[:, 3])
    q = q[:, [3, 0, 1, 2]] / n[:, None]
    q[q[:, 0] < 0] *= -1.0
    return q


def matrix_from_axis_angle(axis: npt.ArrayLike, angle: float) -> FloatArray:
    """Return the rotation by ``angle`` (rad) about ``axis`` (normalised here)."""
    from scipy.spatial.transform import Rotation

    a = np.asarray(axis, dtype=float)
    n = float(np.linalg.norm(a))
    if n < tol.zero_norm:
        if abs(angle) > tol.zero_norm:
            raise ValueError("axis-angle with zero axis and non-zero angle")
        return np.eye(3)
    return np.asarray(Rotation.from_rotvec(a / n * angle).as_matrix(), dtype=float)


def pose_from_position_quaternion(p: npt.ArrayLike, q: npt.ArrayLike) -> FloatArray:
    """Return the 4x4 pose with translation ``p`` and quaternion ``q = (qw, qx, qy, qz)``."""
    X = np.eye(4)
    X[:3, :3] = matrix_from_quaternion(q)
    X[:3, 3] = np.asarray(p, dtype=float)
    return X


def position_quaternion_from_pose(X: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Return ``(p, q)`` of a 4x4 pose, ``q = (qw, qx, qy, qz)`` with ``qw >= 0``."""
    M = np.asarray(X, dtype=float)
    return M[:3, 3].copy(), quaternion_from_matrix(M[:3, :3])


def pose_from_xyz_quat(v: npt.ArrayLike) -> FloatArray:
    """Return the pose of a 7-vector ``x y z qw qx qy qz`` (the on-disk order)."""
    a = np.asarray(v, dtype=float)
    if a.shape != (7,):
        raise ValueError(f"expected 7 numbers 'x y z qw qx qy qz', got shape {a.shape}")
    return pose_from_position_quaternion(a[:3], a[3:])


def orthonormalised(X: npt.ArrayLike) -> FloatArray:
    """Return the rigid pose nearest to ``X`` (its rotation block projected onto SO(3)).

    Compositions and float arithmetic (Open3D's, an ICP's steps) let a rotation block drift
    from orthonormal; ``invert_pose`` assumes a rigid pose, so an error there would grow from
    frame to frame.
    """
    M = np.asarray(X, dtype=np.float64)
    U, _, Vt = np.linalg.svd(M[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, 2] = -U[:, 2]
        R = U @ Vt
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = M[:3, 3]
    return out


def invert_pose(X: npt.ArrayLike) -> FloatArray:
    """Return the inverse of a rigid 4x4 pose."""
    M = np.asarray(X, dtype=float)
    R, p = M[:3, :3], M[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ p
    return out


def transform_points(X: npt.ArrayLike, points: npt.ArrayLike) -> FloatArray:
    """Apply pose ``X`` to points of shape (..., 3)."""
    M = np.asarray(X, dtype=float)
    P = np.asarray(points, dtype=float)
    return np.asarray(P @ M[:3, :3].T + M[:3, 3], dtype=float)


def pose_from_twist(twist: npt.ArrayLike) -> FloatArray:
    """Return ``exp`` of a twist ``[omega; v]`` (rotation first) as a 4x4 pose.

    The twist is expressed in the frame the pose is applied in (left multiplication:
    ``X_new = pose_from_twist(xi) @ X``).
    """
    xi = np.asarray(twist, dtype=float)
    w, v = xi[:3], xi[3:]
    th = float(np.linalg.norm(w))
    W = skew(w)
    if th < tol.zero_norm:
        R = np.eye(3) + W
        V = np.eye(3) + 0.5 * W
    else:
        A = np.sin(th) / th
        B = (1 - np.cos(th)) / th**2
        C = (1 - A) / th**2
        R = np.eye(3) + A * W + B * (W @ W)
        V = np.eye(3) + B * W + C * (W @ W)
    X = np.eye(4)
    X[:3, :3] = R
    X[:3, 3] = V @ v
    return X


def rotation_angle(R: npt.ArrayLike) -> float:
    """Return the rotation angle (rad, in [0, pi]) of a rotation matrix."""
    M = np.asarray(R, dtype=float)
    c = (np.trace(M) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


# --------------------------------------------------------------------------------------------
# The pose validator
# --------------------------------------------------------------------------------------------


def perpendicular_basis(n: FloatArray) -> FloatArray:
    """Return a deterministic orthonormal basis (2, 3) of the plane perpendicular to unit ``n``.

    ``t1 = n x (1, 0, 0)`` normalised (``n x (0, 1, 0)`` when ``|n_x| >= 0.9``), ``t2 = n x t1``,
    so ``(t1, t2, n)`` is right-handed. The one basis of the contact search and of pose
    correction (``n`` is not normalised here).

    Examples
    --------
    >>> perpendicular_basis(np.array([0.0, 0.0, 1.0])).tolist()
    [[0.0, 1.0, -0.0], [-1.0, 0.0, 0.0]]
    """
    x, y, z = float(n[0]), float(n[1]), float(n[2])
    t1 = np.array([0.0, z, -y]) if abs(x) < 0.9 else np.array([-z, 0.0, x])
    t1 /= math.sqrt(float(t1 @ t1))
    a, b, c = float(t1[0]), float(t1[1]), float(t1[2])
    return np.stack([t1, np.array([y * c - z * b, z * a - x * c, x * b - y * a])])


def pose_defect(X: npt.ArrayLike) -> tuple[int, str, str] | None:
    """Find the first pose of ``X`` (N, 4, 4) that is not a finite rigid transform.

    The one rule of a valid pose: finite entries, a 3x3 block ``R`` with
    ``max |R R^T - I| <= tol.rotation`` and ``det R > 0``, last row ``0 0 0 1`` (within the
    same tolerance).

    Returns
    -------
    tuple of (int, str, str) or None
        ``(index, what, description)`` with ``what`` one of ``"finite"``, ``"rotation"``,
        ``"last row"``; None when every pose is valid.

    Examples
    --------
    >>> import numpy as np
    >>> X = np.stack([np.eye(4), np.diag([1.0, 1.0, 2.0, 1.0])])
    >>> pose_defect(X)[:2]
    (1, 'rotation')
    >>> pose_defect(np.eye(4)[None]) is None
    True
    """
    M = np.asarray(X, dtype=np.float64)
    for test in (_defect_finite, _defect_rotation, _defect_last_row):
        for a in range(0, len(M), DEFECT_BLOCK):  # working arrays of a block, not of all
            found = test(M[a : a + DEFECT_BLOCK])
            if found is not None:
                return found[0] + a, found[1], found[2]
    return None


#: Poses tested at a time by :func:`pose_defect` (its working arrays: some 300 bytes a pose).
DEFECT_BLOCK = 4096


def _defect_finite(M: FloatArray) -> tuple[int, str, str] | None:
    """Return the first pose of ``M`` with a non-finite entry, if any."""
    finite = np.isfinite(M).all(axis=(1, 2))
    if not finite.all():
        return int(np.argmin(finite)), "finite", "is not finite"
    return None


def _defect_rotation(M: FloatArray) -> tuple[int, str, str] | None:
    """Return the first pose of ``M`` (finite) whose 3x3 block is not a rotation, if any."""
    R = M[:, :3, :3]
    err = np.abs(np.einsum("nij,nkj->nik", R, R) - np.eye(3)).max(axis=(1, 2), initial=0.0)
    det = np.linalg.det(R) if len(M) else np.zeros(0)
    bad = (err > tol.rotation) | (det <= 0)
    if bad.any():
        k = int(np.argmax(bad))
        return (
            k,
            "rotation",
            f"rotation part is not a rotation matrix (max |R R^T - I| = {err[k]:.1e}, "
            f"tolerance {tol.rotation:g}; det {det[k]:.3g})",
        )
    return None


def _defect_last_row(M: FloatArray) -> tuple[int, str, str] | None:
    """Return the first pose of ``M`` whose last row is not ``0 0 0 1``, if any."""
    last = np.any(np.abs(M[:, 3] - [0.0, 0.0, 0.0, 1.0]) > tol.rotation, axis=1)
    if last.any():
        return int(np.argmax(last)), "last row", "last row is not 0 0 0 1"
    return None


def check_pose(X: npt.ArrayLike, *, name: str = "X_EG") -> FloatArray:
    """Return ``X`` as a float (4, 4) pose after checking it is a finite rigid transform.

    Raises
    ------
    InputFormatError
        (a ``ValueError``) naming ``name``: wrong shape, non-finite entries, a 3x3 block that
        is not a rotation (:data:`apo.constants.tol` ``.rotation``), or a last row other than
        ``0 0 0 1``.

    Examples
    --------
    >>> check_pose(np.eye(3))
    Traceback (most recent call last):
    ...
    apo.errors.InputFormatError: X_EG must have shape (4, 4), got shape (3, 3)
    """
    M = np.asarray(X, dtype=np.float64)
    if M.shape != (4, 4):
        raise InputFormatError(f"{name} must have shape (4, 4), got shape {M.shape}")
    defect = pose_defect(M[None])
    if defect is not None:
        raise InputFormatError(f"{name} {defect[2]}")
    return M


def check_poses(
    X_seq: Iterable[npt.ArrayLike] | npt.ArrayLike, *, name: str = "X_EG"
) -> FloatArray:
    """Return poses as a float (N, 4, 4) array after checking each as :func:`check_pose`.

    ``X_seq`` is an array (N, 4, 4) or an iterable of (4, 4) poses; the message of a bad one
    starts with ``pose <index>:``.

    Raises
    ------
    InputFormatError
        (a ``ValueError``) naming the first bad pose and what is wrong with it.
    """
    if isinstance(X_seq, np.ndarray) and X_seq.ndim == 3:
        items: Sequence[Any] | FloatArray = np.asarray(X_seq, dtype=np.float64)
    else:
        items = list(X_seq)  # type: ignore[arg-type]
        if not items:
            return np.zeros((0, 4, 4))
    try:
        M = np.asarray(items, dtype=np.float64)
    except ValueError:
        M = np.zeros((0,))
    if M.ndim == 3 and M.shape[1:] == (4, 4):
        defect = pose_defect(M)
        if defect is None:
            return M
        raise InputFormatError(f"pose {defect[0]}: {name} {defect[2]}")
    for k, X in enumerate(items):  # find the pose of the wrong shape
        try:
            check_pose(X, name=name)
        except InputFormatError as exc:
            raise InputFormatError(f"pose {k}: {exc}") from None
    raise InputFormatError(f"{name} sequence must have shape (N, 4, 4), got shape {M.shape}")
