"""Frames folder layout: round trip and every validation error (apo.perception.frames)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from apo.errors import InputFormatError
from apo.perception.frames import (
    Camera,
    open_frames,
    read_camera,
    write_background,
    write_camera,
    write_frame,
    write_timestamps,
)
from apo.spatial import pose_from_xyz_quat

CAM = Camera(100.0, 100.0, 15.5, 11.5, 32, 24, 0.001)


def make_folder(root: Path, n: int = 3, *, times: bool = True) -> Path:
    write_camera(root / "camera.json", CAM)
    rng = np.random.default_rng(0)
    for i in range(n):
        rgb = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
        depth = np.full((24, 32), 0.5 + 0.01 * i)
        depth[0, 0] = 0.0
        write_frame(root, i, rgb, depth, CAM)
    if times:
        write_timestamps(root, np.arange(n) * 0.1 + 2.0)
    return root


def test_round_trip(tmp_path: Path) -> None:
    make_folder(tmp_path)
    frames = open_frames(tmp_path)
    assert len(frames) == 3
    assert frames.camera == CAM
    np.testing.assert_allclose(frames.times, [2.0, 2.1, 2.2])
    d = frames.depth(2)
    assert d.dtype == np.float32 and d.shape == (24, 32)
    assert d[0, 0] == 0.0  # no measurement stays 0
    np.testing.assert_allclose(d[1, 1], 0.52, atol=1e-6)  # 1 mm units
    assert frames.rgb(0).shape == (24, 32, 3)
    assert frames.background() == (None, None)


def test_background_and_default_times(tmp_path: Path) -> None:
    make_folder(tmp_path, 2, times=False)
    write_background(tmp_path, np.zeros((24, 32, 3), np.uint8), np.full((24, 32), 0.7), CAM)
    frames = open_frames(tmp_path, fps=10.0)
    np.testing.assert_allclose(frames.times, [0.0, 0.1])
    rgb, depth = frames.background()
    assert rgb is not None and depth is not None
    np.testing.assert_allclose(depth, 0.7, atol=1e-6)


def test_several_background_frames_are_combined_by_median(tmp_path: Path) -> None:
    make_folder(tmp_path, 2)
    rng = np.random.default_rng(0)
    frames_bg = [0.7 + rng.normal(0, 0.002, (24, 32)) for _ in range(5)]
    frames_bg[1][3, 4] = 0.0  # a dropout in one frame does not count
    frames_bg[2][3, 4] = 0.1  # an outlier in one frame is outvoted
    write_background(tmp_path, np.zeros((24, 32, 3), np.uint8), *frames_bg[:1], CAM, *frames_bg[1:])
    frames = open_frames(tmp_path)
    assert frames.background_count == 5  # type: ignore[attr-defined]
    _, depth = frames.background()
    assert depth is not None
    stack = np.round(np.stack(frames_bg) * 1e3) / 1e3  # 1 mm units
    expected = np.sort(stack, axis=0)[2]
    expected[3, 4] = np.sort(stack[[0, 2, 3, 4], 3, 4])[1]  # the lower median of the 4 measured
    np.testing.assert_allclose(depth, expected, atol=1e-6)
    # Its noise is well below one frame's.
    assert np.std(depth - 0.7) < 0.8 * np.std(stack[0] - 0.7)


def test_camera_pose_round_trip(tmp_path: Path) -> None:
    X = pose_from_xyz_quat([0.1, -0.2, 0.3, 0.9, 0.1, -0.3, 0.2])
    cam = Camera(1.0, 2.0, 3.0, 4.0, 5, 6, 1e-4, X)
    write_camera(tmp_path / "camera.json", cam)
    back = read_camera(tmp_path / "camera.json")
    assert back.X_WC is not None
    np.testing.assert_allclose(back.X_WC, X, atol=1e-12)


def test_backproject_project_inverse() -> None:
    depth = np.zeros((24, 32))
    depth[5, 7] = 0.4
    P = CAM.backproject(depth)
    np.testing.assert_allclose(P, [[(7 - 15.5) * 0.4 / 100, (5 - 11.5) * 0.4 / 100, 0.4]])
    np.testing.assert_allclose(CAM.project(P), [[7.0, 5.0]])


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        ({"fx": None}, "missing key"),
        ({"fx": "100"}, "fx must be a finite number"),
        ({"width": 32.5}, "width must be a positive integer"),
        ({"depth_scale": 0}, "depth_scale must be positive"),
        ({"pose": [1, 2, 3]}, "pose must be 7 numbers"),
        ({"pose": [0, 0, 0, 0, 0, 0, 0]}, "pose: quaternion has zero norm"),
        ({"focal": 1}, "unknown key"),
    ],
)
def test_bad_camera_json(tmp_path: Path, edit: dict[str, object], match: str) -> None:
    data = CAM.to_json()
    for k, v in edit.items():
        if v is None:
            del data[k]
        else:
            data[k] = v
    (tmp_path / "camera.json").write_text(json.dumps(data))
    with pytest.raises(InputFormatError, match=match):
        read_camera(tmp_path / "camera.json")


def test_missing_and_invalid_camera_json(tmp_path: Path) -> None:
    make_folder(tmp_path)
    (tmp_path / "camera.json").unlink()
    with pytest.raises(InputFormatError, match=r"camera\.json: camera calibration file not found"):
        open_frames(tmp_path)
    (tmp_path / "camera.json").write_text("{fx: 1")
    with pytest.raises(InputFormatError, match="not valid JSON"):
        open_frames(tmp_path)


def test_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(InputFormatError, match="frames folder not found"):
        open_frames(tmp_path / "nope")


def test_gap_in_numbering(tmp_path: Path) -> None:
    make_folder(tmp_path, 3, times=False)
    (tmp_path / "rgb" / "000001.png").unlink()
    (tmp_path / "depth" / "000001.png").unlink()
    with pytest.raises(
        InputFormatError, match=r"rgb/000001\.png: missing; frames must be numbered"
    ):
        open_frames(tmp_path)


def test_unpaired_frames(tmp_path: Path) -> None:
    make_folder(tmp_path, 3, times=False)
    (tmp_path / "depth" / "000002.png").unlink()
    with pytest.raises(
        InputFormatError, match=r"depth/000002\.png: missing \(rgb/000002\.png exists\)"
    ):
        open_frames(tmp_path)


def test_badly_named_frame(tmp_path: Path) -> None:
    make_folder(tmp_path, 1)
    (tmp_path / "rgb" / "frame1.png").write_bytes(b"")
    with pytest.raises(InputFormatError, match="six digits"):
        open_frames(tmp_path)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("0.0\n0.1\n", "2 times for 3 frames"),
        ("0.0\nabc\n0.2\n", r"timestamps\.txt:2: expected one time"),
        ("0.0\n0.2\n0.1\n", "times must increase; frame 2"),
    ],
)
def test_bad_timestamps(tmp_path: Path, text: str, match: str) -> None:
    make_folder(tmp_path, 3, times=False)
    (tmp_path / "timestamps.txt").write_text(text)
    with pytest.raises(InputFormatError, match=match):
        open_frames(tmp_path)


def test_depth_must_be_16_bit(tmp_path: Path) -> None:
    make_folder(tmp_path, 1)
    Image.fromarray(np.zeros((24, 32), np.uint8)).save(tmp_path / "depth" / "000000.png")
    frames = open_frames(tmp_path)
    with pytest.raises(
        InputFormatError, match=r"000000\.png: depth must be a 16-bit single-channel"
    ):
        frames.depth(0)


def test_image_size_must_match_camera(tmp_path: Path) -> None:
    make_folder(tmp_path, 1)
    Image.fromarray(np.zeros((10, 10, 3), np.uint8)).save(tmp_path / "rgb" / "000000.png")
    frames = open_frames(tmp_path)
    with pytest.raises(InputFormatError, match=r"image is 10x10, camera\.json says 32x24"):
        frames.rgb(0)


def test_depth_too_far_for_16_bits(tmp_path: Path) -> None:
    with pytest.raises(InputFormatError, match="does not fit 16 bits"):
        write_frame(tmp_path, 0, np.zeros((24, 32, 3), np.uint8), np.full((24, 32), 70.0), CAM)


def test_subsampled_camera_sees_every_other_pixel() -> None:
    sub = CAM.subsampled(2)
    assert (sub.width, sub.height) == (16, 12)
    P = np.array([[0.01, -0.02, 0.5], [0.03, 0.01, 0.4]])
    np.testing.assert_allclose(sub.project(P) * 2, CAM.project(P))
    with pytest.raises(ValueError, match="step must be a positive integer"):
        CAM.subsampled(0)
