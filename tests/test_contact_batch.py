"""The batched contact search against a plain per-frame reference, on noisy random variants.

``ContactFinder.find_batch`` (every stage one numpy pass over a block of frames) and
``ContactFinder.find_labels`` (the same search keeping only each frame's element keys) are
checked against ``find_naive`` (all pairs, scalar cone tests) one frame at a time, on
randomised demonstrations with pose noise (``apo.synthetic``), singular vertex-edge and
vertex-vertex contacts, and poses a hair inside and outside the threshold.
"""

from __future__ import annotations

import numpy as np
import pytest

from apo import synthetic
from apo.contact import ContactFinder, ContactKind, ContactState, default_threshold
from apo.spatial import matrix_from_axis_angle, pose_from_twist
from test_contact import CUBE, TABLE, _assert_same_states  # cube on a table; same states
from test_contact import pose as _pose


def _corner_on(target: tuple[float, float], axis: list[float], angle: float) -> np.ndarray:
    """The cube turned about ``axis``, its corner (-0.05, -0.05, 0) at (x, y, 0) of the table."""
    R = matrix_from_axis_angle(axis, angle)
    c = np.array([-0.05, -0.05, 0.0])
    return _pose(R, np.array([target[0], target[1], 0.0]) - R @ c)


SINGULAR = {
    "vertex_on_edge": _corner_on((0.5, 0.0), [1, 1, 1], 0.5),  # VE on the table's edge
    "vertex_on_vertex": _corner_on((0.5, 0.5), [1, 1, 0], 0.4),  # VV on its corner
}

KINDS = {"vertex_on_edge": ContactKind.VE, "vertex_on_vertex": ContactKind.VV}


def _noisy_variant(seed: int) -> synthetic.SyntheticDemo:
    sigma = (0.5, 1.0, 2.0, 3.0)[seed % 4]
    demo = synthetic.random_variant(2000 + seed)
    return synthetic.add_noise(demo, sigma_mm=sigma, sigma_deg=sigma, seed=seed)


def _labels_of(states: list[ContactState]) -> tuple[list[int], list[int]]:
    """Labels by state key in order of first appearance, and the first frame of each."""
    index: dict[object, int] = {}
    labels = [index.setdefault(s.key, len(index)) for s in states]
    first = [labels.index(k) for k in range(len(index))]
    return labels, first


def _check_labels(finder: ContactFinder, X: np.ndarray) -> list[ContactState]:
    states = finder.find_batch(X)
    labels, first = finder.find_labels(X)
    assert (labels.tolist(), first.tolist()) == _labels_of(states)
    return states


