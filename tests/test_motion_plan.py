"""The planner: task model -> skill program (sub-skills in order, geometry from the task)."""

from __future__ import annotations

import json
from dataclasses import replace
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from apo import synthetic
from apo.errors import InputFormatError
from apo.motion import (
    PlanParameters,
    Primitive,
    PrimitiveKind,
    SkillProgram,
    plan,
    program_from_dict,
    program_to_dict,
)
from apo.recognition import recognize
from apo.spatial import matrix_from_axis_angle
from apo.task import Element, State, SubSkill, TaskModel, Transition

SUBSKILL_KINDS = {PrimitiveKind.PUSH_TO, PrimitiveKind.SLIDE, PrimitiveKind.RELEASE}

# The paper's section 5.1.1 for the T-peg (states A..H): (1), (4), (7) push-to in both spaces
# with type I rotation; (2) slide in both; (3) none; (5) rotational slide only; (6) critical.
PAPER_T_PEG = [
    ("approach", None, None),
    ("push_to", "translation", None),
    ("push_to", "rotation", "I"),
    ("slide", "translation", None),
    ("slide", "rotation", None),
    ("push_to", "translation", None),
    ("push_to", "rotation", "I"),
    ("slide", "rotation", None),
    ("align", None, None),
    ("push_to", "translation", None),
    ("push_to", "rotation", "I"),
]


@cache
def _task(name: str) -> TaskModel:
    demo = synthetic.all_demos()[name]
    return recognize(demo.grasped, demo.environment, demo.times, demo.X_EG, units="mm")


@cache
def _real_task(path: str) -> TaskModel:
    from apo.io.meshes import load_polyhedron
    from apo.io.poses import load_demonstration

    dem = load_demonstration(path)
    assert dem.grasped_path is not None and dem.environment_path is not None
    G = load_polyhedron(dem.grasped_path, units="mm")
    E = load_polyhedron(dem.environment_path, units="mm")
    return recognize(G, E, dem.times, dem.X_EG, units="mm", source=Path(path).name)


DEMOS = sorted(synthetic.all_demos())


def check_program_structure(task: TaskModel, program: SkillProgram) -> None:
    """The invariants every plan keeps (a reusable assertion for the sim's tests too)."""
    prims = program.primitives
    assert prims[0].kind == PrimitiveKind.APPROACH
    assert [p.index for p in prims] == list(range(len(prims)))
    # 1:1 with the task's sub-skill sequence, in order, with the task's directions
    skills = [p for p in prims if p.kind in SUBSKILL_KINDS]
    assert [(str(p.kind), str(p.space), p.type) for p in skills] == [
        (k, s, t) for k, s, t in task.subskill_sequence()
    ]
    flat = [(i, u) for i, t in enumerate(task.transitions) for u in t.subskills]
    for p, (i, u) in zip(skills, flat, strict=True):
        assert p.transition == i
        # the task's direction, or its reverse when the demonstration clearly moves against it
        flipped = p.source == "poses" and u.source != "poses"
        np.testing.assert_allclose(
            p.direction, -u.direction if flipped else u.direction, atol=1e-12
        )
        assert (p.from_state, p.to_state) == (
            task.transitions[i].from_id,
            task.transitions[i].to_id,
        )
    # an align right before the primitive that executes each critical transition
    critical = [i for i, t in enumerate(task.transitions) if t.critical]
    aligns = [k for k, p in enumerate(prims) if p.kind == PrimitiveKind.ALIGN]
    assert [prims[k].transition for k in aligns] == critical
    for k in aligns:
        nxt = prims[k + 1] if k + 1 < len(prims) else None
        assert nxt is not None and nxt.kind in SUBSKILL_KINDS
        assert nxt.transition == prims[k].transition or prims[k].transition in nxt.folded
    # every transition without sub-skill is folded exactly once, into a later primitive
    folded = [f for p in prims for f in p.folded]
    assert folded == [i for i, t in enumerate(task.transitions) if not t.subskills]
    for p in prims:
        for f in p.folded:
            assert p.transition is None or f < p.transition or p is prims[-1]
    # the end is the task's final state
    final = task.states[-1]
    assert program.final_state == final.id
    np.testing.assert_allclose(prims[-1].target.X_EG, final.X_EG, atol=1e-12)
    for p in prims:
        check_compliance(p)


