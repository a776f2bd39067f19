"""Rigid transforms, quaternions and twists (no I/O).

Conventions (``docs/conventions.md``): poses are 4x4 homogeneous matrices ``X_AB`` (frame B in
frame A, ``p_A = X_AB @ p_B``); quaternions are ``(qw, qx, qy, qz)``; poses on disk are
``x y z qw qx qy qz``; twists are ``[S0; S1]`` = ``[omega; v]``, rotation first, with ``v`` the
velocity of the point at the origin of the frame the twist is expressed in.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

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
    if n < 1e-9:
        raise ValueError("quaternion has zero norm")
    return arr / n


def skew(v: npt.ArrayLike) -> FloatArray:
    """Return the 3x3 cross-product matrix of ``v`` (``skew(a) @ b == cross(a, b)``)."""
    x, y, z = np.asarray(v, dtype=float)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def matrix_from_quaternion(q: npt.ArrayLike) -> FloatArray:
    """Return the rotation matrix of a quaternion ``(qw, qx, qy, qz)``."""
    w, x, y, z = check_quaternion(q)
    return np.asarray(Rotation.from_quat([x, y, z, w]).as_matrix(), dtype=float)


def quaternion_from_matrix(R: npt.ArrayLike) -> FloatArray:
    """Return the quaternion ``(qw, qx, qy, qz)`` of a rotation matrix, with ``qw >= 0``."""
    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat()
    q = np.array([w, x, y, z])
    return -q if w < 0 else q


def matrix_from_axis_angle(axis: npt.ArrayLike, angle: float) -> FloatArray:
    """Return the rotation by ``angle`` (rad) about ``axis`` (normalised here)."""
    a = np.asarray(axis, dtype=float)
    n = float(np.linalg.norm(a))
    if n < 1e-12:
        if abs(angle) > 1e-12:
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
    if th < 1e-12:
        R = np.eye(3) + W
        V = np.eye(3) + 0.5 * W
    else:
        R = np.asarray(Rotation.from_rotvec(w).as_matrix(), dtype=float)
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
