"""Perception on recordings of a second, independent renderer (issue 11's acceptance kind).

Renders ``N`` recordings with :mod:`apo.perception.raycast` (Open3D ray casting, a projector
beside the camera, disparity noise half spatially correlated, depth in whole millimetres,
flying pixels, random intrinsics, random shapes and motions from
:func:`apo.synthetic.random_variant`), then runs, as a user would and without initial poses,
``apo track FRAMES`` and ``apo analyze FRAMES`` on each. Per recording, as
``benchmarks/perception.py --variants``: median and p95 error of ``X_EG`` against the
truth's symmetric twin nearest over the sequence (flips charged), flips, re-initialisations,
lost frames, the wall and CPU seconds of ``apo track`` and whether ``apo analyze FRAMES``
gives the true task model. A command that fails (exit code, message) is a row too.

Run: ``.venv/bin/python benchmarks/perception_independent.py [--recordings N] [--seed S]``.
Prints a table and writes ``benchmarks/results/perception_independent.json``. Not a test.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from perception import _command, _tracked_poses, _twin_errors, same_task_model


def _failed(exc: subprocess.CalledProcessError) -> str:
    lines = (exc.stderr or b"").decode(errors="replace").strip().splitlines()
    return f"exit {exc.returncode}: {lines[-1] if lines else ''}"


def run_recording(seed: int) -> dict[str, Any]:
    """Render one recording; track it and analyse it; compare with the truth."""
    import trimesh

    from apo.io.taskfile import read_task
    from apo.perception.raycast import random_conditions, render_independent
    from apo.recognition import recognize
    from apo.symmetry import symmetries

    c = random_conditions(seed)
    row: dict[str, Any] = {"seed": seed, "label": c.label(), "conditions": c.__dict__}
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        r = render_independent(c, Path(tmp) / "frames")
        row["render_s"] = time.perf_counter() - t0
        g, e = Path(tmp) / "g.stl", Path(tmp) / "e.stl"
        trimesh.Trimesh(*r.grasped).export(g)
        trimesh.Trimesh(*r.environment).export(e)
        models = ["--grasped", str(g), "--environment", str(e), "--units", "m"]
        out = Path(tmp) / "poses.csv"
        try:
            row["track_s"], row["track_cpu_s"] = _command(
                ["track", str(r.frames), *models, "--out", str(out)]
            )
            row["load_average_1min"] = os.getloadavg()[0]
            _command(["analyze", str(r.frames), *models, "--out", str(Path(tmp) / "task")])
        except subprocess.CalledProcessError as exc:
            row["error"] = _failed(exc)
            return row
        X_EG, row["reinitialisations"] = _tracked_poses(out, r.demo.times)
        got = read_task(Path(tmp) / "task" / "task.json")
    d = r.demo
    pos, rot, row["flips"] = _twin_errors(
        X_EG, d.X_EG_true, symmetries(*r.grasped), symmetries(*r.environment)
    )
    truth = recognize(d.grasped, d.environment, d.times, d.X_EG_true)
    row["true_task_model"] = same_task_model(got, truth)
    row["states"] = [len(got.states), len(truth.states)]
    row["frames"] = len(d.times)
    row["lost"] = int((~np.isfinite(X_EG[:, 0, 0])).sum())
    for name, v in (("pos_mm", pos), ("rot_deg", rot)):
        row[f"median_{name}"] = float(np.median(v))
        row[f"p95_{name}"] = float(np.percentile(v, 95))
    return row


def _line(r: dict[str, Any]) -> str:
    if "error" in r:
        return f"{r['seed']:4d}  FAILED {r['error']}  {r['label']}"
    return (
        f"{r['seed']:4d} {r['frames']:4d} {r['median_pos_mm']:7.3f} {r['p95_pos_mm']:7.3f} "
        f"{r['median_rot_deg']:7.3f} {r['p95_rot_deg']:7.3f} {r['flips']:5d} "
        f"{r['reinitialisations']:6d} {r['lost']:4d} {r['track_s']:7.2f} {r['track_cpu_s']:6.2f} "
        f"{r['true_task_model']!s:>7} {r['load_average_1min']:5.2f}  {r['label']}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0, help="first recording seed")
    args = ap.parse_args()
    print(
        f"{'seed':>4} {'n':>4} {'med mm':>7} {'p95 mm':>7} {'med deg':>7} {'p95 deg':>7} "
        f"{'flips':>5} {'reinit':>6} {'lost':>4} {'track s':>7} {'cpu s':>6} {'task ok':>7} "
        f"{'load':>5}  conditions"
    )
    rows = []
    for seed in range(args.seed, args.seed + args.recordings):
        rows.append(run_recording(seed))
        print(_line(rows[-1]), flush=True)
    out = Path(__file__).parent / "results" / "perception_independent.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"rows": rows}, indent=2, default=str) + "\n")
    print(f"-> {out}")


if __name__ == "__main__":
    main()
