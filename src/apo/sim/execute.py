"""Execution of a skill program (and of the observed poses) by the compliant hand.

The executor interprets each primitive of :class:`apo.motion.SkillProgram` generically, as
``docs/motion.md`` ("Executing a program") defines it for any robot controller; nothing here
depends on the primitive's kind beyond what the program says:

- the hand follows the primitive's nominal path from its current pose through the ``via``
  poses to ``target.pose`` (:func:`nominal_path`: the compliance centre, or the pivot
  ``point`` of a rotational sub-skill, on straight lines, the orientation slerped about it,
  smoothstep time law at the primitive's ``profile`` speeds), with an ``align``'s search
  sweep (:func:`search_sweep`) added to the position once the path is over;
- under the primitive's ``compliance``: force-controlled rows apply ``forces`` /
  ``torques`` about the centre, position-controlled rows track the path;
- it ends well as soon as one of ``stop.until`` holds for ``stop.confirm`` seconds
  (:func:`_ended`), and fails beyond ``stop.travel``, on a collision (``stop.collision``),
  or after the nominal path plus ``stop.stall`` seconds (jammed).

Playback (:func:`run_playback`): the observed poses are followed by position control with the
same impedance, without force control or guarded stops (the baseline of the benchmark).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from apo.sim.hand import Hand
from apo.typing import FloatArray

__all__ = ["PrimitiveRun", "nominal_path", "run_playback", "run_program", "search_sweep"]

_SETTLE = 0.05
"""Seconds of holding after a playback."""
_SEARCH_GRACE = 0.5
"""Seconds an alignment search waits for the drop after its sweep ends."""
_LEGACY_UNTIL = {
    ("approach", False): ("pose",),
    ("align", False): ("entrance",),
    ("push_to", False): ("force",),
    ("push_to", True): ("pose_in_contact", "torque"),
    ("slide", False): ("force", "expected"),
    ("slide", True): ("pose", "torque"),
    ("release", False): ("expected", "pose"),
    ("release", True): ("expected", "pose"),
}
"""End conditions of programs written before ``stop.until`` existed (``docs/motion.md``)."""


@dataclass
class PrimitiveRun:
    """What happened to one primitive.

    Attributes
    ----------
    index : int
    kind : str
    outcome : str
        ``"contact"`` (guarded stop on the sensed reaction), ``"reached"`` (expected travel or
        target pose), ``"travel"`` (exceeded the travel limit: failure), ``"stall"`` (jammed:
        failure), ``"collision"`` (unexpected contact in free space: failure).
    t_start, t_end : float
        Simulated seconds.
    travel : float
        Metres or radians moved along the direction / about the axis.
    force, torque : float
        Sensed contact force (N) and torque about the centre (N m) at the end, norms.
    """

    index: int
    kind: str
    outcome: str
    t_start: float
    t_end: float
    travel: float
    force: float
    torque: float

    @property
    def ok(self) -> bool:
        """True if the primitive ended as planned."""
        return self.outcome in ("contact", "reached")


Sampler = Callable[[Hand], None]


@dataclass
class _Path:
    """Straight path of the pose: centre point linear, orientation slerped about it."""

    X0: FloatArray
    X1: FloatArray
    center_G: FloatArray
    duration: float
    _rv: FloatArray = field(init=False)

    def __post_init__(self) -> None:
        from scipy.spatial.transform import Rotation

        self._rv = Rotation.from_matrix(self.X1[:3, :3] @ self.X0[:3, :3].T).as_rotvec()

    def at(self, t: float) -> FloatArray:
        from scipy.spatial.transform import Rotation

        u = 1.0 if self.duration <= 0 else min(1.0, max(0.0, t / self.duration))
        s = u * u * (3 - 2 * u)  # smooth start and stop
        R = Rotation.from_rotvec(s * self._rv).as_matrix() @ self.X0[:3, :3]
        c0 = self.X0[:3, :3] @ self.center_G + self.X0[:3, 3]
        c1 = self.X1[:3, :3] @ self.center_G + self.X1[:3, 3]
        c = (1 - s) * c0 + s * c1
        X = np.eye(4)
        X[:3, :3] = R
        X[:3, 3] = c - R @ self.center_G
        return X


def _path(
    X0: FloatArray, X1: FloatArray, center_G: FloatArray, speed: float, angular: float
) -> _Path:
    from scipy.spatial.transform import Rotation

    c0 = X0[:3, :3] @ center_G + X0[:3, 3]
    c1 = X1[:3, :3] @ center_G + X1[:3, 3]
    ang = float(np.linalg.norm(Rotation.from_matrix(X1[:3, :3] @ X0[:3, :3].T).as_rotvec()))
    # the smoothstep peaks at 1.5x the mean speed
    T = 1.5 * max(float(np.linalg.norm(c1 - c0)) / speed, ang / angular, 0.02)
    return _Path(X0, X1, center_G, T)


def _basis(S: FloatArray) -> FloatArray:
    w, V = np.linalg.eigh(S)
    out: FloatArray = V[:, w > 0.5].T
    return out


@dataclass
class _Chain:
    """Paths one after the other."""

    legs: list[_Path]

    @property
    def duration(self) -> float:
        return sum(p.duration for p in self.legs)

    def at(self, t: float) -> FloatArray:
        for p in self.legs[:-1]:
            if t <= p.duration:
                return p.at(t)
            t -= p.duration
        return self.legs[-1].at(t)


def _to_G(X: FloatArray, p: FloatArray) -> FloatArray:
    out: FloatArray = X[:3, :3].T @ (p - X[:3, 3])
    return out


def _angle_about(R0: FloatArray, R: FloatArray, axis: FloatArray) -> float:
    from scipy.spatial.transform import Rotation

    return float(Rotation.from_matrix(R @ R0.T).as_rotvec() @ axis)


def _speeds(prim: Any, pp: Any) -> tuple[float, float]:
    """Return the path speeds (m/s, rad/s): the primitive's ``profile``, else the plan's."""
    pr = getattr(prim, "profile", None)
    if pr is not None:
        return float(pr.speed), float(pr.angular_speed)
    f = getattr(pp, "free_speed_factor", 4.0) if str(prim.kind) == "approach" else 1.0
    return f * pp.speed, f * pp.angular_speed


def nominal_path(
    prim: Any, X0: FloatArray, point_G: FloatArray, speeds: tuple[float, float]
) -> tuple[_Chain, float]:
    """Return the primitive's path from ``X0`` through its ``via`` poses to its target.

    ``point_G`` (object frame) moves on straight lines while the orientation turns about it
    (the compliance centre; the pivot of a rotational sub-skill). Returns the path and the
    time at which its last leg starts (guarded stops and travel count from there).
    """
    legs, X_prev = [], X0
    for X in [*(np.asarray(v, dtype=np.float64) for v in prim.via), prim.target.X_EG]:
        legs.append(_path(X_prev, X, point_G, *speeds))
        X_prev = X
    return _Chain(legs), sum(p.duration for p in legs[:-1])


@dataclass
class _Sweep:
    """Offsets (metres) along a polyline visited at a constant speed."""

    points: FloatArray
    speed: float

    @property
    def duration(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum()) / self.speed

    def at(self, t: float) -> FloatArray:
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        s = t * self.speed
        for k, L in enumerate(seg):
            if s <= L and L > 0:
                out: FloatArray = self.points[k] + (s / L) * (self.points[k + 1] - self.points[k])
                return out
            s -= L
        last: FloatArray = self.points[-1]
        return last


def search_sweep(search: Any) -> _Sweep:
    """Offsets of an alignment search (``Search``): zig-zag, square spiral, or none."""
    B = np.asarray(search.directions, dtype=np.float64).reshape(-1, 3)
    pitch, radius = float(search.pitch), float(search.radius)
    n = round(radius / pitch)
    pts: list[FloatArray] = [np.zeros(3)]
    if search.pattern == "zigzag":
        for k in range(1, n + 1):
            pts.append(((-1) ** k) * k * pitch * B[0])
    elif search.pattern == "spiral":
        x = y = 0.0
        step, k = 1, 0
        while max(abs(x), abs(y)) < radius - 1e-12:
            for axis in range(2):
                sign = 1 if k % 2 == 0 else -1
                if axis == 0:
                    x += sign * step * pitch
                else:
                    y += sign * step * pitch
                pts.append(x * B[0] + y * B[1])
            step, k = step + 1, k + 1
    return _Sweep(np.array(pts), float(search.speed))


@dataclass
class _Control:
    """What the hand is told every step of a primitive (world frame, SI)."""

    center_G: FloatArray
    S_t: FloatArray
    S_r: FloatArray
    force: FloatArray
    torque: FloatArray

    @classmethod
    def of(cls, prim: Any) -> _Control:
        c = prim.compliance
        return cls(
            center_G=_to_G(prim.target.X_EG, np.asarray(c.center, dtype=np.float64)),
            S_t=c.force_directions.T @ c.force_directions,
            S_r=c.torque_axes.T @ c.torque_axes,
            force=c.force_directions.T @ c.forces,
            torque=c.torque_axes.T @ c.torques,
        )


@dataclass
class _Watch:
    """What a primitive has done so far: the quantities its stop conditions look at."""

    t0: float
    guard_from: float
    path_time: float
    X_start: FloatArray
    c_start: FloatArray
    travel: float = 0.0
    drop: float = 0.0
    c_search: FloatArray | None = None
    streak: int = 0
    force: FloatArray = field(default_factory=lambda: np.zeros(3))
    torque: FloatArray = field(default_factory=lambda: np.zeros(3))


def _until(prim: Any) -> tuple[str, ...]:
    until = tuple(getattr(prim.stop, "until", ()) or ())
    return until or _LEGACY_UNTIL.get((str(prim.kind), _rotational(prim)), ("pose",))


def _rotational(prim: Any) -> bool:
    return prim.space is not None and str(prim.space) == "rotation"


def _pose_within(prim: Any, X: FloatArray, ctl: _Control) -> bool:
    """Return whether the pose error is within tolerance in the primitive's own directions."""
    from scipy.spatial.transform import Rotation

    X1 = prim.target.X_EG
    e_p = (X1[:3, :3] @ ctl.center_G + X1[:3, 3]) - (X[:3, :3] @ ctl.center_G + X[:3, 3])
    e_r = Rotation.from_matrix(X1[:3, :3] @ X[:3, :3].T).as_rotvec()
    al, st = prim.alignment, prim.stop
    d = np.asarray(prim.direction, dtype=np.float64)
    if al is not None:
        ok_t = not len(al.translations) or np.max(np.abs(al.translations @ e_p)) <= al.tolerance
        ok_r = not len(al.rotations) or np.max(np.abs(al.rotations @ e_r)) <= al.angular_tolerance
        return bool(ok_t and ok_r)
    if prim.space is None or not np.any(d):
        return bool(
            np.linalg.norm(e_p) <= st.tolerance and np.linalg.norm(e_r) <= st.angular_tolerance
        )
    if _rotational(prim):
        return abs(float(e_r @ d)) <= float(st.angular_tolerance)
    return abs(float(e_p @ d)) <= float(st.tolerance)


