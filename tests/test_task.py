import copy
import json

import numpy as np
import pytest

from apo.errors import InputFormatError
from apo.spatial import pose_from_position_quaternion
from apo.task import (
    SCHEMA,
    Element,
    ModelRef,
    Rejected,
    State,
    SubSkill,
    TaskModel,
    Transition,
    state_letters,
    task_from_dict,
    task_to_dict,
)

FREE = {"translation": (3, 0, 0, 0, 0, 0), "rotation": (3, 0, 0, 0, 0, 0)}
ONE_VF = {"translation": (2, 1, 0, 0, 0, 0), "rotation": (2, 1, 0, 0, 0, 0)}


def make_task(units: str = "mm") -> TaskModel:
    X0 = pose_from_position_quaternion([0.01, 0.02, 0.1], [1, 0, 0, 0])
    X1 = pose_from_position_quaternion([0.01, 0.02, 0.0005], [np.cos(0.2), 0, np.sin(0.2), 0])
    vf = Element("VF", ("v", 3), ("f", 7), np.array([0.001, 0.002, 0.0]), np.array([[0, 0, 1.0]]))
    ve = Element(
        "VE", ("v", 1), ("e", 2), np.array([0.0, 0.0, 0.0]), np.array([[0, 0, 1.0], [1.0, 0, 0]])
    )
    states = (
        State("A", (0, 4), (0.0, 0.4), False, (3, 0, 0, 3, 0, 0, 0, 0), FREE, (), X0, 0),
        State("B", (5, 5), (0.5, 0.5), True, (2, 1, 0, 2, 1, 0, 2, 2), ONE_VF, (vf, ve), X1, 5),
        State("C", (6, 9), (0.6, 0.9), False, (3, 0, 0, 3, 0, 0, 0, 0), FREE, (), X0, 7,
              same_as="A"),
    )  # fmt: skip
    push = SubSkill(
        "push_to", "rotation", "I", np.array([0.0, 1.0, 0.0]), np.array([0.001, 0.0, 0.003]),
        "contacts", np.array([[0.0, 1.0, 0.0]]),
    )  # fmt: skip
    transitions = (
        Transition("A", "B", 5, {"translation": (("M", "SD"),), "rotation": (("M", "SD"),)},
                   (push,), False, choice={"translation": "geometry", "rotation": "unique"},
                   alternatives={"translation": ((("M", "D"), ("D", "SD")),), "rotation": ()}),
        Transition("B", "C", 6, {"translation": (), "rotation": ()}, (), True),
    )  # fmt: skip
    return TaskModel(
        units=units,
        grasped=ModelRef("peg.step", "a" * 64, "peg"),
        environment=ModelRef("/abs/hole.step", None, "hole"),
        states=states,
        transitions=transitions,
        rejected=(Rejected((3, 3), ("VF v0-f1",), ("A",), "infeasible"),),
        n_frames=10,
        source="demo",
        threshold=0.002,
    )


@pytest.mark.parametrize("units", ["mm", "m", "cm", "in"])
def test_round_trip_through_json_text(units):
    task = make_task(units)
    d = task_to_dict(task)
    back = task_from_dict(json.loads(json.dumps(d)))
    assert task_to_dict(back) == d
    np.testing.assert_allclose(back.states[1].X_EG, task.states[1].X_EG, atol=1e-9)
    np.testing.assert_allclose(back.states[1].elements[0].point, [0.001, 0.002, 0], atol=1e-10)
    assert back.threshold == pytest.approx(0.002)


def test_lengths_written_in_the_task_units():
    d = task_to_dict(make_task("mm"))
    assert d["schema"] == SCHEMA
    assert d["frame"] == "environment"
    assert d["states"][0]["pose"]["position"] == pytest.approx([10.0, 20.0, 100.0])
    assert d["states"][1]["elements"][0]["point"] == pytest.approx([1.0, 2.0, 0.0])
    assert d["states"][1]["elements"][1]["normals"] == [[0, 0, 1], [1, 0, 0]]
    assert d["threshold"] == pytest.approx(2.0)
    q = d["states"][1]["pose"]["quaternion"]
    assert q == pytest.approx([np.cos(0.2), 0, np.sin(0.2), 0])
    assert d["transitions"][0]["dof_transitions"]["translation"] == [["M", "SD"]]
    assert d["transitions"][0]["subskills"][0] == {
        "kind": "push_to", "space": "rotation", "type": "I", "direction": [0.0, 1.0, 0.0],
        "point": [1.0, 0.0, 3.0], "source": "contacts", "subspace": [[0.0, 1.0, 0.0]],
    }  # fmt: skip
    assert d["models"]["grasped"] == {"path": "peg.step", "sha256": "a" * 64, "name": "peg"}
    assert d["transitions"][0]["decomposition"] == {
        "translation": {"choice": "geometry", "alternatives": [[["M", "D"], ["D", "SD"]]]},
        "rotation": {"choice": "unique", "alternatives": []},
    }


def test_subskill_sequence():
    assert make_task().subskill_sequence() == [("push_to", "rotation", "I")]


def test_state_lookup():
    t = make_task()
    assert t.state("B").singular
    with pytest.raises(KeyError):
        t.state("Z")


def test_state_letters():
    assert state_letters(0) == []
    assert state_letters(27)[25:] == ["Z", "AA"]
    assert len(set(state_letters(800))) == 800


def _mutate(path, value):
    d = task_to_dict(make_task())
    d2 = copy.deepcopy(d)
    cur = d2
    for k in path[:-1]:
        cur = cur[k]
    if value is KeyError:
        del cur[path[-1]]
    else:
        cur[path[-1]] = value
    return d2


