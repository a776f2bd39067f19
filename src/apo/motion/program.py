"""The skill program: robot primitives generated from a task model (schema ``apo.motion/1``).

A :class:`SkillProgram` is what :func:`apo.motion.plan` returns and what ``motion.json``
stores (``docs/motion.md``). Inside, everything is SI (metres, radians, newtons, newton
metres) in the environment frame E; :func:`program_to_dict` writes lengths in the program's
``units`` (those of the task) and :func:`program_from_dict` reads them back, validating every
field and raising :class:`apo.errors.InputFormatError` naming the file and the field.

Pure data and validation: no simulator, no file I/O. Quaternions are ``(qw, qx, qy, qz)``;
poses ``X_EG`` are 4x4 matrices of the grasped object G in E (``docs/conventions.md``).
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from apo.jsonform import JsonReader, pose_to_dict, rounded, rounded_list, rounded_rows
from apo.task import (
    UNITS,
    Element,
    ModelRef,
    element_from_dict,
    element_to_dict,
    model_from_dict,
    model_to_dict,
)
from apo.typing import FloatArray

__all__ = [
    "END_CONDITIONS",
    "SCHEMA",
    "SEARCH_PATTERNS",
    "Alignment",
    "Compliance",
    "MotionSpace",
    "PlanParameters",
    "Primitive",
    "PrimitiveKind",
    "Profile",
    "RotationType",
    "Search",
    "SkillProgram",
    "StopCondition",
    "Target",
    "program_from_dict",
    "program_to_dict",
]

SCHEMA = "apo.motion/1"
"""Schema identifier written in and required from ``motion.json``."""


class PrimitiveKind(enum.StrEnum):
    """What a primitive does (``docs/motion.md``)."""

    APPROACH = "approach"  # position-controlled move through free space to a stand-off
    ALIGN = "align"  # position-controlled correction in the constrained directions
    PUSH_TO = "push_to"  # guarded move into a new contact (tsukiate)
    SLIDE = "slide"  # guarded move along kept contacts until the support ends (suberashi)
    RELEASE = "release"  # move away from a lost contact (tsukihanashi)


class MotionSpace(enum.StrEnum):
    """Space a sub-skill primitive acts in."""

    TRANSLATION = "translation"
    ROTATION = "rotation"


class RotationType(enum.StrEnum):
    """Type of a rotational push-to (paper 3.5): I turns both ways, II one way only."""

    I = "I"  # noqa: E741
    II = "II"


@dataclass(frozen=True)
class Target:
    """Where a primitive ends: a contact state of the task and its corrected pose.

    Attributes
    ----------
    state : str
        Id of the task state reached (``task.json`` ``states[].id``).
    elements : tuple of apo.task.Element
        Its contact elements (environment frame, metres); empty for a free state.
    X_EG : ndarray, shape (4, 4)
        Pose of the grasped object at the end of the primitive, metres: the state's
        corrected pose, or the stand-off pose for an approach, or the aligned pose.
    """

    state: str
    elements: tuple[Element, ...]
    X_EG: FloatArray


@dataclass(frozen=True)
class StopCondition:
    """When a guarded move ends.

    The move ends as soon as the sensed contact force (norm of the force on the grasped
    object, newtons) exceeds ``force`` or the contact torque about the compliance centre
    (newton metres) exceeds ``torque``; it fails if it travels farther than ``travel``
    (metres for a translation, radians for a rotation) without either. A position-controlled
    primitive (``approach``, ``align``) ends when the target pose is reached within its
    tolerance; its ``force`` and ``torque`` are then the contact load at which it must stop
    as a failure (an unexpected collision).

    Attributes
    ----------
    force : float
        Newtons, > 0.
    torque : float
        Newton metres, > 0.
    travel : float
        Metres (translation) or radians (rotation), > 0: the safeguard.
    expected : float
        Metres or radians, >= 0: the travel the demonstration shows (start to target pose
        of the primitive, along ``direction`` or about the axis). A ``release`` moves this far
        (at least ``PlanParameters.standoff``); a ``slide`` that meets no obstacle ends here.
    until : tuple of str
        The conditions that end the primitive well, any of them (:data:`END_CONDITIONS`);
        empty in programs written before the field existed (the executor then derives them
        from the kind as ``docs/motion.md`` says).
    tolerance, angular_tolerance : float
        Metres and radians of the ``pose`` conditions.
    touch : float
        Newtons: the contact force of ``pose_in_contact``.
    confirm : float
        Seconds an end condition must hold without a break (filters impacts).
    stall : float
        Seconds the primitive may run beyond its nominal path without ending or failing;
        then it has jammed and fails.
    collision : bool
        A contact force above ``force`` (or torque above ``torque``) is a failure (an
        unexpected collision), not an end: position-controlled moves through free space.
    """

    force: float
    torque: float
    travel: float
    expected: float = 0.0
    until: tuple[str, ...] = ()
    tolerance: float = 2e-4
    angular_tolerance: float = 0.035
    touch: float = 0.5
    confirm: float = 0.01
    stall: float = 3.0
    collision: bool = False


END_CONDITIONS = ("force", "torque", "expected", "pose", "pose_in_contact", "entrance")
"""What can end a primitive well (``StopCondition.until``, ``docs/motion.md``):

