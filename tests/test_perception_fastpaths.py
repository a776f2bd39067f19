"""The tracker's fast paths give the results of the paths they replace (randomised cases).

- ``register(engine="numpy")`` (the tracker's closest-point fallback, no Open3D import)
  against Open3D's ICP from the same start, on noisy partial views with clutter;
- the histogram's frames decoded in a thread pool (``_prefetch``) against decoded in turn,
  on rendered random variants.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from apo.perception.example import peg_and_slot
from apo.perception.register import ModelCloud, register
from apo.spatial import invert_pose, rotation_angle, transform_points

pytest.importorskip("open3d")


def _pose(rotvec: np.ndarray, t: np.ndarray) -> np.ndarray:
    X = np.eye(4)
    X[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    X[:3, 3] = t
    return X


@pytest.mark.parametrize("seed", range(6))
def test_numpy_engine_matches_open3d(seed: int) -> None:
    rng = np.random.default_rng(seed)
    peg, slot = peg_and_slot()
    model = ModelCloud(peg if seed % 2 == 0 else slot, seed=seed)
    X_true = _pose(rng.normal(0, 1.0, 3), np.r_[rng.normal(0, 0.03, 2), rng.uniform(0.3, 0.9)])
    towards = invert_pose(X_true)[:3, :3] @ -X_true[:3, 3]
    seen = model.dense_points[model.dense_normals @ towards > 0]
    seen = seen[rng.choice(len(seen), min(len(seen), 1500), replace=False)]
    P = transform_points(X_true, seen)
    P += rng.normal(0, 1.5e-3 * P[:, 2:3] ** 2, P.shape)  # sigma(z) = c z^2
    clutter = P.mean(0) + rng.uniform(-0.04, 0.04, (len(P) // 10, 3))
    P = np.concatenate([P, clutter])
    start = X_true @ _pose(rng.normal(0, 0.04, 3), rng.normal(0, 0.002, 3))
    for coarse in (False, True):
        reach = None if coarse else 0.008
        a = register(P, model, start, max_distance=reach, coarse=coarse)
        b = register(P, model, start, max_distance=reach, coarse=coarse, engine="numpy")
        assert (
            np.linalg.norm(a.X_CM[:3, 3] - b.X_CM[:3, 3]) < 1e-5
        )  # 10 um (measured: 1e-7 or less)
        assert rotation_angle(a.X_CM[:3, :3].T @ b.X_CM[:3, :3]) < np.radians(0.01)
        assert abs(a.fitness - b.fitness) < 0.005
        # and both found the pose
        assert np.linalg.norm(b.X_CM[:3, 3] - X_true[:3, 3]) < 1e-3


def test_unknown_engine_is_an_error() -> None:
    peg, _ = peg_and_slot()
    with pytest.raises(ValueError, match="engine"):
        register(np.zeros((10, 3)), ModelCloud(peg), np.eye(4), engine="pcl")


@pytest.mark.parametrize("seed", [31, 32])
def test_prefetched_histogram_frames_give_the_same_environment_points(
    tmp_path: Path, seed: int
) -> None:
    """Frames decoded in a thread pool while the scene opens: the same points and cache."""
    from apo.perception.frames import open_frames
    from apo.perception.track import (
        TrackOptions,
        _environment_points,
        _noise_model,
        _prefetch,
        _Segmenter,
    )
    from apo.perception.variants import random_variant, render_variant

    r = render_variant(random_variant(seed, n_frames=16), tmp_path / "frames")
    src = open_frames(r.frames)
    opt = TrackOptions(histogram_frames=7)
    seg = _Segmenter(src, opt, _noise_model(src, opt))
    cache: dict = {}
    parts, median, surface = _environment_points(src, seg, opt, cache)
    cache_p: dict = {}
    with ThreadPoolExecutor(max_workers=2) as pool:
        prefetch = _prefetch(pool, src, opt)
        parts_p, median_p, surface_p = _environment_points(src, seg, opt, cache_p, prefetch)
    assert not prefetch  # every prefetched frame was used
    assert len(parts) == len(parts_p) >= 1
    for a, b in zip(parts, parts_p, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(median, median_p)
    np.testing.assert_array_equal(surface, surface_p)
    assert sorted(cache) == sorted(cache_p) and len(cache) == 7
    for i in cache:
        for a, b in zip(cache[i], cache_p[i], strict=True):
            np.testing.assert_array_equal(a, b)


def test_batch_icp_on_every_core_gives_the_same_transforms(monkeypatch: pytest.MonkeyPatch) -> None:
    """Large k-d tree queries run with ``workers=-1`` (``PARALLEL_QUERY``): identical results."""
    from apo.perception import search

    rng = np.random.default_rng(5)
    peg, _ = peg_and_slot()
    model = ModelCloud(peg)
    X_true = _pose(rng.normal(0, 1.0, 3), np.array([0.01, -0.02, 0.5]))
    P = transform_points(X_true, model.dense_points[rng.choice(len(model.dense_points), 400)])
    starts = np.stack([invert_pose(X_true @ _pose(rng.normal(0, 0.1, 3), rng.normal(0, 0.004, 3)))
                       for _ in range(40)])  # fmt: skip
    assert starts.shape[0] * len(P) >= search.PARALLEL_QUERY  # the parallel query is used
    kw = {"distance": 0.01, "scale": 0.005, "iterations": 8}
    parallel = search.batch_icp(P, model, starts, **kw)
    monkeypatch.setattr(search, "PARALLEL_QUERY", 10**12)
    serial = search.batch_icp(P, model, starts, **kw)
    np.testing.assert_array_equal(parallel, serial)
    assert not np.allclose(parallel, starts)  # the ICP moved them


@pytest.mark.parametrize("dense", [True, False])
def test_nearest_sample_is_the_brute_force_nearest(dense: bool) -> None:
    """The k-d trees (built with ``compact_nodes=False``) give the exact nearest sample."""
    rng = np.random.default_rng(11)
    _, slot = peg_and_slot()
    model = ModelCloud(slot, seed=3)
    samples = model.dense_points if dense else model.points
    base = samples[rng.choice(len(samples), 300)]
    for spread in (0.0005, 0.004, 0.02):  # near the surface, millimetres off, far
        P = base + rng.normal(0, spread, base.shape)
        side, dist, idx = model.nearest_sample(P, dense=dense, max_distance=0.01)
        d_all = np.linalg.norm(P[:, None, :] - samples[None], axis=2)
        best = d_all.argmin(axis=1)
        near = d_all.min(axis=1) <= 0.01
        np.testing.assert_array_equal(idx[near], best[near])
        np.testing.assert_allclose(dist[near], d_all.min(axis=1)[near], rtol=0, atol=1e-15)
        assert np.all(idx[~near] == -1) and np.all(np.isinf(side[~near]))
