"""The skill program types and their JSON form ``apo.motion/1``."""

from __future__ import annotations

import copy
import json
from typing import Any

import numpy as np
import pytest

from apo.errors import InputFormatError
from apo.motion import (
    Alignment,
    Compliance,
    MotionSpace,
    PlanParameters,
    Primitive,
    PrimitiveKind,
    RotationType,
    SkillProgram,
    StopCondition,
    Target,
    program_from_dict,
    program_to_dict,
)
from apo.spatial import matrix_from_axis_angle
from apo.task import Element, ModelRef


def _pose(angle: float, p: list[float]) -> np.ndarray:
    X = np.eye(4)
    X[:3, :3] = matrix_from_axis_angle([0.3, -0.2, 1.0], angle)
    X[:3, 3] = p
    return X


def _compliance(force_rows: int) -> Compliance:
    basis = np.eye(3)
    return Compliance(
        center=np.array([0.01, 0.02, 0.03]),
        force_directions=basis[:force_rows],
        forces=np.full(force_rows, 2.0),
        torque_axes=basis[:1],
        torques=np.array([0.1]),
        position_directions=basis[force_rows:],
        position_axes=basis[1:],
    )


def _element() -> Element:
    return Element(
        kind="VF",
        grasped=("v", 3),
        environment=("f", 7),
        point=np.array([0.001, 0.002, 0.0]),
        normals=np.array([[0.0, 0.0, 1.0]]),
    )


def _program(units: str = "mm") -> SkillProgram:
    stop = StopCondition(force=4.0, torque=0.15, travel=0.02)
    approach = Primitive(
        index=0,
        kind=PrimitiveKind.APPROACH,
        space=None,
        type=None,
        transition=None,
        from_state="A",
        to_state="A",
        folded=(),
        direction=np.array([0.0, -1.0, 0.0]),
        point=None,
        subspace=np.zeros((0, 3)),
        source="plan",
        target=Target("A", (), _pose(0.1, [0.0, 0.05, 0.0])),
        stop=stop,
        compliance=_compliance(0),
    )
    align = Primitive(
        index=1,
        kind=PrimitiveKind.ALIGN,
        space=None,
        type=None,
        transition=0,
        from_state="A",
        to_state="B",
        folded=(),
        direction=np.zeros(3),
        point=None,
        subspace=np.zeros((0, 3)),
        source="plan",
        target=Target("A", (), _pose(0.1, [0.0, 0.04, 0.0])),
        stop=stop,
        compliance=_compliance(0),
        alignment=Alignment(np.eye(3)[:2], np.eye(3)[2:], 2e-4, 0.01),
    )
    push = Primitive(
        index=2,
        kind=PrimitiveKind.PUSH_TO,
        space=MotionSpace.ROTATION,
        type=RotationType.I,
        transition=0,
        from_state="A",
        to_state="B",
        folded=(),
        direction=np.array([1.0, 0.0, 0.0]),
        point=np.array([0.0, 0.035, 0.00007]),
        subspace=np.eye(3)[:1],
        source="contacts",
        target=Target("B", (_element(),), _pose(0.0, [0.0, 0.03, 0.0])),
        stop=StopCondition(force=4.0, torque=0.15, travel=0.3),
        compliance=_compliance(1),
    )
    return SkillProgram(
        units=units,
        task=ModelRef("task.json", "0" * 64, "task.json"),
        grasped=ModelRef("peg.step", None, "peg"),
        environment=ModelRef("../hole.step", "a" * 64, "hole"),
        start_X_EG=_pose(0.2, [0.0, 0.06, 0.0]),
        final_state="B",
        final_elements=(_element(),),
        primitives=(approach, align, push),
        parameters=PlanParameters(standoff=0.004),
    )


def _assert_programs_equal(a: SkillProgram, b: SkillProgram) -> None:
    assert program_to_dict(a) == program_to_dict(b)
    for pa, pb in zip(a.primitives, b.primitives, strict=True):
        np.testing.assert_allclose(pa.target.X_EG, pb.target.X_EG, atol=1e-9)
        np.testing.assert_allclose(pa.compliance.selection(), pb.compliance.selection())
        assert pa.stop.travel == pytest.approx(pb.stop.travel)


