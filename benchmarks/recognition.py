"""Benchmark of the recognition pipeline: speed and accuracy.

Whole process (what a user waits for): ``apo analyze`` in a fresh interpreter, median of
``--runs`` (at least 5), wall and CPU time and peak memory, on the first author's 41 frames
with every default output (also with ``--plot``, and with an empty model cache) and on
those frames repeated to 2,993 and 29,930 (``--json``), beside the first author's C++
figures as quoted in the issue (not rerun here: the C++ is not available on this machine),
with the load average before and after.

In-process speed: frames per second of the recognition alone on the 41 frames, on them
repeated to 2,993, and on a 3,000-frame synthetic demonstration.

Accuracy: for each noise kind (white, drift, 2 % outliers, 10 % dropped frames) and level
sigma (mm and deg per axis), over ``--seeds`` seeds, the share of runs recognised exactly
(the state sequence with every state's Fig. 25 numbers, the sub-skills and the critical
marks) on the four scripted demonstrations and on a new random variant per seed
(``apo.synthetic.random_variant``: speed, frame rate 10-60 frames/s, approach angle,
margin, placement).

Run ``.venv/bin/python benchmarks/recognition.py [--seeds 50] [--quick] [--sigmas 0,1,2]
[--kinds white,drift] [--skip speed,whole,accuracy]``; prints tables and writes
``benchmarks/results/recognition.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "apo-peg-in-hole"
SIGMAS = (0.0, 0.5, 1.0, 2.0, 3.0, 4.0)


def _best_of(fn: Any, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench_real(repeat: int) -> dict[str, Any]:
    from apo.io.meshes import load_polyhedron
    from apo.io.poses import load_demonstration
    from apo.recognition import recognize_frames

    path = DATA / "peg_in_hole.pose.list"
    dem = load_demonstration(path)
    G = load_polyhedron(DATA / "peg.step")
    E = load_polyhedron(DATA / "hole.step")
    out: dict[str, Any] = {}
    sec = _best_of(lambda: recognize_frames(G, E, dem.times, dem.X_EG), repeat)
    out["real_41"] = {"frames": len(dem.X_EG), "seconds": sec, "fps": len(dem.X_EG) / sec}
    reps = int(np.ceil(2993 / len(dem.X_EG)))
    X = np.concatenate([dem.X_EG] * reps)[:2993]
    t = np.arange(len(X), dtype=float)
    rec = None

    def run() -> None:
        nonlocal rec
        rec = recognize_frames(G, E, t, X)

    sec = _best_of(run, repeat)
    out["real_repeated_2993"] = {
        "frames": len(X),
        "seconds": sec,
        "fps": len(X) / sec,
        "timings": rec.timings if rec is not None else {},
    }
    return out


#: The first author's C++ (pose correction plus task analysis), wall time as quoted in the
#: issue (built on this machine kind, medians of 7); not available here to rerun.
CPP_SECONDS = {"real_41": 0.093, "repeated_2993": 1.05, "repeated_29930": 10.6}


def _repeated_list(folder: Path, n: int) -> Path:
    """The real pose list repeated to ``n`` scenes, beside copies of the models."""
    import shutil

    lines = (DATA / "peg_in_hole.pose.list").read_text().split("\n")
    scenes = "\n".join(lines[5:]).strip("\n").split("\n\n")
    body = "\n\n".join(scenes[i % len(scenes)] for i in range(n))
    for m in ("peg.step", "hole.step"):
        shutil.copy(DATA / m, folder / m)
    out = folder / f"repeated{n}.pose.list"
    out.write_text("\n".join(lines[:4]) + f"\nNo of Scenes: {n}\n" + body + "\n")
    return out


def _env() -> dict[str, str]:
    """The environment of a user's run: bytecode cached (as after ``pip install``).

    ``PYTHONDONTWRITEBYTECODE`` (set in some development shells) would make every run
    compile apo's sources again (0.2 s); the untimed first run of each case writes them.
    """
    return {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def _timed_run(cmd: list[str], env: dict[str, str] | None = None) -> tuple[float, float, float]:
    """Wall time (s), CPU time (user + system, s) and peak resident memory (MB) of a process."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        ["/usr/bin/time", "-f", "%U %S %M", *cmd],
        check=True, capture_output=True, text=True, env=env or _env(),
    )  # fmt: skip
    wall = time.perf_counter() - t0
    user, system, kb = (float(v) for v in proc.stderr.strip().splitlines()[-1].split())
    return wall, user + system, kb / 1024.0


