"""Block-wise processing (segmentation, decoding, outputs) equals whole-sequence processing."""

from __future__ import annotations

import numpy as np
import pytest

from apo import synthetic
from apo.recognition import correction, recognize_frames, segmentation
from apo.recognition.decoding import UniformViterbi, Viterbi, viterbi, viterbi_uniform
from apo.report.writer import frames_csv_chunks, task_document


def _reference_viterbi(e: np.ndarray, trans: np.ndarray) -> list[int]:
    """The textbook Viterbi over the whole sequence (first minimum on ties)."""
    n, k = e.shape
    back = np.zeros((n, k), dtype=np.int64)
    acc = e[0].copy()
    for t in range(1, n):
        tot = acc[:, None] + trans
        back[t] = np.argmin(tot, axis=0)
        acc = tot[back[t], np.arange(k)] + e[t]
    path = [int(np.argmin(acc))]
    for t in range(n - 1, 0, -1):
        path.append(int(back[t, path[-1]]))
    return path[::-1]


def _reference_uniform(e: np.ndarray, switch: float) -> list[int]:
    """The whole-sequence uniform Viterbi (a state is left only when strictly cheaper)."""
    n, k = e.shape
    back = np.zeros((n, k), dtype=np.int64)
    acc = e[0].copy()
    for t in range(1, n):
        j = int(np.argmin(acc))
        move = acc[j] + switch < acc
        back[t] = np.where(move, j, np.arange(k))
        acc = np.where(move, acc[j] + switch, acc) + e[t]
    path = [int(np.argmin(acc))]
    for t in range(n - 1, 0, -1):
        path.append(int(back[t, path[-1]]))
    return path[::-1]


def _feed(dec: Viterbi | UniformViterbi, e: np.ndarray, rng: np.random.Generator) -> None:
    a = 0
    while a < len(e):
        b = a + int(rng.integers(1, 9))
        dec.feed(e[a:b])
        a = b


@pytest.mark.parametrize("seed", range(6))
def test_viterbi_fed_in_random_blocks_is_the_whole_sequence_viterbi(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, k = int(rng.integers(1, 60)), int(rng.integers(1, 7))
    e = rng.integers(0, 4, size=(n, k)).astype(float)  # small integers: many exact ties
    trans = rng.integers(0, 3, size=(k, k)).astype(float)
    np.fill_diagonal(trans, 0.0)
    want = _reference_viterbi(e, trans)
    dec = Viterbi(trans)
    _feed(dec, e, rng)
    assert dec.path()[0].tolist() == want == viterbi(e, trans)[0].tolist()
    dec_u = UniformViterbi(k, 1.0)
    _feed(dec_u, e, rng)
    want_u = _reference_uniform(e, 1.0)
    assert dec_u.path()[0].tolist() == want_u == viterbi_uniform(e, 1.0).tolist()


def test_back_pointers_are_small_integers() -> None:
    dec = Viterbi(np.zeros((5, 5)))
    dec.feed(np.zeros((10, 5)))
    assert dec.back[0].dtype == np.int8
    dec_u = UniformViterbi(200, 1.0)
    dec_u.feed(np.zeros((16, 200)))
    assert dec_u.moved[0].nbytes == 16 * 25  # one bit per frame and state


def _outputs(demo: synthetic.SyntheticDemo, block: int) -> tuple[str, str, np.ndarray]:
    rec = recognize_frames(demo.grasped, demo.environment, demo.times, demo.X_EG)
    return task_document(rec)[1], "".join(frames_csv_chunks(rec, block)), rec.emission


@pytest.mark.parametrize("seed", [1, 4, 7])
def test_block_wise_recognition_equals_whole_sequence(monkeypatch, seed: int) -> None:
    """Blocks of 7 frames (costs, decoding, correction, frames.csv) give the task, frames.csv
    and costs of one block for everything."""
    demo = synthetic.add_noise(
        synthetic.random_variant(seed), sigma_mm=1.0, sigma_deg=1.0, outlier_rate=0.02, seed=seed
    )
    monkeypatch.setattr(segmentation, "BLOCK_FRAMES", 10**9)
    monkeypatch.setattr(correction, "CORRECTION_BLOCK", 10**9)
    whole = _outputs(demo, 10**9)
    monkeypatch.setattr(segmentation, "BLOCK_FRAMES", 7)
    monkeypatch.setattr(correction, "CORRECTION_BLOCK", 7)
    blocks = _outputs(demo, 7)
    assert blocks[0] == whole[0]
    assert blocks[1] == whole[1]
    assert blocks[1].count("\n") == len(demo.X_EG) + 1
    assert np.array_equal(blocks[2], whole[2])


@pytest.mark.parametrize("seed", [2, 9])
def test_streamed_distances_give_the_costs_of_every_distance_kept(monkeypatch, seed: int) -> None:
    """The two passes compute the element distances a span at a time and keep only the
    observed elements' between them: the costs of both passes are those of every element's
    distances at every frame (one ``DistanceCache`` over the whole sequence), bit for bit."""
    from apo.recognition import analysis, costs, pipeline
    from apo.recognition.contacts import observe
    from apo.recognition.distances import DistanceCache, StreamedDistances
    from apo.recognition.types import SegmentationCosts

    demo = synthetic.add_noise(
        synthetic.random_variant(seed), sigma_mm=1.5, sigma_deg=1.5, outlier_rate=0.02, seed=seed
    )
    G, E, X = demo.grasped, demo.environment, demo.X_EG
    est = pipeline.pose_noise(G, X, None)
    scene = pipeline.make_scene(G, E, X, None, SegmentationCosts(), est)
    observed = observe(scene)
    monkeypatch.setattr(segmentation, "BLOCK_FRAMES", 7)  # spans of 28 frames
    dists = StreamedDistances(G, E, X, scene.unit)
    path0, own, seen = segmentation.first_pass(scene, observed, dists)
    an = analysis.analyse_needed(scene, observed, own, path0)
    seg = segmentation.segment(scene, an, dists, observed, seen)
    whole = DistanceCache(G, E, X, scene.unit)
    labels, w = observed.labels, scene.costs
    enc = costs.enclosed_frames(observed.keys, labels, scene.outliers)
    lay = costs.EmissionLayout(observed.keys, [s.touching for s in observed.states])
    e1 = costs.emission_costs(whole, lay, labels, w, enc)
    assert np.array_equal(own, e1[np.arange(len(X)), labels])
    states = an.states(observed)
    lay2 = costs.EmissionLayout(an.keys, [s.touching for s in states])
    e2 = costs.candidate_costs(whole, lay2, an.candidates, an.bridges, labels, w, enclosed=enc)
    e2 = e2[:, seg.columns]
    e2 = np.where(scene.outliers[:, None] & np.isfinite(e2), 0.0, e2)
    assert np.array_equal(seg.costs, e2)
    assert len(seen.values) == sum(len(observed.keys[k]) for k in labels.tolist())
    assert len(an.candidates) > len([c for c in an.candidates if c is not None])  # some unneeded
