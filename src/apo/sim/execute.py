"""Execution of a skill program (and of the observed poses) by the compliant hand.

Each primitive of :class:`apo.motion.SkillProgram` becomes a run of control steps of
:class:`apo.sim.hand.Hand` (``docs/sim.md``):

- ``approach``, ``align``: the position-controlled part of the pose follows a straight
  path (centre point linear, orientation about it) to the target at the plan's speeds; it
  ends when the target is reached within tolerance (``align``: the alignment tolerance in
  its directions). A contact force above the stop force during an approach is a collision.
- ``push_to``: a guarded move. The directions of the primitive's compliance are force
  controlled (the push along the direction or about the axis, the holding forces into the
  kept contacts), the rest follow the path to the planned target. It ends when the sensed
  reaction against the motion (contact force along ``-direction``, or contact torque about
  the axis against the push) exceeds the stop force (torque); travelling farther than the
  stop travel without that is a failure.
- ``slide``: the same control; it ends when the expected travel is done, or earlier on the
  reaction (blocked by a new contact); beyond the stop travel it fails.
- ``release``: the direction is position-controlled away from the contact; it ends when the
  expected travel is done.

None of them stops on a time-out; a primitive that neither ends nor fails within
``nominal time + STALL_TIME`` has stalled (jammed) and fails.

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

__all__ = ["STALL_TIME", "PrimitiveRun", "run_playback", "run_program"]

STALL_TIME = 3.0
"""Seconds a primitive may run beyond its nominal duration before it counts as jammed."""
ROTATE_SLIDES_BY_POSITION = True
"""Execute a rotational slide by a position-controlled turn about its axis (see module doc)."""
_CONFIRM = 10
"""Steps a stop condition must hold in a row (filters contact impacts)."""
_REACH_TOL = 2e-4
"""Position tolerance (m) of approach targets; rotations: _REACH_TOL / object size."""
_SETTLE = 0.05
"""Seconds of holding after each primitive."""
_SETTLED = 0.01
"""Angular speed (rad/s) below which a type I rotational push-to has settled."""
_TOUCH = 0.5
"""Contact force (N) that counts as touching when a type I push-to settles."""
_ANGLE_MARGIN = 0.087
"""Radians added to the angle of a position-controlled turn for its travel limit."""
_ANGLE_TOL = 0.035
"""Radians: a position-controlled rotational slide has arrived when this close to its target
orientation about the axis (the plan's orientation may be off by the environment's offset)."""


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


def _with_axis(S: FloatArray, d: FloatArray) -> FloatArray:
    """Projector on span(S) + d."""
    return _projector(np.vstack([_basis(S), d]))


def _without_axis(S: FloatArray, d: FloatArray) -> FloatArray:
    """Projector on span(S) minus its component along d."""
    B = _basis(S)
    B = B - np.outer(B @ d, d)
    return _projector(B)


def _basis(S: FloatArray) -> FloatArray:
    w, V = np.linalg.eigh(S)
    out: FloatArray = V[:, w > 0.5].T
    return out


def _projector(rows: FloatArray) -> FloatArray:
    if rows.size == 0:
        return np.zeros((3, 3))
    u, sv, _ = np.linalg.svd(rows.T, full_matrices=False)
    U = u[:, sv > 1e-9 * max(1.0, float(sv.max()))]
    out: FloatArray = U @ U.T
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


def _approach_path(
    prim: Any,
    X0: FloatArray,
    center_G: FloatArray,
    speeds: tuple[float, float],
    up: FloatArray | None,
) -> _Chain:
    """Path of an approach: through the primitive's ``via`` poses if any, else lift first.

    Without via poses the object first moves along ``up`` (the reverse of the first
    translational push-to that follows) until it is level with the stand-off pose, then goes
    straight: leaving a resting place sideways through the environment is the usual way a
    straight approach collides.
    """
    goals = [np.asarray(X, dtype=np.float64) for X in getattr(prim, "via", ())]
    goals.append(prim.target.X_EG)
    if not goals[:-1] and up is not None and np.linalg.norm(up) > 0:
        c0 = X0[:3, :3] @ center_G + X0[:3, 3]
        c1 = goals[-1][:3, :3] @ center_G + goals[-1][:3, 3]
        rise = float((c1 - c0) @ up)
        if rise > 0:
            X_up = X0.copy()
            X_up[:3, 3] += rise * np.asarray(up)
            goals.insert(0, X_up)
    legs, X_prev = [], X0
    for X in goals:
        legs.append(_path(X_prev, X, center_G, *speeds))
        X_prev = X
    return _Chain(legs)


def _via_path(
    prim: Any, X0: FloatArray, center_G: FloatArray, speeds: tuple[float, float]
) -> _Chain:
    """Path through the poses of the folded transitions (``prim.via``) to the target."""
    legs, X_prev = [], X0
    for X in [*(np.asarray(v, dtype=np.float64) for v in prim.via), prim.target.X_EG]:
        legs.append(_path(X_prev, X, center_G, *speeds))
        X_prev = X
    return _Chain(legs)


def _to_G(X: FloatArray, p: FloatArray) -> FloatArray:
    out: FloatArray = X[:3, :3].T @ (p - X[:3, 3])
    return out


def _angle_about(R0: FloatArray, R: FloatArray, axis: FloatArray) -> float:
    from scipy.spatial.transform import Rotation

    return float(Rotation.from_matrix(R @ R0.T).as_rotvec() @ axis)


def _hold(hand: Hand, prim: Any, X: FloatArray, center_G: FloatArray, sample: Sampler) -> None:
    """Keep the primitive's compliance at pose ``X`` for :data:`_SETTLE` seconds."""
    comp = prim.compliance
    St, Sr = comp.force_directions.T @ comp.force_directions, comp.torque_axes.T @ comp.torque_axes
    f, t = comp.force_directions.T @ comp.forces, comp.torque_axes.T @ comp.torques
    n = round(_SETTLE / hand.scene.params.timestep)
    for _ in range(n):
        hand.step(X, center_G, S_t=St, S_r=Sr, force=f, torque=t)
        sample(hand)