- ``force``: the sensed contact force against ``direction`` reaches ``stop.force``;
- ``torque``: the contact torque about the axis (``direction`` through ``point``) against
  ``direction`` reaches ``stop.torque``;
- ``expected``: the travel along ``direction`` / about the axis reaches ``stop.expected``
  (and the nominal path is over);
- ``pose``: the nominal path is over and the pose is within ``stop.tolerance`` /
  ``stop.angular_tolerance`` of the target (an ``align``: its alignment tolerances);
- ``pose_in_contact``: ``pose`` with a contact force of at least ``stop.touch``;
- ``entrance``: during an alignment search, the object has moved ``search.drop`` along
  ``search.direction`` (it found the entrance).
"""


@dataclass(frozen=True)
class Profile:
    """Speeds of a primitive's nominal path (the executor's time law, ``docs/motion.md``).

    Attributes
    ----------
    speed : float
        m/s of the compliance centre (or of the pivot of a rotational sub-skill) on the path.
    angular_speed : float
        rad/s of the orientation.
    slow_zone : float
        Metres before the expected end of a guarded translational push-to in which its
        force-controlled motion slows down to ``slow_speed`` (0: never).
    slow_speed : float
        m/s in the slow zone.
    """

    speed: float
    angular_speed: float
    slow_zone: float = 0.0
    slow_speed: float = 0.0


@dataclass(frozen=True)
class Search:
    """Where an ``align`` feels for the entrance (a guarded spiral/zig-zag search).

    The object is pressed with ``force`` along ``direction`` (the direction of the move
    through the entrance) while its position sweeps ``directions`` about the aligned
    position: a zig-zag of growing amplitude (one direction) or a square spiral (two), passes
    ``pitch`` apart, out to ``radius``, at ``speed``. The search has found the entrance once
    the object has moved ``drop`` along ``direction``; a sweep that ends without it fails.

    Attributes
    ----------
    direction : ndarray, shape (3,)
        Unit, environment frame.
    force : float
        Newtons along ``direction``.
    pattern : str
        ``"zigzag"``, ``"spiral"`` or ``"none"`` (no translation to search: only ``drop``).
    directions : ndarray, shape (k, 3)
        Orthonormal rows orthogonal to ``direction`` (k = 1 for a zig-zag, 2 for a spiral).
    pitch, radius : float
        Metres.
    speed : float
        m/s along the sweep.
    drop : float
        Metres.
    """

    direction: FloatArray
    force: float
    pattern: str
    directions: FloatArray
    pitch: float
    radius: float
    speed: float
    drop: float


SEARCH_PATTERNS = ("zigzag", "spiral", "none")


@dataclass(frozen=True)
class Compliance:
    """Hybrid force/position split of the six directions of motion of the grasped object.

    All directions are unit rows in the environment frame; rotational directions are axes
    through ``center``, and torques are about ``center``. The force-controlled rows and the
    position-controlled rows of each space are together an orthonormal basis of that space
    (so every direction is exactly one of the two).

    Attributes
    ----------
    center : ndarray, shape (3,)
        Compliance centre, metres, environment frame: the point of the grasped object
        (at its target pose) about which rotations and torques are expressed.
    force_directions : ndarray, shape (k, 3)
        Translational directions under force control.
    forces : ndarray, shape (k,)
        Force to apply along each of them, newtons (signed along the row).
    torque_axes : ndarray, shape (l, 3)
        Rotation axes under torque control.
    torques : ndarray, shape (l,)
        Torque to apply about each, newton metres (right hand about the row).
    position_directions : ndarray, shape (3 - k, 3)
        Translational directions under position control.
    position_axes : ndarray, shape (3 - l, 3)
        Rotation axes under position control.
    """

    center: FloatArray
    force_directions: FloatArray
    forces: FloatArray
    torque_axes: FloatArray
    torques: FloatArray
    position_directions: FloatArray
    position_axes: FloatArray

    def selection(self) -> FloatArray:
        """Return the 6x6 force-selection matrix ``S`` in ``[omega; v]`` order.

        ``S`` projects onto the force-controlled subspace (rotation block: the torque
        axes; translation block: the force directions); ``I - S`` onto the
        position-controlled one.
        """
        S = np.zeros((6, 6))
        S[:3, :3] = self.torque_axes.T @ self.torque_axes
        S[3:, 3:] = self.force_directions.T @ self.force_directions
        return S

    def wrench(self) -> FloatArray:
        """Return the commanded wrench ``[torque; force]`` about ``center`` (N·m, N)."""
        return np.concatenate(
            [self.torque_axes.T @ self.torques, self.force_directions.T @ self.forces]
        )


@dataclass(frozen=True)
class Alignment:
    """What an ``align`` primitive corrects before a critical transition.

    Attributes
    ----------
    translations : ndarray, shape (k, 3)
        Orthonormal translational directions to align: those the critical transition's
        target state constrains that were not constrained before (SM/SD -> C).
    rotations : ndarray, shape (l, 3)
        Orthonormal rotation axes to align (same rule in the rotation space).
    tolerance : float
        Largest position error allowed along ``translations``, metres.
    angular_tolerance : float
        Largest angle error allowed about ``rotations``, radians.
    search : Search or None
        How to feel for the entrance after the position-controlled move to the aligned pose
        (None: no search, the aligned pose is the end).
    """

    translations: FloatArray
    rotations: FloatArray
    tolerance: float
    angular_tolerance: float
    search: Search | None = None


@dataclass(frozen=True)
class Primitive:
    """One step of the skill program.

    Attributes
    ----------
    index : int
        Position in :attr:`SkillProgram.primitives` (0-based).
    kind : PrimitiveKind
    space : MotionSpace or None
        Sub-skill primitives: the space of the sub-skill. ``approach`` and ``align``: None
        (they may move in both).
    type : RotationType or None
        Rotational push-to only: type I or II.
    transition : int or None
        Index of the task transition this primitive executes (``task.json``
        ``transitions[i]``); None for the approach.
    from_state, to_state : str
        State ids before and after that transition (approach: the first state, twice).
    folded : tuple of int
        Indices of earlier transitions without a sub-skill (SM -> M and the like) whose
        state change happens during this primitive (paper 3.5: "part of the next motion").
    direction : ndarray, shape (3,)
        Unit direction of motion (translation) or rotation axis (rotation, right hand),
        environment frame. Approach: the direction of its last leg, into the stand-off.
        Align: zeros (see ``alignment``). Zeros when the task does not fix it.
    point : ndarray, shape (3,) or None
        Rotation: a point on the axis, metres (the sub-skill's pivot). None otherwise.
    subspace : ndarray, shape (k, 3)
        Every direction (or axis) the sub-skill acts in, sign-free orthonormal rows.
    source : str
        What fixed ``direction``: the sub-skill's ``source`` (``"contacts"``,
        ``"detaching_direction"``, ``"poses"``, ``"none"``) or ``"plan"`` (computed here
        from poses: approach, align).
    target : Target
    stop : StopCondition
    compliance : Compliance
    alignment : Alignment or None
        ``align`` primitives only.
    via : tuple of ndarray, shape (4, 4)
        Poses (metres) the nominal path passes through before ``target.X_EG``: for the
        approach, the lift-and-cross-over poses; otherwise the poses of the states of the
        ``folded`` transitions, in order.
    profile : Profile or None
        Speeds of the path to the target (None in programs written before the field
        existed: the plan's ``speed`` and ``angular_speed``).
    """

    index: int
    kind: PrimitiveKind
    space: MotionSpace | None
    type: RotationType | None
    transition: int | None
    from_state: str
    to_state: str
    folded: tuple[int, ...]
    direction: FloatArray
    point: FloatArray | None
    subspace: FloatArray
    source: str
    target: Target
    stop: StopCondition
    compliance: Compliance
    alignment: Alignment | None = None
    via: tuple[FloatArray, ...] = ()
    profile: Profile | None = None

    @property
    def guarded(self) -> bool:
        """True for the sub-skill primitives (they end on sensed contact, not on a pose)."""
        return self.kind in (PrimitiveKind.PUSH_TO, PrimitiveKind.SLIDE, PrimitiveKind.RELEASE)


@dataclass(frozen=True)
class PlanParameters:
    """The planner's settings, recorded in the program (SI units).

    Attributes
    ----------
    standoff : float
        Metres: distance from the first contact at which the approach stops.
    clearance : float
        Metres per side: the gap the alignment tolerance is derived from.
    push_force : float
        Newtons applied along the direction of a translational push-to or slide.
    hold_force : float
        Newtons applied along each kept contact normal (into the contact).
    push_torque : float
        Newton metres applied about the axis of a rotational sub-skill.
    force_threshold, torque_threshold : float
        Stop condition of guarded moves (N, N·m).
    travel_margin : float
        Metres added to the expected travel of a translational guarded move.
    angular_margin : float
        Radians added to the expected travel of a rotational guarded move.
    speed, angular_speed : float
        m/s and rad/s of the nominal trajectory.
    sample_period : float
        Seconds between two samples of the trajectory (``motion.csv``).
    free_speed_factor : float
        The approach (free space) moves this many times faster than ``speed``.
    slow_zone, slow_speed : float
        Metres before the expected contact of a translational push-to, and the m/s it
        slows to there.
    reach_tolerance : float
        Metres: the approach has reached its target (rotation: this over the object's size).
    turn_tolerance : float
        Radians: a rotational push-to or slide has reached its target orientation.
    touch_force : float
        Newtons: contact force that counts as touching (rotational push-to).
    confirm_time, stall_time, settle_time : float
        Seconds: an end condition must hold this long; a primitive that neither ends nor
        fails this long after its nominal path has jammed; the compliance is held this long
        after each primitive that ended well.
    search_pitch, search_radius, search_speed, search_drop : float
        The alignment search (:class:`Search`): metres, metres, m/s, metres.
    """

    standoff: float = 0.005
    clearance: float = 0.0002
    push_force: float = 5.0
    hold_force: float = 2.0
    push_torque: float = 0.2
    force_threshold: float = 4.0
    torque_threshold: float = 0.15
    travel_margin: float = 0.005
    angular_margin: float = 0.087
    speed: float = 0.02
    angular_speed: float = 0.35
    sample_period: float = 0.02
    free_speed_factor: float = 4.0
    slow_zone: float = 0.003
    slow_speed: float = 0.005
    reach_tolerance: float = 0.0002
    turn_tolerance: float = 0.035
    touch_force: float = 0.5
    confirm_time: float = 0.01
    stall_time: float = 3.0
    settle_time: float = 0.05
    search_pitch: float = 0.0002
    search_radius: float = 0.002
    search_speed: float = 0.004
    search_drop: float = 0.001


@dataclass(frozen=True)
class SkillProgram:
    """The robot program of a task model.

    Attributes
    ----------
    units : str
        Length unit of the JSON form (that of the task); the program itself is SI.
    task : ModelRef
        The task file the program was planned from: path as given to the planner and its
        SHA-256 (None if planned from an in-memory task).
    grasped, environment : apo.task.ModelRef
        The models, paths exactly as recorded in ``task.json`` (relative to its folder).
    start_X_EG : ndarray, shape (4, 4)
        Start pose of the grasped object (the first state's pose), metres.
    final_state : str
        Id of the task's final state.
    final_elements : tuple of apo.task.Element
        Its contact elements: what success means.
    primitives : tuple of Primitive
    parameters : PlanParameters
    frame : str
        ``"environment"``.
    """

    units: str
    task: ModelRef
    grasped: ModelRef
    environment: ModelRef
    start_X_EG: FloatArray
    final_state: str
    final_elements: tuple[Element, ...]
    primitives: tuple[Primitive, ...]
    parameters: PlanParameters = field(default_factory=PlanParameters)
    frame: str = "environment"

    def sequence(self) -> list[tuple[str, str | None, str | None]]:
        """Return ``(kind, space, type)`` of every primitive, in order."""
        return [
            (
                str(p.kind),
                None if p.space is None else str(p.space),
                None if p.type is None else str(p.type),
            )
            for p in self.primitives
        ]


# --------------------------------------------------------------------------------------------
# To JSON
# --------------------------------------------------------------------------------------------


def _elements(elements: Sequence[Element], k: float) -> list[dict[str, Any]]:
    return [element_to_dict(e, k) for e in elements]


def _stop_to_dict(st: StopCondition, rot: bool, k: float) -> dict[str, Any]:
    kt = 1.0 if rot else k
    return {
        "force": rounded(st.force),
        "torque": rounded(st.torque),
        "travel": rounded(st.travel * kt),
        "expected": rounded(st.expected * kt),
        "until": list(st.until),
        "tolerance": rounded(st.tolerance * k),
        "angular_tolerance": rounded(st.angular_tolerance),
        "touch": rounded(st.touch),
        "confirm": rounded(st.confirm),
        "stall": rounded(st.stall),
        "collision": bool(st.collision),
    }


def _alignment_to_dict(a: Alignment | None, k: float) -> dict[str, Any] | None:
    if a is None:
        return None
    out: dict[str, Any] = {
        "translations": rounded_rows(a.translations),
        "rotations": rounded_rows(a.rotations),
        "tolerance": rounded(a.tolerance * k),
        "angular_tolerance": rounded(a.angular_tolerance),
        "search": None,
    }
    if a.search is not None:
        se = a.search
        out["search"] = {
            "direction": rounded_list(se.direction),
            "force": rounded(se.force),
            "pattern": se.pattern,
            "directions": rounded_rows(se.directions),
            "pitch": rounded(se.pitch * k),
            "radius": rounded(se.radius * k),
            "speed": rounded(se.speed * k),
            "drop": rounded(se.drop * k),
        }
    return out


def _primitive_to_dict(p: Primitive, k: float) -> dict[str, Any]:
    c = p.compliance
    pr = p.profile
    return {
        "index": int(p.index),
        "kind": str(p.kind),
        "space": None if p.space is None else str(p.space),
        "type": None if p.type is None else str(p.type),
        "transition": p.transition,
        "from": p.from_state,
        "to": p.to_state,
        "folded": [int(i) for i in p.folded],
        "direction": rounded_list(p.direction),
        "point": None if p.point is None else rounded_list(p.point, k),
        "subspace": rounded_rows(p.subspace),
        "source": p.source,
        "target": {
            "state": p.target.state,
            "elements": _elements(p.target.elements, k),
            "pose": pose_to_dict(p.target.X_EG, k),
        },
        "stop": _stop_to_dict(p.stop, p.space == MotionSpace.ROTATION, k),
        "compliance": {
            "center": rounded_list(c.center, k),
            "force_directions": rounded_rows(c.force_directions),
            "forces": rounded_list(c.forces),
            "torque_axes": rounded_rows(c.torque_axes),
            "torques": rounded_list(c.torques),
            "position_directions": rounded_rows(c.position_directions),
            "position_axes": rounded_rows(c.position_axes),
        },
        "alignment": _alignment_to_dict(p.alignment, k),
        "via": [pose_to_dict(X, k) for X in p.via],
        "profile": None
        if pr is None
        else {
            "speed": rounded(pr.speed * k),
            "angular_speed": rounded(pr.angular_speed),
            "slow_zone": rounded(pr.slow_zone * k),
            "slow_speed": rounded(pr.slow_speed * k),
        },
    }


_LENGTH_PARAMETERS = (
    "standoff", "clearance", "travel_margin", "speed", "slow_zone", "slow_speed",
    "reach_tolerance", "search_pitch", "search_radius", "search_speed", "search_drop",
)  # fmt: skip


def _parameters_to_dict(pp: PlanParameters, k: float) -> dict[str, float]:
    return {
        name: rounded(getattr(pp, name) * (k if name in _LENGTH_PARAMETERS else 1.0))
        for name in PlanParameters.__dataclass_fields__
    }


def program_to_dict(program: SkillProgram) -> dict[str, Any]:
    """Return the JSON form of ``program`` (schema ``"apo.motion/1"``, lengths in its units).

    Parameters
    ----------
    program : SkillProgram

    Returns
    -------
    dict
        Plain lists, strings, numbers, booleans and None, ready for :func:`json.dump`.
    """
    if program.units not in UNITS:
        raise ValueError(f"unknown units {program.units!r}; expected one of {sorted(UNITS)}")
    k = 1.0 / UNITS[program.units]
    return {
        "schema": SCHEMA,
        "units": program.units,
        "frame": program.frame,
        "task": model_to_dict(program.task),
        "models": {
            "grasped": model_to_dict(program.grasped),
            "environment": model_to_dict(program.environment),
        },
        "start_pose": pose_to_dict(program.start_X_EG, k),
        "final_state": {
            "id": program.final_state,
            "elements": _elements(program.final_elements, k),
        },
        "parameters": _parameters_to_dict(program.parameters, k),
        "primitives": [_primitive_to_dict(p, k) for p in program.primitives],
    }


# --------------------------------------------------------------------------------------------
# From JSON, with validation (apo.jsonform.JsonReader: messages name the file and the field)
# --------------------------------------------------------------------------------------------


def _read_elements(rd: JsonReader, v: Any, where: str, k: float) -> tuple[Element, ...]:
    return tuple(
        element_from_dict(rd, e, f"{where}[{j}]", k) for j, e in enumerate(rd.lst(v, where))
    )


def _compliance_from_dict(rd: JsonReader, v: Any, where: str, k: float) -> Compliance:
    d = rd.obj(v, where)
    parts = {
        name: rd.rows(rd.get(d, name, where), f"{where}.{name}")
        for name in ("force_directions", "torque_axes", "position_directions", "position_axes")
    }
    for a, b in (("force_directions", "position_directions"), ("torque_axes", "position_axes")):
        basis = np.vstack([parts[a], parts[b]])
        if basis.shape[0] != 3 or not np.allclose(basis @ basis.T, np.eye(3), atol=1e-4):
            raise rd.fail(f"{where}.{b}", f"{a} and {b} must together be an orthonormal basis")
    forces = rd.lst(rd.get(d, "forces", where), f"{where}.forces", len(parts["force_directions"]))
    torques = rd.lst(rd.get(d, "torques", where), f"{where}.torques", len(parts["torque_axes"]))
    return Compliance(
        center=rd.vector(rd.get(d, "center", where), f"{where}.center", 3) * k,
        forces=np.array([rd.number(x, f"{where}.forces[{i}]") for i, x in enumerate(forces)]),
        torques=np.array([rd.number(x, f"{where}.torques[{i}]") for i, x in enumerate(torques)]),
        **parts,
    )


def _search_from_dict(rd: JsonReader, v: Any, where: str, k: float) -> Search | None:
    if v is None:
        return None
    d = rd.obj(v, where)
    pattern = rd.string(rd.get(d, "pattern", where), f"{where}.pattern", SEARCH_PATTERNS)
    directions = rd.rows(rd.get(d, "directions", where), f"{where}.directions")
    if len(directions) != {"zigzag": 1, "spiral": 2, "none": 0}[pattern]:
        raise rd.fail(f"{where}.directions", f"a {pattern} search needs "
                      f"{ {'zigzag': 1, 'spiral': 2, 'none': 0}[pattern]} directions")  # fmt: skip

    def length(name: str) -> float:
        return rd.positive(rd.get(d, name, where), f"{where}.{name}") * k

    return Search(
        direction=rd.unit(rd.get(d, "direction", where), f"{where}.direction"),
        force=rd.non_negative(rd.get(d, "force", where), f"{where}.force"),
        pattern=pattern,
        directions=directions,
        pitch=length("pitch"),
        radius=length("radius"),
        speed=length("speed"),
        drop=length("drop"),
    )


def _alignment_from_dict(rd: JsonReader, v: Any, where: str, k: float) -> Alignment | None:
    if v is None:
        return None
    d = rd.obj(v, where)
    return Alignment(
        translations=rd.rows(rd.get(d, "translations", where), f"{where}.translations"),
        rotations=rd.rows(rd.get(d, "rotations", where), f"{where}.rotations"),
        tolerance=rd.positive(rd.get(d, "tolerance", where), f"{where}.tolerance") * k,
        angular_tolerance=rd.positive(
            rd.get(d, "angular_tolerance", where), f"{where}.angular_tolerance"
        ),
        search=_search_from_dict(rd, d.get("search"), f"{where}.search", k),
    )


def _stop_from_dict(rd: JsonReader, v: Any, where: str, k: float, kt: float) -> StopCondition:
    """Read a stop condition; ``kt`` scales its travels (1 for a rotation), ``k`` lengths."""
    d = rd.obj(v, where)
    dflt = StopCondition(1.0, 1.0, 1.0)
    until = tuple(
        rd.string(x, f"{where}.until[{j}]", END_CONDITIONS)
        for j, x in enumerate(rd.lst(d.get("until", []), f"{where}.until"))
    )

    def opt(name: str, scale: float = 1.0) -> float:
        if name not in d:
            return float(getattr(dflt, name))
        return rd.non_negative(d[name], f"{where}.{name}") * scale

    return StopCondition(
        force=rd.positive(rd.get(d, "force", where), f"{where}.force"),
        torque=rd.positive(rd.get(d, "torque", where), f"{where}.torque"),
        travel=rd.positive(rd.get(d, "travel", where), f"{where}.travel") * kt,
        expected=rd.non_negative(d.get("expected", 0.0), f"{where}.expected") * kt,
        until=until,
        tolerance=opt("tolerance", k),
        angular_tolerance=opt("angular_tolerance"),
        touch=opt("touch"),
        confirm=opt("confirm"),
        stall=opt("stall"),
        collision=rd.boolean(d.get("collision", False), f"{where}.collision"),
    )


def _profile_from_dict(rd: JsonReader, v: Any, where: str, k: float) -> Profile | None:
    if v is None:
        return None
    d = rd.obj(v, where)
    return Profile(
        speed=rd.positive(rd.get(d, "speed", where), f"{where}.speed") * k,
        angular_speed=rd.positive(rd.get(d, "angular_speed", where), f"{where}.angular_speed"),
        slow_zone=rd.non_negative(d.get("slow_zone", 0.0), f"{where}.slow_zone") * k,
        slow_speed=rd.non_negative(d.get("slow_speed", 0.0), f"{where}.slow_speed") * k,
    )


def _primitive_head(
    rd: JsonReader, d: Any, w: str
) -> tuple[PrimitiveKind, MotionSpace | None, RotationType | None, int | None]:
    """Kind, space, type and transition of primitive ``w``, checked against each other."""
    kind = PrimitiveKind(rd.string(rd.get(d, "kind", w), f"{w}.kind", list(PrimitiveKind)))
    sp = rd.get(d, "space", w)
    space = None if sp is None else MotionSpace(rd.string(sp, f"{w}.space", list(MotionSpace)))
    if (space is None) != (kind in (PrimitiveKind.APPROACH, PrimitiveKind.ALIGN)):
        raise rd.fail(f"{w}.space", f"a {kind} primitive {'has no' if space else 'needs a'} space")
    ty = d.get("type")
    rtype = None if ty is None else RotationType(rd.string(ty, f"{w}.type", list(RotationType)))
    tr = rd.optional_int(rd.get(d, "transition", w), f"{w}.transition")
    if (tr is None) != (kind == PrimitiveKind.APPROACH):
        raise rd.fail(f"{w}.transition", f"unexpected {tr!r} for a {kind} primitive")
    return kind, space, rtype, tr


def _primitive_from_dict(rd: JsonReader, v: Any, i: int, k: float) -> Primitive:
    w = f"primitives[{i}]"
    d = rd.obj(v, w)
    index = rd.integer(rd.get(d, "index", w), f"{w}.index")
    if index != i:
        raise rd.fail(f"{w}.index", f"expected {i}, got {index}")
    kind, space, rtype, tr = _primitive_head(rd, d, w)
    pt = d.get("point")
    td = rd.obj(rd.get(d, "target", w), f"{w}.target")
    travel_k = 1.0 if space == MotionSpace.ROTATION else k
    alignment = _alignment_from_dict(rd, d.get("alignment"), f"{w}.alignment", k)
    if (alignment is None) == (kind == PrimitiveKind.ALIGN):
        raise rd.fail(f"{w}.alignment", f"an {kind} primitive must have an alignment iff align")
    return Primitive(
        index=index,
        kind=kind,
        space=space,
        type=rtype,
        transition=tr,
        from_state=rd.string(rd.get(d, "from", w), f"{w}.from"),
        to_state=rd.string(rd.get(d, "to", w), f"{w}.to"),
        folded=tuple(
            rd.integer(x, f"{w}.folded[{j}]")
            for j, x in enumerate(rd.lst(d.get("folded", []), f"{w}.folded"))
        ),
        direction=rd.unit(rd.get(d, "direction", w), f"{w}.direction", allow_zero=True),
        point=None if pt is None else rd.vector(pt, f"{w}.point", 3) * k,
        subspace=rd.rows(d.get("subspace", []), f"{w}.subspace"),
        source=rd.string(d.get("source", "none"), f"{w}.source"),
        target=Target(
            state=rd.string(rd.get(td, "state", f"{w}.target"), f"{w}.target.state"),
            elements=_read_elements(rd, td.get("elements", []), f"{w}.target.elements", k),
            X_EG=rd.pose(rd.get(td, "pose", f"{w}.target"), f"{w}.target.pose", k),
        ),
        stop=_stop_from_dict(rd, rd.get(d, "stop", w), f"{w}.stop", k, travel_k),
        compliance=_compliance_from_dict(rd, rd.get(d, "compliance", w), f"{w}.compliance", k),
        alignment=alignment,
        via=tuple(
            rd.pose(X, f"{w}.via[{j}]", k)
            for j, X in enumerate(rd.lst(d.get("via", []), f"{w}.via"))
        ),
        profile=_profile_from_dict(rd, d.get("profile"), f"{w}.profile", k),
    )


def _parameters_from_dict(rd: JsonReader, v: Any, k: float) -> PlanParameters:
    d = rd.obj(v, "parameters")
    values: dict[str, float] = {}
    for name in PlanParameters.__dataclass_fields__:
        if name in d:
            scale = k if name in _LENGTH_PARAMETERS else 1.0
            values[name] = rd.positive(d[name], f"parameters.{name}") * scale
    return PlanParameters(**values)


def program_from_dict(data: Any, *, source: str = "") -> SkillProgram:
    """Validate the JSON form of a skill program and return it (SI units).

    Parameters
    ----------
    data : dict
        As produced by :func:`program_to_dict` (e.g. ``json.load`` of a ``motion.json``).
    source : str, optional
        File name used in error messages.

    Returns
    -------
    SkillProgram

    Raises
    ------
    InputFormatError
        Wrong or missing schema, missing or mistyped fields, unknown units or kinds,
        directions that are not unit vectors, a compliance split that is not a basis,
        non-positive thresholds, primitives out of order. The message names ``source``
        and the field (e.g. ``motion.json: primitives[2].stop.force: ...``).
    """
    rd = JsonReader(source or "motion")
    d = rd.obj(data, "top level")
    schema = d.get("schema")
    if schema != SCHEMA:
        raise rd.fail("schema", f"expected {SCHEMA!r}, got {schema!r}")
    units = rd.string(rd.get(d, "units", "top level"), "units", tuple(UNITS))
    k = UNITS[units]
    frame = rd.string(rd.get(d, "frame", "top level"), "frame", ("environment",))
    models = rd.obj(rd.get(d, "models", "top level"), "models")
    fs = rd.obj(rd.get(d, "final_state", "top level"), "final_state")
    prims = rd.lst(rd.get(d, "primitives", "top level"), "primitives")
    if not prims:
        raise rd.fail("primitives", "expected at least one primitive")
    return SkillProgram(
        units=units,
        frame=frame,
        task=model_from_dict(rd, rd.get(d, "task", "top level"), "task"),
        grasped=model_from_dict(rd, rd.get(models, "grasped", "models"), "models.grasped"),
        environment=model_from_dict(
            rd, rd.get(models, "environment", "models"), "models.environment"
        ),
        start_X_EG=rd.pose(rd.get(d, "start_pose", "top level"), "start_pose", k),
        final_state=rd.string(rd.get(fs, "id", "final_state"), "final_state.id"),
        final_elements=_read_elements(rd, fs.get("elements", []), "final_state.elements", k),
        parameters=_parameters_from_dict(rd, d.get("parameters", {}), k),
        primitives=tuple(_primitive_from_dict(rd, p, i, k) for i, p in enumerate(prims)),
    )