def check_compliance(p: Primitive) -> None:
    c = p.compliance
    for F, P in ((c.force_directions, c.position_directions), (c.torque_axes, c.position_axes)):
        B = np.vstack([F, P])
        np.testing.assert_allclose(B @ B.T, np.eye(3), atol=1e-9)
    S = c.selection()
    np.testing.assert_allclose(S @ S, S, atol=1e-9)


@pytest.mark.parametrize("name", DEMOS)
def test_every_scripted_demo_plans_its_subskills_in_order(name: str) -> None:
    task = _task(name)
    program = plan(task)
    check_program_structure(task, program)


def test_t_peg_plan_is_the_papers() -> None:
    program = plan(_task("peg_in_hole_2d"))
    assert program.sequence() == PAPER_T_PEG
    align = program.primitives[8]
    assert align.alignment is not None
    assert align.transition == 5  # (6) F -> G, the critical one
    assert program.primitives[9].folded == (5,)
    assert program.primitives[5].folded == (2,)  # (3) C -> D: SM -> M, part of the next motion


def test_real_demonstration_plan_is_the_papers(real_data_dir: Path) -> None:
    task = _real_task(str(real_data_dir / "peg_in_hole.pose.list"))
    program = plan(task)
    check_program_structure(task, program)
    assert program.sequence() == PAPER_T_PEG


@pytest.mark.parametrize("name", DEMOS)
def test_forces_push_along_the_direction_and_into_kept_contacts(name: str) -> None:
    task = _task(name)
    pp = PlanParameters()
    for p in plan(task, parameters=pp).primitives:
        c = p.compliance
        f = c.force_directions.T @ c.forces
        tq = c.torque_axes.T @ c.torques
        if p.kind in (PrimitiveKind.PUSH_TO, PrimitiveKind.SLIDE) and p.space == "translation":
            # the direction of motion is force-controlled, pushing along it
            assert np.linalg.norm(c.force_directions @ p.direction) == pytest.approx(1.0)
            assert f @ p.direction == pytest.approx(pp.push_force)
        if p.space == "rotation":
            # a turn is position-controlled about its axis, guarded by the reaction torque
            assert np.linalg.norm(c.position_axes @ p.direction) == pytest.approx(1.0)
            assert abs(tq @ p.direction) < 1e-12
            if p.kind != PrimitiveKind.RELEASE:
                assert "torque" in p.stop.until
        if p.kind in SUBSKILL_KINDS:
            assert p.stop.until and p.profile is not None
            # the force acts at the centroid of the contacts kept during the motion
            kept = [e for e in task.state(p.from_state).elements if p.kind != "release"]
            if kept:
                a = task.state(p.from_state)
                pts = [p.target.X_EG @ np.linalg.inv(a.X_EG) @ np.append(e.point, 1) for e in kept]
                np.testing.assert_allclose(c.center, np.mean(pts, axis=0)[:3], atol=1e-9)
        if p.kind == PrimitiveKind.RELEASE:
            # a release moves away by position control, no force along its direction
            rows = c.force_directions if p.space == "translation" else c.torque_axes
            assert np.all(np.abs(rows @ p.direction) < 1e-9)
        if p.kind == PrimitiveKind.APPROACH:
            assert c.force_directions.shape[0] == 0 and c.torque_axes.shape[0] == 0
            assert p.stop.collision and p.stop.until == ("pose",)
        if p.kind == PrimitiveKind.ALIGN:
            # feels for the entrance: pressed along it, everything else position-controlled
            se = p.alignment.search
            assert se is not None and p.stop.until == ("entrance",)
            np.testing.assert_allclose(
                c.force_directions.T @ c.forces, pp.hold_force * se.direction
            )
            assert c.torque_axes.shape[0] == 0
            assert np.allclose(se.directions @ se.direction, 0.0)
            assert se.pattern == ("none", "zigzag", "spiral")[len(se.directions)]
        # never pulls away from a contact of the start state it keeps
        if p.transition is not None and p.kind != PrimitiveKind.ALIGN:
            a = task.state(p.from_state)
            for e in a.elements:
                for n in e.normals:
                    assert f @ n <= 1e-9 + pp.push_force * max(0.0, p.direction @ n)


