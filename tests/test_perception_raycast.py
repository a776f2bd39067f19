"""The second, independent renderer (apo.perception.raycast): what it writes is a recording."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

pytest.importorskip("open3d")

from apo.perception.frames import open_frames
from apo.perception.raycast import (
    _demo,
    _triangles,
    random_conditions,
    render_independent,
)


def _small(seed: int, **changes: object) -> object:
    """A 160x120 version of a seed's conditions (the camera scaled by 1/4)."""
    c = random_conditions(seed)
    return dataclasses.replace(c, camera=c.camera.scaled(0.25), **changes)


def _distance_to_surface(points: np.ndarray, meshes: list) -> np.ndarray:
    import trimesh

    d = np.full(len(points), np.inf)
    for V, T in meshes:
        q = trimesh.proximity.closest_point(trimesh.Trimesh(V, T, process=False), points)[1]
        d = np.minimum(d, q)
    return d


@pytest.mark.parametrize("seed", [3, 8])
def test_depth_is_the_scene_within_the_noise(tmp_path, seed):
    """Back-projected depth lies on the true surfaces (mm quantisation and c z^2 noise)."""
    from apo.perception.raycast import _table

    c = _small(seed, hand=False, blobs=0)
    rec = render_independent(c, tmp_path / "f")
    frames = open_frames(rec.frames)
    assert len(frames) == len(rec.demo.times)
    assert np.allclose(frames.times, rec.demo.times, atol=1e-6)
    cam = json.loads((rec.frames / "camera.json").read_text())
    assert cam["depth_scale"] == 0.001
    k = len(frames) // 2
    z = frames.depth(k).astype(np.float64)
    P_C = frames.camera.backproject(z)
    X_EC = np.linalg.inv(rec.X_CE)
    P_E = P_C @ X_EC[:3, :3].T + X_EC[:3, 3]
    X_EG = rec.demo.X_EG_true[k]
    G = (rec.grasped[0] @ X_EG[:3, :3].T + X_EG[:3, 3], rec.grasped[1])
    _, up = _demo(c)
    d = _distance_to_surface(P_E, [rec.environment, G, _table(rec.environment, up)])
    sigma = c.noise * float(np.median(z[z > 0])) ** 2
    assert np.median(d) < 0.6e-3 + 2 * sigma  # whole millimetres: 0.29 mm rms
    assert np.mean(d < 0.01) > 0.97  # flying pixels at edges only
    assert 0.5 < np.mean(z > 0) < 0.999  # the projector's shadows and dropouts


def test_same_seed_same_recording_and_the_hand_occludes(tmp_path):
    c = _small(5, hand=True)
    a = render_independent(c, tmp_path / "a")
    b = render_independent(c, tmp_path / "b")
    no_hand = render_independent(dataclasses.replace(c, hand=False), tmp_path / "n")
    read = [open_frames(r.frames) for r in (a, b, no_hand)]
    assert np.array_equal(read[0].depth(0), read[1].depth(0))
    assert np.array_equal(read[0].rgb(0), read[1].rgb(0))
    nearer = (read[0].depth(0) > 0) & (read[0].depth(0) < read[2].depth(0) - 0.01)
    assert nearer.sum() > 20  # the hand and forearm stand in front of something
    assert (rec := a).grasped[0].shape[1] == 3 and len(_triangles(rec.demo.grasped)[1]) > 0


def test_conditions_vary_with_the_seed():
    cs = [random_conditions(s) for s in range(40)]
    assert {c.demo for c in cs} == {"peg_in_hole_2d", "square_peg_in_hole"}
    assert len({round(c.camera.fx) for c in cs}) > 30
    assert any(c.hand for c in cs) and not all(c.hand for c in cs)
    assert min(c.distance for c in cs) < 0.45 and max(c.distance for c in cs) > 0.85
