"""Plan a skill program from a task model (``docs/motion.md``).

:func:`plan` walks the task's transitions in order and emits one primitive per sub-skill
(``push_to``, ``slide``, ``release``), preceded by an ``approach`` through free space to a
stand-off before the first contact and by an ``align`` before each critical transition
(SM -> C, SD -> C). Transitions without a sub-skill (SM -> M and the like) are folded into
the next primitive (paper 3.5). Every direction, axis, force and tolerance comes from the
task model's geometry: the sub-skills' directions, points and subspaces, the elements'
separating normals and the DOF subspaces of the states (:func:`apo.dof.analyze`).

SI units and the environment frame throughout; no simulator and no I/O here.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from apo.dof import analyze
from apo.errors import InputFormatError
from apo.motion.program import (
    Alignment,
    Compliance,
    MotionSpace,
    PlanParameters,
    Primitive,
    PrimitiveKind,
    Profile,
    RotationType,
    Search,
    SkillProgram,
    StopCondition,
    Target,
)
from apo.spatial import invert_pose, matrix_from_axis_angle
from apo.task import Element, ModelRef, State, SubSkill, TaskModel
from apo.typing import FloatArray

__all__ = ["plan"]

_EPS = 1e-9
_RANK_TOL = 1e-6


# --------------------------------------------------------------------------------------------
# Small geometry helpers
# --------------------------------------------------------------------------------------------


def _unit(v: npt.ArrayLike | None) -> FloatArray | None:
    if v is None:  # a sub-skill direction the analysis could not determine
        return None
    a = np.asarray(v, dtype=float)
    n = float(np.linalg.norm(a))
    return None if n < _EPS else a / n


def _basis(rows: Sequence[FloatArray] | FloatArray) -> FloatArray:
    """Orthonormal rows spanning ``rows`` (empty (0, 3) if they span nothing)."""
    a = np.asarray(rows, dtype=float).reshape(-1, 3)
    if a.size == 0:
        return np.zeros((0, 3))
    _, s, vt = np.linalg.svd(a)
    r = int(np.sum(s > _RANK_TOL * max(1.0, float(s[0]))))
    return np.asarray(vt[:r], dtype=float)


def _complement(basis: FloatArray) -> FloatArray:
    """Orthonormal rows spanning the orthogonal complement of ``basis`` in R^3."""
    if basis.shape[0] == 0:
        return np.eye(3)
    _, _, vt = np.linalg.svd(np.vstack([basis, np.zeros((3 - basis.shape[0], 3))]))
    return np.asarray(vt[basis.shape[0] :], dtype=float)


def _remove(rows: FloatArray, span: FloatArray) -> FloatArray:
    """Orthonormal rows of ``rows`` minus their components in ``span``."""
    if rows.shape[0] == 0 or span.shape[0] == 0:
        return _basis(rows)
    return _basis(rows - rows @ span.T @ span)


def _translate(X: FloatArray, t: FloatArray) -> FloatArray:
    out = X.copy()
    out[:3, 3] += t
    return out


def _rotate_about(X: FloatArray, axis: FloatArray, point: FloatArray, angle: float) -> FloatArray:
    """``X`` turned by ``angle`` about the line through ``point`` along ``axis`` (in E)."""
    R = matrix_from_axis_angle(axis, angle)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = point - R @ point
    return T @ X


def _rotvec(X_from: FloatArray, X_to: FloatArray) -> FloatArray:
    """Rotation vector of ``R_to R_from^T`` (environment frame, rad)."""
    return np.asarray(Rotation.from_matrix(X_to[:3, :3] @ X_from[:3, :3].T).as_rotvec())


def _moved(X_from: FloatArray, X_to: FloatArray, p: FloatArray) -> FloatArray:
    """Where the point of G that is at ``p`` at ``X_to`` was at ``X_from``."""
    q = invert_pose(X_to) @ np.append(p, 1.0)
    return np.asarray((X_from @ q)[:3])


# --------------------------------------------------------------------------------------------
# Contacts of the task
# --------------------------------------------------------------------------------------------


def _key(e: Element) -> tuple[str, tuple[str, int], tuple[str, int]]:
    return (e.kind, e.grasped, e.environment)


def _kept(a: State, b: State) -> list[Element]:
    """Elements of ``b`` that ``a`` has too (the maintained contacts)."""
    keys = {_key(e) for e in a.elements}
    return [e for e in b.elements if _key(e) in keys]


def _new(a: State, b: State) -> list[Element]:
    """Elements of ``b`` that ``a`` does not have."""
    keys = {_key(e) for e in a.elements}
    return [e for e in b.elements if _key(e) not in keys]


def _centroid(elements: Sequence[Element]) -> FloatArray | None:
    if not elements:
        return None
    return np.asarray(np.mean([e.point for e in elements], axis=0), dtype=float)


def _normals(elements: Sequence[Element]) -> FloatArray:
    if not elements:
        return np.zeros((0, 3))
    return np.vstack([e.normals for e in elements])


def _constrained(state: State) -> tuple[FloatArray, FloatArray]:
    """Regular constraining subspaces (translation, rotation axes) of a state's contacts."""
    if not state.elements:
        return np.zeros((0, 3)), np.zeros((0, 3))
    res = analyze(state.elements)  # contact elements are DOF-analysis contact points
    g = res.geometry
    return np.asarray(g.translation_constraining), np.asarray(g.rotation_constraining)


