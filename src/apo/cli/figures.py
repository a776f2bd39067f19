"""``apo figures task.json --out DIR``: figures for papers (SVG and PNG, matplotlib)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from apo.constants import UNITS
from apo.errors import InputFormatError


def register(subparsers: Any) -> None:
    """Add the ``figures`` sub-command."""
    p = subparsers.add_parser(
        "figures",
        help="write SVG and PNG figures of a task.json (DOF timeline, state graph, states)",
        description=(
            "Write figures for papers: the DOF timeline (dof_timeline), the state graph of "
            "the paper's Fig. 24/25 (state_graph) and one picture per state with the two "
            "objects at the state's pose and its contacts (state_<ID>), each as SVG and PNG."
        ),
    )
    p.add_argument("task", metavar="TASK_JSON", help="task.json written by apo analyze / demo")
    p.add_argument("--out", metavar="DIR", required=True, help="output folder")
    p.add_argument(
        "--format",
        default="svg,png",
        help="comma-separated formats (svg, png, pdf; default: svg,png)",
    )
    p.add_argument("--dpi", type=int, default=200, help="resolution of PNG figures (default 200)")
    p.add_argument(
        "--model-units",
        choices=tuple(UNITS),
        help="unit of mesh model files (STL/OBJ/PLY; default: the task's units)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``apo figures``; return the exit code."""
    from apo.cli.report import read_task_json
    from apo.report.figures import write_figures
    from apo.report.sources import load_models

    formats = [f.strip().lower() for f in args.format.split(",") if f.strip()]
    bad = [f for f in formats if f not in ("svg", "png", "pdf")]
    if bad or not formats:
        raise InputFormatError(f"--format: expected svg, png or pdf, got {args.format!r}")
    if not 20 <= args.dpi <= 1200:
        raise InputFormatError(f"--dpi must be within 20..1200, got {args.dpi}")
    from apo.outputs import OutputSet

    out = Path(args.out)
    task_path = Path(args.task)
    with OutputSet(out, label="--out") as outs:  # checks the destination before the work
        doc = read_task_json(task_path)
        G, E, _files, notes = load_models(doc, task_path.parent, units=args.model_units)
        for n in notes:
            print(f"apo figures: warning: {n}", file=sys.stderr)
        paths = write_figures(doc, outs, grasped=G, environment=E, formats=formats, dpi=args.dpi)
    print(f"wrote {len(paths)} figure file(s) to {out}")
    for p in paths:
        print(f"  {p.name}")
    return 0