@pytest.mark.parametrize("units", ["mm", "m", "in"])
def test_round_trip_through_json(units: str) -> None:
    prog = _program(units)
    d = json.loads(json.dumps(program_to_dict(prog)))
    back = program_from_dict(d, source="motion.json")
    _assert_programs_equal(prog, back)
    assert back.parameters.standoff == pytest.approx(0.004)
    assert back.primitives[2].stop.travel == pytest.approx(0.3)  # radians: not scaled
    assert back.primitives[0].stop.travel == pytest.approx(0.02)  # metres: scaled


def test_lengths_are_written_in_task_units() -> None:
    d = program_to_dict(_program("mm"))
    assert d["schema"] == "apo.motion/1"
    assert d["start_pose"]["position"] == pytest.approx([0.0, 60.0, 0.0])
    p = d["primitives"][2]
    assert p["point"] == pytest.approx([0.0, 35.0, 0.07])
    assert p["stop"]["travel"] == pytest.approx(0.3)
    assert d["primitives"][0]["stop"]["travel"] == pytest.approx(20.0)
    assert d["primitives"][1]["alignment"]["tolerance"] == pytest.approx(0.2)
    assert d["parameters"]["standoff"] == pytest.approx(4.0)
    assert d["parameters"]["push_force"] == pytest.approx(5.0)


def test_selection_and_wrench() -> None:
    c = _compliance(1)
    S = c.selection()
    assert np.trace(S) == pytest.approx(2.0)
    np.testing.assert_allclose(c.wrench(), [0.1, 0, 0, 2.0, 0, 0])


def _mutate(d: dict[str, Any], path: list[Any], value: Any) -> dict[str, Any]:
    out = copy.deepcopy(d)
    node: Any = out
    for key in path[:-1]:
        node = node[key]
    if value is _DELETE:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return out


_DELETE = object()


@pytest.mark.parametrize(
    ("path", "value", "match"),
    [
        (["schema"], "apo.task/1", r"schema: expected 'apo.motion/1'"),
        (["units"], "furlong", r"units: expected one of"),
        (["primitives"], [], r"primitives: expected at least one"),
        (["primitives", 1, "index"], 5, r"primitives\[1\].index: expected 1"),
        (["primitives", 2, "kind"], "wiggle", r"primitives\[2\].kind: expected one of"),
        (["primitives", 2, "space"], None, r"primitives\[2\].space"),
        (["primitives", 0, "transition"], 3, r"primitives\[0\].transition"),
        (["primitives", 2, "direction"], [1, 1, 0], r"primitives\[2\].direction: expected a unit"),
        (["primitives", 2, "stop", "force"], 0, r"primitives\[2\].stop.force: expected a positive"),
        (["primitives", 2, "stop"], _DELETE, r"primitives\[2\]: missing field 'stop'"),
        (
            ["primitives", 2, "compliance", "position_directions"],
            [[0, 1, 0]],
            r"primitives\[2\].compliance.position_directions: .*orthonormal basis",
        ),
        (
            ["primitives", 2, "compliance", "forces"],
            [1.0, 2.0],
            r"primitives\[2\].compliance.forces: expected 1 entries",
        ),
        (["primitives", 1, "alignment"], None, r"primitives\[1\].alignment"),
        (
            ["primitives", 1, "alignment", "tolerance"],
            -1,
            r"primitives\[1\].alignment.tolerance: expected a positive",
        ),
        (
            ["primitives", 2, "target", "pose", "quaternion"],
            [1, 1, 0, 0],
            r"primitives\[2\].target.pose.quaternion: not a unit",
        ),
        (
            ["final_state", "elements", 0, "kind"],
            "FF",
            r"final_state.elements\[0\].kind: expected one of",
        ),
        (["models", "grasped", "sha256"], "xyz", r"models.grasped.sha256"),
        (["start_pose"], _DELETE, r"top level: missing field 'start_pose'"),
        (["parameters", "standoff"], "far", r"parameters.standoff: expected a finite"),
    ],
)
def test_bad_input_names_file_and_field(path: list[Any], value: Any, match: str) -> None:
    d = _mutate(program_to_dict(_program()), path, value)
    with pytest.raises(InputFormatError, match=r"^motion\.json: " + match):
        program_from_dict(d, source="motion.json")


def test_not_an_object() -> None:
    with pytest.raises(InputFormatError, match=r"motion\.json: top level: expected an object"):
        program_from_dict([1, 2], source="motion.json")
