"""Back-face culling of solids and the projective ICP's crop give the renderings and rows of
the whole thing (session 6 speed-ups of ``apo track``).

- ``meshdistance.is_solid``: closed, consistently oriented, normals out.
- ``render.rasterize(..., cull=True)``: the same depth as without culling; the same triangle
  at every pixel where the uncull rendering shows a face turned to the camera.
- ``projective._cropped``: ``projective_icp`` on the box of the mask and the model equals the
  run on the whole window, bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest

import apo.perception.projective as projective
from apo.perception.camera import Camera
from apo.perception.example import peg_and_slot
from apo.perception.meshdistance import is_solid
from apo.perception.projective import face_planes, projective_icp
from apo.perception.render import box_triangles, pose_looking_at, rasterize
from apo.spatial import invert_pose, pose_from_twist, transform_points

CAMERA = Camera(383.0, 383.0, 320.5, 237.8, 640, 480, 1e-4)  # RealSense D435


def _random_pose(rng: np.random.Generator, target: np.ndarray) -> np.ndarray:
    """``X_CM``: the camera 0.3 to 1 m from ``target`` (model frame), any direction."""
    d = rng.normal(size=3)
    eye = target + rng.uniform(0.3, 1.0) * d / np.linalg.norm(d)
    up = rng.normal(size=3)
    return invert_pose(pose_looking_at(eye, target, up=tuple(up)))


def test_is_solid() -> None:
    (V, T), (Ve, Te) = peg_and_slot()
    assert is_solid(V, T) and is_solid(Ve, Te)
    Vb, Tb = box_triangles((0.03, 0.02, 0.01))
    assert is_solid(Vb, Tb)
    assert not is_solid(Vb, Tb[:, ::-1])  # normals in
    assert not is_solid(Vb, Tb[1:])  # open
    flipped = Tb.copy()
    flipped[0] = flipped[0, ::-1]  # one face the wrong way round
    assert not is_solid(Vb, flipped)
    assert face_planes(V, T).solid and not face_planes(Vb, Tb[1:]).solid


@pytest.mark.parametrize("seed", range(4))
def test_culling_keeps_the_depth_and_the_faces_in_view(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for V, T in peg_and_slot():
        faces = face_planes(V, T)
        for _ in range(10):
            X = _random_pose(rng, V.mean(0) + rng.normal(scale=0.01, size=3))
            V_C = transform_points(X, V)
            depth, tri = rasterize(V_C, T, CAMERA)
            depth_c, tri_c = rasterize(V_C, T, CAMERA, cull=True)
            assert np.count_nonzero(depth) > 100
            np.testing.assert_array_equal(depth_c, depth)
            n_C = faces.normals @ X[:3, :3].T
            a = V_C[T[:, 0]]
            front = np.einsum("ij,ij->i", n_C, a) < 0  # turned to the camera
            shown = (tri >= 0) & front[np.maximum(tri, 0)]
            np.testing.assert_array_equal(tri_c[shown], tri[shown])
            assert np.all(front[tri_c[tri_c >= 0]])


@pytest.mark.parametrize(("seed", "clutter"), [(0, False), (1, True), (2, False), (3, True)])
def test_cropped_rows_are_the_whole_windows(
    seed: int, clutter: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    (V, T), _ = peg_and_slot()
    faces = face_planes(V, T)
    rng = np.random.default_rng(seed)
    X_true = _random_pose(rng, V.mean(0))
    depth, _ = rasterize(transform_points(X_true, V), T, CAMERA)
    mask = depth > 0
    far = float(X_true[2, 3]) + 0.1
    depth = np.where(mask, depth, far) + rng.normal(0.0, 2e-3 * far**2, depth.shape)
    v, u = np.nonzero(mask)  # a window twice the peg's box
    h, w = v.max() - v.min() + 1, u.max() - u.min() + 1
    v0, u0 = max(v.min() - h // 2, 0), max(u.min() - w // 2, 0)
    box = np.s_[v0 : v.max() + h // 2, u0 : u.max() + w // 2]
    cam = CAMERA.crop(int(u0), int(v0), *depth[box].shape[::-1])
    twist = np.concatenate([rng.normal(size=3) * 0.02, rng.normal(size=3) * 0.002])
    start = pose_from_twist(twist) @ X_true
    sigma = np.full(depth[box].shape, 1e-3)
    args = {"mask": mask[box], "sigma": sigma, "clutter": clutter, "max_pixels": 1500}
    got = projective_icp(depth[box].astype(np.float32), cam, faces, start, **args)
    monkeypatch.setattr(projective, "_cropped", lambda win, rendered, tri: (win, rendered, tri))
    whole = projective_icp(depth[box].astype(np.float32), cam, faces, start, **args)
    np.testing.assert_array_equal(got.X_CM, whole.X_CM)
    assert (got.pairs, got.iterations, got.rms) == (whole.pairs, whole.iterations, whole.rms)
