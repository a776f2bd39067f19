"""Replay benchmark: the skill program vs playback of the observed poses, in MuJoCo.

For each scenario (a task model written by ``apo demo`` / ``apo analyze``), ``--trials``
seeded trials, each with a random start perturbation of up to 2 mm / 2 deg and an unknown
environment offset of up to 1 mm / 1 deg (sizes uniform, directions uniform), executed at
clearances 0.5, 0.2 and 0.1 mm, by the skill program and by ``--playback`` on the same
trials. Prints a table and writes ``benchmarks/results/replay.json``.

    python benchmarks/replay.py [--trials 60] [--jobs 2] [--scenarios demo real ...]
                                [--clearances 0.5 0.2 0.1] [--modes skills playback]

Scenarios: ``demo`` (``apo demo``'s T-peg into U-slot), ``real`` (the first author's
``peg_in_hole.pose.list``), and the other scripted demonstrations of ``apo.synthetic``
(square peg into a square hole, block pushed into a corner, block tipping), each analysed
from noisy poses as a user would. Success is judged up to the models' symmetries.
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
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
REAL = Path(
    os.environ.get(
        "APO_REAL_DEMO",
        HERE.parents[1] / "shared" / "data" / "apo-peg-in-hole" / "peg_in_hole.pose.list",
    )
)
"""The real demonstration (``../shared`` beside the checkout; ``APO_REAL_DEMO`` overrides)."""
CLEARANCES_MM = (0.5, 0.2, 0.1)


def _apo(*args: str) -> None:
    env = dict(os.environ, PYTHONPATH=str(HERE.parent / "src"))
    subprocess.run([sys.executable, "-m", "apo.cli", *args], check=True, env=env,
                   stdout=subprocess.DEVNULL)  # fmt: skip


SYNTHETIC = ("square_peg_in_hole", "block_on_table_to_corner", "block_tipping")
"""The other scripted demonstrations of ``apo.synthetic`` (the demo is ``peg_in_hole_2d``)."""
SCENARIOS = ("demo", "real", *SYNTHETIC)


def _write_stl(poly: object, path: Path) -> None:
    """Write a polyhedron (metres) as an STL file in millimetres."""
    import trimesh

    faces = np.concatenate(poly.face_triangles)  # type: ignore[attr-defined]
    trimesh.Trimesh(poly.vertices * 1e3, faces, process=False).export(path)  # type: ignore[attr-defined]


def _synthetic_task(folder: Path, name: str) -> Path:
    """Analyse a scripted demonstration as a user would: STL models + noisy pose CSV."""
    from apo.io.poses import write_pose_csv
    from apo.synthetic import add_noise, all_demos

    demo = all_demos()[name]
    noisy = add_noise(demo, sigma_mm=0.5, sigma_deg=0.5, seed=0)
    src = folder / f"{name}-input"
    src.mkdir(parents=True, exist_ok=True)
    _write_stl(demo.grasped, src / "grasped.stl")
    _write_stl(demo.environment, src / "environment.stl")
    write_pose_csv(src / "poses.csv", noisy.times, noisy.X_EG, units="mm")
    _apo("analyze", str(src / "poses.csv"), "--grasped", str(src / "grasped.stl"),
         "--environment", str(src / "environment.stl"), "--units", "mm",
         "--out", str(folder / name), "--no-plot", "--no-report")  # fmt: skip
    return folder / name / "task.json"


def make_tasks(folder: Path, names: list[str]) -> dict[str, Path]:
    """Write the scenarios' task models (as a user would) and return their task.json paths.

    ``demo``: ``apo demo`` (the T-peg into the U-slot, noise 0.5 mm / 0.5 deg); ``real``:
    ``apo analyze`` of the first author's ``peg_in_hole.pose.list`` (skipped when
    ``../shared`` is absent); the others: the scripted demonstration of ``apo.synthetic``
    with the same noise, written as STL models and a pose CSV and analysed by ``apo analyze``.
    """
    out: dict[str, Path] = {}
    if "demo" in names:
        _apo("demo", "--out", str(folder / "demo"), "--no-plot", "--no-report", "--no-replay")
        out["demo"] = folder / "demo" / "task.json"
    if "real" in names and not REAL.is_file():
        print(f"scenario real skipped: {REAL} not found (set APO_REAL_DEMO)", file=sys.stderr)
    if "real" in names and REAL.is_file():
        _apo("analyze", str(REAL), "--out", str(folder / "real"), "--no-plot", "--no-report")
        out["real"] = folder / "real" / "task.json"
    for name in SYNTHETIC:
        if name in names:
            out[name] = _synthetic_task(folder, name)
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
    failed = [r for r in res.primitives if not r.ok]
    return {
        "scenario": scenario,
        "clearance_mm": clearance_mm,
        "mode": "playback" if playback else "skills",
        "trial": i,
        "perturb": [perturb[0] * 1e3, math.degrees(perturb[1])],
        "offset": [offset[0] * 1e3, math.degrees(offset[1])],
        "success": bool(res.success),
        "by_symmetry": bool(res.by_symmetry),
        "final_state": res.final_state,
        "states_reached": res.states_reached,
        "failed_primitive": None
        if not failed
        else f"{failed[0].index} {failed[0].kind} {failed[0].outcome}",
        "max_penetration_mm": res.max_penetration * 1e3,
        "max_force_n": res.max_force,
        "sim_s": res.sim_time,
        "wall_s": time.perf_counter() - t,
        "exec_wall_s": res.wall_time,
    }


def _group(rows: list[dict[str, Any]]) -> dict[str, Any]:
    pen = np.array([float(r["max_penetration_mm"]) for r in rows])
    sim = sum(float(r["sim_s"]) for r in rows)
    wall = sum(float(r["exec_wall_s"]) for r in rows)
    ok = sum(bool(r["success"]) for r in rows)
    return {
        "trials": len(rows), "successes": ok, "success_rate": ok / len(rows),
        "failed_trials": [r["trial"] for r in rows if not r["success"]],
        "by_symmetry": sum(bool(r["by_symmetry"]) for r in rows),
        "max_penetration_mm": float(pen.max()), "median_penetration_mm": float(np.median(pen)),
        "trials_over_0.05mm": int((pen >= 0.05).sum()),
        "sim_s_per_wall_s": sim / wall if wall > 0 else float("nan"),
        "mean_sim_s": sim / len(rows),
    }  # fmt: skip


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per scenario and clearance: each mode's success, penetration and speed, same trials."""
    groups: dict[tuple[str, float], dict[str, list[dict[str, Any]]]] = {}
    for r in rows:
        groups.setdefault((r["scenario"], r["clearance_mm"]), {}).setdefault(r["mode"], [])
        groups[(r["scenario"], r["clearance_mm"])][r["mode"]].append(r)
    order = {s: k for k, s in enumerate(SCENARIOS)}
    out = []
    for (sc, cl), modes in sorted(
        groups.items(), key=lambda kv: (order.get(kv[0][0], 99), -kv[0][1])
    ):
        out.append({"scenario": sc, "clearance_mm": cl,
                    **{m: _group(rs) for m, rs in sorted(modes.items())}})  # fmt: skip
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


