"""Time-parametrised pose trajectory of the grasped object along a skill program.

For robots that take poses rather than primitives: the nominal path through the program's
waypoints (the start pose, then per primitive its ``via`` poses and its target pose). In a
segment the point of the object at the primitive's compliance centre moves on a straight
line while the orientation turns on the geodesic (:class:`scipy.spatial.transform.Slerp`)
about that point; the centre of a rotational sub-skill lies on its axis, so such a segment
is the turn about the pivot the sub-skill prescribes, and the approach turns about the
object's origin while it crosses over at a safe level. Timing: a minimum-jerk profile
``s(u) = 10u^3 - 15u^4 + 6u^5`` (zero velocity and acceleration at every waypoint, where
guarded moves start and stop); a segment lasts ``max(distance / speed, angle /
angular_speed)`` with the distance that of the centre, and at least one sample period.

SI units, environment frame; no I/O (``apo plan`` writes ``motion.csv`` and
``motion.pose.list`` with :mod:`apo.io.poses`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation, Slerp

from apo.motion.program import SkillProgram
from apo.spatial import invert_pose
from apo.typing import FloatArray, IntArray

__all__ = ["Trajectory", "min_jerk", "trajectory"]


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
    segments: list[tuple[float, float, FloatArray, FloatArray, int, FloatArray]] = []
    for X, idx, center in _waypoints(program):
        dt = _duration(X_prev, X, center, program)
        segments.append((t0, t0 + dt, X_prev, X, idx, center))
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
    for ta, tb, Xa, Xb, idx, center in segments:
        c_G = invert_pose(Xb) @ np.append(center, 1.0)
        c_a = (Xa @ c_G)[:3]
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([Xa[:3, :3], Xb[:3, :3]])))
        k1 = k
        while k1 < times.shape[0] and times[k1] <= tb + 1e-12:
            k1 += 1
        if k1 == k:
            continue
        s = np.clip(min_jerk((times[k:k1] - ta) / (tb - ta)), 0.0, 1.0)
        R = slerp(s).as_matrix()
        c = c_a + s[:, None] * (center - c_a)
        poses[k:k1, :3, :3] = R
        poses[k:k1, :3, 3] = c - np.einsum("nij,j->ni", R, c_G[:3])
        poses[k:k1, 3, 3] = 1.0
        prim[k:k1] = idx
        k = k1
    return Trajectory(times=np.asarray(times, dtype=np.float64), X_EG=poses, primitive=prim)