def _expected(prim: Any, X_from: FloatArray, center_G: FloatArray) -> float:
    """Return the expected travel of a primitive (metres or radians), from the plan."""
    e = getattr(prim.stop, "expected", None)
    if e is not None:
        return float(e)
    d = prim.direction
    X1 = prim.target.X_EG
    if prim.space is not None and str(prim.space) == "rotation":
        return abs(_angle_about(X_from[:3, :3], X1[:3, :3], d))
    c0 = X_from[:3, :3] @ center_G + X_from[:3, 3]
    c1 = X1[:3, :3] @ center_G + X1[:3, 3]
    return abs(float((c1 - c0) @ d))


def run_primitive(
    hand: Hand,
    prim: Any,
    X_plan: FloatArray,
    speeds: tuple[float, float],
    sample: Sampler,
    up: FloatArray | None = None,
) -> PrimitiveRun:
    """Execute one primitive from the hand's current pose; return what happened.

    ``X_plan`` is the planned pose at the primitive's start (for the expected travel);
    ``speeds`` the plan's ``(speed m/s, angular_speed rad/s)``; ``up`` the direction an
    approach leaves along first (:func:`_approach_path`).
    """
    kind = str(prim.kind)
    comp = prim.compliance
    X0 = hand.pose()
    center_G = _to_G(prim.target.X_EG, comp.center)
    path: _Path | _Chain = _path(X0, prim.target.X_EG, center_G, *speeds)
    guard_from = 0.0  # guarded stops apply once the via poses (folded transitions) are passed
    if kind == "approach":
        path = _approach_path(prim, X0, center_G, speeds, up)
    elif len(getattr(prim, "via", ())):
        path = _via_path(prim, X0, center_G, speeds)
        guard_from = sum(p.duration for p in path.legs[:-1])
    St = comp.force_directions.T @ comp.force_directions
    Sr = comp.torque_axes.T @ comp.torque_axes
    f_cmd = comp.force_directions.T @ comp.forces
    t_cmd = comp.torque_axes.T @ comp.torques
    d = np.asarray(prim.direction, dtype=np.float64)
    rot = prim.space is not None and str(prim.space) == "rotation"
    # type I: the axis detaches both ways, a torque about it only tips the object over an
    # end of the contact; the push-to lets the contact settle flush instead (zero torque)
    settle = kind == "push_to" and rot and prim.type is not None and str(prim.type) == "I"
    if settle:
        t_cmd = t_cmd - d * (d @ t_cmd)
        Sr = _with_axis(Sr, d)
    turn = kind == "slide" and rot and ROTATE_SLIDES_BY_POSITION
    travel_limit = prim.stop.travel
    if turn:
        # the turn goes to the target orientation whatever the sign of the recorded axis:
        # its safeguard is the angle to that orientation (plus the plan's margin)
        to_go = abs(_angle_about(X0[:3, :3], prim.target.X_EG[:3, :3], d))
        travel_limit = max(travel_limit, to_go + _ANGLE_MARGIN)
        d = d if _angle_about(X0[:3, :3], prim.target.X_EG[:3, :3], d) >= 0 else -d
        # a rotational slide turns by the planned angle under position control about its
        # axis (the rest stays as planned): a pure torque wedges the object (docs/sim.md)
        t_cmd = t_cmd - d * (d @ t_cmd)
        Sr = _without_axis(Sr, d)
    c_start = X0[:3, :3] @ center_G + X0[:3, 3]
    expected = _expected(prim, X_plan, center_G)
    t0 = hand.time
    limit = path.duration + STALL_TIME
    streak, outcome, travel = 0, "stall", 0.0
    Fc, Tc = np.zeros(3), np.zeros(3)
    dt = hand.scene.params.timestep
    size = max(1e-3, float(np.linalg.norm(center_G)))
    while hand.time - t0 < limit:
        X_des = path.at(hand.time - t0)
        Fc, Tc = hand.step(X_des, center_G, S_t=St, S_r=Sr, force=f_cmd, torque=t_cmd)
        sample(hand)
        X = hand.pose()
        c = X[:3, :3] @ center_G + X[:3, 3]
        travel = _angle_about(X0[:3, :3], X[:3, :3], d) if rot else float((c - c_start) @ d)
        if kind in ("approach", "align"):
            if kind == "approach" and np.linalg.norm(Fc) > prim.stop.force:
                outcome = "collision"
                break
            done = hand.time - t0 >= path.duration and _reached(prim, X, center_G, size)
        elif kind == "release":
            done = travel >= expected and hand.time - t0 >= path.duration
        else:
            if settle:
                w, _ = hand.velocity(c)
                hit = np.linalg.norm(Fc) >= _TOUCH and abs(float(w @ d)) < _SETTLED
            elif rot:
                hit = float(-(Tc @ d)) >= prim.stop.torque
            else:
                hit = float(-(Fc @ d)) >= prim.stop.force
            if hit and hand.time - t0 >= guard_from:
                streak += 1
            else:
                streak = 0
            if streak >= _CONFIRM:
                outcome = "contact"
                break
            if abs(travel) > travel_limit:
                outcome = "travel"
                break
            if kind == "slide" and turn:
                # arrived at the planned orientation about the axis (within the offset)
                done = hand.time - t0 >= path.duration and (
                    abs(_angle_about(X[:3, :3], prim.target.X_EG[:3, :3], d)) <= _ANGLE_TOL
                )
            else:
                done = kind == "slide" and travel >= expected
        if done:
            outcome = "reached"
            break
    del dt
    if outcome in ("contact", "reached"):
        _hold(hand, prim, hand.pose(), center_G, sample)
    return PrimitiveRun(
        prim.index,
        kind,
        outcome,
        t0,
        hand.time,
        float(travel),
        float(np.linalg.norm(Fc)),
        float(np.linalg.norm(Tc)),
    )


