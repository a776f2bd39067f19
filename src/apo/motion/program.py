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
import numpy.typing as npt

from apo.spatial import pose_from_position_quaternion, position_quaternion_from_pose
from apo.task import (
    KINDS,
    UNITS,
    Element,
    ModelRef,
    _model_from_dict,
    _model_to_dict,
    _r,
    _Reader,
    _vec,
)
from apo.typing import FloatArray

__all__ = [
    "SCHEMA",
    "Alignment",
    "Compliance",
    "MotionSpace",
    "PlanParameters",
    "Primitive",
    "PrimitiveKind",
    "RotationType",
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
    """

    force: float
    torque: float
    travel: float
    expected: float = 0.0


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
    """

    translations: FloatArray
    rotations: FloatArray
    tolerance: float
    angular_tolerance: float


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


def _rows(a: npt.ArrayLike) -> list[list[float]]:
    return [_vec(row) for row in np.asarray(a, dtype=float).reshape(-1, 3)]


def _pose(X: FloatArray, k: float) -> dict[str, list[float]]:
    p, q = position_quaternion_from_pose(X)
    return {"position": _vec(p, k), "quaternion": _vec(q)}


def _elements(elements: Sequence[Element], k: float) -> list[dict[str, Any]]:
    return [
        {
            "kind": e.kind,
            "grasped": [e.grasped[0], int(e.grasped[1])],
            "environment": [e.environment[0], int(e.environment[1])],
            "point": _vec(e.point, k),
            "normals": _rows(e.normals),
        }
        for e in elements
    ]


def _primitive_to_dict(p: Primitive, k: float) -> dict[str, Any]:
    c = p.compliance
    rot = p.space == MotionSpace.ROTATION
    out: dict[str, Any] = {
        "index": int(p.index),
        "kind": str(p.kind),
        "space": None if p.space is None else str(p.space),
        "type": None if p.type is None else str(p.type),
        "transition": p.transition,
        "from": p.from_state,
        "to": p.to_state,
        "folded": [int(i) for i in p.folded],
        "direction": _vec(p.direction),
        "point": None if p.point is None else _vec(p.point, k),
        "subspace": _rows(p.subspace),
        "source": p.source,
        "target": {
            "state": p.target.state,
            "elements": _elements(p.target.elements, k),
            "pose": _pose(p.target.X_EG, k),
        },
        "stop": {
            "force": _r(p.stop.force),
            "torque": _r(p.stop.torque),
            "travel": _r(p.stop.travel if rot else p.stop.travel * k),
            "expected": _r(p.stop.expected if rot else p.stop.expected * k),
        },
        "compliance": {
            "center": _vec(c.center, k),
            "force_directions": _rows(c.force_directions),
            "forces": _vec(c.forces),
            "torque_axes": _rows(c.torque_axes),
            "torques": _vec(c.torques),
            "position_directions": _rows(c.position_directions),
            "position_axes": _rows(c.position_axes),
        },
        "alignment": None,
        "via": [_pose(X, k) for X in p.via],
    }
    if p.alignment is not None:
        a = p.alignment
        out["alignment"] = {
            "translations": _rows(a.translations),
            "rotations": _rows(a.rotations),
            "tolerance": _r(a.tolerance * k),
            "angular_tolerance": _r(a.angular_tolerance),
        }
    return out


_LENGTH_PARAMETERS = ("standoff", "clearance", "travel_margin", "speed")


def _parameters_to_dict(pp: PlanParameters, k: float) -> dict[str, float]:
    return {
        name: _r(getattr(pp, name) * (k if name in _LENGTH_PARAMETERS else 1.0))
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
        "task": _model_to_dict(program.task),
        "models": {
            "grasped": _model_to_dict(program.grasped),
            "environment": _model_to_dict(program.environment),
        },
        "start_pose": _pose(program.start_X_EG, k),
        "final_state": {
            "id": program.final_state,
            "elements": _elements(program.final_elements, k),
        },
        "parameters": _parameters_to_dict(program.parameters, k),
        "primitives": [_primitive_to_dict(p, k) for p in program.primitives],
    }


# --------------------------------------------------------------------------------------------
# From JSON, with validation
# --------------------------------------------------------------------------------------------


class _MotionReader(_Reader):
    """The task reader's typed accessors plus the shapes a skill program needs."""

    def __init__(self, source: str) -> None:
        super().__init__(source or "motion")

    def positive(self, v: Any, where: str) -> float:
        x = self.number(v, where)
        if x <= 0:
            raise self.fail(where, f"expected a positive number, got {x!r}")
        return x

    def non_negative(self, v: Any, where: str) -> float:
        x = self.number(v, where)
        if x < 0:
            raise self.fail(where, f"expected a non-negative number, got {x!r}")
        return x

    def unit(self, v: Any, where: str, *, allow_zero: bool = False) -> FloatArray:
        a = self.vector(v, where, 3)
        n = float(np.linalg.norm(a))
        if abs(n - 1.0) > 1e-4 and not (allow_zero and n < 1e-12):
            raise self.fail(where, f"expected a unit vector, got {a.tolist()}")
        return a

    def rows(self, v: Any, where: str, *, orthonormal: bool = True) -> FloatArray:
        items = self.lst(v, where)
        if len(items) > 3:
            raise self.fail(where, f"expected at most 3 rows, got {len(items)}")
        a = np.array(
            [self.vector(r, f"{where}[{i}]", 3) for i, r in enumerate(items)], dtype=float
        ).reshape(-1, 3)
        if orthonormal and a.size and not np.allclose(a @ a.T, np.eye(len(a)), atol=1e-4):
            raise self.fail(where, "rows must be orthonormal unit vectors")
        return a

    def pose(self, v: Any, where: str, k: float) -> FloatArray:
        d = self.obj(v, where)
        p = self.vector(self.get(d, "position", where), f"{where}.position", 3) * k
        q = self.vector(self.get(d, "quaternion", where), f"{where}.quaternion", 4)
        if abs(float(np.linalg.norm(q)) - 1.0) > 1e-6:
            raise self.fail(f"{where}.quaternion", f"not a unit quaternion: {q.tolist()}")
        return pose_from_position_quaternion(p, q)

    def elements(self, v: Any, where: str, k: float) -> tuple[Element, ...]:
        out: list[Element] = []
        for j, ed_ in enumerate(self.lst(v, where)):
            we = f"{where}[{j}]"
            ed = self.obj(ed_, we)
            normals_l = self.lst(self.get(ed, "normals", we), f"{we}.normals")
            if not normals_l:
                raise self.fail(f"{we}.normals", "expected at least one normal")
            normals = np.array(
                [self.unit(n, f"{we}.normals[{m}]") for m, n in enumerate(normals_l)]
            )
            out.append(
                Element(
                    kind=self.string(self.get(ed, "kind", we), f"{we}.kind", KINDS),
                    grasped=self.feature(self.get(ed, "grasped", we), f"{we}.grasped"),
                    environment=self.feature(self.get(ed, "environment", we), f"{we}.environment"),
                    point=self.vector(self.get(ed, "point", we), f"{we}.point", 3) * k,
                    normals=normals,
                )
            )
        return tuple(out)

    def model(self, v: Any, where: str) -> ModelRef:
        return _model_from_dict(self, v, where)

    def optional_int(self, v: Any, where: str) -> int | None:
        return None if v is None else self.integer(v, where)


def _compliance_from_dict(rd: _MotionReader, v: Any, where: str, k: float) -> Compliance:
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


def _alignment_from_dict(rd: _MotionReader, v: Any, where: str, k: float) -> Alignment | None:
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
    )


