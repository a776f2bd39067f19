"""Time-parametrised pose trajectory of the grasped object along a skill program.

For robots that take poses rather than primitives: the nominal path through the program's
waypoints (the start pose, then per primitive its ``via`` poses and its target pose), each
segment a screw motion (the geodesic of SE(3): ``X(s) = exp(s xi) X_a`` with
``xi = log(X_b inv(X_a))``, a twist in the environment frame, so that a turn about a pivot
keeps the pivot still), timed by a minimum-jerk profile ``s(u) = 10u^3 - 15u^4 + 6u^5``
(zero velocity and acceleration at every waypoint, where guarded moves start and stop).
A segment lasts ``max(distance / speed, angle / angular_speed)`` with the distance that
of the primitive's compliance centre, and at least one sample period.

SI units, environment frame; no I/O (``apo plan`` writes ``motion.csv`` and
``motion.pose.list`` with :mod:`apo.io.poses`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from apo.motion.program import SkillProgram
from apo.spatial import invert_pose, pose_from_twist, skew
from apo.typing import FloatArray, IntArray

__all__ = ["Trajectory", "min_jerk", "trajectory", "twist_from_pose"]


@dataclass(frozen=True)
class Trajectory:
    """Poses of the grasped object over time.

    Attributes
    ----------
    times : ndarray, shape (N,)
        Seconds from the start, strictly increasing, ``times[0] == 0``.
    X_EG : ndarray, shape (N, 4, 4)
        Poses of G in E, metres.
    primitive : ndarray of int, shape (N,)
        Index of the primitive each sample belongs to (the one whose segment ends after it).
    """

    times: FloatArray
    X_EG: FloatArray
    primitive: IntArray


def twist_from_pose(X: npt.ArrayLike) -> FloatArray:
    """Return the twist ``[omega; v]`` whose exponential is ``X`` (inverse of ``pose_from_twist``).

    The rotation angle is taken in ``[0, pi]``.

    Examples
    --------
    >>> import numpy as np
    >>> from apo.spatial import pose_from_twist
    >>> xi = np.array([0.1, -0.2, 0.3, 0.01, 0.02, -0.03])
    >>> bool(np.allclose(twist_from_pose(pose_from_twist(xi)), xi))
    True
    """
    M = np.asarray(X, dtype=float)
    w = np.asarray(Rotation.from_matrix(M[:3, :3]).as_rotvec(), dtype=float)
    th = float(np.linalg.norm(w))
    W = skew(w)
    if th < 1e-12:
        V = np.eye(3) + 0.5 * W
    else:
        B = (1 - np.cos(th)) / th**2
        C = (1 - np.sin(th) / th) / th**2
        V = np.eye(3) + B * W + C * (W @ W)
    return np.concatenate([w, np.linalg.solve(V, M[:3, 3])])


def min_jerk(u: npt.ArrayLike) -> FloatArray:
    """Return ``10u^3 - 15u^4 + 6u^5`` (0 to 1 with zero end velocity and acceleration)."""
    x = np.clip(np.asarray(u, dtype=float), 0.0, 1.0)
    return np.asarray(x**3 * (10 - 15 * x + 6 * x**2), dtype=float)


def _waypoints(program: SkillProgram) -> list[tuple[FloatArray, int, FloatArray]]:
    """``(pose, primitive index, centre)`` of every waypoint after the start."""
    out: list[tuple[FloatArray, int, FloatArray]] = []
    for p in program.primitives:
        for X in (*p.via, p.target.X_EG):
            out.append((X, p.index, p.compliance.center))
    return out


def _duration(X_a: FloatArray, X_b: FloatArray, center: FloatArray, program: SkillProgram) -> float:
    pp = program.parameters
    c_a = X_a @ invert_pose(X_b) @ np.append(center, 1.0)
    dist = float(np.linalg.norm(center - c_a[:3]))
    angle = float(np.linalg.norm(Rotation.from_matrix(X_b[:3, :3] @ X_a[:3, :3].T).as_rotvec()))
    return max(dist / pp.speed, angle / pp.angular_speed, pp.sample_period)


def trajectory(program: SkillProgram) -> Trajectory:
    """Return the nominal pose trajectory of ``program``, sampled every ``sample_period``.

    Parameters
    ----------
    program : SkillProgram

    Returns
    -------
    Trajectory
        Samples at ``k * sample_period`` and at the very end; every waypoint pose is
        passed through (exactly at the segment ends that fall on a sample).
    """
    pp = program.parameters
    X_prev = program.start_X_EG
    t0 = 0.0
    segments: list[tuple[float, float, FloatArray, FloatArray, int]] = []
    for X, idx, center in _waypoints(program):
        dt = _duration(X_prev, X, center, program)
        segments.append((t0, t0 + dt, X_prev, X, idx))
        t0 += dt
        X_prev = X
    total = t0
    n = int(np.floor(total / pp.sample_period + 1e-9)) + 1
    times = np.arange(n, dtype=np.float64) * pp.sample_period
    if total - times[-1] > 1e-9:
        times = np.append(times, total)
    poses = np.zeros((times.shape[0], 4, 4))
    prim = np.zeros(times.shape[0], dtype=np.int64)
    poses[0], prim[0] = program.start_X_EG, segments[0][4]
    k = 1
    for ta, tb, Xa, Xb, idx in segments:
        xi = twist_from_pose(Xb @ invert_pose(Xa))
        while k < times.shape[0] and times[k] <= tb + 1e-12:
            s = float(min_jerk((times[k] - ta) / (tb - ta)))
            poses[k] = pose_from_twist(s * xi) @ Xa
            prim[k] = idx
            k += 1
    return Trajectory(times=np.asarray(times, dtype=np.float64), X_EG=poses, primitive=prim)