def _reached(prim: Any, X: FloatArray, center_G: FloatArray, size: float) -> bool:
    """Target pose reached (align: within its tolerance in its directions)."""
    from scipy.spatial.transform import Rotation

    X1 = prim.target.X_EG
    e_p = (X1[:3, :3] @ center_G + X1[:3, 3]) - (X[:3, :3] @ center_G + X[:3, 3])
    e_r = Rotation.from_matrix(X1[:3, :3] @ X[:3, :3].T).as_rotvec()
    al = prim.alignment
    if al is not None:
        ok_t = not len(al.translations) or np.max(np.abs(al.translations @ e_p)) <= al.tolerance
        ok_r = not len(al.rotations) or np.max(np.abs(al.rotations @ e_r)) <= al.angular_tolerance
        return bool(ok_t and ok_r)
    return bool(np.linalg.norm(e_p) <= _REACH_TOL and np.linalg.norm(e_r) <= _REACH_TOL / size)


def align_in_contact(
    hand: Hand, prim: Any, entrance: FloatArray, push: float, sample: Sampler
) -> PrimitiveRun:
    """Align by compliance while touching: the contacts centre the object.

    The alignment directions and axes are force controlled with zero force and torque (free
    to move), the object is pushed lightly (``push`` N) along ``entrance`` (the direction of
    the critical move that follows), every other direction holds the current pose. It ends
    when the object has settled in the alignment directions (speeds below
    ``_REACH_TOL`` per second and :data:`_SETTLED` rad/s for ``_CONFIRM`` steps).
    """
    al = prim.alignment
    X0 = hand.pose()
    center_G = _to_G(prim.target.X_EG, prim.compliance.center)
    T = np.vstack([al.translations.reshape(-1, 3), entrance.reshape(-1, 3)])
    St = T.T @ np.linalg.pinv(T @ T.T) @ T
    Sr = al.rotations.T @ al.rotations if len(al.rotations) else np.zeros((3, 3))
    f = push * entrance
    t0, streak = hand.time, 0
    Fc, Tc = np.zeros(3), np.zeros(3)
    while hand.time - t0 < STALL_TIME:
        Fc, Tc = hand.step(X0, center_G, S_t=St, S_r=Sr, force=f)
        sample(hand)
        X = hand.pose()
        w, v = hand.velocity(X[:3, :3] @ center_G + X[:3, 3])
        vt = al.translations @ v if len(al.translations) else np.zeros(0)
        wr = al.rotations @ w if len(al.rotations) else np.zeros(0)
        still = np.all(np.abs(vt) < _REACH_TOL) and np.all(np.abs(wr) < _SETTLED)
        streak = streak + 1 if still else 0
        if streak >= 5 * _CONFIRM:
            break
    outcome = "reached" if streak >= 5 * _CONFIRM else "stall"
    return PrimitiveRun(prim.index, "align", outcome, t0, hand.time, 0.0,
                        float(np.linalg.norm(Fc)), float(np.linalg.norm(Tc)))  # fmt: skip