def _cell(g: dict[str, Any] | None) -> str:
    if g is None:
        return f"{'-':>22}"
    rate = f"{g['successes']:>3}/{g['trials']:<3} {100 * g['success_rate']:5.1f}%"
    return f"{rate} {g['max_penetration_mm']:7.4f}"


def print_table(table: list[dict[str, Any]]) -> None:
    """One line per scenario and clearance: skills and playback side by side."""
    print(f"{'scenario':<25} {'clear':>5}  {'skills: success  max pen mm':>28}  "
          f"{'playback: success  max pen':>27}  {'sim s/wall s':>12}")  # fmt: skip
    for r in table:
        speed = r.get("skills", r.get("playback", {})).get("sim_s_per_wall_s", float("nan"))
        print(f"{r['scenario']:<25} {r['clearance_mm']:>5}  {_cell(r.get('skills')):>28}  "
              f"{_cell(r.get('playback')):>27}  {speed:>12.2f}")  # fmt: skip


def _jobs(
    tasks: dict[str, Path], args: argparse.Namespace
) -> list[tuple[str, str, float, bool, int]]:
    """Every replay, in the order of the clearances given; trial by trial within one."""
    return [
        (sc, str(tasks[sc]), cl, mode == "playback", i)
        for cl in args.clearances
        for i in range(args.trials)
        for sc in args.scenarios
        if sc in tasks
        for mode in args.modes
    ]


