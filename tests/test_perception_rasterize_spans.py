"""``rasterize`` by row spans equals the bounding-box rasteriser it replaced, bit for bit.

The reference below is the earlier implementation (every pixel of each triangle's bounding
box tested, the nearest kept by a stable sort); the span version tests only each row's
interval of the triangle, widened by a margin, and keeps the nearest by ``minimum.at``.
Randomised triangles, including vertices on pixel centres and half pixels, edges nearly
parallel to the rows, triangles behind the near plane and off the image.
"""

from __future__ import annotations

import numpy as np
import pytest

from apo.perception.frames import Camera
from apo.perception.render import _projected, box_triangles, rasterize


def reference(
    V: np.ndarray, T: np.ndarray, camera: Camera, near: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """The bounding-box rasteriser (apo before the span version; the same projection)."""
    tris = _projected(V, T, camera, near)
    W = camera.width
    depth = np.zeros((camera.height, W), dtype=np.float32)
    tri_img = np.full(depth.shape, -1, dtype=np.int64)
    if tris is None:
        return depth, tri_img
    ids, U, Vv, Z, umin, umax, vmin, wv, area = tris
    wu = umax - umin + 1
    count = wu * wv
    t = np.repeat(np.arange(len(ids)), count)
    off = np.arange(int(count.sum())) - (np.cumsum(count) - count)[t]
    px = umin[t] + off % wu[t]
    py = vmin[t] + off // wu[t]
    Ut, Vt = U[t], Vv[t]
    w0 = (Ut[:, 1] - px) * (Vt[:, 2] - py) - (Ut[:, 2] - px) * (Vt[:, 1] - py)
    w1 = (Ut[:, 2] - px) * (Vt[:, 0] - py) - (Ut[:, 0] - px) * (Vt[:, 2] - py)
    b0 = w0 / area[t]
    b1 = w1 / area[t]
    b2 = 1.0 - b0 - b1
    inside = (b0 >= -1e-9) & (b1 >= -1e-9) & (b2 >= -1e-9)
    Zt = Z[t]
    inv_z = b0 / Zt[:, 0] + b1 / Zt[:, 1] + b2 / Zt[:, 2]
    inside &= inv_z > 0
    px, py, t, inv_z = px[inside], py[inside], t[inside], inv_z[inside]
    zz = 1.0 / inv_z
    pix = py * W + px
    order = np.lexsort((zz, pix))
    first = np.ones(len(order), dtype=bool)
    first[1:] = pix[order][1:] != pix[order][:-1]
    win = order[first]
    depth.ravel()[pix[win]] = zz[win]
    tri_img.ravel()[pix[win]] = ids[t[win]]
    return depth, tri_img


def _case(rng: np.random.Generator, kind: int) -> tuple[np.ndarray, np.ndarray, Camera]:
    W, H = int(rng.integers(1, 90)), int(rng.integers(1, 90))
    f = float(rng.uniform(20, 200))
    cam = Camera(f, f, float(rng.uniform(-5, W + 5)), float(rng.uniform(-5, H + 5)), W, H)
    n = int(rng.integers(3, 40))
    if kind == 2:  # a box, as the models are
        V, T = box_triangles(rng.uniform(0.01, 0.1, 3).tolist())
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        shift = [rng.normal(0, 0.02), rng.normal(0, 0.02), rng.uniform(0.0, 0.6)]
        return V @ R.T + shift, T, cam
    if kind == 0:  # anywhere, some behind the near plane
        V = rng.normal(0, 0.05, (n, 3))
        V[:, 2] += rng.uniform(0.0, 0.5)
    else:  # on pixel centres (1) or half pixels, a hair off (3): edges through pixel centres
        uv = rng.integers(-3, max(W, H) + 3, (n, 2)).astype(float)
        if kind == 3:
            uv = uv / 2.0 + rng.choice([0.0, 1e-10, -1e-10, 1e-7], (n, 2))
        z = rng.choice([0.3, 0.5, 0.7], n) if kind == 1 else rng.uniform(0.2, 0.8, n)
        V = np.column_stack(((uv[:, 0] - cam.cx) / f * z, (uv[:, 1] - cam.cy) / f * z, z))
    return V, rng.integers(0, n, (int(rng.integers(1, 30)), 3)), cam


@pytest.mark.parametrize("seed", range(4))
def test_spans_equal_bounding_boxes(seed: int) -> None:
    rng = np.random.default_rng(seed)
    covered = 0
    for k in range(300):
        V, T, cam = _case(rng, k % 4)
        depth, tri = rasterize(V, T, cam)
        ref_depth, ref_tri = reference(V, T, cam)
        assert np.array_equal(tri, ref_tri), (seed, k)
        assert np.array_equal(depth, ref_depth), (seed, k)
        covered += int(np.count_nonzero(tri >= 0))
    assert covered > 10000  # the cases draw something


def test_spans_equal_bounding_boxes_full_frame() -> None:
    """Many triangles at 640x480 (a scene, as the benchmark renders it)."""
    rng = np.random.default_rng(7)
    cam = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
    parts = []
    for _ in range(20):
        V, T = box_triangles(rng.uniform(0.01, 0.2, 3).tolist())
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        parts.append((V @ R.T + [rng.normal(0, 0.1), rng.normal(0, 0.1), rng.uniform(0.3, 1)], T))
    V = np.concatenate([p[0] for p in parts])
    T = np.concatenate([p[1] + 8 * i for i, p in enumerate(parts)])
    depth, tri = rasterize(V, T, cam)
    ref_depth, ref_tri = reference(V, T, cam)
    assert np.array_equal(tri, ref_tri)
    assert np.array_equal(depth, ref_depth)
    assert np.count_nonzero(tri >= 0) > 20000