def _holds(name: str, prim: Any, w: _Watch, X: FloatArray, ctl: _Control, t: float) -> bool:
    """Return whether the end condition ``name`` (``apo.motion.END_CONDITIONS``) holds now."""
    st = prim.stop
    d = np.asarray(prim.direction, dtype=np.float64)
    if name == "force":
        return float(-(w.force @ d)) >= float(st.force)
    if name == "torque":
        return float(-(w.torque @ d)) >= float(st.torque)
    if name == "expected":
        return w.travel >= float(st.expected)
    if name == "entrance":
        return w.drop >= float(prim.alignment.search.drop)
    over = t >= w.path_time
    if name == "pose":
        return over and _pose_within(prim, X, ctl)
    if name == "pose_in_contact":
        touching = float(np.linalg.norm(w.force)) >= st.touch
        return over and touching and _pose_within(prim, X, ctl)
    raise ValueError(f"unknown end condition {name!r}")


def _sense(prim: Any, ctl: _Control, w: _Watch, X: FloatArray, t: float) -> None:
    """Update travel and drop; the reaction torque about the axis (through ``point``)."""
    c = X[:3, :3] @ ctl.center_G + X[:3, 3]
    if t < w.guard_from:  # travel counts from the end of the via poses
        w.X_start, w.c_start = X, c
    d = np.asarray(prim.direction, dtype=np.float64)
    if _rotational(prim):
        w.travel = _angle_about(w.X_start[:3, :3], X[:3, :3], d)
        if prim.point is not None:  # torque about the axis through the pivot
            w.torque = w.torque + np.cross(c - np.asarray(prim.point), w.force)
    else:
        w.travel = float((c - w.c_start) @ d)
    al = prim.alignment
    if al is not None and al.search is not None and t >= w.path_time:
        if w.c_search is None:  # the search starts where the path ends
            w.c_search = c
        w.drop = float((c - w.c_search) @ np.asarray(al.search.direction))