# --------------------------------------------------------------------------------------------
# Poses along a transition
# --------------------------------------------------------------------------------------------


def _angle_about(X_from: FloatArray, X_to: FloatArray, axis: FloatArray) -> float:
    """Non-negative angle the motion ``X_from -> X_to`` turns about ``axis`` (rad)."""
    return max(0.0, float(_rotvec(X_from, X_to) @ axis))


def _intermediate_poses(
    X_start: FloatArray, X_end: FloatArray, subskills: Sequence[SubSkill], ref: FloatArray
) -> list[FloatArray]:
    """Target pose of each sub-skill of a transition, the last being ``X_end``.

    Walks backwards from ``X_end``: before a rotational sub-skill the object is turned
    back about its axis through its point by the angle the demonstration turns about that
    axis; before a translational one it is moved back along its direction by the distance
    the point ``ref`` (at ``X_end``) travels along it.
    """
    poses = [X_end]
    for u in reversed(subskills[1:]):
        d = _unit(u.direction)
        X = poses[0]
        if d is not None and u.space == "rotation":
            pivot = u.point if u.point is not None else ref
            X = _rotate_about(X, d, pivot, -_angle_about(X_start, X, d))
        elif d is not None:
            step = max(0.0, float((ref - _moved(X_start, X_end, ref)) @ d))
            X = _translate(X, -step * d)
        poses.insert(0, X)
    return poses


# --------------------------------------------------------------------------------------------
# Compliance, stop condition
# --------------------------------------------------------------------------------------------


@dataclass
class _Split:
    """Force-controlled rows and the wrench wanted, gathered before orthonormalising."""

    force_rows: list[FloatArray] = field(default_factory=list)
    force: FloatArray = field(default_factory=lambda: np.zeros(3))
    torque_rows: list[FloatArray] = field(default_factory=list)
    torque: FloatArray = field(default_factory=lambda: np.zeros(3))
    position_only_t: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    position_only_r: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))

    def compliance(self, center: FloatArray) -> Compliance:
        Ft = _remove(_basis(self.force_rows), self.position_only_t)
        Fr = _remove(_basis(self.torque_rows), self.position_only_r)
        return Compliance(
            center=center,
            force_directions=Ft,
            forces=Ft @ self.force,
            torque_axes=Fr,
            torques=Fr @ self.torque,
            position_directions=_complement(Ft),
            position_axes=_complement(Fr),
        )


def _position_only(center: FloatArray) -> Compliance:
    return _Split().compliance(center)


def _hold(
    split: _Split,
    kept: Sequence[Element],
    center: FloatArray,
    free: FloatArray,
    pp: PlanParameters,
    carry: FloatArray,
) -> None:
    """Force control into the kept contacts; torque control (zero) about their moment axes.

    ``free`` is the unit direction of motion (or zeros): the holding force is taken
    orthogonal to it. Opposing normals (walls on both sides) cancel: those directions are
    force-controlled with zero force, i.e. compliant. ``carry`` moves the kept contact
    points (recorded at the start state's pose) to the target pose, where ``center`` is.
    """
    N = _normals(kept)
    if N.shape[0] == 0:
        return
    rows = N - np.outer(N @ free, free)
    split.force_rows.extend(rows)
    s = rows.sum(axis=0)
    us = _unit(s)
    if us is not None and float(np.linalg.norm(s)) > 0.5:
        split.force = split.force - pp.hold_force * us
    for e in kept:
        for n in e.normals:
            m = np.cross((carry @ np.append(e.point, 1.0))[:3] - center, n)
            if np.linalg.norm(m) > _RANK_TOL:
                split.torque_rows.append(m)


