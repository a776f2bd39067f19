"""Stereo front end (apo.perception.stereo): SGBM depth of a rendered pair, folder layout."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from apo.errors import InputFormatError
from apo.perception.example import example_camera, peg_and_slot
from apo.perception.frames import open_frames
from apo.perception.render import TABLE, WHITE, render_scene
from apo.perception.stereo import depth_from_disparity

BASELINE = 0.08


def write_stereo(root: Path, n: int = 1) -> np.ndarray:
    """Render the slot on its table from two rectified cameras; return the true left depth."""
    cam, X_CE = example_camera(320, 240)
    _, slot = peg_and_slot()
    table = (np.array([[-0.4, -0.4, 0], [0.4, -0.4, 0], [0.4, 0.4, 0], [-0.4, 0.4, 0.0]]),
             np.array([[0, 1, 2], [0, 2, 3]]))  # fmt: skip
    X_RC = np.eye(4)
    X_RC[0, 3] = -BASELINE  # the right camera is BASELINE along the left camera's +x
    views = {}
    for name, X in (("left", X_CE), ("right", X_RC @ X_CE)):
        r = render_scene([table, slot], [X, X], cam, albedo=[TABLE, WHITE], textured=[True, True])
        views[name] = r
        for i in range(n):
            (root / name).mkdir(parents=True, exist_ok=True)
            Image.fromarray(r.rgb).save(root / name / f"{i:06d}.png")
    cal = {k: v for k, v in cam.to_json().items() if k != "depth_scale"}
    cal["baseline"] = BASELINE
    cal["num_disparities"] = 96  # 63 px at the slot; SGBM leaves the first 96 columns empty
    (root / "stereo.json").write_text(json.dumps(cal))
    return views["left"].depth


def test_sgbm_depth_of_rendered_pair(tmp_path: Path) -> None:
    pytest.importorskip("cv2")
    truth = write_stereo(tmp_path)
    frames = open_frames(tmp_path)  # a stereo folder is recognised by stereo.json
    assert len(frames) == 1
    depth = frames.depth(0)
    both = (depth > 0) & (truth > 0)
    assert both.sum() > 0.6 * (truth[:, 96:] > 0).sum()  # most of the matchable view
    err = np.abs(depth[both] - truth[both])
    # dz = z^2 / (f b) * dd = 0.4^2 / (262 * 0.08) * dd = 7.6 mm per pixel of disparity:
    # SGBM's sub-pixel error of about 0.2 px on this texture gives 1.5 mm.
    assert np.median(err) < 0.0025
    assert np.mean(err < 0.005) > 0.85
    assert frames.rgb(0).shape == (240, 320, 3)
    assert frames.camera.X_WC is not None


def test_depth_from_disparity() -> None:
    d = depth_from_disparity(np.array([[10.0, 0.0, -1.0]]), fx=500.0, baseline=0.1)
    np.testing.assert_allclose(d, [[5.0, 0.0, 0.0]])


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        ({"baseline": None}, "missing key baseline"),
        ({"baseline": -0.1}, "baseline must be a positive number"),
        ({"num_disparities": 100}, "num_disparities must be a multiple of 16"),
        ({"block_size": 4}, "block_size must be a positive odd integer"),
        ({"fx": None}, "missing key"),
    ],
)
def test_bad_stereo_json(tmp_path: Path, edit: dict[str, object], match: str) -> None:
    write_stereo(tmp_path)
    cal = json.loads((tmp_path / "stereo.json").read_text())
    for k, v in edit.items():
        if v is None:
            cal.pop(k)
        else:
            cal[k] = v
    (tmp_path / "stereo.json").write_text(json.dumps(cal))
    with pytest.raises(InputFormatError, match=match):
        open_frames(tmp_path)


def test_unpaired_stereo_frames(tmp_path: Path) -> None:
    write_stereo(tmp_path, n=2)
    (tmp_path / "right" / "000001.png").unlink()
    with pytest.raises(InputFormatError, match="left/ has 2 frames, right/ has 1"):
        open_frames(tmp_path)
