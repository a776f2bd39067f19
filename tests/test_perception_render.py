"""Synthetic rendering (apo.perception.render): exact depth, labels, noise model, layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from apo.errors import InputFormatError
from apo.perception.frames import Camera, open_frames
from apo.perception.render import (
    DepthNoise,
    add_depth_noise,
    box_triangles,
    hand_triangles,
    mesh_triangles,
    pose_looking_at,
    rasterize,
    render_demonstration,
    render_scene,
)
from apo.spatial import invert_pose

CAM = Camera(200.0, 200.0, 79.5, 59.5, 160, 120, 1e-4)


def box_at(z: float) -> np.ndarray:
    X = np.eye(4)
    X[2, 3] = z
    return X


def test_box_facing_camera_has_exact_depth() -> None:
    # A 50 mm cube 0.5 m ahead: its near face is the plane z = 0.475 m, and it spans
    # 200 px/m * 0.05 m / 0.475 m = 21 px across.
    V, T = box_triangles((0.05, 0.05, 0.05))
    depth, tri = rasterize(V + np.array([0.0, 0.0, 0.5]), T, CAM)
    assert depth[59, 79] == pytest.approx(0.475, abs=1e-6)
    hit = depth > 0
    assert np.all(np.isclose(depth[hit], 0.475, atol=1e-6))
    cols = np.nonzero(hit.any(axis=0))[0]
    assert 20 <= len(cols) <= 22
    assert set(np.unique(tri[hit])) <= {8, 9}  # the z- face (triangles 8, 9)


def test_nearest_surface_wins_and_labels() -> None:
    box = box_triangles((0.05, 0.05, 0.05))
    r = render_scene([box, box], [box_at(0.6), box_at(0.4)], CAM)
    assert r.label[59, 79] == 1  # the nearer box
    assert r.depth[59, 79] == pytest.approx(0.375, abs=1e-6)
    assert r.rgb[59, 79].min() > 200  # white, facing the light
    assert r.label[0, 0] == -1 and r.depth[0, 0] == 0


def test_depth_noise_grows_with_distance_squared() -> None:
    rng = np.random.default_rng(1)
    near = np.full((200, 200), 0.5, np.float32)
    far = np.full((200, 200), 1.0, np.float32)
    noise = DepthNoise(sigma_1m=2e-3, dropout=0.0)
    s_near = np.std(add_depth_noise(near, noise, rng) - near)
    s_far = np.std(add_depth_noise(far, noise, rng) - far)
    assert s_near == pytest.approx(0.5e-3, rel=0.05)
    assert s_far == pytest.approx(2e-3, rel=0.05)


def test_dropouts_at_depth_edges() -> None:
    d = np.full((50, 50), 1.0, np.float32)
    d[:, 25:] = 0.8  # a 0.2 m step between columns 24 and 25
    out = add_depth_noise(
        d, DepthNoise(sigma_1m=0.0, edge_dropout=1.0, dropout=0.0), np.random.default_rng(0)
    )
    assert np.all(out[:, 24:26] == 0)
    assert np.all(out[:, :24] > 0) and np.all(out[:, 26:] > 0)


def test_mesh_triangles_accepts_trimesh_arrays_and_units() -> None:
    trimesh = pytest.importorskip("trimesh")
    m = trimesh.creation.box((50.0, 50.0, 50.0))
    V, _ = mesh_triangles(m, units="mm")
    assert np.ptp(V, axis=0) == pytest.approx([0.05] * 3)
    V2, _ = mesh_triangles((m.vertices, m.faces), units="cm")
    assert np.ptp(V2, axis=0) == pytest.approx([0.5] * 3)
    with pytest.raises(InputFormatError, match="unknown units"):
        mesh_triangles(m, units="furlong")
    with pytest.raises(InputFormatError, match=r"vertices of shape \(N, 3\)"):
        mesh_triangles((np.zeros((4, 2)), [[0, 1, 2]]))
    with pytest.raises(InputFormatError, match="out of range"):
        mesh_triangles((np.zeros((3, 3)), [[0, 1, 5]]))
    with pytest.raises(InputFormatError, match="expected a trimesh"):
        mesh_triangles(42)


def test_hand_surrounds_the_grasped_object() -> None:
    peg = box_triangles((0.02, 0.02, 0.05), (0, 0, 0.025))
    V, _ = hand_triangles(peg)
    assert V[:, 1].min() < -0.01 and V[:, 1].max() > 0.01  # fingers on both sides
    assert V[:, 2].max() > 0.05  # the wrist is above the object


def test_render_demonstration_writes_the_layout(tmp_path: Path) -> None:
    X_WC = pose_looking_at([0.0, -0.3, 0.3], [0.0, 0.0, 0.0])
    cam = Camera(200.0, 200.0, 79.5, 59.5, 160, 120, 1e-4, X_WC)
    env = box_triangles((60.0, 60.0, 20.0), (0, 0, 10.0))
    peg = box_triangles((20.0, 20.0, 40.0), (0, 0, 20.0))
    X_EG = np.repeat(np.eye(4)[None], 3, axis=0)
    X_EG[:, 2, 3] = [60.0, 50.0, 40.0]
    X_CE = invert_pose(X_WC)
    X_CE[:3, 3] *= 1e3  # poses in the model units (mm)
    out = render_demonstration(
        peg, env, X_CE, X_EG, [0.0, 0.5, 1.0], cam,
        tmp_path / "f", units="mm", hand=True, seed=3,
    )  # fmt: skip
    frames = open_frames(out)
    assert len(frames) == 3
    np.testing.assert_allclose(frames.times, [0.0, 0.5, 1.0])
    assert frames.camera == cam
    rgb, depth = frames.background()
    assert rgb is not None and depth is not None
    d = frames.depth(1)
    assert (d > 0).mean() > 0.5  # the table fills most of the view
    assert np.any((depth > 0) & (d > 0) & (d < depth - 0.01))  # objects stand out


def test_render_demonstration_checks_shapes(tmp_path: Path) -> None:
    box = box_triangles((1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match=r"X_EG_seq must have shape \(N, 4, 4\)"):
        render_demonstration(box, box, np.eye(4), np.eye(4), [0.0], CAM, tmp_path)
    with pytest.raises(ValueError, match="times has shape"):
        render_demonstration(box, box, np.eye(4), np.eye(4)[None], [0.0, 1.0], CAM, tmp_path)


def test_up_turns_the_hand_and_the_table() -> None:
    from apo.perception.render import _table_triangles

    # The same object with y up instead of z up: the hand and the table turn with it.
    peg_z = box_triangles((0.02, 0.02, 0.05), (0, 0, 0.025))
    R = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # z up -> y up
    peg_y = (peg_z[0] @ R.T, peg_z[1])
    Vz, _ = hand_triangles(peg_z)
    Vy, _ = hand_triangles(peg_y, up=(0, 1, 0))
    np.testing.assert_allclose(np.sort(Vy, axis=0), np.sort(Vz @ R.T, axis=0), atol=1e-12)
    T, _ = _table_triangles(peg_y, up=(0.0, 2.0, 0.0))
    np.testing.assert_allclose(T[:, 1], 0.0, atol=1e-12)  # under the object, perpendicular to y
    with pytest.raises(ValueError, match="up must be a non-zero 3-vector"):
        hand_triangles(peg_z, up=(0, 0, 0))


def test_static_scene_composited_once_equals_full_render(tmp_path: Path) -> None:
    # render_demonstration renders the table and environment once and composites the
    # grasped object per frame; without noise that is the z-buffer of the whole scene.
    X_WC = pose_looking_at([0.0, -0.3, 0.3], [0.0, 0.0, 0.0])
    cam = Camera(200.0, 200.0, 79.5, 59.5, 160, 120, 1e-4, X_WC)
    env = box_triangles((0.06, 0.06, 0.02), (0, 0, 0.01))
    peg = box_triangles((0.02, 0.02, 0.04), (0, 0, 0.02))
    X_CE = invert_pose(X_WC)
    X_EG = np.eye(4)[None].copy()
    X_EG[0, :3, 3] = [0.03, 0.0, 0.01]  # half in front of, half behind the block's top
    out = render_demonstration(
        peg, env, X_CE, X_EG, [0.0], cam, tmp_path, noise=DepthNoise.none(), background=False
    )
    full = render_scene([env, peg], [X_CE, X_CE @ X_EG[0]], cam)
    depth = open_frames(out).depth(0)
    table = (full.depth == 0) & (depth > 0)  # the table is only in the written frame
    np.testing.assert_allclose(depth[~table], full.depth[~table], atol=1e-4)