_UNTIL = {
    (PrimitiveKind.PUSH_TO, False): ("force",),
    (PrimitiveKind.PUSH_TO, True): ("pose_in_contact", "torque"),
    (PrimitiveKind.SLIDE, False): ("force", "expected"),
    (PrimitiveKind.SLIDE, True): ("pose", "torque"),
    (PrimitiveKind.RELEASE, False): ("expected", "pose"),
    (PrimitiveKind.RELEASE, True): ("expected", "pose"),
}
"""What ends a sub-skill primitive well, by (kind, rotational) (``docs/motion.md``)."""


def _stop(
    kind: PrimitiveKind, rot: bool, expected: float, pp: PlanParameters, **more: object
) -> StopCondition:
    """Stop condition of a guarded move: thresholds, travel limit, end conditions."""
    margin = pp.angular_margin if rot else pp.travel_margin
    if kind == PrimitiveKind.RELEASE and not rot:
        expected = max(expected, pp.standoff)
    fields: dict[str, object] = {
        "until": _UNTIL.get((kind, rot), ("pose",)),
        "tolerance": pp.reach_tolerance,
        "angular_tolerance": pp.turn_tolerance,
        "touch": pp.touch_force,
        "confirm": pp.confirm_time,
        "stall": pp.stall_time,
        **more,
    }
    return StopCondition(
        force=pp.force_threshold,
        torque=pp.torque_threshold,
        travel=expected + margin,
        expected=expected,
        **fields,  # type: ignore[arg-type]
    )


def _profile(kind: PrimitiveKind, rot: bool, pp: PlanParameters) -> Profile:
    """Speeds of a primitive's path: free-space moves faster, a push-to slows before contact."""
    if kind == PrimitiveKind.APPROACH:
        f = pp.free_speed_factor
        return Profile(speed=f * pp.speed, angular_speed=f * pp.angular_speed)
    slow = kind == PrimitiveKind.PUSH_TO and not rot
    return Profile(
        speed=pp.speed,
        angular_speed=pp.angular_speed,
        slow_zone=pp.slow_zone if slow else 0.0,
        slow_speed=pp.slow_speed if slow else 0.0,
    )


# --------------------------------------------------------------------------------------------
# Primitives
# --------------------------------------------------------------------------------------------


@dataclass
class _Cursor:
    """State of the walk: the nominal pose reached, the transitions awaiting a primitive."""

    X: FloatArray
    state: State
    folded: list[int] = field(default_factory=list)
    align_for: int | None = None
    out: list[Primitive] = field(default_factory=list)


def _checked_sign(
    u: SubSkill,
    d: FloatArray | None,
    X_start: FloatArray,
    X_target: FloatArray,
    center: FloatArray,
    pp: PlanParameters,
) -> tuple[FloatArray | None, str]:
    """Return the sub-skill's direction, reversed if the demonstration clearly moves against it.

    The sign from the contacts is reliable in one dimension but only indicative inside a
    larger subspace (``docs/transitions.md``); when the demonstrated motion from the
    primitive's start to its target goes the other way by more than half the travel margin,
    the observed sign wins and ``source`` becomes ``"poses"``.
    """
    if d is None:
        return None, u.source
    if u.space == "rotation":
        # a turn is position-controlled to the target orientation: its axis takes the sense
        # the demonstration turns in (the reaction torque it is guarded by opposes that)
        s, limit = float(_rotvec(X_start, X_target) @ d), 1e-9
    else:
        s, limit = float((center - _moved(X_start, X_target, center)) @ d), 0.5 * pp.travel_margin
    return (-d, "poses") if s < -limit else (d, u.source)


