"""Tests of the recognition package's stage functions, one at a time."""

import numpy as np
import pytest

from apo.contact import ContactFinder
from apo.errors import InputFormatError
from apo.recognition.candidates import canonical_ids
from apo.recognition.contacts import group_states, observed_states
from apo.recognition.decoding import constrained_path, near_pairs, reachable, run_bounds
from apo.recognition.inputs import check_scale
from apo.recognition.types import CandidateState, Scene, SegmentationCosts
from apo.shapes import box


def _scene(zs):
    g, e = box([0.02, 0.02, 0.02]), box([0.1, 0.1, 0.02])
    X = np.tile(np.eye(4), (len(zs), 1, 1))
    X[:, 2, 3] = zs
    f = ContactFinder(g, e, threshold=0.002)
    return Scene(g, e, X, f, ContactFinder(g, e), SegmentationCosts())


def test_run_bounds_gives_first_and_last_of_each_run():
    assert run_bounds(np.array([3, 3, 1, 1, 1, 3])) == [(0, 1), (2, 4), (5, 5)]


def test_reachable_is_the_transitive_closure():
    f = np.eye(3, dtype=bool)
    f[0, 1] = f[1, 2] = True
    r = reachable(f)
    assert r[0, 2] and not r[2, 0]


def test_near_pairs_only_pairs_within_the_window():
    labels = np.array([0] * 30 + [1] * 30 + [2] * 30)
    near = near_pairs(labels, 3, 4)
    assert near[0, 1] and near[1, 2] and not near[0, 2]


def test_constrained_path_goes_through_the_state_that_makes_a_change_direct():
    e = np.array([[0, 5, 5], [0, 5, 5], [5, 3, 3.5], [5, 5, 0], [5, 5, 0]], dtype=float)
    feasible = np.array([[1, 1, 0], [1, 1, 1], [0, 1, 1]], dtype=bool)
    assert constrained_path(e, feasible, 1.0, 1e6).tolist() == [0, 0, 1, 2, 2]
    # without the jump penalty the direct change is cheaper
    assert constrained_path(e, feasible, 1.0, 0.0).tolist() == [0, 0, 2, 2, 2]


def test_group_states_labels_in_order_of_first_appearance():
    # G resting on E's top face (z = 0.01 + 0.01), lifted, resting again
    scene = _scene([0.02, 0.05, 0.05, 0.0205])
    obs = group_states(observed_states(scene))
    assert obs.labels.tolist() == [0, 1, 1, 0]
    assert len(obs.keys) == 2 and obs.keys[1] == frozenset()
    assert len(obs.keys[0]) == 4  # the four bottom corners on the top face


def test_canonical_ids_join_candidates_with_the_same_closure():
    scene = _scene([0.02])
    s = scene.finder.find(scene.X[0])

    def cand(converged):
        return CandidateState(s.key, s, None, 0, scene.X[0], converged, 1)

    ids = canonical_ids([cand(True), None, cand(True), cand(False)])
    assert ids.tolist() == [0, 1, 0, 3]


def test_check_scale_names_the_units_when_the_object_is_never_near():
    scene = _scene([1000.0])
    with pytest.raises(InputFormatError, match="units"):
        check_scale(scene.grasped, scene.environment, scene.X, "demo.pose.list")


def test_hypotheses_start_with_the_observed_elements_and_are_distinct():
    from apo.recognition.hypotheses import hypotheses

    scene = _scene([0.0215])  # 1.5 mm above the top face: within the 2 mm threshold
    observed = scene.finder.find(scene.X[0])
    hyps = hypotheses(scene, scene.X[0], observed)
    keys = [frozenset(e.key for e in h) for h in hyps]
    assert keys[0] == observed.key
    assert len(set(keys)) == len(keys)
    # the four subsets of three corners are among them
    assert sum(len(k) == 3 and k < observed.key for k in keys) == 4


def test_rescue_finds_the_four_corner_contacts_of_the_real_state_f(real_data_dir):
    from apo.io.meshes import load_polyhedron
    from apo.io.poses import load_demonstration
    from apo.recognition.hypotheses import rescue
    from apo.recognition.inputs import default_threshold

    dem = load_demonstration(real_data_dir / "peg_in_hole.pose.list")
    G = load_polyhedron(dem.grasped_path, units="mm")
    E = load_polyhedron(dem.environment_path, units="mm")
    theta = default_threshold(G, E)
    X = np.asarray(dem.X_EG)
    scene = Scene(
        G, E, X, ContactFinder(G, E, threshold=theta), ContactFinder(G, E), SegmentationCosts()
    )
    observed = scene.finder.find(X[31])  # two EV, two VV: their correction turns G 10 deg
    found = rescue(scene, [31], observed)
    assert found is not None
    X_r, frame, moved = found
    state = scene.exact.find(X_r)
    assert frame == 31 and moved < 8 * theta
    assert sorted(e.kind.value for e in state.elements) == ["VV"] * 4
    assert all((e.grasped, e.environment) in state.touching for e in observed.elements)


@pytest.mark.parametrize("seed", range(3))
def test_candidates_analysed_from_one_batched_search_equal_one_by_one(seed):
    # analysis.analyse corrects every pending candidate first, then searches the contact
    # states at all their corrected poses in one find_batch per finder (states_at): each
    # candidate must be what analysing it alone (single-pose find) gives.
    from apo import synthetic
    from apo.recognition.candidates import analyse_candidate, correct_best, states_at
    from apo.recognition.contacts import observe
    from apo.recognition.pipeline import make_scene, pose_noise

    demo = synthetic.add_noise(
        synthetic.random_variant(seed), sigma_mm=1.0, sigma_deg=1.0, seed=seed
    )
    G, E, X = demo.grasped, demo.environment, demo.X_EG
    scene = make_scene(G, E, X, None, SegmentationCosts(), pose_noise(G, X, None))
    obs = observe(scene)
    cost = np.random.default_rng(seed).random(len(X))
    ks = range(len(obs.keys))
    corrected = {k: correct_best(scene, obs.labels, k, obs.states[k], cost) for k in ks}
    at = states_at(scene, corrected)
    assert at, "no candidate converged: the batched path is not exercised"
    for k in ks:
        args = (scene, obs.labels, k, obs.keys[k], obs.states[k], cost)
        alone = analyse_candidate(*args)
        batched = analyse_candidate(*args, corrected=corrected[k], at=at.get(k))
        a, b = alone.state, batched.state
        assert a.key == b.key and a.touching == b.touching
        for ea, eb in zip(a.elements, b.elements, strict=True):
            assert np.array_equal(ea.point, eb.point) and np.array_equal(ea.normals, eb.normals)
        assert batched.frame == alone.frame and batched.converged == alone.converged
        assert np.array_equal(batched.X_EG, alone.X_EG)
