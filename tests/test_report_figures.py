"""``apo figures`` and ``apo report --motion``: files, contents, errors."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from apo.cli import main
from apo.report.figures import direction_text, subskill_text
from apo.report.html import read_report_data, unpack_array


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "--out", str(out), "--no-plot", "--no-report", "--seed", "5"]) == 0
    return out


def test_direction_and_subskill_text() -> None:
    assert direction_text([0, -2, 0]) == "\u2212y"
    assert direction_text([0, 0, 0]) == ""
    assert direction_text([1, 1, 0]) == "(0.71, 0.71, 0.00)"
    k = {"kind": "push_to", "space": "rotation", "type": "I", "direction": [1, 0, 0]}
    assert subskill_text(k) == "push-to R(I) about +x"


@pytest.mark.slow
def test_figures_for_every_state(demo_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "fig"
    assert main(["figures", str(demo_dir / "task.json"), "--out", str(out), "--dpi", "60"]) == 0
    task = json.loads((demo_dir / "task.json").read_text())
    names = ["dof_timeline", "state_graph"] + [f"state_{s['id']}" for s in task["states"]]
    for n in names:
        for ext in ("svg", "png"):
            assert (out / f"{n}.{ext}").stat().st_size > 1000, f"{n}.{ext}"
    svg = (out / "dof_timeline.svg").read_text()
    for s in task["states"]:
        assert re.search(rf">{s['id']}<", svg), s["id"]
    assert "time [s]" in svg and "translation DOF" in svg and "restraining" in svg
    graph = (out / "state_graph.svg").read_text()
    assert all(f"({k + 1})" in graph for k in range(len(task["transitions"])))
    if any(t["critical"] for t in task["transitions"]):
        assert "CRITICAL" in graph and "critical" in svg
    sing = next(s for s in task["states"] if s["singular"])
    pic = (out / f"state_{sing['id']}.svg").read_text()
    assert "[mm]" in pic and "singular element" in pic and "separating normal" in pic
    from PIL import Image

    px = np.asarray(Image.open(out / f"state_{sing['id']}.png").convert("L"))
    assert (px < 200).mean() > 0.02  # something is drawn


def test_figures_errors(demo_dir: Path, tmp_path: Path, capsys) -> None:
    task = str(demo_dir / "task.json")
    assert main(["figures", task, "--out", str(tmp_path), "--format", "gif"]) == 2
    assert "--format" in capsys.readouterr().err
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["figures", task, "--out", str(f)]) == 2
    assert "not a folder" in capsys.readouterr().err


def _motion_files(folder: Path, task: dict, *, with_csv: bool, with_replay: bool) -> Path:
    pose = task["states"][0]["pose"]
    prims = [
        {
            "index": i,
            "kind": k,
            "space": sp,
            "type": None,
            "to": s["id"],
            "target": {"state": s["id"], "elements": [], "pose": s["pose"]},
        }
        for i, (k, sp, s) in enumerate(
            [("approach", None, task["states"][0]), ("push_to", "translation", task["states"][1])]
        )
    ]
    doc = {
        "schema": "apo.motion/1",
        "units": "mm",
        "frame": "environment",
        "start_pose": pose,
        "primitives": prims,
    }
    p = folder / "motion.json"
    p.write_text(json.dumps(doc))
    rows = ["t,x,y,z,qw,qx,qy,qz,primitive"]
    for i in range(20):
        rows.append(f"{0.1 * i},{i},{50 - i},0,1,0,0,0,{0.0 if i < 10 else 1.0}")
    if with_csv:
        (folder / "motion.csv").write_text("\n".join(rows) + "\n")
    if with_replay:
        (folder / "replay.csv").write_text("\n".join(rows[:16]) + "\n")
        (folder / "replay.json").write_text(json.dumps({"verdict": "success"}))
    return p


@pytest.mark.parametrize("with_csv", [True, False])
def test_report_with_motion_tracks(demo_dir: Path, tmp_path: Path, with_csv: bool) -> None:
    task = json.loads((demo_dir / "task.json").read_text())
    mpath = _motion_files(tmp_path, task, with_csv=with_csv, with_replay=with_csv)
    out = tmp_path / "r.html"
    args = ["report", str(demo_dir / "task.json"), "--motion", str(mpath), "--out", str(out)]
    assert main(args) == 0
    data = read_report_data(out.read_text())
    tracks = data["tracks"]
    if with_csv:
        assert [t["kind"] for t in tracks] == ["planned", "executed"]
        planned = tracks[0]
        assert planned["labels"] == ["0 approach -> A", "1 push_to translation -> B"]
        pose = unpack_array(planned["pose"])
        np.testing.assert_allclose(pose[:, 0], np.arange(20), atol=1e-5)
        assert tracks[1]["note"] == "success"
        assert unpack_array(tracks[1]["pose"]).shape == (15, 7)
    else:
        assert [t["kind"] for t in tracks] == ["planned"]
        assert unpack_array(tracks[0]["pose"]).shape == (3, 7)


def test_report_rejects_bad_motion(demo_dir: Path, tmp_path: Path, capsys) -> None:
    m = tmp_path / "motion.json"
    m.write_text(json.dumps({"schema": "other"}))
    args = [
        "report",
        str(demo_dir / "task.json"),
        "--motion",
        str(m),
        "--out",
        str(tmp_path / "r.html"),
    ]
    assert main(args) == 2
    assert "apo.motion/1" in capsys.readouterr().err
    task = json.loads((demo_dir / "task.json").read_text())
    _motion_files(tmp_path, task, with_csv=True, with_replay=False)
    (tmp_path / "motion.csv").write_text("t,x,y\n0,1,2\n")
    assert main(args) == 2
    assert "missing column" in capsys.readouterr().err
    assert not (tmp_path / "r.html").exists()


def test_report_with_replay_output(demo_dir: Path, tmp_path: Path, capsys) -> None:
    rows = ["t,x,y,z,qw,qx,qy,qz"] + [f"{0.5 * i},{i},0,0,1,0,0,0" for i in range(10)]
    (tmp_path / "replay.csv").write_text("\n".join(rows) + "\n")
    verdict = {
        "verdict": "SUCCESS: final contact state H",
        "units": "mm",
        "primitives": [
            {"index": 0, "kind": "approach", "outcome": "reached", "t": [0.0, 2.0]},
            {"index": 1, "kind": "push_to", "outcome": "contact", "t": [2.0, 4.5]},
        ],
        "visits": [
            {"state": "A", "t": [0.0, 2.2]},
            {"state": None, "t": [2.3, 2.9]},
            {"state": "B", "t": [3.0, 4.5]},
        ],
    }
    (tmp_path / "replay.json").write_text(json.dumps(verdict))
    out = tmp_path / "r.html"
    task = str(demo_dir / "task.json")
    assert main(["report", task, "--replay", str(tmp_path), "--out", str(out)]) == 0
    tr = read_report_data(out.read_text())["tracks"]
    assert [t["kind"] for t in tr] == ["executed"]
    assert tr[0]["note"].startswith("SUCCESS")
    labels = [tr[0]["labels"][k] for k in unpack_array(tr[0]["label"])]
    assert labels[0] == "0 approach (reached)" and labels[-1] == "1 push_to (contact)"
    ids = [s["id"] for s in read_report_data(out.read_text())["task"]["states"]]
    per = unpack_array(tr[0]["state"])
    assert [ids[k] if k != 0xFFFF else None for k in per[[0, 5, 9]]] == ["A", None, "B"]
    (tmp_path / "replay.csv").unlink()
    assert main(["report", task, "--replay", str(tmp_path), "--out", str(out)]) == 2
    assert "replay.csv: file not found" in capsys.readouterr().err
