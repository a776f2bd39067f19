"""``apo track`` end to end on rendered frames, with model files in millimetres."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from apo.cli import main
from apo.perception.example import example_camera, insertion_trajectory, peg_and_slot
from apo.perception.render import DepthNoise, render_demonstration
from apo.spatial import position_quaternion_from_pose

pytest.importorskip("open3d")
trimesh = pytest.importorskip("trimesh")


def pose_text(X: np.ndarray, scale: float) -> str:
    p, q = position_quaternion_from_pose(X)
    return " ".join(f"{v:.9g}" for v in [*(p * scale), *q])


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> dict:
    root = tmp_path_factory.mktemp("rec")
    peg, slot = peg_and_slot()
    for name, (V, T) in (("peg", peg), ("slot", slot)):
        trimesh.Trimesh(V * 1e3, T, process=False).export(root / f"{name}.stl")
    cam, X_CE = example_camera(320, 240)
    times, X_EG = insertion_trajectory(8, duration=0.8)
    render_demonstration(
        peg, slot, X_CE, X_EG, times, cam, root / "frames", noise=DepthNoise(1.5e-3), seed=2
    )
    return {"root": root, "X_CE": X_CE, "X_EG": X_EG, "times": times}


def test_track_writes_csv_and_environment(
    recording: dict, capsys: pytest.CaptureFixture[str]
) -> None:
    root, X_CE, X_EG = recording["root"], recording["X_CE"], recording["X_EG"]
    out = root / "out" / "poses.csv"
    code = main(
        [
            "track", str(root / "frames"),
            "--grasped", str(root / "peg.stl"), "--environment", str(root / "slot.stl"),
            "--units", "mm",
            "--init-grasped", pose_text(X_CE @ X_EG[0], 1e3),
            "--init-environment", pose_text(X_CE, 1e3),
            "--out", str(out),
        ]
    )  # fmt: skip
    assert code == 0
    assert "8 of 8 frames tracked" in capsys.readouterr().out
    lines = out.read_text().splitlines()
    assert lines[0] == "t,x,y,z,qw,qx,qy,qz,confidence"
    data = np.array([[float(v) for v in line.split(",")] for line in lines[1:]])
    assert data.shape == (8, 9)
    np.testing.assert_allclose(data[:, 0], recording["times"], atol=1e-6)
    # Positions in mm, in the environment frame: within 1 mm of the truth.
    np.testing.assert_allclose(data[:, 1:4], X_EG[:, :3, 3] * 1e3, atol=1.0)
    assert np.all(data[:, 4] >= 0) and np.all(data[:, 8] > 0.9)
    env = json.loads((root / "out" / "poses.environment.json").read_text())
    assert env["frame"] == "camera" and env["units"] == "mm" and env["lost_frames"] == []
    np.testing.assert_allclose(env["X_CE"][:3], X_CE[:3, 3] * 1e3, atol=0.5)
    np.testing.assert_allclose(env["X_WE"][:3], [0, 0, 0], atol=0.5)  # the camera pose is X_EC


def test_track_rejects_bad_pose(recording: dict, capsys: pytest.CaptureFixture[str]) -> None:
    root = recording["root"]
    code = main(
        [
            "track", str(root / "frames"),
            "--grasped", str(root / "peg.stl"), "--environment", str(root / "slot.stl"),
            "--init-grasped", "1 2 3", "--out", str(root / "x.csv"),
        ]
    )  # fmt: skip
    assert code == 2
    assert "--init-grasped: expected 7 numbers" in capsys.readouterr().err


def test_track_reports_bad_frames_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "frames").mkdir()
    code = main(
        ["track", str(tmp_path / "frames"), "--grasped", "g.stl", "--environment", "e.stl",
         "--out", str(tmp_path / "p.csv")]
    )  # fmt: skip
    assert code == 2
    assert "camera.json: camera calibration file not found" in capsys.readouterr().err