def _center(
    kept: Sequence[Element], a: State, b: State, kind: PrimitiveKind, X_target: FloatArray
) -> FloatArray:
    """Compliance centre of a sub-skill primitive: where its force acts, torques are about.

    The centroid of the contacts kept during the motion (its support), else of the contacts
    it is about (new ones; lost ones for a release), else the target's origin. The wrench a
    primitive commands is a force through this point with zero torque about the kept
    contacts' moment axes; through the support's centroid that force tilts the object about
    no edge of the support (the hold force presses the support flat and a push along it
    acts in its plane), whereas a force applied away from it, e.g. at the new contact a
    push is heading for, tips the object over the support's edge (nothing resists a
    torque-free axis: the block pushed into a wall fell over).
    """
    c_kept = _centroid(kept)
    if c_kept is not None:  # at the start state's pose: carried with the object to the target
        return _moved(X_target, a.X_EG, c_kept)
    release = kind == PrimitiveKind.RELEASE
    focus, at = (_new(b, a), a) if release else (_new(a, b), b)
    if not focus:
        focus, at = list(b.elements), b
    c0 = _centroid(focus)
    return X_target[:3, 3].copy() if c0 is None else _moved(X_target, at.X_EG, c0)


def _subskill_primitive(
    task: TaskModel,
    i: int,
    j: int,
    X_start: FloatArray,
    X_target: FloatArray,
    held: FloatArray | None,
    pp: PlanParameters,
) -> Primitive:
    """Return the primitive of sub-skill ``j`` of transition ``i`` (``X_start`` to ``X_target``)."""
    tr = task.transitions[i]
    u = tr.subskills[j]
    a, b = task.state(tr.from_id), task.state(tr.to_id)
    kind = PrimitiveKind(u.kind)
    rot = u.space == "rotation"
    d = _unit(u.direction)
    dz = np.zeros(3) if d is None else d
    # contacts kept during the motion: all of the start state's, except those a release
    # breaks (a slide keeps its support until the very end, where the support ends)
    kept = _kept(a, b) if kind == PrimitiveKind.RELEASE else list(a.elements)
    center = _center(kept, a, b, kind, X_target)
    carry = X_target @ invert_pose(a.X_EG)  # start state's contact points to the target pose
    d, source = _checked_sign(u, d, X_start, X_target, center, pp)
    dz = np.zeros(3) if d is None else d
    split = _Split()
    if rot:
        expected = 0.0 if d is None else _angle_about(X_start, X_target, d)
        if d is not None:  # turned by position control (push-to, slide: guarded by contact)
            split.position_only_r = d[None, :]
        _hold(split, kept, center, np.zeros(3), pp, carry)
        if held is not None:
            split.force_rows.append(held)
            split.force = split.force + pp.hold_force * held
    else:
        expected = abs(float((center - _moved(X_start, X_target, center)) @ dz))
        if d is not None and kind != PrimitiveKind.RELEASE:
            split.force_rows.append(d)
            split.force = split.force + pp.push_force * d
        elif d is not None:
            split.position_only_t = d[None, :]
        _hold(split, kept, center, dz, pp, carry)
    return Primitive(
        index=0,
        kind=kind,
        space=MotionSpace(u.space),
        type=None if u.type is None else RotationType(u.type),
        transition=i,
        from_state=tr.from_id,
        to_state=tr.to_id,
        folded=(),
        direction=dz,
        point=None if not rot or u.point is None else np.asarray(u.point, dtype=float),
        subspace=np.asarray(u.subspace, dtype=float).reshape(-1, 3),
        source=source,
        target=Target(state=b.id, elements=b.elements, X_EG=X_target),
        stop=_stop(kind, rot, expected, pp),
        compliance=split.compliance(center),
        profile=_profile(kind, rot, pp),
    )


def _position_controlled(
    kind: PrimitiveKind,
    state: State,
    X: FloatArray,
    center: FloatArray,
    expected: float,
    pp: PlanParameters,
) -> Primitive:
    """Return a position-controlled move (approach, align) to ``X``, staying in ``state``."""
    return Primitive(
        index=0,
        kind=kind,
        space=None,
        type=None,
        transition=None,
        from_state=state.id,
        to_state=state.id,
        folded=(),
        direction=np.zeros(3),
        point=None,
        subspace=np.zeros((0, 3)),
        source="plan",
        target=Target(state=state.id, elements=state.elements, X_EG=X),
        stop=replace(
            _stop(kind, False, expected, pp),
            until=("pose",),
            collision=kind == PrimitiveKind.APPROACH,
        ),
        compliance=_position_only(center),
        profile=_profile(kind, False, pp),
    )


