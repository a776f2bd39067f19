"""The environment's pose refined on the unbiased depth of its pixels (apo.perception.environment).

The depth of a static pixel counted only where it passes a foreground test (above the
support plane by some sigmas) is biased towards the camera; :func:`surface_depth` is not.
On random variants (not the benchmark's seeds 100-109) the refined environment pose is
nearer the truth than the closest-point ICP's on the median depth.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from apo.perception.environment import surface_depth
from apo.perception.frames import masked_median
from apo.perception.segment import DepthNoiseModel
from apo.perception.variants import random_variant, render_variant
from apo.spatial import rotation_angle
from apo.symmetry import symmetries


def test_surface_depth_is_unbiased_where_a_foreground_test_truncates() -> None:
    # A surface 4 mm above the table at 0.9 m (sigma 2.8 mm), 30 frames; a part passes in
    # front of it (30 mm nearer) in 8 of them. The median over the frames where the pixel
    # passes a 2-sigma foreground test is biased by millimetres; surface_depth is not.
    rng = np.random.default_rng(5)
    noise = DepthNoiseModel(3.5e-3)
    z, table, n = 0.9, 0.904, 30
    sigma = float(noise.sigma(z))
    D = (z + sigma * rng.standard_normal((n, 40, 50))).astype(np.float32)
    D[:8, :, :25] -= 0.03  # the passages in front
    D[rng.random(D.shape) < 0.05] = 0.0  # dropouts
    fg = (D > 0) & (table - 2 * sigma > D)
    pixels = np.ones((40, 50), dtype=bool)
    biased = masked_median(D, fg)[pixels] - z
    est = surface_depth(D, pixels, noise)[pixels] - z
    assert np.median(biased) < -1e-3  # the truncated median: over a millimetre nearer
    assert abs(float(np.mean(est))) < 1e-4  # unbiased over the 2,000 pixels
    assert float(np.std(est)) < 1.5 * sigma / np.sqrt(n - 8)  # noise averaged
    assert not surface_depth(D, np.zeros((40, 50), dtype=bool), noise).any()


def _environment_error(X: np.ndarray, X_true: np.ndarray, syms: list) -> tuple[float, float]:
    errs = [
        (
            float(np.linalg.norm(X[:3, 3] - (X_true @ s.S)[:3, 3])),
            float(rotation_angle(X[:3, :3].T @ (X_true @ s.S)[:3, :3])),
        )
        for s in syms
    ]
    return min(errs, key=lambda e: e[0] + 0.05 * e[1])  # the nearest twin


@pytest.mark.slow
@pytest.mark.parametrize("seed", [7, 8, 11])
def test_refined_environment_is_nearer_the_truth(tmp_path: Path, seed: int) -> None:
    # Variants at 0.65 to 0.99 m, c 3 to 5.6 mm/m^2 (seed 7 without a hand, 8 and 11 with
    # one); 20 frames. Measured: seed 7 1.35 -> 0.44 mm (120 frames: 1.01 -> 0.13 mm);
    # at 120 frames seed 8 0.57 -> 0.04 mm, seed 11 1.32 -> 0.17 mm.
    pytest.importorskip("open3d")
    from apo.perception.track import TrackOptions, _find_environment, _open_scene

    v = random_variant(seed, n_frames=20)
    r = render_variant(v, tmp_path / "f")
    syms = symmetries(*r.environment)
    err = {}
    for refine in (False, True):
        opt = replace(TrackOptions(), refine_environment=refine)
        scene = _open_scene(r.frames, r.grasped, r.environment, "m", opt)
        _find_environment(scene, None)
        err[refine] = _environment_error(scene.X_CE, r.X_CE, syms)
    before, after = err[False], err[True]
    assert after[0] < 0.5e-3 and after[1] < np.radians(0.25), (before, after)
    assert after[0] + 0.05 * after[1] < before[0] + 0.05 * before[1], (before, after)


# The two sides of the 2-D peg-in-hole's slot without background frames, at a noise of 3 to
# 5.4 mm (c z^2): the block's 18 mm below the slot is within the support plane's threshold
# (4 sigma) and the peg in the slot is not static, so the environment's static pixels are
# two components. The global search on the larger alone (one block) found the other
# block's place, turned a quarter turn (confidence 0.87-0.90, 26 and 67 mm off on two dev
# variants); on the components within the model's diameter of each other it finds the
# environment. The views are drawn at random over the range where the slot is in view.
@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_environment_cut_in_pieces_is_found_whole(tmp_path: Path, seed: int) -> None:
    from apo.perception.frames import open_frames
    from apo.perception.track import (
        TrackOptions,
        _environment_points,
        _find_environment,
        _open_scene,
    )

    rng = np.random.default_rng(1000 + seed)
    v = replace(
        random_variant(seed, demo="peg_in_hole_2d", n_frames=30),
        azimuth=float(rng.choice([-1.0, 1.0]) * rng.uniform(10.0, 55.0)),
        elevation=float(rng.uniform(30.0, 56.0)),
        distance=float(rng.uniform(0.8, 0.95)),
        noise=float(rng.uniform(4.7e-3, 6e-3)),
        background=False,
        hand=False,
    )
    r = render_variant(v, tmp_path / "f")
    opt = TrackOptions()
    scene = _open_scene(open_frames(r.frames), r.grasped, r.environment, "m", opt)
    parts, _, _ = _environment_points(scene.src, scene.seg, opt, {}, reach=scene.E.diameter)
    # the first region holds both sides (x < 0 and x > 0 in the environment's frame)
    x = (parts[0] - r.X_CE[:3, 3]) @ r.X_CE[:3, 0]
    assert np.mean(x < -0.02) > 0.2 and np.mean(x > 0.02) > 0.2, v.label()
    _find_environment(scene, None)
    pos, rot = _environment_error(scene.X_CE, r.X_CE, symmetries(*r.environment))
    assert pos < 1e-3 and np.degrees(rot) < 0.5, (v.label(), pos, np.degrees(rot))


# The square hole's block seen from high above (55-70 deg): its top face and one or two sides
# are in view, the rest of the block below the table's threshold. Turned a quarter turn, the
# block shows a side face where the top is and hides everything else below the table: every
# surface it shows is explained (confidence 1.0) while it explains a third to a half of the
# static points, and it showed 0.5-1 % more of its surface than the truth. Ranked by
# plausibility alone, the search kept it in 5 of 10 such draws (38-85 mm off, these four
# among them); ranked by plausibility times fitness (whole_plausibility) it finds the block.
@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 3, 5, 7])
def test_box_seen_from_above_is_not_turned_a_quarter(tmp_path: Path, seed: int) -> None:
    from apo.perception.frames import open_frames
    from apo.perception.track import TrackOptions, _find_environment, _open_scene

    rng = np.random.default_rng(2000 + seed)
    v = replace(
        random_variant(seed, demo="square_peg_in_hole", n_frames=30),
        elevation=float(rng.uniform(55.0, 70.0)),
        distance=float(rng.uniform(0.45, 0.85)),
    )
    r = render_variant(v, tmp_path / "f")
    scene = _open_scene(open_frames(r.frames), r.grasped, r.environment, "m", TrackOptions())
    _find_environment(scene, None)
    pos, rot = _environment_error(scene.X_CE, r.X_CE, symmetries(*r.environment))
    assert pos < 1e-3 and np.degrees(rot) < 0.5, (v.label(), pos, np.degrees(rot))
    assert scene.env is not None and scene.env.fitness > 0.9, v.label()


def test_whole_plausibility_prefers_the_pose_that_explains_the_points() -> None:
    from apo.perception.register import (
        Registration,
        SurfaceCheck,
        plausibility,
        whole_plausibility,
    )

    def reg(fitness: float, visible: float) -> Registration:
        s = SurfaceCheck(explained=1.0, visible=visible, violation=0.0, pixels=1000,
                         silhouette_violation=0.0, continued=0.0)  # fmt: skip
        return Registration(np.eye(4), fitness, 1e-3, 0.0, 5000, surface=s)

    truth, turned = reg(1.0, 0.895), reg(0.30, 0.912)  # variant seed 206's two poses
    assert plausibility(turned) > plausibility(truth)
    assert whole_plausibility(truth) > whole_plausibility(turned)
    # equal fitness: the same order as plausibility
    assert (whole_plausibility(reg(0.9, 0.95)) > whole_plausibility(reg(0.9, 0.90))) == (
        plausibility(reg(0.9, 0.95)) > plausibility(reg(0.9, 0.90))
    )
