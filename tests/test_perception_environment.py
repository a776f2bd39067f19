"""The environment's pose refined on the unbiased depth of its pixels (apo.perception.environment).

The depth of a static pixel counted only where it passes a foreground test (above the
support plane by some sigmas) is biased towards the camera; :func:`surface_depth` is not.
On random variants (not the benchmark's seeds 100-109) the refined environment pose is
nearer the truth than the closest-point ICP's on the median depth.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

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


def test_static_region_keeps_the_outline_pixels_the_sensor_drops() -> None:
    # A block's pixels occupied in all 30 frames; the pixels at its depth edge (a ring one
    # pixel wide) measured in about 30 % of the frames only (the sensor drops most pixels
    # on both sides of a depth jump), and occupied whenever measured: they are the block's.
    # A pixel away from the region measured in 5 frames (a forearm passing before a far
    # background that returns no depth) and occupied then is not static.
    from apo.perception.track import _static

    rng = np.random.default_rng(0)
    n = 30
    block = np.zeros((20, 20), dtype=bool)
    block[5:15, 5:15] = True
    ring = np.zeros_like(block)
    ring[4:16, 4:16] = True
    ring &= ~block
    depths = np.zeros((n, 20, 20), dtype=np.float32)
    depths[:, block] = 0.8
    depths[:, ring] = np.where(rng.random((n, int(ring.sum()))) < 0.3, 0.8, 0.0)
    depths[:5, 2, 18] = 0.5  # the forearm, away from the block
    masks = depths > 0
    static = _static(masks, (depths > 0).sum(axis=0), 0.7)
    assert static[block].all() and static[ring & masks.any(axis=0)].all()
    assert not static[2, 18]
    assert np.count_nonzero(static) == np.count_nonzero(block | (ring & masks.any(axis=0)))


@pytest.mark.parametrize("seed", range(4))
def test_static_surface_drops_a_part_held_over_the_environment(seed: int) -> None:
    # A block's top at random depth and noise; a part held over part of it for most of
    # the frames (occupied there, at about the same depth: static by occupancy and by the
    # same-surface test), moved away in the others, where the block is seen behind it.
    # Each block pixel gets one flying depth (an edge's mixed depth, far behind) in one
    # random frame. The block's surface is kept, the part's pixels are not.
    from apo.perception.track import TrackOptions, _static_surface

    rng = np.random.default_rng(seed)
    opt = TrackOptions()
    noise = DepthNoiseModel(float(rng.uniform(1e-3, 6e-3)))
    n, npx = 30, 400
    z = float(rng.uniform(0.4, 1.0))
    sigma = float(noise.sigma(z))
    D = (z + sigma * rng.standard_normal((n, npx))).astype(np.float32)
    D[rng.integers(n, size=npx), np.arange(npx)] += float(rng.uniform(0.03, 0.2))
    part = np.zeros(npx, dtype=bool)
    part[: int(rng.integers(40, 120))] = True
    held = rng.random(n) < float(rng.uniform(0.75, 0.9))  # frames where the part is there
    held[:2] = True
    held[2:4] = False  # at least two frames see the block behind it
    bound_z = max(opt.environment_threshold, opt.noise_sigmas * sigma)
    above = float(rng.uniform(1.3, 3.0)) * bound_z  # beyond the bound, within a few of it
    D[np.ix_(held, part)] = z - above + sigma * rng.standard_normal((held.sum(), part.sum()))
    masks = np.ones(D.shape, dtype=bool)
    measured = np.full(npx, n, dtype=np.int64)

    def bound(d: np.ndarray) -> np.ndarray:
        return np.maximum(opt.environment_threshold, opt.noise_sigmas * noise.sigma(d))

    args = (D, masks, measured, bound, opt.same_surface_fraction)
    surface = _static_surface(*args, opt.behind_frames)
    before = _static_surface(*args, n + 1)  # without the test: the part is static
    assert before[part].all()
    assert not surface[part].any()
    block = surface[~part]
    assert np.mean(block > 0) > 0.99  # a flying pixel and one 4-sigma draw: rare
    assert np.all(np.abs(block[block > 0] - z) < 5 * 1.25 * sigma / np.sqrt(n))  # the median's


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


def _square_peg(tmp_path: Path, seed: int, **conditions: Any) -> tuple[Any, Any, Any]:
    """Render 30 frames of the square peg's variant ``seed`` with ``conditions`` replaced;
    return the variant, the rendering and the tracker's scene (models, noise, segmenter)."""
    from apo.perception.frames import open_frames
    from apo.perception.track import TrackOptions, _open_scene

    v = random_variant(seed, demo="square_peg_in_hole", n_frames=30)
    v = replace(
        v, **{k: (float(x) if isinstance(x, np.floating) else x) for k, x in conditions.items()}
    )
    r = render_variant(v, tmp_path / "f")
    scene = _open_scene(open_frames(r.frames), r.grasped, r.environment, "m", TrackOptions())
    return v, r, scene


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
    from apo.perception.track import _find_environment

    rng = np.random.default_rng(2000 + seed)
    v, r, scene = _square_peg(
        tmp_path, seed, elevation=rng.uniform(55.0, 70.0), distance=rng.uniform(0.45, 0.85)
    )
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


