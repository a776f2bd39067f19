"""Recordings that vary like the world (apo.perception.variants) and the noise model.

Depth-noise estimation from the recording (apo.perception.segment.estimate_depth_noise),
the global search up to the model's symmetries, and tracking without initial poses on
seeded random variants (camera, distance, elevation, table colour, noise c z^2, dropouts,
hand and forearm, with or without background).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from apo.perception.example import peg_and_slot
from apo.perception.frames import open_frames
from apo.perception.segment import DepthNoiseModel, estimate_depth_noise
from apo.perception.variants import CAMERAS, DEMOS, Variant, random_variant, render_variant
from apo.symmetry import symmetries


def test_random_variants_cover_the_documented_ranges() -> None:
    vs = [random_variant(s) for s in range(200)]
    assert all(0.3 <= v.distance <= 1.0 and 20 <= v.elevation <= 70 for v in vs)
    assert all(1e-3 <= v.noise <= 6e-3 for v in vs)
    assert {v.table for v in vs} == {"grey", "white", "textured"}
    assert {v.camera for v in vs} == set(CAMERAS) and {v.demo for v in vs} == set(DEMOS)
    assert {v.hand for v in vs} == {True, False} == {v.background for v in vs}
    assert {v.parts for v in vs} == {"white", "table", "blue"}
    assert random_variant(7) == random_variant(7)


def test_noise_model_sigma() -> None:
    m = DepthNoiseModel(3e-3)
    assert np.isclose(m.sigma(0.5), 0.75e-3)
    assert np.isclose(DepthNoiseModel(0.0, 1e-3).sigma(1.0), 1e-3 / np.sqrt(12))
    with pytest.raises(ValueError, match="at least 2 depth frames"):
        estimate_depth_noise(np.zeros((1, 4, 4)))


@pytest.mark.parametrize(("c", "seed"), [(1e-3, 0), (4e-3, 1), (6e-3, 2)])
def test_noise_estimated_from_the_recording(tmp_path: Path, c: float, seed: int) -> None:
    # A grey table, 15 frames of the moving peg: the estimate of c is within 15 % of the truth.
    v = Variant("peg_in_hole_2d", "kinect_v1", float(np.random.default_rng(seed).uniform(0.4, 0.9)),
                45.0, 10.0, "grey", c, 0.01, False, False, n_frames=15, seed=seed)  # fmt: skip
    r = render_variant(v, tmp_path / "f")
    src = open_frames(r.frames)
    est = estimate_depth_noise(np.stack([src.depth(i) for i in range(len(src))]))
    assert abs(est.c - c) / c < 0.15, est.c


def test_global_search_tries_one_orientation_per_symmetric_twin() -> None:
    from apo.perception.register import distinct_up_to_symmetry

    rng = np.random.default_rng(0)
    Rs = list(Rotation.random(40, random_state=rng).as_matrix())
    peg, _ = peg_and_slot()
    half = [s.S[:3, :3] for s in symmetries(*peg)]
    doubled = Rs + [R @ half[1] for R in Rs]
    kept = distinct_up_to_symmetry(doubled, half)
    assert len(kept) == 40 and all(np.allclose(a, b) for a, b in zip(kept, Rs, strict=True))
    assert len(distinct_up_to_symmetry(doubled, None)) == 80


# Seed 3 (RealSense D435 at 0.47 m, 60 deg, grey table, hand and forearm hiding over half of
# the part): scored by the points it explains, a pose 78 mm off passed the confidence limit;
# scored by the share of the predicted-visible model surface explained it is rejected, and
# the global search, given both pieces the hand cuts the part into, finds the part.
@pytest.mark.slow
@pytest.mark.parametrize("seed", [3, 11])
def test_tracking_random_variants_without_initial_poses(tmp_path: Path, seed: int) -> None:
    pytest.importorskip("open3d")
    from apo.perception.track import track_frames

    v = random_variant(seed, demo="peg_in_hole_2d", n_frames=30)
    r = render_variant(v, tmp_path / "f")
    res = track_frames(r.frames, r.grasped, r.environment, units="m")
    sym_G, sym_E = symmetries(*r.grasped), symmetries(*r.environment)
    # One twin of the truth for the whole sequence: no flips, errors within the targets.
    best = None
    for a in sym_E:
        for b in sym_G:
            T = np.linalg.inv(a.S) @ r.demo.X_EG_true @ b.S
            e = np.linalg.norm(res.X_EG[:, :3, 3] - T[:, :3, 3], axis=1) * 1e3
            if best is None or np.nanmedian(e) < np.nanmedian(best):
                best = e
    assert best is not None
    assert np.nanmedian(best) < 1.0 and np.nanpercentile(best, 95) < 3.0, v.label()
    assert res.reinitialisations <= 2 and not res.lost.any(), v.label()
    assert np.all(res.confidence >= 0.8), v.label()


# Depth alone (issue 11: "colour is an optional cue, never required") with a hand and forearm
# holding the part: the first frame's global search fitted the part into the forearm's box
# (82 mm off on seed 2, 145 mm on seed 5, confidence 1.0), as the hidden model surface counted
# neither for nor against. The outline test (the box's faces run on past a model inside it;
# a held part shows depth jumps at its outline) finds the part.
@pytest.mark.slow
@pytest.mark.parametrize("seed", [2, 5])
def test_depth_alone_with_a_hand_finds_the_part_not_the_hand(
    tmp_path: Path, seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("open3d")
    import apo.perception.track as track
    from apo.perception.segment import ColourModel
    from apo.perception.track import TrackOptions, track_frames

    v = random_variant(seed, n_frames=30)
    assert v.hand
    r = render_variant(v, tmp_path / "f")
    opt = TrackOptions(colour=ColourModel.any_colour())
    fallbacks = []  # frame-to-frame closest-point ICPs (the projective ICP's result not good)
    register = track.register
    monkeypatch.setattr(track, "register", lambda *a, **k: fallbacks.append(1) or register(*a, **k))
    res = track_frames(r.frames, r.grasped, r.environment, units="m", options=opt)
    # The share of the points explained is no bar with a hand's points among them: the
    # projective ICP's result is taken (measured: 43 and 49 fallback runs over the 29 frames
    # before, 7 and 4 after).
    assert len(fallbacks) < 10, (v.label(), len(fallbacks))
    X_CG = np.linalg.inv(r.X_CE) @ np.asarray(res.X_CE) @ np.asarray(res.X_EG)
    err = []
    for k, X in enumerate(X_CG):  # the nearest twin of the truth, frame by frame
        T = [r.demo.X_EG_true[k] @ s.S for s in symmetries(*r.grasped)]
        err.append(min(np.linalg.norm(X[:3, 3] - t[:3, 3]) for t in T) * 1e3)
    assert err[0] < 2.0 and np.median(err) < 1.5, (v.label(), err[:3])
    assert res.reinitialisations == 0 and not res.lost.any(), v.label()


# Depth alone, a hand and forearm holding the part: the first frame's global search fitted
# the part into the hand (dev seeds 4 and 6: 87 and 145 mm off, plausibility 0.93 and 0.77,
# while the true pose scores 0.97 and 0.95): no start of the search reached the part among
# the hand's points. A second search over the pixels that pick leaves unexplained finds it
# (measured 0.4 and 2.6 mm; the frame-to-frame ICP then refines it).
@pytest.mark.slow
@pytest.mark.parametrize("seed", [4, 6])
def test_depth_alone_second_search_finds_the_part_beside_the_hand(
    tmp_path: Path, seed: int
) -> None:
    pytest.importorskip("open3d")
    from apo.perception.frames import open_frames
    from apo.perception.segment import ColourModel
    from apo.perception.track import (
        TrackOptions,
        _find_environment,
        _open_scene,
        _read,
        _Tracker,
        _twin,
    )

    v = random_variant(seed, n_frames=30)
    assert v.hand
    r = render_variant(v, tmp_path / "f")
    opt = TrackOptions(colour=ColourModel.any_colour())
    scene = _open_scene(open_frames(r.frames), r.grasped, r.environment, "m", opt)
    _find_environment(scene, r.X_CE)
    _, depth = _read(scene.src, 0, colour=False)
    found = _Tracker(scene, None).reinitialise(np.zeros((0, 0, 3), np.uint8), depth)
    assert found is not None and found.confidence >= opt.min_confidence, v.label()
    X = _twin(found.X_CM, r.X_CG0, scene.syms_G, scene.G)
    assert np.linalg.norm(X[:3, 3] - r.X_CG0[:3, 3]) < 5e-3, v.label()