@pytest.mark.parametrize("kd", [False, True], ids=["dense", "kdtree"])
@pytest.mark.parametrize("seed", range(6))
def test_batch_and_labels_equal_the_per_frame_reference_on_noisy_variants(
    seed: int, kd: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    import apo.contact.search

    if kd:  # the k-d tree broad phase even for these small models
        monkeypatch.setattr(apo.contact.search, "_DENSE_LIMIT", 0)
    demo = _noisy_variant(seed)
    G, E, X = demo.grasped, demo.environment, demo.X_EG
    d = 3 * default_threshold(G, E, observed=True)
    finder = ContactFinder(G, E, threshold=d)
    states = _check_labels(finder, X)
    assert any(s.elements for s in states)
    # every frame in contact and a few free ones, one frame at a time, all pairs
    rng = np.random.default_rng(seed)
    touching = [i for i, s in enumerate(states) if s.touching]
    free = [i for i, s in enumerate(states) if not s.touching]
    pick = sorted(touching + rng.choice(free, size=min(3, len(free)), replace=False).tolist())
    _assert_same_states([states[i] for i in pick], [finder.find_naive(X[i]) for i in pick])


@pytest.mark.parametrize("name", sorted(SINGULAR))
def test_singular_contacts_under_noise(name: str) -> None:
    # Vertex-edge and vertex-vertex elements (singular) at poses jittered by up to about
    # the threshold: elements appear, change kind and vanish between frames.
    X0 = SINGULAR[name]
    d = default_threshold(CUBE, TABLE)
    rng = np.random.default_rng(len(name))
    xis = np.c_[rng.normal(size=(40, 3)) * d / CUBE.scale, rng.normal(size=(40, 3)) * d]
    X = np.stack([pose_from_twist(xi) @ X0 for xi in xis] + [X0])
    finder = ContactFinder(CUBE, TABLE, threshold=d)
    states = _check_labels(finder, X)
    kinds = {e.kind for s in states for e in s.elements}
    assert KINDS[name] in kinds
    assert any(not s.elements for s in states)
    _assert_same_states(states, [finder.find_naive(P) for P in X])


def _near_threshold_poses(X0: np.ndarray, d: float) -> np.ndarray:
    """``X0`` (touching at z = 0) lifted by d (1 -+ 1e-9) and d (1 -+ 1e-6)."""
    out = []
    for f in (1 - 1e-6, 1 - 1e-9, 1 + 1e-9, 1 + 1e-6):
        X = X0.copy()
        X[2, 3] += d * f
        out.append(X)
    return np.stack(out)


@pytest.mark.parametrize("name", ["flat", *sorted(SINGULAR)])
def test_poses_a_hair_inside_and_outside_the_threshold(name: str) -> None:
    X0 = _pose() if name == "flat" else SINGULAR[name]
    d = default_threshold(CUBE, TABLE)
    X = _near_threshold_poses(X0, d)
    finder = ContactFinder(CUBE, TABLE, threshold=d)
    states = _check_labels(finder, X)
    kind = {"flat": ContactKind.VF, **KINDS}[name]
    assert [any(e.kind is kind for e in s.elements) for s in states] == [True, True, False, False]
    _assert_same_states(states, [finder.find_naive(P) for P in X])


def test_labels_in_blocks_of_frames_with_far_frames_and_empty(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import apo.contact.search

    demo = _noisy_variant(1)
    G, E = demo.grasped, demo.environment
    X = demo.X_EG.copy()
    X[[0, 5], :3, 3] += 10.0  # far away: no box overlap
    finder = ContactFinder(G, E, threshold=3 * default_threshold(G, E, observed=True))
    whole = finder.find_labels(X)
    monkeypatch.setattr(apo.contact.search, "_BATCH_PRIMITIVES", 1)  # one frame per block
    done: list[int] = []
    blocks = finder.find_labels(X, progress=lambda k, n: done.append(k))
    assert [v.tolist() for v in blocks] == [v.tolist() for v in whole]
    assert done == list(range(1, len(X) + 1))
    assert _labels_of(finder.find_batch(X)) == tuple(v.tolist() for v in whole)
    assert [v.tolist() for v in finder.find_labels(np.zeros((0, 4, 4)))] == [[], []]
    with pytest.raises(ValueError, match="pose 1: X_EG is not finite"):
        finder.find_labels(np.stack([np.eye(4), np.full((4, 4), np.nan)]))


@pytest.mark.parametrize("seed", range(4))
def test_observations_equal_the_states_of_every_frame_grouped(seed: int) -> None:
    # recognition.contacts.observe labels frames by find_labels and searches one frame per
    # label: the same labels, keys and first states as grouping every frame's state, also
    # with exact repeats of poses.
    from apo.recognition.contacts import group_states, observe, observed_states
    from apo.recognition.pipeline import make_scene, pose_noise
    from apo.recognition.types import SegmentationCosts

    demo = _noisy_variant(seed)
    G, E = demo.grasped, demo.environment
    X = np.concatenate([demo.X_EG, demo.X_EG[::3]])  # later frames repeat earlier poses
    scene = make_scene(G, E, X, None, SegmentationCosts(), pose_noise(G, X, None))
    got = observe(scene)
    ref = group_states(observed_states(scene))
    assert got.labels.tolist() == ref.labels.tolist()
    assert got.keys == ref.keys
    _assert_same_states(got.states, ref.states)
    assert len(got.keys) > 1


@pytest.mark.parametrize("offset", [0.0, 0.3, 10.0])
def test_squared_distances_by_one_matrix_product_are_within_their_slack(offset: float) -> None:
    # The prefilters of the distance tests use |p|^2 + |c|^2 - 2 p.c plus a slack: it must
    # bound the rounding for points near and far from the origin (no pair is ever dropped).
    from apo.contact._arrays import _sq_dist, _sq_dist_slack

    rng = np.random.default_rng(int(offset * 10))
    P = offset + rng.normal(scale=0.05, size=(300, 3))
    C = P[rng.integers(300, size=40)] + rng.normal(scale=1e-4, size=(40, 3))
    exact = np.sum((P[:, None, :] - C[None, :, :]) ** 2, axis=2)
    assert np.max(np.abs(_sq_dist(P, C) - exact)) <= _sq_dist_slack(P, C)
    assert _sq_dist_slack(P, C) < 1e-12 * max(1.0, offset) ** 2


@pytest.mark.parametrize("seed", range(3))
def test_distances_and_cones_in_small_chunks_are_those_at_once(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The exact distance tests (ROW_CHUNK pairs at a time), the separating normals
    # (CONE_CHUNK pairs of pieces at a time) and the touching pairs (TOUCH_ROWS expanded at
    # a time) are row by row: chunks of a few rows give the same states bit for bit (keys,
    # touching pairs, points, normals) and the same labels, on noisy random variants at a
    # wide threshold (many pairs a frame).
    import apo.contact.distance_tests
    import apo.contact.search

    demo = _noisy_variant(seed)
    G, E = demo.grasped, demo.environment
    finder = ContactFinder(G, E, threshold=3 * default_threshold(G, E, observed=True))
    X = demo.X_EG
    whole, labels = finder.find_batch(X), finder.find_labels(X)
    assert sum(len(s.elements) for s in whole) > 2 * len(X)
    monkeypatch.setattr(apo.contact.distance_tests, "ROW_CHUNK", 7)
    monkeypatch.setattr(apo.contact.search, "CONE_CHUNK", 3)
    monkeypatch.setattr(apo.contact.distance_tests, "TOUCH_ROWS", 5)
    calls = {"cones": 0, "triangles": 0, "unique": 0}

    def counted(name: str, mod: object, f: str) -> None:
        inner = getattr(mod, f)

        def spy(*args: object, **kw: object) -> object:
            calls[name] += 1
            return inner(*args, **kw)

        monkeypatch.setattr(mod, f, spy)

    counted("cones", apo.contact.search, "_cone_pairs")
    counted("triangles", apo.contact.distance_tests, "_point_triangle_distance")
    counted("unique", apo.contact.distance_tests, "unique")
    chunked = finder.find_batch(X)
    blocks = -(-len(X) // finder.block_frames)
    assert min(calls.values()) > 3 * blocks, calls  # chunked
    assert len(chunked) == len(whole)
    for x, y in zip(chunked, whole, strict=True):
        assert x.key == y.key and x.touching == y.touching
        for e, f in zip(x.elements, y.elements, strict=True):
            assert np.array_equal(e.point, f.point) and np.array_equal(e.normals, f.normals)
    for a, b in zip(finder.find_labels(X), labels, strict=True):
        assert np.array_equal(a, b)
