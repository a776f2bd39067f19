"""The HTML report without a browser: data packing, offline page, sources, CLI."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from apo.cli import main
from apo.errors import InputFormatError
from apo.report.html import (
    MAX_REPLAY_FRAMES,
    pack_array,
    poses_to_rows,
    read_report_data,
    replay_indices,
    report_data,
    report_html,
    unpack_array,
)
from apo.report.sources import read_frames_csv
from apo.spatial import pose_from_position_quaternion


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "--out", str(out), "--no-plot", "--seed", "3"]) == 0
    return out


@pytest.mark.parametrize("dtype", ["f4", "f8", "u1", "u2", "u4", "i4"])
def test_pack_array_round_trip(dtype: str) -> None:
    a = (np.random.default_rng(1).random((5, 3)) * 200).astype(dtype)
    p = pack_array(a, dtype)
    assert p["shape"] == [5, 3]
    np.testing.assert_array_equal(unpack_array(p), a)


def test_poses_to_rows_round_trip() -> None:
    rng = np.random.default_rng(7)
    from scipy.spatial.transform import Rotation

    R = Rotation.random(20, random_state=rng).as_matrix()
    X = np.tile(np.eye(4), (20, 1, 1))
    X[:, :3, :3] = R
    X[:, :3, 3] = rng.normal(size=(20, 3))
    rows = poses_to_rows(X, 1000.0)
    assert np.all(rows[:, 3] >= 0)
    for x, r in zip(X, rows, strict=True):
        back = pose_from_position_quaternion(r[:3] / 1000.0, r[3:])
        np.testing.assert_allclose(back, x, atol=1e-12)


def test_replay_indices_keep_every_state_end() -> None:
    rng = np.random.default_rng(0)
    n = MAX_REPLAY_FRAMES * 3
    s = np.cumsum(rng.random(n) < 0.01)  # ~180 states, runs of random length
    keep = replay_indices(s)
    assert keep[0] == 0 and keep[-1] == n - 1
    assert len(keep) <= MAX_REPLAY_FRAMES + 2 * len(np.unique(s))
    assert np.all(np.diff(keep) > 0)
    change = np.flatnonzero(np.diff(s)) + 1
    assert set(change) <= set(keep) and set(change - 1) <= set(keep)
    np.testing.assert_array_equal(replay_indices(s[:100]), np.arange(100))


def test_demo_writes_an_offline_report(demo_dir: Path) -> None:
    html = (demo_dir / "report.html").read_text(encoding="utf-8")
    # every asset inlined: no external script, stylesheet, image or font
    assert not re.search(r"<(script|link|img|iframe)[^>]+(src|href)\s*=", html, re.I)
    assert "@import" not in html
    assert "plotly.js v" in html[:200_000]
    data = read_report_data(html)
    task = json.loads((demo_dir / "task.json").read_text())
    assert data["schema"] == "apo.report/1"
    assert data["task"] == task
    frames = data["frames"]
    assert frames["n_frames"] == task["n_frames"]
    states = unpack_array(frames["state"])
    ids = [s["id"] for s in task["states"]]
    for k, s in enumerate(task["states"]):
        a, b = s["frames"]
        assert np.all(states[a : b + 1] == k), ids[k]
    obs = unpack_array(frames["observed"])
    assert obs.shape == (task["n_frames"], 7)
    np.testing.assert_allclose(np.linalg.norm(obs[:, 3:], axis=1), 1.0, atol=1e-5)
    g = data["models"]["grasped"]
    assert unpack_array(g["triangles"]).max() < unpack_array(g["vertices"]).shape[0]
    assert data["inputs"]["units"] == "mm"


def test_report_command_reads_frames_csv_with_poses(demo_dir: Path, tmp_path: Path) -> None:
    task = json.loads((demo_dir / "task.json").read_text())
    lines = (demo_dir / "frames.csv").read_text().splitlines()
    n = len(lines) - 1
    # add pose columns: the state's pose at every frame, moved by a known offset
    head = lines[0] + ",obs_x_mm,obs_y_mm,obs_z_mm,obs_qw,obs_qx,obs_qy,obs_qz"
    out = [head]
    for i, line in enumerate(lines[1:]):
        out.append(line + f",{i},1,2,1,0,0,0")
    (tmp_path / "frames.csv").write_text("\n".join(out) + "\n")
    doc = dict(task)
    doc["models"] = {
        r: {**m, "path": str((demo_dir / m["path"]).resolve())} for r, m in task["models"].items()
    }
    (tmp_path / "task.json").write_text(json.dumps(doc))
    assert main(["report", str(tmp_path / "task.json")]) == 0
    data = read_report_data((tmp_path / "report.html").read_text())
    obs = unpack_array(data["frames"]["observed"])
    assert obs.shape == (n, 7)
    np.testing.assert_allclose(obs[:, 0], np.arange(n))
    assert data["models"]["grasped"] is not None
    roles = {f["role"]: f["status"] for f in data["inputs"]["files"]}
    assert roles == {
        "task": "ok",
        "per-frame data": "ok",
        "grasped model": "ok",
        "environment model": "ok",
    }


def test_report_without_models_still_writes(demo_dir: Path, tmp_path: Path, capsys) -> None:
    doc = json.loads((demo_dir / "task.json").read_text())
    (tmp_path / "task.json").write_text(json.dumps(doc))  # model paths now point nowhere
    out = tmp_path / "r.html"
    assert main(["report", str(tmp_path / "task.json"), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "grasped model not found" in err
    data = read_report_data(out.read_text())
    assert data["models"]["grasped"] is None
    assert any("not found" in n for n in data["notes"])
    # without frames.csv, each state's pose is held over its frames
    assert data["frames"]["source"] == "task states"


def test_report_rejects_bad_inputs(demo_dir: Path, tmp_path: Path, capsys) -> None:
    bad = tmp_path / "task.json"
    bad.write_text("{not json")
    assert main(["report", str(bad)]) == 2
    assert "task.json: not valid JSON" in capsys.readouterr().err
    doc = json.loads((demo_dir / "task.json").read_text())
    del doc["states"][0]["fig25"]
    bad.write_text(json.dumps(doc))
    assert main(["report", str(bad)]) == 2
    assert "fig25" in capsys.readouterr().err
    assert main(["report", str(tmp_path / "missing.json")]) == 2
    assert "file not found" in capsys.readouterr().err
    assert not (tmp_path / "report.html").exists()
    # frames.csv of another demonstration
    (tmp_path / "task.json").write_text((demo_dir / "task.json").read_text())
    (tmp_path / "frames.csv").write_text("frame,time_s,state\n0,0.0,A\n")
    assert main(["report", str(tmp_path / "task.json")]) == 2
    assert "not the frames of this task" in capsys.readouterr().err


def test_frames_csv_errors_name_file_and_line(tmp_path: Path) -> None:
    p = tmp_path / "frames.csv"
    p.write_text("frame,time_s\n0,0.0\n")
    with pytest.raises(InputFormatError, match=r"frames\.csv: no column 'state'"):
        read_frames_csv(p, units="mm")
    p.write_text("frame,time_s,state\n0,0.0,A\n1,zero,A\n")
    with pytest.raises(InputFormatError, match=r"line 3: column time_s: not a number"):
        read_frames_csv(p, units="mm")
    p.write_text("frame,time_s,state\n1,0.0,A\n")
    with pytest.raises(InputFormatError, match="in order"):
        read_frames_csv(p, units="mm")


def test_no_report_flag(tmp_path: Path) -> None:
    assert main(["demo", "--out", str(tmp_path), "--no-plot", "--no-report"]) == 0
    assert (tmp_path / "task.json").is_file()
    assert not (tmp_path / "report.html").exists()


def test_report_html_of_unknown_state_fails_clearly(demo_dir: Path) -> None:
    from apo.errors import ApoError
    from apo.report.html import FrameTrack

    doc = json.loads((demo_dir / "task.json").read_text())
    track = FrameTrack(times=np.zeros(2), state_ids=["A", "ZZ"])
    with pytest.raises(ApoError, match="'ZZ'"):
        report_data(doc, frames=track)
    assert "apo report" in report_html(report_data(doc))[:2000]
