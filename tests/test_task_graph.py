"""The state graph of task.json: each distinct contact state once, transitions counted."""

import json

import numpy as np
import pytest

from apo.errors import InputFormatError
from apo.task import state_graph, task_from_dict, task_to_dict


@pytest.fixture(scope="module")
def repeated_task():
    from pathlib import Path

    from apo.io.meshes import load_polyhedron
    from apo.io.poses import load_demonstration
    from apo.recognition import recognize

    data = Path(__file__).resolve().parents[2] / "shared" / "data" / "apo-peg-in-hole"
    if not data.is_dir():
        pytest.skip("first author's data not found at ../shared/data/apo-peg-in-hole")
    dem = load_demonstration(data / "peg_in_hole.pose.list")
    G = load_polyhedron(dem.grasped_path, units="mm")
    E = load_polyhedron(dem.environment_path, units="mm")
    X = np.concatenate([dem.X_EG] * 3)
    return recognize(G, E, np.arange(len(X), dtype=float), X)


def test_a_repeated_demonstration_gives_each_state_once_with_its_visits(repeated_task):
    task = repeated_task
    g = state_graph(task)
    assert len(task.states) == 24  # the sequence is unchanged: A .. H three times
    assert [s.id for s in g.states] == list("ABCDEFGH")
    assert all(len(s.visits) == 3 and len(s.states) == 3 for s in g.states)
    assert g.states[0].visits[1][0] == 41 and g.states[0].states[1] == "I"
    counts = {(e.from_id, e.to_id): e.count for e in g.transitions}
    assert counts[("A", "B")] == 3 and counts[("H", "A")] == 2
    assert sum(counts.values()) == len(task.transitions)
    crit = [e for e in g.transitions if e.critical]
    assert [(e.from_id, e.to_id, e.count) for e in crit] == [("F", "G", 3)]


def test_graph_round_trips_and_a_wrong_graph_is_refused(repeated_task):
    d = json.loads(json.dumps(task_to_dict(repeated_task)))
    assert d["graph"]["states"][0] == {"id": "A", "states": ["A", "I", "Q"],
                                       "visits": [[0, 11], [41, 52], [82, 93]]}  # fmt: skip
    back = task_from_dict(d, source="task.json")
    assert back.graph() == state_graph(repeated_task)
    d["graph"]["transitions"][0]["count"] += 1
    with pytest.raises(InputFormatError, match=r"task.json: graph: does not match"):
        task_from_dict(d, source="task.json")
    del d["graph"]  # optional: files written before it was added still read
    assert task_from_dict(d).graph() == state_graph(repeated_task)
