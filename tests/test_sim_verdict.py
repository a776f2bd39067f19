"""The replay's verdict (apo.sim.replay.judge): contact states up to the models' symmetries."""

from __future__ import annotations

import numpy as np
import pytest

from apo.recognition import recognize_frames
from apo.sim.replay import judge, model_symmetries
from apo.synthetic import random_variant

pytest.importorskip("scipy")


def _variant(name: str, seed: int):  # type: ignore[no-untyped-def]
    demo = random_variant(seed, name=name)
    task = recognize_frames(demo.grasped, demo.environment, demo.times, demo.X_EG, units="mm").task
    return demo, task


@pytest.mark.parametrize(("name", "seed"), [("peg_in_hole_2d", 3), ("square_peg_in_hole", 11)])
def test_a_symmetric_twin_of_the_final_state_is_success(name: str, seed: int) -> None:
    demo, task = _variant(name, seed)
    G, E = demo.grasped, demo.environment
    X = task.states[-1].X_EG
    t = np.array([0.0])
    syms = model_symmetries(G)
    assert len(syms) >= 2  # the T-peg turns half a turn about its stem, the square peg 90 deg
    for S in syms[1:]:
        twin = (X @ S.S)[None]
        j = judge(task, G, E, t, twin)
        assert j.success and j.final_state == task.states[-1].id
        assert j.by_symmetry  # other features touch: not the task's elements as such
        exact = judge(task, G, E, t, twin, symmetric=False)
        assert not exact.success
    # the identity is the task's own state, not a twin
    j = judge(task, G, E, t, X[None])
    assert j.success and not j.by_symmetry


def test_an_environment_twin_is_success_and_a_lifted_pose_is_not() -> None:
    demo, task = _variant("peg_in_hole_2d", 5)
    G, E = demo.grasped, demo.environment
    X = task.states[-1].X_EG
    t = np.array([0.0])
    S_E = model_symmetries(E)
    assert len(S_E) >= 2  # the U-slot turns half a turn about its vertical
    j = judge(task, G, E, t, (np.linalg.inv(S_E[1].S) @ X)[None])
    assert j.success
    # the same pose 5 mm out of the slot (against the last insertion) is not the goal
    lifted = X.copy()
    first = task.states[0].X_EG
    lifted[:3, 3] += 0.005 * (first[:3, 3] - X[:3, 3]) / np.linalg.norm(first[:3, 3] - X[:3, 3])
    j = judge(task, G, E, t, lifted[None])
    assert not j.success and j.final_state != task.states[-1].id


def test_the_states_visited_are_judged_in_order() -> None:
    demo, task = _variant("peg_in_hole_2d", 8)
    j = judge(task, demo.grasped, demo.environment, demo.times, demo.X_EG_true)
    assert j.success
    order = [[s.id for s in task.states].index(s) for s in j.states_reached]
    assert order == sorted(order)
    assert j.states_reached[0] == task.states[0].id