def _verdict(prim: Any, w: _Watch, X: FloatArray, ctl: _Control, t: float, dt: float) -> str | None:
    """``"contact"``/``"reached"`` (ended well), a failure, or None (go on)."""
    st = prim.stop
    if getattr(st, "collision", str(prim.kind) == "approach") and (
        float(np.linalg.norm(w.force)) > st.force
    ):
        return "collision"
    if t >= w.guard_from and any(_holds(n, prim, w, X, ctl, t) for n in _until(prim)):
        w.streak += 1
    else:
        w.streak = 0
    if w.streak >= max(1, round(getattr(st, "confirm", 0.01) / dt)):
        reactive = {"force", "torque"} & set(_until(prim))
        hit = any(_holds(n, prim, w, X, ctl, t) for n in reactive)
        return "contact" if hit else "reached"
    if np.any(prim.direction) and prim.space is not None and abs(w.travel) > st.travel:
        return "travel"
    return None


def _hold(hand: Hand, ctl: _Control, X: FloatArray, seconds: float, sample: Sampler) -> None:
    """Keep the primitive's compliance at pose ``X`` for ``seconds``."""
    for _ in range(round(seconds / hand.scene.params.timestep)):
        hand.step(X, ctl.center_G, S_t=ctl.S_t, S_r=ctl.S_r, force=ctl.force, torque=ctl.torque)
        sample(hand)