def _jittered_list(folder: Path, n: int, seed: int = 0) -> Path:
    """The real frames repeated to ``n``, each repeat moved by 1e-6 m and turned by 1e-6 rad.

    No pose repeats another bit for bit (the contact search cannot reuse a result), and the
    motion is far below the contact threshold: the same demonstration, many times.
    """
    from apo.io.poses import read_pose_list, write_pose_list
    from apo.spatial import matrix_from_axis_angle

    dem = read_pose_list(DATA / "peg_in_hole.pose.list")
    rng = np.random.default_rng(seed)
    X = np.concatenate([dem.X_EG] * int(np.ceil(n / len(dem.X_EG))))[:n].copy()
    for i in range(len(dem.X_EG), n):
        axis = rng.normal(size=3)
        X[i, :3, :3] = matrix_from_axis_angle(axis, 1e-6) @ X[i, :3, :3]
        X[i, :3, 3] += 1e-6 * rng.normal(size=3) / np.sqrt(3)
    models = (folder / "peg.step", folder / "hole.step")
    return write_pose_list(folder / f"jittered{n}.pose.list", X, units="mm", models=models)


def _synthetic_csv(folder: Path, n: int) -> tuple[Path, list[str]]:
    """A scripted peg-in-hole of ``n`` frames with 0.5 mm / 0.5 deg noise (every pose distinct)."""
    from apo import synthetic
    from apo.cli.demo import _write_stl
    from apo.io.poses import write_pose_csv

    demo = synthetic.add_noise(
        synthetic.peg_in_hole_2d(n_frames=n), sigma_mm=0.5, sigma_deg=0.5, seed=0
    )
    g, e = folder / "syn_g.stl", folder / "syn_e.stl"
    _write_stl(demo.grasped, g, 1000.0)
    _write_stl(demo.environment, e, 1000.0)
    path = write_pose_csv(folder / f"synthetic{n}.csv", demo.times, demo.X_EG, units="mm")
    return path, ["--grasped", str(g), "--environment", str(e)]


def _whole_cases(folder: Path) -> dict[str, tuple[Path, list[str], int, str]]:
    """Label: (input, extra arguments, frames, the C++ figure it compares with)."""
    real = DATA / "peg_in_hole.pose.list"
    cases = {
        "real_41": (real, [], 41, "real_41"),
        "real_41_plot": (real, ["--plot"], 41, "real_41"),
        "real_41_empty_cache": (real, [], 41, "real_41"),
    }
    for n, cpp in ((2993, "repeated_2993"), (29930, "repeated_29930")):
        cases[f"repeated_{n}"] = (_repeated_list(folder, n), ["--json"], n, cpp)
        cases[f"jittered_{n}"] = (_jittered_list(folder, n), ["--json"], n, cpp)
    for n, cpp in ((3000, "repeated_2993"), (30000, "repeated_29930")):
        path, models = _synthetic_csv(folder, n)
        cases[f"synthetic_{n}"] = (path, ["--json", *models], n, cpp)
    return cases


def bench_whole_process(runs: int, only: str = "") -> dict[str, Any]:
    """`apo analyze` as a user runs it: a fresh interpreter each time, median of ``runs``.

    The real 41 frames with every default output (task.json, frames.csv, report.html), also
    with ``--plot`` (dof.png, opt-in) and with an empty model cache (the STEP files read and
    tessellated); with ``--json`` (the issue's conditions): the frames repeated to 2,993 and
    29,930 as the issue's C++ figures were measured (exact repeats: each distinct pose is
    searched once), the same jittered so that no pose repeats, and a scripted demonstration
    of 3,000 and 30,000 noisy (all distinct) frames. Model cache warm (filled by an untimed
    run) unless said. The load average is recorded before and after: on a shared machine
    the wall time grows with it, the CPU time much less. ``only``: comma list of labels.
    """
    runs = max(runs, 5)
    cmd = [sys.executable, "-m", "apo.cli", "analyze"]
    out: dict[str, Any] = {"load_average_before": list(os.getloadavg()), "runs": runs}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for label, (path, extra, n, cpp) in _whole_cases(folder).items():
            if only and label not in only.split(","):
                continue
            args = [*cmd, str(path), "--out", str(folder / label), *extra]
            subprocess.run(args, check=True, capture_output=True, env=_env())  # warm-up
            samples = []
            for i in range(runs):
                env = _env()
                if label.endswith("empty_cache"):
                    env["APO_CACHE_DIR"] = str(folder / f"cache-{i}")
                samples.append(_timed_run(args, env))
            walls, cpus, mems = (list(v) for v in zip(*samples, strict=True))
            med = float(np.median(walls))
            out[label] = {
                "frames": n, "args": extra[:1], "median_s": med, "runs_s": walls,
                "cpu_median_s": float(np.median(cpus)), "fps": n / med,
                "peak_mb": max(mems), "cpp_s": CPP_SECONDS[cpp],
                "ratio_to_cpp": med / CPP_SECONDS[cpp],
            }  # fmt: skip
            print(
                f"  whole process {label:<20} median {med:6.3f} s (CPU {np.median(cpus):6.3f} s)"
                f"  {n / med:7.0f} frames/s  peak {max(mems):4.0f} MB  "
                f"C++ (quoted) {CPP_SECONDS[cpp]} s",
                flush=True,
            )
    out["load_average_after"] = list(os.getloadavg())
    out["memory_growth"] = _memory_growth(out)
    for kind, g in out["memory_growth"].items():
        print(f"  peak memory growth, {kind}: {g['bytes_per_frame']:.0f} bytes/frame "
              f"({g['from']} -> {g['to']})")  # fmt: skip
    return {"whole_process": out}