@pytest.mark.parametrize("name", DEMOS)
def test_approach_stops_at_the_standoff(name: str) -> None:
    task = _task(name)
    pp = PlanParameters(standoff=0.004)
    program = plan(task, parameters=pp)
    first = program.primitives[1]
    assert first.kind == PrimitiveKind.PUSH_TO and first.space == "translation"
    X_s, X_c = program.primitives[0].target.X_EG, first.target.X_EG
    np.testing.assert_allclose(X_s[:3, :3], X_c[:3, :3], atol=1e-12)
    np.testing.assert_allclose(X_c[:3, 3] - X_s[:3, 3], pp.standoff * first.direction, atol=1e-12)
    assert first.stop.expected == pytest.approx(pp.standoff)
    assert first.stop.travel == pytest.approx(pp.standoff + pp.travel_margin)


def test_direction_against_the_demonstration_is_reversed() -> None:
    # a noisy T-peg whose rotational slide E -> F gets the wrong sign from the contacts
    demo = synthetic.add_noise(synthetic.peg_in_hole_2d(), sigma_mm=0.5, sigma_deg=0.5, seed=3)
    task = recognize(demo.grasped, demo.environment, demo.times, demo.X_EG, units="mm")
    program = plan(task)
    check_program_structure(task, program)
    for p in program.primitives:
        if p.kind in SUBSKILL_KINDS and p.space == "rotation":
            # the motion to the target never goes backwards about the primitive's axis
            start = program.primitives[p.index - 1].target.X_EG
            w = Rotation.from_matrix(p.target.X_EG[:3, :3] @ start[:3, :3].T).as_rotvec()
            assert w @ p.direction > -0.5 * PlanParameters().angular_margin


@pytest.mark.parametrize("name", DEMOS)
def test_approach_crosses_over_above_start_and_standoff(name: str) -> None:
    check_approach(plan(_task(name)))


def check_approach(program: SkillProgram) -> None:
    """Rise (or stay), cross at the top level, then come straight down to the stand-off."""
    approach, first = program.primitives[0], program.primitives[1]
    up = -first.direction
    legs = [program.start_X_EG, *approach.via, approach.target.X_EG]
    levels = [float(up @ X[:3, 3]) for X in legs]
    top = max(levels)
    assert all(lv == pytest.approx(top) for lv in levels[1:-1])
    assert top >= levels[0] - 1e-12 and top >= levels[-1] - 1e-12
    if approach.via:
        np.testing.assert_allclose(approach.via[-1][:3, :3], legs[-1][:3, :3], atol=1e-12)
        drop = legs[-1][:3, 3] - approach.via[-1][:3, 3]
        np.testing.assert_allclose(drop, np.linalg.norm(drop) * first.direction, atol=1e-12)
    np.testing.assert_allclose(approach.direction, first.direction, atol=1e-9)


def test_align_directions_are_the_newly_constrained_ones() -> None:
    task = _task("square_peg_in_hole")
    program = plan(task, parameters=PlanParameters(clearance=0.0001))
    (align,) = [p for p in program.primitives if p.kind == PrimitiveKind.ALIGN]
    a = align.alignment
    assert a is not None
    # square peg entering a square hole along z: x and y translations, all three rotations
    T = a.translations.T @ a.translations
    np.testing.assert_allclose(T, np.diag([1.0, 1.0, 0.0]), atol=1e-9)
    assert a.rotations.shape[0] == 3
    assert a.tolerance == pytest.approx(0.0001)
    assert 0 < a.angular_tolerance < 0.01