def run_primitive(hand: Hand, prim: Any, pp: Any, sample: Sampler) -> PrimitiveRun:
    """Execute one primitive from the hand's current pose, as the program says.

    ``pp`` are the program's ``PlanParameters`` (speeds of programs without ``profile``,
    the settle time).
    """
    ctl = _Control.of(prim)
    X0 = hand.pose()
    pivot_G = ctl.center_G
    if _rotational(prim) and prim.point is not None:
        pivot_G = _to_G(prim.target.X_EG, np.asarray(prim.point, dtype=np.float64))
    path, guard_from = nominal_path(prim, X0, pivot_G, _speeds(prim, pp))
    al = prim.alignment
    sweep = search_sweep(al.search) if al is not None and al.search is not None else None
    c0 = X0[:3, :3] @ ctl.center_G + X0[:3, 3]
    w = _Watch(hand.time, guard_from, path.duration, X0, c0)
    pr = getattr(prim, "profile", None)
    slow_zone = float(pr.slow_zone) if pr is not None else 0.0
    slow = float(pr.speed / pr.slow_speed) if pr is not None and pr.slow_speed > 0 else 1.0
    extra = sweep.duration + _SEARCH_GRACE if sweep is not None else 0.0
    limit = path.duration + extra + float(getattr(prim.stop, "stall", 3.0))
    outcome, dt = "stall", hand.scene.params.timestep
    while hand.time - w.t0 < limit:
        t = hand.time - w.t0
        X_des = path.at(t)
        if sweep is not None and t >= path.duration:
            X_des = X_des.copy()
            X_des[:3, 3] += sweep.at(t - path.duration)
            if t > path.duration + extra:
                break  # the search swept everything without finding the entrance
        near = slow_zone > 0 and w.travel > prim.stop.expected - slow_zone
        w.force, w.torque = hand.step(
            X_des, ctl.center_G, S_t=ctl.S_t, S_r=ctl.S_r, force=ctl.force, torque=ctl.torque,
            slow=slow if near else 1.0,
        )  # fmt: skip
        sample(hand)
        X = hand.pose()
        _sense(prim, ctl, w, X, t)
        verdict = _verdict(prim, w, X, ctl, t, dt)
        if verdict is not None:
            outcome = verdict
            break
    if outcome in ("contact", "reached"):
        _hold(hand, ctl, hand.pose(), float(getattr(pp, "settle_time", _SETTLE)), sample)
    return PrimitiveRun(
        prim.index, str(prim.kind), outcome, w.t0, hand.time, float(w.travel),
        float(np.linalg.norm(w.force)), float(np.linalg.norm(w.torque)),
    )  # fmt: skip


def run_program(hand: Hand, program: Any, sample: Sampler) -> list[PrimitiveRun]:
    """Execute every primitive of ``program`` in order; stop at the first failure."""
    runs: list[PrimitiveRun] = []
    for prim in program.primitives:
        run = run_primitive(hand, prim, program.parameters, sample)
        runs.append(run)
        if not run.ok:
            break
    return runs


def run_playback(
    hand: Hand,
    times: Sequence[float] | FloatArray,
    X_EG: Sequence[FloatArray] | FloatArray,
    center_G: FloatArray,
    sample: Sampler,
    *,
    speeds: tuple[float, float] = (0.02, 0.35),
) -> list[PrimitiveRun]:
    """Follow the observed poses by position control (the baseline).

    The hand first moves to the first pose at ``speeds``, then follows the poses piecewise
    linearly in time (at the demonstration's pace, no faster than ``speeds``).
    """
    runs: list[PrimitiveRun] = []
    X_prev = hand.pose()
    for k, X1 in enumerate(X_EG):
        X1 = np.asarray(X1, dtype=np.float64)
        path = _path(X_prev, X1, center_G, *speeds)
        dt_demo = 0.0 if k == 0 else float(times[k] - times[k - 1])
        duration = max(path.duration, dt_demo)
        path = _Path(X_prev, X1, center_G, duration)
        t0 = hand.time
        Fc, Tc = np.zeros(3), np.zeros(3)
        while hand.time - t0 < duration:
            Fc, Tc = hand.step(path.at(hand.time - t0), center_G)
            sample(hand)
        runs.append(
            PrimitiveRun(k, "pose", "reached", t0, hand.time, 0.0,
                         float(np.linalg.norm(Fc)), float(np.linalg.norm(Tc)))
        )  # fmt: skip
        X_prev = X1
    for _ in range(round(_SETTLE / hand.scene.params.timestep)):
        hand.step(X_prev, center_G)
        sample(hand)
    return runs
