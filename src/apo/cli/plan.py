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
KINDS = ("program", "trajectory", "pose list")


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
    program: Any, out: Path, grasped: Path, environment: Path, files: list[Path]
) -> dict[str, Path]:
    """Write the three outputs into the temporary ``files`` (in ``OUTPUTS`` order)."""
    from apo.io.poses import write_pose_csv, write_pose_list
    from apo.motion import program_to_dict, trajectory

    traj = trajectory(program)
    text = json.dumps(program_to_dict(program), indent=2) + "\n"
    files[0].write_text(text, encoding="utf-8")
    write_pose_csv(
        files[1], traj.times, traj.X_EG, units=program.units, extra={"primitive": traj.primitive}
    )
    models = tuple(_relative(p, out) for p in (grasped, environment))
    write_pose_list(files[2], traj.X_EG, units=program.units, models=(models[0], models[1]))
    return {kind: out / name for kind, name in zip(KINDS, OUTPUTS, strict=True)}


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
    from dataclasses import replace

    from apo.io.taskfile import model_paths, read_task, task_ref
    from apo.motion import plan, program_to_dict
    from apo.outputs import output_files

    task_path = Path(args.task)
    out = Path(args.out) if args.out else task_path.parent
    task = read_task(task_path)
    grasped, environment = model_paths(task, task_path)
    pp = _parameters(args, task.units)
    # destinations checked and locked before the work; each file renamed into place at the end
    with output_files([out / name for name in OUTPUTS], label="--out") as files:
        # the task file as seen from motion.json's folder (its models are relative to it)
        ref = replace(task_ref(task_path), path=_relative(task_path, out))
        program = plan(task, parameters=pp, task_ref=ref)
        written = write_motion(program, out, grasped, environment, files)
    if args.json:
        print(json.dumps(program_to_dict(program), indent=2))
        return 0
    print(summary(program))
    for kind, p in written.items():
        print(f"wrote {kind}: {p}")
    return 0