def _run_all(jobs: list[Any], n_jobs: int, log: Path, done: list[dict[str, Any]]) -> None:
    """Run the replays not in ``done``; append each row to ``log`` (JSON lines) as it ends."""
    have = {(r["scenario"], r["clearance_mm"], r["mode"] == "playback", r["trial"]) for r in done}
    todo = [j for j in jobs if (j[0], j[2], j[3], j[4]) not in have]
    with ProcessPoolExecutor(max_workers=n_jobs) as pool, log.open("a") as fh:
        futures = [pool.submit(run_trial, j) for j in todo]
        for f in as_completed(futures):
            row = f.result()
            done.append(row)
            fh.write(json.dumps(row) + "\n")
            fh.flush()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--trials", type=int, default=60)
    ap.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    ap.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=SCENARIOS)
    ap.add_argument("--clearances", nargs="+", type=float, default=[0.2, 0.5, 0.1],
                    help="mm, run in this order (default 0.2 0.5 0.1)")  # fmt: skip
    ap.add_argument("--modes", nargs="+", default=["skills", "playback"])
    ap.add_argument("--output", default=str(HERE / "results" / "replay.json"))
    ap.add_argument(
        "--resume",
        action="store_true",
        help="keep the rows of OUTPUT's .jsonl log, run only the missing ones",
    )
    ap.add_argument(
        "--report-only",
        action="store_true",
        help="summarise OUTPUT's .jsonl log (an interrupted run) without running",
    )
    ap.add_argument("--no-real-timing", action="store_true")
    args = ap.parse_args()
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    log = out.with_suffix(".jsonl")
    rows: list[dict[str, Any]] = []
    if (args.resume or args.report_only) and log.is_file():
        rows = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    elif log.exists():
        log.unlink()
    load0 = os.getloadavg()
    real, total = None, 0.0
    with tempfile.TemporaryDirectory() as tmp:
        if not args.report_only:
            tasks = make_tasks(Path(tmp), args.scenarios)
            real = None if args.no_real_timing else real_wall_time(tasks)
            t0 = time.perf_counter()
            _run_all(_jobs(tasks, args), args.jobs, log, rows)
            total = time.perf_counter() - t0
    table = summarise(rows)
    print_table(table)
    if real is not None:
        print(f"apo replay of the real demonstration: {real['wall_s']:.2f} s wall "
              f"(success {real['success']}, {real['sim_s']} s simulated)")  # fmt: skip
    load1 = os.getloadavg()
    print(f"{len(rows)} replays, {total:.0f} s wall with {args.jobs} processes; "
          f"load average {load0[0]:.1f} before, {load1[0]:.1f} after")  # fmt: skip
    out.write_text(json.dumps({
        "conditions": {
            "trials": args.trials, "perturb_max": [2.0, 2.0], "offset_max": [1.0, 1.0],
            "units": "mm, deg", "clearances_mm": args.clearances, "jobs": args.jobs,
            "cpu": os.cpu_count(), "load_before": load0[0], "load_after": load1[0],
            "total_wall_s": total,
        },
        "summary": table, "real_replay": real, "trials": rows,
    }, indent=1) + "\n")  # fmt: skip


if __name__ == "__main__":
    main()
