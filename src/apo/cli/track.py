"""``apo track``: recorded depth (or stereo) frames -> pose trajectory CSV.

Writes ``OUT`` with :func:`apo.io.poses.write_pose_csv` (the CSV ``apo analyze`` reads, plus a
``confidence`` column) and, beside it,
``<OUT without .csv>.environment.json`` with the environment's pose in the camera frame.
See ``docs/perception.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

import numpy as np
import numpy.typing as npt

from apo.constants import UNITS
from apo.errors import InputFormatError

if TYPE_CHECKING:
    from collections.abc import Sequence

    from apo.outputs import OutputSet
    from apo.perception.track import TrackResult
    from apo.symmetry import Symmetry


def _pose_arg(text: str, name: str, scale: float) -> npt.NDArray[np.float64]:
    from apo.spatial import pose_from_xyz_quat

    try:
        values = [float(x) for x in text.replace(",", " ").split()]
        if not np.all(np.isfinite(values)):
            raise ValueError("not all finite")
        X = pose_from_xyz_quat(values)
    except ValueError as exc:
        raise InputFormatError(
            f"{name}: expected 7 numbers 'x y z qw qx qy qz', got {text!r} ({exc})"
        ) from None
    X[:3, 3] *= scale
    return X


def _colour_arg(text: str) -> tuple[float, float, float]:
    try:
        r, g, b = (float(x) for x in text.replace(",", " ").split())
    except ValueError:
        raise InputFormatError(f"--colour: expected 'r g b' in 0..255, got {text!r}") from None
    return (r / 255.0, g / 255.0, b / 255.0)


def environment_path(out: Path) -> Path:
    """Return the path of the environment pose file written beside ``out``."""
    stem = out.name[: -len(".csv")] if out.name.lower().endswith(".csv") else out.name
    return out.with_name(stem + ".environment.json")


def _xyzq(X: npt.NDArray[np.float64], scale: float) -> list[float]:
    from apo.spatial import position_quaternion_from_pose

    p, q = position_quaternion_from_pose(X)
    return [*(float(v) / scale for v in p), *(float(v) for v in q)]


def track_from_args(
    args: argparse.Namespace, frames: str | Path, grasped: str | Path, environment: str | Path
) -> TrackResult:
    """Track ``frames`` with the options of :func:`add_tracking_options` (``args.units``)."""
    from apo.perception.segment import ColourModel
    from apo.perception.track import TrackOptions, track_frames

    units = args.units or "mm"
    scale = UNITS[units]
    init_g = _pose_arg(args.init_grasped, "--init-grasped", scale) if args.init_grasped else None
    init_e = (
        _pose_arg(args.init_environment, "--init-environment", scale)
        if args.init_environment
        else None
    )
    colour: ColourModel | None = None  # learnt from the recording
    if args.colour and args.colour.strip().lower() == "none":
        colour = ColourModel.any_colour()
    elif args.colour and args.colour.strip().lower() != "auto":
        colour = ColourModel(_colour_arg(args.colour), args.colour_tolerance)
    if not 0.0 <= args.min_confidence <= 1.0:
        raise InputFormatError(f"--min-confidence must be in [0, 1], got {args.min_confidence}")
    options = TrackOptions(
        colour=colour, min_confidence=args.min_confidence, smooth=getattr(args, "smooth", True)
    )
    return track_frames(
        frames,
        grasped,
        environment,
        units=units,
        init_grasped=init_g,
        init_environment=init_e,
        options=options,
    )


def _symmetry_list(syms: Sequence[Symmetry]) -> list[dict[str, object]]:
    """Symmetries as JSON: ``{"axis": [x, y, z], "angle_deg": a}`` (model frame), identity first."""
    return [
        {
            "axis": [round(float(v), 6) for v in s.axis],
            "angle_deg": round(float(np.degrees(s.angle)), 4),
        }
        for s in syms
    ]


def environment_json(result: TrackResult, units: str) -> dict[str, object]:
    """Return the content of ``<OUT stem>.environment.json`` (environment in the camera frame)."""
    scale = UNITS[units]
    env: dict[str, object] = {
        "frame": "camera",
        "units": units,
        "X_CE": _xyzq(result.X_CE, scale),
        "confidence": round(result.environment_confidence, 4),
        "lost_frames": [int(i) for i in np.nonzero(result.lost)[0]],
        "reinitialisations": result.reinitialisations,
        "reinitialised_frames": [int(i) for i in np.nonzero(result.reinitialised)[0]],
        "symmetries": {
            "grasped": _symmetry_list(result.grasped_symmetries),
            "environment": _symmetry_list(result.environment_symmetries),
        },
    }
    if result.X_WC is not None:
        env["X_WC"] = _xyzq(result.X_WC, scale)
        env["X_WE"] = _xyzq(result.X_WC @ result.X_CE, scale)
    return env


def write_tracking(
    result: TrackResult,
    out: Path,
    units: str,
    *,
    file: TextIO | None = None,
    env_out: Path | None = None,
    shown: Path | None = None,
) -> Path:
    """Write the pose CSV ``out`` and the environment JSON beside it; report on ``file``.

    ``file`` (default stdout) gets the one-line summary; lost frames are reported on stderr.
    ``env_out`` is where to write the JSON (default beside ``out``); ``shown`` is the path
    to print for ``out`` (where it will be once an output set commits). Returns the path of
    the environment JSON as shown.
    """
    from apo.io.poses import write_pose_csv

    shown = shown or out
    keep = ~result.lost
    write_pose_csv(
        out,
        result.times[keep],
        result.X_EG[keep],
        units=units,
        extra={
            "confidence": result.confidence[keep],
            "reinitialised": result.reinitialised[keep].astype(np.int64),
        },
    )
    kept = int(keep.sum())
    lost = [int(i) for i in np.nonzero(result.lost)[0]]
    env = environment_json(result, units)
    from apo.outputs import sha256_file

    # The JSON is renamed into place after the CSV and names it: it is the pair's manifest.
    env["poses"] = {"file": shown.name, "sha256": sha256_file(out)}
    (env_out or environment_path(out)).write_text(
        json.dumps(env, indent=2) + "\n", encoding="utf-8"
    )
    env_path = environment_path(shown)
    from apo.symmetry import describe_symmetries

    conf = result.confidence[keep]
    print(
        f"{kept} of {len(result.times)} frames tracked -> {shown}; environment -> {env_path}\n"
        f"  re-initialisations: {result.reinitialisations}; confidence median "
        f"{np.median(conf) if kept else 0.0:.3f}, lowest {conf.min() if kept else 0.0:.3f}; "
        f"environment {result.environment_confidence:.3f}\n"
        f"  symmetries: grasped {describe_symmetries(list(result.grasped_symmetries))}, "
        f"environment {describe_symmetries(list(result.environment_symmetries))}",
        file=file or sys.stdout,
    )
    if lost:
        print(
            f"warning: {len(lost)} frame(s) lost and left out of {shown}: {lost[:20]}"
            + (" ..." if len(lost) > 20 else ""),
            file=sys.stderr,
        )
    return env_path


@dataclass(frozen=True)
class TrackedDemonstration:
    """The tracked frames of a demonstration, ready for recognition (metres, seconds).

    Attributes
    ----------
    times : ndarray, shape (N,)
        Times of the tracked frames (lost frames left out).
    X_EG : ndarray, shape (N, 4, 4)
        The grasped object in the environment frame.
    units : str
        The length unit of the command line (``--units``) and of the files written.
    result : TrackResult
        Everything the tracker returned (all frames).
    """

    times: npt.NDArray[np.float64]
    X_EG: npt.NDArray[np.float64]
    units: str
    result: TrackResult


def demonstration_from_frames(
    args: argparse.Namespace,
    frames: str | Path,
    grasped: str | Path,
    environment: str | Path,
    outs: OutputSet,
) -> TrackedDemonstration:
    """Track a frames folder for ``apo analyze FRAMES`` / ``apo demo --from-frames``.

    Writes ``poses.csv`` and ``poses.environment.json`` (as ``apo track``) into the output
    set ``outs``, reports on stderr (stdout may carry ``--json``), and returns the tracked
    poses.
    """
    result = track_from_args(args, frames, grasped, environment)
    units = args.units or "mm"
    write_tracking_into(outs, result, units)
    keep = ~result.lost
    return TrackedDemonstration(result.times[keep], result.X_EG[keep], units, result)


def write_tracking_into(outs: OutputSet, result: TrackResult, units: str) -> None:
    """Write ``poses.csv`` and ``poses.environment.json`` into ``outs``; report on stderr."""
    write_tracking(
        result, outs.path("poses.csv"), units, file=sys.stderr, shown=outs.final("poses.csv")
    )


def reject_tracking_options(args: argparse.Namespace, demo: Path) -> None:
    """Raise if a tracking option was given for an input that is not a frames folder."""
    for flag in ("init_grasped", "init_environment", "colour"):
        if getattr(args, flag, None) is not None:
            raise InputFormatError(
                f"{demo}: --{flag.replace('_', '-')} applies to a frames folder only "
                "(this is a pose file)"
            )


def run(args: argparse.Namespace) -> int:
    """Run ``apo track``."""
    from apo.outputs import output_files

    out = Path(args.out)
    # The environment JSON (which names the CSV and its SHA-256) is renamed last: a pair
    # interrupted between the two renames is detectable (the hashes disagree).
    with output_files([environment_path(out), out], label="--out") as (env_tmp, csv_tmp):
        result = track_from_args(args, args.frames, args.grasped, args.environment)
        write_tracking(result, csv_tmp, args.units, env_out=env_tmp, shown=out)
    return 0


def add_tracking_options(p: argparse.ArgumentParser) -> None:
    """Add the tracking options shared by ``apo track`` and ``apo analyze FRAMES``."""
    p.add_argument(
        "--init-grasped",
        metavar="POSE",
        help='grasped object in the camera frame at the first frame, "x y z qw qx qy qz" '
        "(--units; frames input only)",
    )
    p.add_argument(
        "--init-environment",
        metavar="POSE",
        help='environment object in the camera frame, "x y z qw qx qy qz" (--units; frames '
        "input only)",
    )
    p.add_argument(
        "--colour",
        metavar="RGB",
        help='colour of the objects, "r g b" in 0..255, a cue besides the depth; "auto" '
        '(default): learnt from the environment found by depth; "none": depth alone '
        "(the paper's parts were white: 255 255 255)",
    )
    p.add_argument(
        "--colour-tolerance",
        type=float,
        metavar="T",
        default=0.05,
        help="chromaticity tolerance of --colour (default 0.05)",
    )
    p.add_argument(
        "--min-confidence",
        type=float,
        metavar="C",
        default=0.8,
        help="frames below this confidence are re-initialised, then lost (default 0.8)",
    )
    p.add_argument(
        "--smooth",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="smooth the grasped object's poses over neighbouring frames, keeping the jumps "
        "and kinks of contacts sharp (default); --no-smooth: each frame's own registration",
    )


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``track`` sub-command."""
    p = subparsers.add_parser(
        "track",
        help="poses of both objects from recorded depth or stereo frames",
        description=(
            "Track the grasped and the environment object through a frames folder "
            "(camera.json, rgb/, depth/; or a stereo folder: stereo.json, left/, right/; see "
            "docs/perception.md). Writes OUT: t,x,y,z,qw,qx,qy,qz,confidence (the grasped "
            "object in the environment frame, in --units) and OUT's stem + "
            "'.environment.json' (the environment in the camera frame). Lost frames are left "
            "out of the CSV and listed."
        ),
    )
    p.add_argument("frames", metavar="FRAMES", help="frames folder (or stereo folder)")
    p.add_argument("--grasped", required=True, metavar="G", help="grasped object model file")
    p.add_argument(
        "--environment", required=True, metavar="E", help="environment object model file"
    )
    p.add_argument(
        "--units",
        default="mm",
        choices=sorted(UNITS),
        help="units of the model files, the initial poses and the output (default mm)",
    )
    add_tracking_options(p)
    p.add_argument("--out", required=True, metavar="CSV", help="output pose CSV")
    p.set_defaults(func=run)
