"""``apo replay task.json``: plan the task's motion and execute it in MuJoCo.

Argument parsing and output only; the work is :func:`apo.sim.replay.replay` (``docs/sim.md``).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from apo.errors import InputFormatError

DEFAULT_CLEARANCE_MM = 0.2


def register(subparsers: Any) -> None:
    """Add the ``replay`` sub-command."""
    p = subparsers.add_parser(
        "replay",
        help="execute a task.json in MuJoCo with a compliant hand and judge the result",
        description=(
            "Plan the skill program of a task model (apo plan) and execute it in MuJoCo with a "
            "compliant hand (or, with --playback, follow the observed poses by position "
            "control). Prints the contact states reached and the verdict: success when the "
            "final contact state equals the task's final state (docs/sim.md)."
        ),
    )
    p.add_argument("task", metavar="TASK_JSON", help="task.json written by apo analyze/demo")
    p.add_argument(
        "--perturb",
        metavar="MM,DEG",
        default="0,0",
        help="move the start pose of the grasped object by a random rigid motion of this size",
    )
    p.add_argument(
        "--environment-offset",
        metavar="MM,DEG",
        default="0,0",
        help="move the environment by a random rigid motion of this size that the plan does "
        "not know",
    )
    p.add_argument(
        "--clearance",
        type=float,
        metavar="MM",
        default=DEFAULT_CLEARANCE_MM,
        help=f"gap per side of the simulated parts, mm (default {DEFAULT_CLEARANCE_MM}, "
        "at least 0.05)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the random motions (default 0)")
    p.add_argument(
        "--playback",
        action="store_true",
        help="follow the observed poses by position control instead (the baseline)",
    )
    p.add_argument(
        "--video", metavar="FILE", help="render the run offscreen into FILE (.mp4 or .gif)"
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument(
        "--out",
        metavar="DIR",
        help="also write replay.json and replay.csv (executed poses) into DIR",
    )
    p.set_defaults(func=run)


def parse_size(text: str, flag: str) -> tuple[float, float]:
    """Parse ``MM,DEG`` into (metres, radians)."""
    try:
        mm, deg = (float(v) for v in text.split(","))
    except ValueError:
        raise InputFormatError(f"{flag}: expected MM,DEG (e.g. 2,2), got {text!r}") from None
    if not (math.isfinite(mm) and math.isfinite(deg) and mm >= 0 and deg >= 0):
        raise InputFormatError(f"{flag}: sizes must be finite and non-negative, got {text!r}")
    return mm * 1e-3, math.radians(deg)


def observed_frames(task_path: Path, task: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """Observed per-frame poses from ``frames.csv`` beside ``task.json``, if it has them."""
    from apo.spatial import pose_from_position_quaternion
    from apo.task import UNITS

    path = task_path.parent / "frames.csv"
    u = task.units
    cols = [f"obs_x_{u}", f"obs_y_{u}", f"obs_z_{u}", "obs_qw", "obs_qx", "obs_qy", "obs_qz"]
    if not path.is_file():
        return None
    with path.open(encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    if not rows or any(c not in rows[0] for c in [*cols, "time_s"]):
        return None
    k = UNITS[u]
    t, X = [], []
    for r in rows:
        try:
            v = [float(r[c]) for c in cols]
            tt = float(r["time_s"])
        except ValueError:
            continue
        if not all(map(math.isfinite, v)):
            continue
        t.append(tt)
        X.append(pose_from_position_quaternion(np.array(v[:3]) * k, v[3:]))
    return (np.asarray(t), np.stack(X)) if X else None


def result_dict(res: Any, units: str) -> dict[str, Any]:
    """Return the ``--json`` object (lengths in the task's units)."""
    from apo.spatial import position_quaternion_from_pose
    from apo.task import UNITS

    k = 1.0 / UNITS[units]
    p, q = position_quaternion_from_pose(res.final_X_EG)
    return {
        "success": bool(res.success),
        "verdict": res.verdict,
        "mode": res.mode,
        "units": units,
        "states_reached": list(res.states_reached),
        "task_states": list(res.task_states),
        "final_state": res.final_state,
        "final_by_symmetry": bool(getattr(res, "by_symmetry", False)),
        "final_pose": {"position": [float(x) * k for x in p], "quaternion": [float(x) for x in q]},
        "max_force": float(res.max_force),
        "max_penetration": float(res.max_penetration) * k,
        "visits": [
            {"state": v.state, "t": [v.t_start, v.t_end], "elements": v.n_elements}
            for v in res.visits
        ],
        "primitives": [
            {"index": r.index, "kind": r.kind, "outcome": r.outcome, "t": [r.t_start, r.t_end]}
            for r in res.primitives
        ],
        "sim_time": float(res.sim_time),
        "wall_time": float(res.wall_time),
        "settings": {
            "perturb": [res.settings["perturb"][0] * k, math.degrees(res.settings["perturb"][1])],
            "environment_offset": [
                res.settings["environment_offset"][0] * k,
                math.degrees(res.settings["environment_offset"][1]),
            ],
            "clearance": res.settings["clearance"] * k,
            "seed": res.settings["seed"],
            "contact_threshold": res.settings["threshold"] * k,
            "pieces": {
                n: {"method": m, "count": c, "tolerance": t * k}
                for n, (m, c, t) in res.settings["pieces"].items()
            },
        },
    }


def write_replay(out: Path, res: Any, units: str) -> list[Path]:
    """Write ``replay.json`` and ``replay.csv`` (t, x, y, z, qw, qx, qy, qz) into ``out``."""
    from apo.cli.analyze import atomic_path
    from apo.io.poses import write_pose_csv

    out.mkdir(parents=True, exist_ok=True)
    js, cs = out / "replay.json", out / "replay.csv"
    with atomic_path(js) as tmp:
        tmp.write_text(json.dumps(result_dict(res, units), indent=2) + "\n", encoding="utf-8")
    with atomic_path(cs) as tmp:
        write_pose_csv(tmp, res.times, res.X_EG, units=units)
    return [js, cs]


def replay_file(task_path: Path, *, video: Any = None, **options: Any) -> tuple[Any, str]:
    """Replay the ``task.json`` at ``task_path`` with its model files; return (result, units).

    ``options`` go to :func:`apo.sim.replay.replay` (SI units).
    """
    from apo.cli import warnings_to_stderr
    from apo.io.meshes import load_polyhedron
    from apo.io.taskfile import model_paths, read_task
    from apo.sim.replay import replay

    task = read_task(task_path)
    gpath, epath = model_paths(task, task_path)
    with warnings_to_stderr("apo replay"):
        G = load_polyhedron(gpath, units=task.units)
        E = load_polyhedron(epath, units=task.units)
    if options.get("playback"):
        options["frames"] = observed_frames(task_path, task)
    res = replay(task, G, E, video=video, **options)
    return res, task.units


def run(args: argparse.Namespace) -> int:
    """Run ``apo replay``; return 0 on success, 1 when the verdict is a failure."""
    perturb = parse_size(args.perturb, "--perturb")
    offset = parse_size(args.environment_offset, "--environment-offset")
    if not (math.isfinite(args.clearance) and args.clearance >= 0.05):
        raise InputFormatError(f"--clearance must be at least 0.05 mm, got {args.clearance}")
    video = None
    if args.video:
        from apo.sim.video import Recorder

        video = Recorder(Path(args.video))
    res, units = replay_file(
        Path(args.task), video=video, perturb=perturb, environment_offset=offset,
        clearance=args.clearance * 1e-3, seed=args.seed, playback=args.playback,
    )  # fmt: skip
    if video is not None:
        video.close()
    written = write_replay(Path(args.out), res, units) if args.out else []
    if args.json:
        print(json.dumps(result_dict(res, units), indent=2))
    else:
        print(report(res, units))
        for p in written:
            print(f"wrote {p}")
    if video is not None:
        print(f"wrote video: {args.video}", file=sys.stderr if args.json else sys.stdout)
    return 0 if res.success else 1


def report(res: Any, units: str) -> str:
    """Human-readable summary: primitives, states visited, verdict."""
    from apo.task import UNITS

    k = 1.0 / UNITS[units]
    lines = [f"replay ({res.mode}), {res.sim_time:.2f} s simulated in {res.wall_time:.2f} s"]
    for r in res.primitives:
        if res.mode == "skills":
            lines.append(
                f"  {r.index:>2} {r.kind:<9} {r.outcome:<9} t {r.t_start:6.2f}-{r.t_end:6.2f} s  "
                f"force {r.force:5.2f} N"
            )
    lines.append(f"states reached: {' '.join(res.states_reached)}")
    lines.append(f"task states:    {' '.join(res.task_states)}")
    lines.append(
        f"max force {res.max_force:.2f} N, max penetration {res.max_penetration * k:.4g} {units}"
    )
    lines.append(res.verdict)
    return "\n".join(lines)