def _align_rotation(
    X: FloatArray, X_goal: FloatArray, axes: FloatArray, pivot: FloatArray
) -> FloatArray:
    """Turn ``X`` about ``pivot`` until the rotation left to ``X_goal`` has no part on ``axes``.

    Rotations do not commute, so one step by the projected rotation vector leaves a second
    order residue; a few fixed-point steps remove it (to 1e-12 rad).
    """
    for _ in range(50):
        w = _rotvec(X, X_goal)
        w_a = axes.T @ (axes @ w) if axes.shape[0] else np.zeros(3)
        angle = float(np.linalg.norm(w_a))
        if angle < 1e-13:
            break
        X = _rotate_about(X, w_a / angle, pivot, angle)
    return X


def _align_primitive(task: TaskModel, i: int, X_start: FloatArray, pp: PlanParameters) -> Primitive:
    """``align`` before critical transition ``i``: match its target pose where it constrains."""
    tr = task.transitions[i]
    a, b = task.state(tr.from_id), task.state(tr.to_id)
    ct_a, cr_a = _constrained(a)
    ct_b, cr_b = _constrained(b)
    T, Rr = _remove(ct_b, ct_a), _remove(cr_b, cr_a)
    c = _centroid(b.elements)
    ref = b.X_EG[:3, 3].copy() if c is None else c
    # where the entrance point of G is now, then turn about it and move it in T only
    here = _moved(X_start, b.X_EG, ref)
    X = _align_rotation(X_start, b.X_EG, Rr, here)
    shift = T.T @ (T @ (ref - here)) if T.shape[0] else np.zeros(3)
    X = _translate(X, shift)
    pts = np.array([e.point for e in b.elements]) if b.elements else np.zeros((1, 3))
    extent = float(np.max(np.linalg.norm(pts[:, None] - pts[None], axis=-1)))
    alignment = Alignment(
        translations=T,
        rotations=Rr,
        tolerance=pp.clearance,
        angular_tolerance=pp.clearance / max(extent, pp.clearance),
    )
    prim = _position_controlled(PrimitiveKind.ALIGN, a, X, ref, float(np.linalg.norm(shift)), pp)
    return replace(prim, transition=i, to_state=b.id, direction=np.zeros(3), alignment=alignment)


def _approach(
    task: TaskModel, first: int | None, pp: PlanParameters
) -> tuple[Primitive, FloatArray]:
    """Return the approach to a stand-off before transition ``first``, and its target pose."""
    s0 = task.states[0]
    X0 = s0.X_EG
    X_goal = X0
    via: tuple[FloatArray, ...] = ()
    if first is not None and not s0.elements:
        tr = task.transitions[first]
        b = task.state(tr.to_id)
        c = _centroid(_new(s0, b))
        ref = b.X_EG[:3, 3] if c is None else c
        X_first = _intermediate_poses(X0, b.X_EG, tr.subskills, ref)[0]
        u0 = tr.subskills[0]
        d = _unit(u0.direction) if u0.space == "translation" else None
        back = -d if d is not None else _unit(_normals(_new(s0, b)).sum(axis=0))
        if back is not None:
            X_goal = _translate(X_first, pp.standoff * back)
            via = _lift_and_over(task, X0, X_goal, back, ref)
        else:
            X_goal = X_first
    legs = [X0, *via, X_goal]
    dist = sum(float(np.linalg.norm(b[:3, 3] - a[:3, 3])) for a, b in itertools.pairwise(legs))
    prim = _position_controlled(PrimitiveKind.APPROACH, s0, X_goal, X_goal[:3, 3].copy(), dist, pp)
    # the orientation is reached when no point of the object (within the task's contact
    # points) is off by more than the position tolerance
    rho = max([pp.reach_tolerance, *(float(np.linalg.norm(q)) for q in _local_points(task))])
    prim = replace(prim, stop=replace(prim.stop, angular_tolerance=pp.reach_tolerance / rho))
    du = _unit(X_goal[:3, 3] - legs[-2][:3, 3])
    return replace(prim, direction=np.zeros(3) if du is None else du, via=via), X_goal