def _stop_from_dict(rd: _MotionReader, v: Any, where: str, k: float) -> StopCondition:
    d = rd.obj(v, where)
    return StopCondition(
        force=rd.positive(rd.get(d, "force", where), f"{where}.force"),
        torque=rd.positive(rd.get(d, "torque", where), f"{where}.torque"),
        travel=rd.positive(rd.get(d, "travel", where), f"{where}.travel") * k,
        expected=rd.non_negative(d.get("expected", 0.0), f"{where}.expected") * k,
    )


def _primitive_from_dict(rd: _MotionReader, v: Any, i: int, k: float) -> Primitive:
    w = f"primitives[{i}]"
    d = rd.obj(v, w)
    index = rd.integer(rd.get(d, "index", w), f"{w}.index")
    if index != i:
        raise rd.fail(f"{w}.index", f"expected {i}, got {index}")
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
            elements=rd.elements(td.get("elements", []), f"{w}.target.elements", k),
            X_EG=rd.pose(rd.get(td, "pose", f"{w}.target"), f"{w}.target.pose", k),
        ),
        stop=_stop_from_dict(rd, rd.get(d, "stop", w), f"{w}.stop", travel_k),
        compliance=_compliance_from_dict(rd, rd.get(d, "compliance", w), f"{w}.compliance", k),
        alignment=alignment,
        via=tuple(
            rd.pose(X, f"{w}.via[{j}]", k)
            for j, X in enumerate(rd.lst(d.get("via", []), f"{w}.via"))
        ),
    )


def _parameters_from_dict(rd: _MotionReader, v: Any, k: float) -> PlanParameters:
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
    rd = _MotionReader(source)
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
        task=rd.model(rd.get(d, "task", "top level"), "task"),
        grasped=rd.model(rd.get(models, "grasped", "models"), "models.grasped"),
        environment=rd.model(rd.get(models, "environment", "models"), "models.environment"),
        start_X_EG=rd.pose(rd.get(d, "start_pose", "top level"), "start_pose", k),
        final_state=rd.string(rd.get(fs, "id", "final_state"), "final_state.id"),
        final_elements=rd.elements(fs.get("elements", []), "final_state.elements", k),
        parameters=_parameters_from_dict(rd, d.get("parameters", {}), k),
        primitives=tuple(_primitive_from_dict(rd, p, i, k) for i, p in enumerate(prims)),
    )