#: Peak memory growth per frame from about 3,000 to about 30,000 frames that issue 9's
#: "memory bounded" asks for at most (docs/recognition.md): the per-frame arrays only.
MEMORY_GROWTH_TARGET = 400


def _memory_growth(rows: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Peak memory added per frame from about 3,000 to about 30,000 frames, per input kind.

    What "memory bounded" is measured by (``docs/recognition.md``): the per-frame outputs
    and arrays cost a fixed number of bytes per frame; everything else does not grow.
    """
    out: dict[str, dict[str, Any]] = {}
    for kind, small, large in (
        ("repeated", "repeated_2993", "repeated_29930"),
        ("jittered", "jittered_2993", "jittered_29930"),
        ("synthetic", "synthetic_3000", "synthetic_30000"),
    ):
        a, b = rows.get(small), rows.get(large)
        if isinstance(a, dict) and isinstance(b, dict):
            per = (b["peak_mb"] - a["peak_mb"]) * 2**20 / (b["frames"] - a["frames"])
            target = MEMORY_GROWTH_TARGET
            out[kind] = {"from": small, "to": large, "bytes_per_frame": per,
                         "target": target, "met": per <= target}  # fmt: skip
    return out


def _synthetic(n_frames: int | None = None) -> Any:
    from apo import synthetic

    return (
        synthetic.peg_in_hole_2d()
        if n_frames is None
        else synthetic.peg_in_hole_2d(n_frames=n_frames)
    )


def bench_synthetic_speed(repeat: int) -> dict[str, Any]:
    from apo import synthetic
    from apo.recognition import recognize_frames

    demo = _synthetic(3000)
    noisy = synthetic.add_noise(demo, sigma_mm=1.0, sigma_deg=1.0, seed=0)
    rec = None

    def run() -> None:
        nonlocal rec
        rec = recognize_frames(demo.grasped, demo.environment, noisy.times, noisy.X_EG)

    sec = _best_of(run, repeat)
    n = len(noisy.X_EG)
    return {
        "synthetic_3000": {
            "frames": n,
            "seconds": sec,
            "fps": n / sec,
            "timings": rec.timings if rec is not None else {},
        }
    }


NOISE_KINDS = ("white", "drift", "outliers", "dropped")


def _noisy(demo: Any, kind: str, sigma: float, seed: int) -> Any:
    """The demonstration with noise of one kind at level ``sigma`` (mm and deg per axis)."""
    from apo import synthetic

    if kind == "white":
        return synthetic.add_noise(demo, sigma_mm=sigma, sigma_deg=sigma, seed=seed)
    if kind == "drift":  # half white, plus a slow drift of the full size
        return synthetic.add_noise(
            demo, sigma_mm=sigma / 2, sigma_deg=sigma / 2, drift_mm=sigma, drift_deg=sigma,
            seed=seed,
        )  # fmt: skip
    if kind == "outliers":
        return synthetic.add_noise(
            demo, sigma_mm=sigma, sigma_deg=sigma, outlier_rate=0.02, seed=seed
        )
    if kind == "dropped":
        return synthetic.add_noise(demo, sigma_mm=sigma, sigma_deg=sigma, drop_rate=0.1, seed=seed)
    raise ValueError(kind)


def exact_result(demo: Any, task: Any) -> bool:
    """True if the states (with their Fig. 25 numbers), sub-skills and critical marks match."""
    want = [demo.true_states[int(demo.labels[a])].fig25 for _s, a, _b in demo.segments()]
    truth = [k for et in demo.expected_subskills for k in et.subskills]
    return (
        [tuple(s.fig25) for s in task.states] == [tuple(w) for w in want]
        and task.subskill_sequence() == truth
        and [t.critical for t in task.transitions]
        == [et.critical for et in demo.expected_subskills]
    )


def _demos(seed: int) -> dict[str, Any]:
    """The four scripted demonstrations, and one random variant (a new one per seed).

    The random variant (``apo.synthetic.random_variant``) is one of the four kinds or a
    random prism tipped over, with random sizes and proportions, frame count, frame rate
    (10-60 frames/s), approach angle, margin and placement.
    """
    from apo import synthetic

    out = dict(synthetic.all_demos())
    out["random variant"] = synthetic.random_variant(10_000 + seed)
    return out


#: Frame-rate bands (frames/s) of the random variants, reported separately.
FPS_BANDS = ((10.0, 20.0), (20.0, 40.0), (40.0, 60.0))


def _fps_band(demo: Any) -> str:
    fps = float(demo.meta["fps"])
    for lo, hi in FPS_BANDS:
        if lo <= fps < hi or fps == hi == FPS_BANDS[-1][1]:
            return f"{lo:g}-{hi:g}"
    return "other"


def _accuracy_seed(job: tuple[str, float, int]) -> list[tuple[str, str, str, bool, float]]:
    """Recognise every demonstration of one seed: ``(name, variant, fps band, exact, s)``."""
    from apo.recognition import recognize_frames

    kind, sigma, seed = job
    out = []
    for name, demo in _demos(seed).items():
        noisy = _noisy(demo, kind, sigma, seed)
        t0 = time.perf_counter()
        rec = recognize_frames(noisy.grasped, noisy.environment, noisy.times, noisy.X_EG)
        secs = time.perf_counter() - t0
        variant = demo.meta["variant"]["name"] if name == "random variant" else ""
        out.append((name, variant, _fps_band(demo), exact_result(noisy, rec.task), secs))
    return out


def _accuracy_row(kind: str, sigma: float, seeds: int, jobs: int = 1) -> dict[str, Any]:
    """Runs of one noise kind and level over ``seeds`` seeds: shares recognised exactly.

    ``jobs`` > 1 spreads the seeds over that many processes (same runs, same results).
    """
    ok: dict[str, int] = {}
    runs: dict[str, int] = {}
    shapes: dict[str, list[int]] = {}
    bands: dict[str, list[int]] = {}
    secs: list[float] = []
    work = [(kind, sigma, seed) for seed in range(seeds)]
    if jobs > 1:
        import multiprocessing

        with multiprocessing.Pool(jobs) as pool:
            results = pool.map(_accuracy_seed, work)
    else:
        results = [_accuracy_seed(job) for job in work]
    for rows in results:
        for name, variant, band, good, s in rows:
            secs.append(s)
            ok[name] = ok.get(name, 0) + good
            runs[name] = runs.get(name, 0) + 1
            if name == "random variant":
                shapes.setdefault(variant, [0, 0])[0] += good
                shapes[variant][1] += 1
                bands.setdefault(band, [0, 0])[0] += good
                bands[band][1] += 1
    total = sum(ok.values()) / sum(runs.values())
    return {
        "kind": kind, "sigma": sigma, "runs_per_demo": seeds, "runs": sum(runs.values()),
        "exact": {k: v / runs[k] for k, v in ok.items()}, "exact_all": total,
        "random_by_kind": {k: {"exact": a / n, "runs": n} for k, (a, n) in sorted(shapes.items())},
        "random_by_fps": {k: {"exact": a / n, "runs": n} for k, (a, n) in sorted(bands.items())},
        "seconds_per_run": float(np.mean(secs)), "processes": jobs,
    }  # fmt: skip


def bench_accuracy(
    seeds: int,
    sigmas: tuple[float, ...],
    kinds: tuple[str, ...],
    levels: dict[str, Any],
    jobs: int = 1,
) -> dict[str, Any]:
    """Share of runs recognised exactly, per demonstration, noise kind and level."""
    rows = []
    for kind in kinds:
        for sigma in levels.get(kind, sigmas):
            row = _accuracy_row(kind, sigma, seeds, jobs)
            rows.append(row)
            print(
                f"  {kind:<9} sigma {sigma:>3}: exact {row['exact_all']:6.1%}  "
                + "  ".join(f"{k[:10]} {v:.0%}" for k, v in row["exact"].items()),
                flush=True,
            )
    return {"accuracy": rows}


def _section(res: dict[str, Any], name: str, fn: Any) -> None:
    """Run one part of the benchmark; a missing module skips it with a note."""
    try:
        res.update(fn())
    except (ImportError, subprocess.CalledProcessError) as exc:
        print(f"({name}: skipped: {exc})")
        res.setdefault("skipped", {})[name] = str(exc)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="5 seeds, 1 repeat")
    ap.add_argument("--sigmas", default=",".join(str(v) for v in SIGMAS))
    ap.add_argument("--kinds", default=",".join(NOISE_KINDS))
    ap.add_argument(
        "--levels",
        default="",
        help="per-kind levels overriding --sigmas, e.g. 'drift=1,2;outliers=1'",
    )
    ap.add_argument("--runs", type=int, default=5, help="fresh-process runs (median)")
    ap.add_argument("--only", default="", help="whole process: comma list of case labels")
    ap.add_argument("--skip", default="", help="comma list of: speed,whole,accuracy")
    ap.add_argument("--jobs", type=int, default=1, help="accuracy: processes (seeds spread)")
    args = ap.parse_args()
    seeds, repeat = (5, 1) if args.quick else (args.seeds, args.repeat)
    sigmas = tuple(float(v) for v in args.sigmas.split(","))
    kinds = tuple(args.kinds.split(","))
    skip = set(args.skip.split(","))
    res: dict[str, Any] = {
        "machine": {
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
        },
        "reference_cpp_fps": 1270,
        "target_fps": 2500,
    }
    if not (DATA / "peg_in_hole.pose.list").exists():
        print(f"(real data not found at {DATA}: skipped)")
    elif "whole" not in skip:
        _section(res, "whole process", lambda: bench_whole_process(args.runs, args.only))
    if (DATA / "peg_in_hole.pose.list").exists() and "speed" not in skip:
        _section(res, "real data", lambda: bench_real(repeat))
    if "speed" not in skip:
        _section(res, "synthetic speed", lambda: bench_synthetic_speed(repeat))
    if "accuracy" not in skip:
        print(f"accuracy over {seeds} seeds per noise level (exact states, Fig. 25, sub-skills):")
        levels = {
            k: tuple(float(v) for v in vals.split(","))
            for k, vals in (item.split("=") for item in args.levels.split(";") if item)
        }
        _section(res, "accuracy", lambda: bench_accuracy(seeds, sigmas, kinds, levels, args.jobs))

    print()
    print("speed (whole recognition, best of", repeat, "runs)")
    print(f"  {'input':<22} {'frames':>7} {'seconds':>9} {'frames/s':>9}")
    for k in ("real_41", "real_repeated_2993", "synthetic_3000"):
        if k in res:
            r = res[k]
            print(f"  {k:<22} {r['frames']:>7} {r['seconds']:>9.3f} {r['fps']:>9.0f}")
    whole = res.get("whole_process", {})
    if whole:
        print()
        print(f"whole process (`apo analyze`, fresh interpreter, median of {whole['runs']} runs; "
              f"load average {whole['load_average_before'][0]:.1f} -> "
              f"{whole['load_average_after'][0]:.1f})")  # fmt: skip
        print(f"  {'input':<22} {'wall s':>7} {'CPU s':>7} {'frames/s':>9} {'MB':>5} {'C++ s':>6}")
        for k, r in whole.items():
            if isinstance(r, dict) and "median_s" in r:
                print(
                    f"  {k:<22} {r['median_s']:>7.3f} {r['cpu_median_s']:>7.3f} {r['fps']:>9.0f}"
                    f" {r['peak_mb']:>5.0f} {r['cpp_s']:>6}"
                )
        for kind, g in whole.get("memory_growth", {}).items():
            print(f"  peak memory growth {kind:<10} {g['bytes_per_frame']:>7.0f} bytes/frame "
                  f"({g['from']} -> {g['to']}; target at most {g['target']})")  # fmt: skip
    print()
    print(
        f"  {'noise':<9} {'sigma mm/deg':>12} {'runs':>5} {'exact (all demos)':>18}  random by fps"
    )
    for r in res.get("accuracy", []):
        fps = "  ".join(f"{k} {v['exact']:.0%}" for k, v in r.get("random_by_fps", {}).items())
        print(
            f"  {r['kind']:<9} {r['sigma']:>12} {r.get('runs', 0):>5} {r['exact_all']:>18.1%}  "
            + fps
        )
    out = ROOT / "benchmarks" / "results" / "recognition.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.exists():  # keep the sections of an earlier run that this one skipped
        with contextlib.suppress(ValueError):
            res = {**json.loads(out.read_text(encoding="utf-8")), **res}
    out.write_text(json.dumps(res, indent=2) + "\n", encoding="utf-8")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