def _local_points(task: TaskModel) -> list[FloatArray]:
    """Every contact point of the task in the grasped object's frame (metres)."""
    return [
        (invert_pose(s.X_EG) @ np.append(e.point, 1.0))[:3] for s in task.states for e in s.elements
    ]


def _lift_and_over(
    task: TaskModel, X0: FloatArray, X_goal: FloatArray, up: FloatArray, contact: FloatArray
) -> tuple[FloatArray, ...]:
    """Via poses of the approach: rise along ``up``, cross over, come down to the stand-off.

    ``up`` is the retreat direction from the first contact (``contact``). The crossing is
    at the highest of two levels (along ``up``, of the object's origin): the start pose's,
    and the stand-off's raised by (a) how far the highest contact point of the whole task
    lies above the first contact (the environment reaches up to its contact points; the
    object at the stand-off clears the first contact by the stand-off) and (b) the chord
    ``2 rho sin(theta / 2)`` by which the turn ``theta`` between the start and stand-off
    orientations can lower a point of the object at distance ``rho`` from its origin
    (``rho``: the farthest contact point of the object from its origin, over the task).
    The turn happens during the crossing, about the origin (:mod:`apo.motion.trajectory`).
    """
    points = [e.point for s in task.states for e in s.elements]
    rise = max([0.0, *(float(up @ (p - contact)) for p in points)])
    rho = max([0.0, *(float(np.linalg.norm(q)) for q in _local_points(task))])
    theta = float(np.linalg.norm(_rotvec(X0, X_goal)))
    rise += 2.0 * rho * np.sin(min(theta, np.pi) / 2.0)
    level0, level_s = float(up @ X0[:3, 3]), float(up @ X_goal[:3, 3])
    level = max(level0, level_s + rise)
    via = []
    if level - level0 > _EPS:
        via.append(_translate(X0, (level - level0) * up))
    if level - level_s > _EPS:
        via.append(_translate(X_goal, (level - level_s) * up))
    return tuple(via)


def _emit_transition(task: TaskModel, i: int, cur: _Cursor, pp: PlanParameters) -> None:
    """Append the primitives of transition ``i`` (which has sub-skills) to ``cur.out``."""
    tr = task.transitions[i]
    if tr.critical and cur.align_for is None:
        cur.align_for = i
    if cur.align_for is not None:
        cur.out.append(_align_primitive(task, cur.align_for, cur.X, pp))
        cur.X = cur.out[-1].target.X_EG
        cur.align_for = None
    b = task.state(tr.to_id)
    c = _centroid(b.elements)
    ref = b.X_EG[:3, 3] if c is None else c
    targets = _intermediate_poses(cur.X, b.X_EG, tr.subskills, ref)
    held: FloatArray | None = None
    for j, (u, X_t) in enumerate(zip(tr.subskills, targets, strict=True)):
        prim = _subskill_primitive(task, i, j, cur.X, X_t, held, pp)
        if j == 0 and cur.folded:
            via = tuple(task.state(task.transitions[f].to_id).X_EG for f in cur.folded)
            prim = replace(prim, folded=tuple(cur.folded), via=via)
            cur.folded = []
        cur.out.append(prim)
        cur.X = X_t
        if u.space == "translation" and u.kind == "push_to" and _unit(u.direction) is not None:
            held = _unit(u.direction)
    cur.state = b


def _check_task(task: TaskModel) -> None:
    if not task.states:
        raise InputFormatError(f"{task.source or 'task'}: no states: nothing to plan")
    if len(task.transitions) != len(task.states) - 1:
        raise InputFormatError(
            f"{task.source or 'task'}: {len(task.transitions)} transitions for "
            f"{len(task.states)} states"
        )


