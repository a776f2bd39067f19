"""Segmentation (apo.perception.segment): colour model, support plane, occupancy histogram."""

from __future__ import annotations

import numpy as np
import pytest

from apo.perception.frames import Camera
from apo.perception.segment import (
    ColourModel,
    fit_support_plane,
    foreground_from_background,
    foreground_from_plane,
    grasped_mask,
    occupancy,
    static_mask,
)


def test_white_model_ignores_shading_rejects_colours() -> None:
    rgb = np.array(
        [[[235, 235, 230], [110, 110, 108], [90, 76, 64], [217, 153, 115], [20, 20, 20]]],
        np.uint8,
    )  # lit white, shaded white, brown table, skin, black
    assert ColourModel.white().mask(rgb).tolist() == [[True, True, False, False, False]]


def test_custom_colour_and_any_colour() -> None:
    rgb = np.array([[[200, 30, 30], [230, 230, 230]]], np.uint8)
    red = ColourModel((1.0, 0.15, 0.15), 0.05, 0.3)
    assert red.mask(rgb).tolist() == [[True, False]]
    assert ColourModel.any_colour().mask(rgb).all()


def test_support_plane_fit_and_foreground() -> None:
    cam = Camera(100.0, 100.0, 49.5, 39.5, 100, 80)
    # A table plane tilted towards the camera, plus a 20 mm block on it.
    v, u = np.mgrid[0:80, 0:100]
    rx, ry = (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy
    n = np.array([0.0, -0.6, -0.8])  # unit normal, pointing to the camera
    d = -0.4  # n . p = d on the table
    depth = d / (n[0] * rx + n[1] * ry + n[2])
    block = (slice(30, 40), slice(40, 60))
    depth[block] -= 0.02 / 0.8  # 20 mm above the plane (along the normal), seen along z
    depth[0, :] = 0.0
    plane = fit_support_plane(cam.backproject(depth), seed=0)
    np.testing.assert_allclose(plane.normal, n, atol=1e-3)
    assert plane.offset == pytest.approx(d, abs=1e-4)
    fg = foreground_from_plane(depth, cam, plane, threshold=0.004)
    assert fg[block].all() and fg.sum() == fg[block].size


def test_foreground_from_background() -> None:
    bg = np.array([[1.0, 1.0, 0.0, 1.0]])
    d = np.array([[0.99, 0.9, 0.8, 0.0]])
    assert foreground_from_background(d, bg, threshold=0.02).tolist() == [
        [False, True, True, False]
    ]


def test_occupancy_separates_static_environment() -> None:
    masks = np.zeros((10, 4, 4), bool)
    masks[:, 0, 0] = True  # environment: always
    masks[2:4, 1, 1] = True  # grasped object passing: 2 of 10 frames
    hist = occupancy(masks)
    assert hist[0, 0] == 1.0 and hist[1, 1] == 0.2
    assert static_mask(hist).tolist()[0][0] and not static_mask(hist)[1, 1]


def test_grasped_mask_in_front_of_environment() -> None:
    objects = np.array([[True, True, True, False]])
    depth = np.array([[0.5, 0.45, 0.7, 0.5]])
    env = np.array([[0.501, 0.5, 0.0, 0.5]])
    # pixel 0 is the environment, 1 the grasped object in front of it, 2 off the environment
    assert grasped_mask(objects, depth, env, threshold=0.004).tolist() == [
        [False, True, True, False]
    ]


def test_learnt_colour_accepts_the_parts_and_not_the_hand() -> None:
    from apo.perception.segment import learn_colour

    rng = np.random.default_rng(0)
    for part in ((0.55, 0.55, 0.55), (0.20, 0.35, 0.75), (0.35, 0.30, 0.25)):
        shade = rng.uniform(0.4, 1.0, (500, 1))  # shading changes brightness, not chromaticity
        px = np.clip(np.array(part) * shade * 255 + rng.normal(0, 2, (500, 3)), 0, 255)
        model = learn_colour(px.astype(np.uint8))
        assert model.used
        assert model.mask(px.astype(np.uint8)[:, None, :]).mean() > 0.95
        skin = np.array([[[217, 153, 115]]], dtype=np.uint8)
        assert not model.mask(skin)[0, 0]
    assert not learn_colour(np.zeros((10, 3), dtype=np.uint8)).used  # too few pixels
