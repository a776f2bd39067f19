"""Symmetric parts: the task model does not depend on which symmetric twin a tracker chose.

A tracker that sees only surfaces returns any twin ``X_EG @ S`` of the grasped object's pose
(``S`` one of its symmetries), and ``X_CE @ S_E`` for the environment, i.e.
``X_E'G = S_E^-1 @ X_EG``. The contact states and the sub-skills recognised must be the same.
"""

from __future__ import annotations

import numpy as np
import pytest

from apo.perception.example import polyhedron_triangles
from apo.recognition import recognize
from apo.symmetry import nearest_twin, symmetries
from apo.synthetic import peg_in_hole_2d, square_peg_in_hole


def _summary(task: object) -> tuple[list[str], list[tuple[str, str, str | None]]]:
    return [s.id for s in task.states], task.subskill_sequence()  # type: ignore[attr-defined]


@pytest.mark.parametrize("make", [peg_in_hole_2d, square_peg_in_hole])
def test_task_model_does_not_depend_on_the_twin(make: object) -> None:
    demo = make()  # type: ignore[operator]
    sym_G = symmetries(*polyhedron_triangles(demo.grasped))
    sym_E = symmetries(*polyhedron_triangles(demo.environment))
    assert len(sym_G) >= 2  # both pegs are symmetric (the T-peg 2, the square peg 8)
    truth = _summary(recognize(demo.grasped, demo.environment, demo.times, demo.X_EG_true))
    rng = np.random.default_rng(0)
    # One twin for the whole sequence (what the tracker returns: each pose is the twin
    # nearest the previous one): every twin of G, with the identity and another twin of E.
    pairs = [(k_E, k_G) for k_E in {0, len(sym_E) - 1} for k_G in range(len(sym_G))]
    for i in rng.choice(len(pairs), min(len(pairs), 4), replace=False):
        k_E, k_G = pairs[i]
        X = np.linalg.inv(sym_E[k_E].S) @ demo.X_EG_true @ sym_G[k_G].S
        got = recognize(demo.grasped, demo.environment, demo.times, X)
        assert _summary(got) == truth, (k_E, k_G)
    # A different twin at every frame (a tracker that flips) breaks the motion between
    # frames; mapping each pose to the twin nearest the previous one, as apo track does,
    # restores one continuous twin and the same task.
    ks = rng.integers(len(sym_G), size=len(demo.times))
    X = np.einsum("nij,njk->nik", demo.X_EG_true, np.stack([sym_G[k].S for k in ks]))
    length = float(np.ptp(demo.grasped.vertices, axis=0).max())
    for n in range(1, len(X)):
        X[n] = nearest_twin(X[n], X[n - 1], sym_G, length=length)[0]
    assert np.allclose(X, demo.X_EG_true @ sym_G[ks[0]].S, atol=1e-9)
    got = recognize(demo.grasped, demo.environment, demo.times, X)
    assert _summary(got) == truth