# The square hole's block seen from the front (azimuth within 15 deg) by a low-resolution
# camera (RealSense D435, 1 px = 1.7-2.3 mm at 0.65-0.9 m) from 35-60 deg: its faces leave
# its position along its horizontal axis nearest the image plane to the outline (the side
# faces that would hold it are seen past 75 deg). The contour rows are one-sided (no row
# while the rendering and the observation put the outline between the same pixel centres),
# so the refinement stopped anywhere in a band up to a pixel wide; and the sensor drops most
# pixels at depth edges, so the static region lost its outline pixels and each side pulled
# inwards only. Started 0.75 and 1.5 mm either side of the true pose along that axis, the
# refinement ends at one place near the truth. Measured, largest error of the five ends
# (mm) for these seeds: 0.18, 0.79, 1.33, 1.10 before; 0.04, 0.08, 0.26, 0.15 with the
# outline rows and the static outline pixels (with the outline rows alone 0.18, 0.51,
# 1.33, 1.10; with the static outline pixels alone 0.63, 0.85, 1.26, 0.65, seed 1 ending
# anywhere from -0.32 to 0.63 mm).
@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3, 5])
def test_environment_position_along_the_outline_has_no_dead_band(tmp_path: Path, seed: int) -> None:
    from apo.perception.environment import refine_environment
    from apo.perception.track import _environment_points, _window

    rng = np.random.default_rng(3000 + seed)
    v, r, scene = _square_peg(
        tmp_path, seed, camera="realsense_d435", azimuth=rng.uniform(-15.0, 15.0),
        elevation=rng.uniform(35.0, 60.0), distance=rng.uniform(0.65, 0.9),
        noise=rng.uniform(2e-3, 6e-3),
    )  # fmt: skip
    _, median, surface = _environment_points(
        scene.src, scene.seg, scene.opt, {}, reach=scene.E.diameter
    )
    ends = []
    for dx in (-1.5e-3, -0.75e-3, 0.0, 0.75e-3, 1.5e-3):
        start = r.X_CE.copy()
        start[:3, 3] += dx * r.X_CE[:3, 0]  # along the block's x
        win = _window(scene.camera, start, scene.E, 0.01)
        X = refine_environment(surface, median, scene.camera, scene.E, start, scene.noise, 30, win)
        ends.append((np.linalg.inv(r.X_CE) @ X)[:3, 3])
    e = np.array(ends) * 1e3  # mm, the environment's frame
    assert np.abs(e).max() < 0.35 and np.ptp(e[:, 0]) < 0.15, (v.label(), e.round(3))
