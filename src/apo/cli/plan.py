"""``apo plan task.json [--out DIR]``: the skill program and pose trajectory of a task.

Writes ``motion.json`` (schema ``apo.motion/1``), ``motion.csv`` and ``motion.pose.list``
(``docs/motion.md``). Argument parsing and file writing only; the planning is
:func:`apo.motion.plan`.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

from apo.errors import InputFormatError

OUTPUTS = ("motion.json", "motion.csv", "motion.pose.list")


def register(subparsers: Any) -> None:
    """Add the ``plan`` sub-command."""
    p = subparsers.add_parser(
        "plan",
        help="robot skill program and pose trajectory from a task.json",
        description=(
            "Plan the robot motion of a task model: one primitive per sub-skill (approach, "
            "push_to, slide, release, align before critical transitions) with directions, "
            "compliance and stop conditions, and a pose trajectory of the grasped object. "
            "Writes motion.json, motion.csv and motion.pose.list (docs/motion.md)."
        ),
    )
    p.add_argument("task", metavar="TASK_JSON", help="task.json written by apo analyze/demo")
    p.add_argument(
        "--out",
        metavar="DIR",
        help="output folder (default: the folder of TASK_JSON, so that the models' paths "
        "recorded relative to it stay valid)",
    )
    p.add_argument(
        "--standoff", type=float, metavar="LEN", help="approach stand-off, task units (5 mm)"
    )
    p.add_argument(
        "--clearance",
        type=float,
        metavar="LEN",
        help="gap per side the alignment tolerance is derived from, task units (0.2 mm)",
    )
    p.add_argument(
        "--sample-period", type=float, metavar="S", help="trajectory sample period, s (0.02)"
    )
    p.add_argument("--json", action="store_true", help="print motion.json to stdout")
    p.set_defaults(func=run)


def check_destination(out: Path) -> None:
    """Fail before any work if ``out`` cannot receive the outputs."""
    if out.exists() and not out.is_dir():
        raise InputFormatError(f"{out}: --out exists and is not a folder")
    probe = out
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise InputFormatError(f"{out}: cannot write there ({probe} is not a writable folder)")
    for name in OUTPUTS:
        if (out / name).is_dir():
            raise InputFormatError(f"{out / name}: is a folder; cannot write {name} there")


def _parameters(args: argparse.Namespace, units: str) -> Any:
    from dataclasses import replace

    from apo.motion import PlanParameters
    from apo.task import UNITS

    pp = PlanParameters()
    k = UNITS[units]
    for flag, name, scale in (
        ("standoff", "standoff", k),
        ("clearance", "clearance", k),
        ("sample_period", "sample_period", 1.0),
    ):
        v = getattr(args, flag)
        if v is None:
            continue
        if not v > 0:
            raise InputFormatError(f"--{flag.replace('_', '-')} must be positive, got {v}")
        pp = replace(pp, **{name: v * scale})
    return pp


def write_motion(
    program: Any, task_path: Path, out: Path, grasped: Path, environment: Path
) -> dict[str, Path]:
    """Write the three outputs atomically into ``out``; return them by kind."""
    from apo.cli.analyze import atomic_path
    from apo.io.poses import write_pose_csv, write_pose_list
    from apo.motion import program_to_dict, trajectory

    out.mkdir(parents=True, exist_ok=True)
    traj = trajectory(program)
    written: dict[str, Path] = {}
    target = out / "motion.json"
    with atomic_path(target) as tmp:
        tmp.write_text(json.dumps(program_to_dict(program), indent=2) + "\n", encoding="utf-8")
    written["program"] = target
    target = out / "motion.csv"
    with atomic_path(target) as tmp:
        write_pose_csv(
            tmp, traj.times, traj.X_EG, units=program.units, extra={"primitive": traj.primitive}
        )
    written["trajectory"] = target
    target = out / "motion.pose.list"
    models = tuple(_relative(p, out) for p in (grasped, environment))
    with atomic_path(target) as tmp:
        write_pose_list(tmp, traj.X_EG, units=program.units, models=(models[0], models[1]))
    written["pose list"] = target
    return written


def _relative(path: Path, base: Path) -> str:
    try:
        return os.path.relpath(path.resolve(), base.resolve())
    except ValueError:  # another drive (Windows)
        return str(path.resolve())


def summary(program: Any) -> str:
    """One line per primitive: kind, space, transition, direction, stop condition."""
    from apo.task import UNITS

    k = 1.0 / UNITS[program.units]
    lines = [f"{'#':>2}  {'primitive':<22} {'transition':<14} {'direction':<22} stop"]
    for p in program.primitives:
        name = str(p.kind) + (f" {p.space}" if p.space else "") + (f" {p.type}" if p.type else "")
        tr = "" if p.transition is None else f"({p.transition + 1}) {p.from_state}->{p.to_state}"
        if p.folded:
            tr += "+" + ",".join(f"({f + 1})" for f in p.folded)
        d = " ".join(f"{v:+.2f}" for v in p.direction)
        rot = str(p.space) == "rotation"
        travel = f"{p.stop.travel:.3f} rad" if rot else f"{p.stop.travel * k:.3g} {program.units}"
        lines.append(
            f"{p.index:>2}  {name:<22} {tr:<14} {d:<22} "
            f"{p.stop.force:g} N / {p.stop.torque:g} N·m, travel <= {travel}"
        )
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Run ``apo plan``; return the exit code."""
    from apo.io.taskfile import model_paths, read_task, task_ref
    from apo.motion import plan, program_to_dict

    task_path = Path(args.task)
    out = Path(args.out) if args.out else task_path.parent
    check_destination(out)
    task = read_task(task_path)
    grasped, environment = model_paths(task, task_path)
    program = plan(task, parameters=_parameters(args, task.units), task_ref=task_ref(task_path))
    written = write_motion(program, task_path, out, grasped, environment)
    if args.json:
        print(json.dumps(program_to_dict(program), indent=2))
        return 0
    print(summary(program))
    for kind, p in written.items():
        print(f"wrote {kind}: {p}")
    return 0