@pytest.mark.parametrize(
    ("path", "value", "match"),
    [
        (("schema",), "apo.task/0", r"schema: expected 'apo.task/1'"),
        (("units",), "furlong", r"units: expected one of"),
        (("frame",), "camera", r"frame: expected one of"),
        (("models", "grasped"), KeyError, r"models: missing field 'grasped'"),
        (("models", "grasped", "sha256"), "xyz", r"models.grasped.sha256"),
        (("states", 1, "fig25"), [1, 2, 3], r"states\[1\].fig25: expected 8 entries"),
        (("states", 1, "fig25", 0), 4, r"states\[1\].fig25: entries must be in 0..3"),
        (("states", 1, "fig25", 0), 1.5, r"states\[1\].fig25\[0\]: expected an integer"),
        (("states", 1, "id"), "A", r"duplicate state id"),
        (("states", 1, "frames"), [3, 5], r"states\[1\].frames: frames \[3, 5\] out of order"),
        (("states", 1, "singular"), False, r"states\[1\].singular: False disagrees"),
        (("states", 1, "elements", 0, "kind"), "XX", r"elements\[0\].kind: expected one of"),
        (("states", 1, "elements", 0, "point"), [1, 2], r"point: expected 3 entries"),
        (("states", 1, "elements", 0, "point", 0), float("nan"), r"expected a finite number"),
        (("states", 1, "elements", 0, "normals"), [[0, 0, 2]], r"normals must be unit"),
        (("states", 1, "pose", "quaternion"), [1, 1, 0, 0], r"not a unit quaternion"),
        (("states", 2, "same_as"), "Q", r"unknown earlier state 'Q'"),
        (("states", 1, "six", "rotation"), [1, 1, 1, 1, 0, 0], r"summing to 3"),
        (("transitions",), [], r"expected 2 \(one between each pair"),
        (("transitions", 0, "to"), "C", r"expected A -> B, got A -> C"),
        (("transitions", 0, "dof_transitions", "rotation", 0), ["M", "Q"], r"expected one of"),
        (("transitions", 0, "subskills", 0, "kind"), "wiggle", r"subskills\[0\].kind"),
        (("transitions", 0, "subskills", 0, "type"), "III", r"subskills\[0\].type"),
        (("transitions", 0, "critical"), "yes", r"critical: expected true or false"),
        (("rejected", 0, "replaced_by"), ["Z"], r"rejected\[0\].replaced_by"),
        (("n_frames",), 5, r"n_frames: 5 but the last state ends at frame 9"),
        (("states",), {"A": 1}, r"states: expected a list"),
    ],
)
def test_validation_names_the_field(path, value, match):
    with pytest.raises(InputFormatError, match=match):
        task_from_dict(_mutate(path, value), source="task.json")


def test_validation_names_the_source():
    with pytest.raises(InputFormatError, match=r"^out/task.json: top level: expected an object"):
        task_from_dict([1, 2], source="out/task.json")


def test_unknown_units_rejected_on_write():
    with pytest.raises(ValueError, match="unknown units"):
        task_to_dict(make_task("furlong"))


def test_empty_task_round_trips():
    t = TaskModel("m", ModelRef("g.stl", None), ModelRef("e.stl", None), (), ())
    d = task_to_dict(t)
    assert task_from_dict(d).states == ()


# ---------------------------------------------------------------------------------------------
# Reports of a task (apo.report)
# ---------------------------------------------------------------------------------------------


def test_table_shows_states_numbers_subskills_and_critical_marks():
    from apo.report import render_table

    text = render_table(make_task())
    lines = text.splitlines()
    assert lines[0].split()[:3] == ["state", "frames", "time"]
    row_a = next(ln for ln in lines if ln.startswith("A "))
    assert row_a.split()[1:] == ["0-4", "0.000-0.400", "3", "0", "0", "3", "0", "0", "0", "0", "0"]
    row_b = next(ln for ln in lines if ln.startswith("B*"))
    assert "S 2 1 0" in row_b
    assert "(1) A->B  push-to R(I)" in text
    assert "(2) B->C  CRITICAL  -" in text
    assert "(= A)" in next(ln for ln in lines if ln.startswith("C "))
    assert "frames 3-3 -> A: infeasible" in text


def test_plot_writes_a_png(tmp_path):
    from apo.report import plot_dof

    out = plot_dof(make_task(), tmp_path / "dof.png", times=np.linspace(0, 0.9, 10))
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert out.stat().st_size > 5000


def test_table_lists_the_longest_rejected_runs_and_counts_the_rest():
    from dataclasses import replace

    from apo.report import render_table
    from apo.report.table import MAX_REJECTED_LINES

    runs = tuple(
        Rejected((10 * i, 10 * i + (5 if i == 7 else 0)), ("VF v0-f1",), ("A",), "noise")
        for i in range(MAX_REJECTED_LINES + 3)
    )
    text = render_table(replace(make_task(), rejected=runs))
    listed = [ln for ln in text.splitlines() if ln.startswith("  frames ")]
    assert len(listed) == MAX_REJECTED_LINES
    assert "  frames 70-75 -> A: noise" in listed  # the long run is kept
    assert [int(ln.split()[1].split("-")[0]) for ln in listed] == sorted(
        int(ln.split()[1].split("-")[0]) for ln in listed
    )
    assert "... and 3 shorter run(s)" in text
    assert f"repair: {MAX_REJECTED_LINES + 3} observed run(s) rejected" in text
