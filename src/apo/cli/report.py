"""``apo report task.json``: the offline interactive HTML report of a recognised task."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from apo.constants import UNITS
from apo.errors import InputFormatError


def register(subparsers: Any) -> None:
    """Add the ``report`` sub-command."""
    p = subparsers.add_parser(
        "report",
        help="write the offline interactive HTML report of a task.json",
        description=(
            "Write one self-contained HTML file (works offline, no server) showing the "
            "recognised task: a 3D replay of the two objects with contacts and separating "
            "normals, the DOF timeline, the state graph (paper Fig. 24/25), the tables of "
            "states and transitions and the inputs. Per-frame poses come from frames.csv "
            "beside task.json where present; models from the paths in task.json."
        ),
    )
    p.add_argument("task", metavar="TASK_JSON", help="task.json written by apo analyze / demo")
    p.add_argument("--motion", metavar="MOTION_JSON", help="robot motion (apo plan) to replay too")
    p.add_argument(
        "--replay",
        metavar="REPLAY",
        help="simulated execution: replay.json or the folder of apo replay --out DIR",
    )
    p.add_argument(
        "--out", metavar="HTML", help="output file (default: report.html beside TASK_JSON)"
    )
    p.add_argument(
        "--frames",
        metavar="CSV",
        help="per-frame data (default: frames.csv beside TASK_JSON, if present)",
    )
    p.add_argument(
        "--model-units",
        choices=tuple(UNITS),
        help="unit of mesh model files (STL/OBJ/PLY; default: the task's units)",
    )
    p.set_defaults(func=run)


def read_task_json(path: Path) -> dict[str, Any]:
    """Read and validate ``task.json``; return its document (clear errors naming the file)."""
    from apo.io.jsonfile import read_json
    from apo.task import task_from_dict

    doc = read_json(path)
    task_from_dict(doc, source=str(path))  # validates every field
    return dict(doc)


def run(args: argparse.Namespace) -> int:
    """Run ``apo report``; return the exit code."""
    from apo.outputs import atomic_file
    from apo.report.html import report_data, write_report
    from apo.report.sources import file_entry, inputs_summary, load_models, read_frames_csv

    task_path = Path(args.task)
    out = Path(args.out) if args.out else task_path.parent / "report.html"
    if out.exists() and out.is_dir():
        raise InputFormatError(f"--out {out}: is a folder; give a file name")
    doc = read_task_json(task_path)
    files = [file_entry("task", task_path)]
    frames = None
    csv_path = Path(args.frames) if args.frames else task_path.parent / "frames.csv"
    if args.frames or csv_path.is_file():
        frames = read_frames_csv(csv_path, units=str(doc["units"]))
        if frames.times.shape[0] != int(doc["n_frames"]):
            raise InputFormatError(
                f"{csv_path}: {frames.times.shape[0]} frames, but {task_path} has "
                f"{doc['n_frames']}: not the frames of this task"
            )
        files.append(file_entry("per-frame data", csv_path))
    G, E, model_files, notes = load_models(doc, task_path.parent, units=args.model_units)
    files += model_files
    tracks: list[Any] = []
    if args.motion:
        from apo.report.motion import read_motion_tracks

        mpath = Path(args.motion)
        tracks, mfiles = read_motion_tracks(mpath, units=str(doc["units"]))
        files += [file_entry("motion", mpath), *mfiles]
    if args.replay:
        from apo.report.motion import read_replay_track

        tracks = [t for t in tracks if t.kind != "executed"]  # --replay wins
        track, rfiles = read_replay_track(Path(args.replay), units=str(doc["units"]))
        tracks.append(track)
        files += rfiles
    data = report_data(
        doc,
        grasped=G,
        environment=E,
        frames=frames,
        tracks=tracks,
        inputs=inputs_summary(doc, files),
        notes=notes,
    )
    with atomic_file(out) as tmp:
        size = write_report(tmp, data)
    for n in notes:
        print(f"apo report: warning: {n}", file=sys.stderr)
    print(f"wrote report: {out} ({size / 1e6:.1f} MB)")
    return 0
