"""Replay benchmark: the skill program vs playback of the observed poses, in MuJoCo.

For each scenario (a task model written by ``apo demo`` / ``apo analyze``), ``--trials``
seeded trials, each with a random start perturbation of up to 2 mm / 2 deg and an unknown
environment offset of up to 1 mm / 1 deg (sizes uniform, directions uniform), executed at
clearances 0.5, 0.2 and 0.1 mm, by the skill program and by ``--playback`` on the same
trials. Prints a table and writes ``benchmarks/results/replay.json``.

    python benchmarks/replay.py [--trials 60] [--jobs 2] [--scenarios demo real]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REAL = HERE.parents[1] / "shared" / "data" / "apo-peg-in-hole" / "peg_in_hole.pose.list"
CLEARANCES_MM = (0.5, 0.2, 0.1)


def _apo(*args: str) -> None:
    env = dict(os.environ, PYTHONPATH=str(HERE.parent / "src"))
    subprocess.run([sys.executable, "-m", "apo.cli", *args], check=True, env=env,
                   stdout=subprocess.DEVNULL)  # fmt: skip


def make_tasks(folder: Path, names: list[str]) -> dict[str, Path]:
    """Write the scenarios' task models (as a user would) and return their task.json paths."""
    out: dict[str, Path] = {}
    if "demo" in names:
        _apo("demo", "--out", str(folder / "demo"), "--no-plot", "--no-report", "--no-replay")
        out["demo"] = folder / "demo" / "task.json"
    if "real" in names and REAL.is_file():
        _apo("analyze", str(REAL), "--out", str(folder / "real"), "--no-plot", "--no-report")
        out["real"] = folder / "real" / "task.json"
    return out


def trial_sizes(i: int) -> tuple[tuple[float, float], tuple[float, float]]:
    """Start perturbation and environment offset sizes (m, rad) of trial ``i``."""
    rng = np.random.default_rng(10_000 + i)
    perturb = (rng.uniform(0, 2e-3), math.radians(rng.uniform(0, 2)))
    offset = (rng.uniform(0, 1e-3), math.radians(rng.uniform(0, 1)))
    return perturb, offset


def run_trial(job: tuple[str, str, float, bool, int]) -> dict[str, object]:
    """One replay; returns its figures."""
    from apo.cli.replay import replay_file

    scenario, task, clearance_mm, playback, i = job
    perturb, offset = trial_sizes(i)
    t = time.perf_counter()
    res, _ = replay_file(
        Path(task), perturb=perturb, environment_offset=offset,
        clearance=clearance_mm * 1e-3, seed=i, playback=playback,
    )  # fmt: skip
    return {
        "scenario": scenario,
        "clearance_mm": clearance_mm,
        "mode": "playback" if playback else "skills",
        "trial": i,
        "success": bool(res.success),
        "final_state": res.final_state,
        "states_reached": res.states_reached,
        "max_penetration_mm": res.max_penetration * 1e3,
        "max_force_n": res.max_force,
        "sim_s": res.sim_time,
        "wall_s": time.perf_counter() - t,
        "exec_wall_s": res.wall_time,
    }


def summarise(rows: list[dict[str, object]]) -> list[dict[str, object]]:
    """Success rate and penetration per scenario, clearance and mode."""
    groups: dict[tuple[object, object, object], list[dict[str, object]]] = {}
    for r in rows:
        groups.setdefault((r["scenario"], r["clearance_mm"], r["mode"]), []).append(r)
    out = []
    for (sc, cl, mode), rs in sorted(groups.items(), key=lambda kv: str(kv[0])):
        pen = np.array([float(r["max_penetration_mm"]) for r in rs])  # type: ignore[arg-type]
        sim = sum(float(r["sim_s"]) for r in rs)  # type: ignore[arg-type]
        wall = sum(float(r["exec_wall_s"]) for r in rs)  # type: ignore[arg-type]
        out.append({
            "scenario": sc, "clearance_mm": cl, "mode": mode, "trials": len(rs),
            "successes": sum(bool(r["success"]) for r in rs),
            "success_rate": sum(bool(r["success"]) for r in rs) / len(rs),
            "max_penetration_mm": float(pen.max()),
            "median_penetration_mm": float(np.median(pen)),
            "sim_s_per_wall_s": sim / wall if wall > 0 else float("nan"),
        })  # fmt: skip
    return out


def real_wall_time(tasks: dict[str, Path]) -> dict[str, float] | None:
    """Wall time of ``apo replay`` of the real demonstration's task model (whole command)."""
    if "real" not in tasks:
        return None
    env = dict(os.environ, PYTHONPATH=str(HERE.parent / "src"))
    t = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "apo.cli", "replay", str(tasks["real"]), "--json"],
        env=env, capture_output=True, text=True, check=False,
    )  # fmt: skip
    wall = time.perf_counter() - t
    data = json.loads(proc.stdout) if proc.stdout.strip() else {}
    return {"wall_s": wall, "success": bool(data.get("success")), "sim_s": data.get("sim_time")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--trials", type=int, default=60)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--scenarios", nargs="+", default=["demo", "real"])
    ap.add_argument("--clearances", nargs="+", type=float, default=list(CLEARANCES_MM))
    ap.add_argument("--modes", nargs="+", default=["skills", "playback"])
    ap.add_argument("--output", default=str(HERE / "results" / "replay.json"))
    ap.add_argument("--no-real-timing", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tasks = make_tasks(Path(tmp), args.scenarios)
        jobs = [
            (sc, str(p), cl, mode == "playback", i)
            for sc, p in tasks.items()
            for cl in args.clearances
            for mode in args.modes
            for i in range(args.trials)
        ]
        t0 = time.perf_counter()
        with ProcessPoolExecutor(max_workers=args.jobs) as pool:
            rows = list(pool.map(run_trial, jobs, chunksize=4))
        total = time.perf_counter() - t0
        real = None if args.no_real_timing else real_wall_time(tasks)
    table = summarise(rows)
    print(f"{'scenario':<9} {'clear mm':>8} {'mode':<9} {'success':>12} "
          f"{'max pen mm':>10} {'med pen mm':>10} {'sim s/wall s':>12}")  # fmt: skip
    for r in table:
        print(
            f"{r['scenario']!s:<9} {r['clearance_mm']:>8} {r['mode']!s:<9} "
            f"{r['successes']:>3}/{r['trials']:<3} {100 * float(r['success_rate']):5.1f}% "  # type: ignore[arg-type]
            f"{r['max_penetration_mm']:>10.4f} {r['median_penetration_mm']:>10.4f} "
            f"{r['sim_s_per_wall_s']:>12.2f}"
        )
    if real is not None:
        print(f"apo replay of the real demonstration: {real['wall_s']:.2f} s wall "
              f"(success {real['success']}, {real['sim_s']} s simulated)")  # fmt: skip
    print(f"{len(rows)} replays in {total:.0f} s wall with {args.jobs} processes")
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        "conditions": {
            "trials": args.trials, "perturb_max": [2.0, 2.0], "offset_max": [1.0, 1.0],
            "units": "mm, deg", "clearances_mm": args.clearances, "jobs": args.jobs,
            "cpu": os.cpu_count(),
        },
        "summary": table, "real_replay": real, "trials": rows,
    }, indent=1) + "\n")  # fmt: skip


if __name__ == "__main__":
    main()