@pytest.mark.parametrize("name", DEMOS)
def test_round_trip_of_planned_programs(name: str) -> None:
    program = plan(_task(name))
    d = json.loads(json.dumps(program_to_dict(program)))
    back = program_from_dict(d, source="motion.json")
    _assert_json_close(program_to_dict(back), d)
    assert back.sequence() == program.sequence()


def _assert_json_close(a: object, b: object, where: str = "") -> None:
    """Equal JSON values, numbers to 1e-8 (a length rounded in mm, read back in m)."""
    if isinstance(a, dict) and isinstance(b, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _assert_json_close(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list) and isinstance(b, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_json_close(x, y, f"{where}[{i}]")
    elif isinstance(a, float | int) and not isinstance(a, bool):
        assert b == pytest.approx(a, abs=1e-8), where
    else:
        assert a == b, where


# --------------------------------------------------------------------------------------------
# A rigid motion of the whole scene moves the plan with it
# --------------------------------------------------------------------------------------------


def _move_element(e: Element, T: np.ndarray) -> Element:
    R = T[:3, :3]
    return replace(e, point=R @ e.point + T[:3, 3], normals=e.normals @ R.T)


def _move_subskill(u: SubSkill, T: np.ndarray) -> SubSkill:
    R = T[:3, :3]
    return replace(
        u,
        direction=R @ u.direction,
        point=None if u.point is None else R @ u.point + T[:3, 3],
        subspace=u.subspace @ R.T,
    )


def _move_task(task: TaskModel, T: np.ndarray) -> TaskModel:
    states = tuple(
        replace(
            s,
            elements=tuple(_move_element(e, T) for e in s.elements),
            X_EG=T @ s.X_EG,
        )
        for s in task.states
    )
    transitions = tuple(
        replace(t, subskills=tuple(_move_subskill(u, T) for u in t.subskills))
        for t in task.transitions
    )
    return replace(task, states=states, transitions=transitions)


def _projector(rows: np.ndarray) -> np.ndarray:
    return rows.T @ rows


@settings(max_examples=8, deadline=None)
@given(
    axis=st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda a: np.linalg.norm(a) > 0.1),
    angle=st.floats(-np.pi, np.pi),
    shift=st.tuples(*[st.floats(-0.5, 0.5)] * 3),
    name=st.sampled_from(DEMOS),
)
def test_plan_moves_with_the_scene(
    axis: tuple[float, float, float], angle: float, shift: tuple[float, float, float], name: str
) -> None:
    T = np.eye(4)
    T[:3, :3] = matrix_from_axis_angle(axis, angle)
    T[:3, 3] = shift
    R = T[:3, :3]
    task = _task(name)
    a, b = plan(task), plan(_move_task(task, T))
    assert a.sequence() == b.sequence()
    for p, q in zip(a.primitives, b.primitives, strict=True):
        np.testing.assert_allclose(q.direction, R @ p.direction, atol=1e-7)
        np.testing.assert_allclose(q.target.X_EG, T @ p.target.X_EG, atol=1e-7)
        if p.point is not None:
            assert q.point is not None
            np.testing.assert_allclose(q.point, R @ p.point + T[:3, 3], atol=1e-7)
        pc, qc = p.compliance, q.compliance
        np.testing.assert_allclose(qc.center, R @ pc.center + T[:3, 3], atol=1e-7)
        for rows_p, rows_q in (
            (pc.force_directions, qc.force_directions),
            (pc.torque_axes, qc.torque_axes),
        ):
            np.testing.assert_allclose(_projector(rows_q), R @ _projector(rows_p) @ R.T, atol=1e-7)
        np.testing.assert_allclose(
            qc.force_directions.T @ qc.forces, R @ (pc.force_directions.T @ pc.forces), atol=1e-7
        )
        np.testing.assert_allclose(
            qc.torque_axes.T @ qc.torques, R @ (pc.torque_axes.T @ pc.torques), atol=1e-7
        )
        assert q.stop.expected == pytest.approx(p.stop.expected, abs=1e-7)
        if p.alignment is not None:
            assert q.alignment is not None
            for rp, rq in (
                (p.alignment.translations, q.alignment.translations),
                (p.alignment.rotations, q.alignment.rotations),
            ):
                np.testing.assert_allclose(_projector(rq), R @ _projector(rp) @ R.T, atol=1e-6)


# --------------------------------------------------------------------------------------------
# Edge cases and bad input
# --------------------------------------------------------------------------------------------


def test_task_without_states_is_an_error() -> None:
    task = replace(_task("block_tipping"), states=(), transitions=())
    with pytest.raises(InputFormatError, match="no states"):
        plan(task)


def test_single_state_task_is_an_approach_only() -> None:
    task = _task("block_tipping")
    one = replace(task, states=task.states[:1], transitions=())
    program = plan(one)
    assert program.sequence() == [("approach", None, None)]
    np.testing.assert_allclose(program.primitives[0].target.X_EG, task.states[0].X_EG)


def test_trailing_transition_without_subskill_is_folded_into_the_last_primitive() -> None:
    task = _task("block_tipping")
    last = task.states[-1]
    extra = State(
        id="Z",
        frames=(last.frames[1] + 1, last.frames[1] + 1),
        times=(last.times[1] + 1, last.times[1] + 1),
        singular=last.singular,
        fig25=last.fig25,
        six=last.six,
        elements=last.elements,
        X_EG=last.X_EG,
    )
    tr = Transition(
        from_id=last.id,
        to_id="Z",
        frame=extra.frames[0],
        dof_transitions={"translation": (), "rotation": ()},
        subskills=(),
        critical=False,
    )
    longer = replace(
        task,
        states=(*task.states, extra),
        transitions=(*task.transitions, tr),
        n_frames=task.n_frames + 1,
    )
    program = plan(longer)
    assert program.primitives[-1].folded == (len(longer.transitions) - 1,)
    assert program.primitives[-1].target.state == "Z"
    assert program.final_state == "Z"


# --------------------------------------------------------------------------------------------
# Randomised variants, noisy observations
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("name", DEMOS)
def test_randomised_noisy_variants_plan_their_subskills(name: str, seed: int) -> None:
    # frame count, rate, approach angle, margin and a random placement of the whole scene
    demo = synthetic.random_variant(seed, name=name)
    demo = synthetic.add_noise(demo, sigma_mm=0.3, sigma_deg=0.3, seed=seed)
    task = recognize(demo.grasped, demo.environment, demo.times, demo.X_EG, units="mm")
    program = plan(task)
    check_program_structure(task, program)
    check_approach(program)
    for p in program.primitives:
        if p.alignment is not None:
            check_alignment(task, p)


def check_alignment(task: TaskModel, p: Primitive) -> None:
    """After an align, the object matches the entrance in the aligned directions."""
    a = p.alignment
    assert a is not None and p.transition is not None
    b = task.state(task.transitions[p.transition].to_id)
    X_al, X_b = p.target.X_EG, b.X_EG
    D = X_b @ np.linalg.inv(X_al)
    w = Rotation.from_matrix(D[:3, :3]).as_rotvec()
    assert np.all(np.abs(a.rotations @ w) < 1e-9)
    c = np.mean([e.point for e in b.elements], axis=0)
    c_al = (X_al @ np.linalg.inv(X_b) @ np.append(c, 1.0))[:3]
    assert np.all(np.abs(a.translations @ (c - c_al)) < 1e-9)
    assert a.translations.shape[0] + a.rotations.shape[0] >= 1


def test_real_demonstration_align(real_data_dir: Path) -> None:
    task = _real_task(str(real_data_dir / "peg_in_hole.pose.list"))
    (align,) = [p for p in plan(task).primitives if p.kind == PrimitiveKind.ALIGN]
    check_alignment(task, align)
    assert align.stop.expected > 0  # the observed pose at the entrance is not aligned