def _entrance(program: Any, k: int) -> FloatArray:
    """Direction of the first translational move after primitive ``k`` (zeros if none)."""
    for p in program.primitives[k + 1 :]:
        if p.space is not None and str(p.space) == "translation":
            return np.asarray(p.direction, dtype=np.float64)
    return np.zeros(3)


def run_program(hand: Hand, program: Any, sample: Sampler) -> list[PrimitiveRun]:
    """Execute every primitive of ``program`` in order; stop at the first failure.

    An ``align`` aligns by compliance (:func:`align_in_contact`), not by servoing to the
    planned aligned pose: with an environment the plan does not know exactly (an offset
    larger than the clearance), only the contacts can tell where the entrance is, and the
    object may already have passed it during the previous move.
    """
    pp = program.parameters
    speeds = (pp.speed, pp.angular_speed)
    runs: list[PrimitiveRun] = []
    X_plan = program.start_X_EG
    pushes = [
        p.direction
        for p in program.primitives
        if str(p.kind) == "push_to" and p.space is not None and str(p.space) == "translation"
    ]
    up = -np.asarray(pushes[0], dtype=np.float64) if pushes else None
    for k, prim in enumerate(program.primitives):
        if str(prim.kind) == "align" and prim.alignment is not None:
            run = align_in_contact(hand, prim, _entrance(program, k), pp.hold_force, sample)
        else:
            run = run_primitive(hand, prim, X_plan, speeds, sample, up)
        runs.append(run)
        X_plan = prim.target.X_EG
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