def plan(
    task: TaskModel,
    *,
    parameters: PlanParameters | None = None,
    task_ref: ModelRef | None = None,
) -> SkillProgram:
    """Return the skill program that executes ``task`` (``docs/motion.md``).

    Parameters
    ----------
    task : apo.task.TaskModel
        The recognised demonstration (SI units, environment frame).
    parameters : PlanParameters, optional
        Stand-off, clearance, forces, thresholds and speeds (SI); defaults if None.
    task_ref : apo.task.ModelRef, optional
        The ``task.json`` file planned from (path and SHA-256), recorded in the program.

    Returns
    -------
    SkillProgram
        ``approach``, then per transition with sub-skills one primitive per sub-skill (an
        ``align`` first if the transition, or one folded into it, is critical).

    Raises
    ------
    InputFormatError
        A task without states or with inconsistent transitions.
    """
    pp = parameters or PlanParameters()
    _check_task(task)
    with_skills = [i for i, t in enumerate(task.transitions) if t.subskills]
    approach, X = _approach(task, with_skills[0] if with_skills else None, pp)
    cur = _Cursor(X=X, state=task.states[0], out=[approach])
    for i, tr in enumerate(task.transitions):
        if tr.subskills:
            _emit_transition(task, i, cur, pp)
            continue
        cur.folded.append(i)
        if tr.critical and cur.align_for is None:
            cur.align_for = i
    _finish(task, cur, pp)
    prims = tuple(replace(p, index=k) for k, p in enumerate(_with_searches(cur.out, pp)))
    final = task.states[-1]
    return SkillProgram(
        units=task.units,
        task=task_ref or ModelRef(path="", sha256=None, name=task.source),
        grasped=task.grasped,
        environment=task.environment,
        start_X_EG=task.states[0].X_EG,
        final_state=final.id,
        final_elements=final.elements,
        primitives=prims,
        parameters=pp,
    )


def _leading_point(X: FloatArray, later: Target, e: FloatArray, band: float) -> FloatArray | None:
    """Return the object's leading point along ``e`` at pose ``X``.

    The mean of the contact points of a later target (carried to ``X``) within ``band`` of
    the farthest along ``e``: the part that enters first, about which an align turns (so it
    stays at the entrance).
    """
    if not later.elements:
        return None
    pts = np.array([_moved(X, later.X_EG, el.point) for el in later.elements])
    s = pts @ e
    return np.asarray(pts[s >= s.max() - band].mean(axis=0), dtype=float)


def _with_searches(prims: Sequence[Primitive], pp: PlanParameters) -> list[Primitive]:
    """Give each ``align`` its search for the entrance and the compliance that feels for it.

    The entrance direction is that of the next translational sub-skill (the move through the
    entrance). The align presses along it with ``hold_force`` (force control; everything
    else position-controlled) while it moves to the aligned pose and then sweeps its aligned
    translations across that direction (a zig-zag for one, a square spiral for two) until
    the object drops ``search_drop`` along it. The plan cannot know the environment closer
    than the task's poses (an unknown offset larger than the clearance is the usual case):
    only contact tells where the entrance is, the usual peg-in-hole search.
    """
    out = list(prims)
    for k, p in enumerate(out):
        if p.kind != PrimitiveKind.ALIGN or p.alignment is None:
            continue
        nxt = [q for q in out[k + 1 :] if q.space == MotionSpace.TRANSLATION]
        e = _unit(nxt[0].direction) if nxt else None
        if e is None:
            continue
        U = _remove(p.alignment.translations, e[None, :])
        lead = _leading_point(p.target.X_EG, nxt[0].target, e, pp.search_drop)
        search = Search(
            direction=e,
            force=pp.hold_force,
            pattern=("none", "zigzag", "spiral", "spiral")[U.shape[0]],
            directions=U[:2],
            pitch=pp.search_pitch,
            radius=pp.search_radius,
            speed=pp.search_speed,
            drop=pp.search_drop,
        )
        out[k] = replace(
            p,
            alignment=replace(p.alignment, search=search),
            stop=replace(p.stop, until=("entrance",)),
            compliance=_Split(force_rows=[e], force=pp.hold_force * e).compliance(
                p.compliance.center if lead is None else lead
            ),
        )
    return out


def _finish(task: TaskModel, cur: _Cursor, pp: PlanParameters) -> None:
    """Fold trailing transitions without sub-skill into the last primitive."""
    if cur.align_for is not None:
        cur.out.append(_align_primitive(task, cur.align_for, cur.X, pp))
    if not cur.folded:
        return
    last = cur.out[-1]
    final = task.states[-1]
    via = tuple(task.state(task.transitions[f].to_id).X_EG for f in cur.folded[:-1])
    cur.out[-1] = replace(
        last,
        folded=(*last.folded, *cur.folded),
        via=(*last.via, last.target.X_EG, *via),
        target=Target(state=final.id, elements=final.elements, X_EG=final.X_EG),
    )
