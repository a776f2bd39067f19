"""``apo demo``: the whole pipeline on the built-in T-peg / U-slot example.

The example (paper Fig. 21, own geometry) comes from :mod:`apo.synthetic`: a scripted
insertion of a T-shaped peg into a U-shaped slot with realistic observation noise. The
models are written to the output folder as STL (millimetres) so that ``task.json`` refers
to real files with content hashes.

Hook for other sources of the demonstration: :func:`demonstration_from_args` returns the
models, times and poses; a new option adds an argument in :func:`register` and a branch there.
``--from-frames`` is one: the example's true poses are rendered into depth and colour frames
(``OUT/frames/``, with depth-sensor noise and a hand holding the peg), tracked by
:mod:`apo.perception` from the first frame's poses (``OUT/poses.csv``), and the tracked poses
are recognised instead of noisy copies of the truth.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from apo.errors import InputFormatError
from apo.outputs import OutputSet
from apo.report.writer import (
    PlotWorker,
    model_ref_as,
    report_maker,
    write_recognition,
)

if TYPE_CHECKING:
    from apo.geometry import Polyhedron

DEFAULT_OUT = "apo-demo"
DEFAULT_NOISE_MM = 0.5
"""Default position noise of the built-in example, mm (sigma per axis)."""
DEFAULT_NOISE_DEG = 0.5
"""Default rotation noise of the built-in example, degrees (sigma per axis)."""
DEFAULT_RESOLUTION = "640x480"
"""Image size of ``--from-frames``."""
DEFAULT_DEPTH_NOISE_MM = 1.5
"""Depth noise of ``--from-frames``, mm at 1 m (Kinect-v1 class; 0.26 mm at the parts)."""


def register(subparsers: Any) -> None:
    """Add the ``demo`` sub-command."""
    p = subparsers.add_parser(
        "demo",
        help="the whole pipeline on the built-in T-peg / U-slot example",
        description=(
            "Generate a scripted T-peg into U-slot demonstration with observation noise, "
            "recognise it, print the Fig. 25-style table and write task.json, dof.png and the "
            "models to --out."
        ),
    )
    p.add_argument(
        "--out", metavar="DIR", default=DEFAULT_OUT, help=f"output folder (default: {DEFAULT_OUT})"
    )
    p.add_argument("--seed", type=int, default=0, help="random seed of the noise (default 0)")
    p.add_argument(
        "--noise-mm",
        type=float,
        default=None,
        metavar="X",
        help=f"position noise sigma, mm (default {DEFAULT_NOISE_MM})",
    )
    p.add_argument(
        "--noise-deg",
        type=float,
        default=None,
        metavar="Y",
        help=f"rotation noise sigma, deg (default {DEFAULT_NOISE_DEG})",
    )
    p.add_argument("--json", action="store_true", help="print task.json instead of the table")
    p.add_argument("--no-plot", action="store_true", help="do not write dof.png")
    p.add_argument("--no-report", action="store_true", help="do not write report.html (apo report)")
    p.add_argument(
        "--no-replay",
        action="store_true",
        help="do not end with the replay of the task model in MuJoCo (apo replay)",
    )
    p.add_argument(
        "--from-frames",
        action="store_true",
        help="render the example into depth/colour frames (OUT/frames), track them "
        "(OUT/poses.csv) and recognise the tracked poses (needs Open3D)",
    )
    p.add_argument(
        "--resolution",
        metavar="WxH",
        default=DEFAULT_RESOLUTION,
        help=f"image size of --from-frames (default {DEFAULT_RESOLUTION})",
    )
    p.add_argument(
        "--depth-noise",
        type=float,
        default=None,
        metavar="MM",
        help=f"depth noise sigma at 1 m of --from-frames, mm (default {DEFAULT_DEPTH_NOISE_MM}; "
        "it grows with the square of the distance)",
    )
    p.set_defaults(func=run)


@dataclass(frozen=True)
class DemoInput:
    """A demonstration ready for recognition (metres, environment frame)."""

    grasped: Polyhedron
    environment: Polyhedron
    times: np.ndarray
    X_EG: np.ndarray
    source: str
    truth: Any = None


def _write_stl(poly: Polyhedron, path: Path, scale: float) -> None:
    """Write ``poly``'s face triangulation as binary STL, lengths multiplied by ``scale``."""
    from apo.outputs import atomic_file

    tris = np.concatenate(poly.face_triangles)
    fidx = np.concatenate([np.full(len(t), f) for f, t in enumerate(poly.face_triangles)])
    rec = np.zeros(
        len(tris),
        dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")],
    )
    rec["n"] = poly.face_normals[fidx]
    rec["v"] = poly.vertices[tris] * scale
    header = f"apo {poly.name}".encode().ljust(80, b" ")[:80]
    with atomic_file(path) as tmp, open(tmp, "wb") as fh:
        fh.write(header)
        fh.write(np.uint32(len(tris)).tobytes())
        fh.write(rec.tobytes())


def _write_models(dem: DemoInput, outs: OutputSet) -> tuple[Polyhedron, Polyhedron]:
    """Write the models as STL (mm) into ``outs``; return them as read back from those files.

    The task's feature ids (``["v", 3]``, ``["e", 5]``) must be those of the files the task
    names, so the recognition runs on the models re-read from them.
    """
    from apo.cli import warnings_to_stderr
    from apo.io.meshes import load_polyhedron

    loaded = []
    for poly, name in ((dem.grasped, "grasped.stl"), (dem.environment, "environment.stl")):
        _write_stl(poly, outs.path(name), 1000.0)
        with warnings_to_stderr("apo demo"):
            loaded.append(load_polyhedron(outs.path(name), units="mm", name=poly.name))
    return loaded[0], loaded[1]


def demonstration_from_args(args: argparse.Namespace, outs: OutputSet | None = None) -> DemoInput:
    """Return the demonstration the arguments ask for (the built-in example by default).

    ``--from-frames`` writes its frames and tracked poses into ``outs`` (required then).
    """
    if getattr(args, "from_frames", False):
        if outs is None:
            raise ValueError("--from-frames writes into an output set: pass outs")
        return _demonstration_from_frames(args, outs)
    for flag, given in (
        ("--resolution", getattr(args, "resolution", DEFAULT_RESOLUTION) != DEFAULT_RESOLUTION),
        ("--depth-noise", getattr(args, "depth_noise", None) is not None),
    ):
        if given:
            raise InputFormatError(f"{flag} applies to --from-frames only")
    from apo import synthetic

    for flag, v in (("--noise-mm", args.noise_mm), ("--noise-deg", args.noise_deg)):
        if v is not None and not (np.isfinite(v) and v >= 0):
            raise InputFormatError(f"{flag} must be a non-negative number, got {v}")
    demo = synthetic.peg_in_hole_2d()
    noisy = synthetic.add_noise(
        demo,
        sigma_mm=DEFAULT_NOISE_MM if args.noise_mm is None else args.noise_mm,
        sigma_deg=DEFAULT_NOISE_DEG if args.noise_deg is None else args.noise_deg,
        seed=args.seed,
    )
    return DemoInput(
        grasped=demo.grasped,
        environment=demo.environment,
        times=np.asarray(noisy.times, dtype=np.float64),
        X_EG=np.asarray(noisy.X_EG, dtype=np.float64),
        source=f"apo demo (seed {args.seed})",
        truth=demo,
    )


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputFormatError(f"--resolution: expected WxH (e.g. 640x480), got {text!r}") from None
    if not (16 <= w <= 4096 and 16 <= h <= 4096):
        raise InputFormatError(f"--resolution: {w}x{h} is outside 16x16 .. 4096x4096")
    return w, h


def _demonstration_from_frames(args: argparse.Namespace, outs: OutputSet) -> DemoInput:
    """Render the example's true poses, track the frames, return the tracked poses."""
    for flag, v in (("--noise-mm", args.noise_mm), ("--noise-deg", args.noise_deg)):
        if v is not None:
            raise InputFormatError(
                f"{flag} is the pose noise of the default demo; with --from-frames the noise "
                "is in the depth frames (--depth-noise)"
            )
    sigma_mm = DEFAULT_DEPTH_NOISE_MM if args.depth_noise is None else args.depth_noise
    if not (np.isfinite(sigma_mm) and sigma_mm >= 0):
        raise InputFormatError(f"--depth-noise must be a non-negative number, got {sigma_mm}")
    width, height = _resolution(args.resolution)
    from apo.cli.track import write_tracking_into
    from apo.perception.example import render_builtin
    from apo.perception.render import DepthNoise
    from apo.perception.track import track_frames

    print(f"rendering the example into {outs.final('frames')} ...", file=sys.stderr)
    r = render_builtin(
        outs.path("frames"),
        width=width,
        height=height,
        noise=DepthNoise(sigma_1m=sigma_mm * 1e-3),
        seed=args.seed,
        hand=True,
    )
    print("tracking ...", file=sys.stderr)
    result = track_frames(
        r.frames, r.grasped, r.environment, units="m", init_grasped=r.X_CG0, init_environment=r.X_CE
    )
    write_tracking_into(outs, result, "mm")
    keep = ~result.lost
    return DemoInput(
        grasped=r.demo.grasped,
        environment=r.demo.environment,
        times=result.times[keep],
        X_EG=result.X_EG[keep],
        source=f"apo demo --from-frames (seed {args.seed})",
        truth=r.demo,
    )


def run(args: argparse.Namespace) -> int:
    """Run ``apo demo``; return the exit code."""
    from apo.cli.analyze import print_written

    worker = None if args.no_plot else PlotWorker()
    try:
        with OutputSet(args.out, label="--out") as outs:  # checked and locked before the work
            written = _run(args, outs, worker)
    finally:
        if worker is not None:
            worker.close()
    print_written(written)
    if not args.no_replay:
        replay_verdict(written, file=sys.stderr if args.json else sys.stdout)
    return 0


def replay_verdict(written: dict[str, Path], *, file: Any) -> None:
    """Replay the written ``task.json`` in MuJoCo (as ``apo replay``) and print the verdict.

    Skipped with a note when the extra ``sim`` is not installed.
    """
    task = next((p for p in written.values() if Path(p).name == "task.json"), None)
    if task is None:
        return
    try:
        import mujoco  # noqa: F401
    except ImportError:
        print("replay skipped: MuJoCo is not installed (pip install 'apo[sim]')", file=file)
        return
    from apo.cli.replay import replay_file

    res, _ = replay_file(Path(task))
    print(
        f"replay in MuJoCo (apo replay {task}): states {' '.join(res.states_reached)}; "
        f"{res.verdict}",
        file=file,
    )


def _run(args: argparse.Namespace, outs: OutputSet, worker: PlotWorker | None) -> dict[str, Path]:
    from apo.cli.analyze import print_result
    from apo.recognition import recognize_frames
    from apo.recognition.pipeline import TRACKED_FLOOR_SHARE

    dem = demonstration_from_args(args, outs)
    tracked = bool(getattr(args, "from_frames", False))
    G, E = _write_models(dem, outs)
    rec = recognize_frames(
        G,
        E,
        dem.times,
        dem.X_EG,
        units="mm",
        models=(
            model_ref_as(outs.path("grasped.stl"), outs.final("grasped.stl"), outs.given, G.name),
            model_ref_as(
                outs.path("environment.stl"), outs.final("environment.stl"), outs.given, E.name
            ),
        ),
        source=dem.source,
        floor_share=TRACKED_FLOOR_SHARE if tracked else None,
    )
    return write_recognition(
        outs,
        rec,
        plot=not args.no_plot,
        title=f"DOF indices: {dem.source}",
        worker=worker,
        report=None if args.no_report else report_maker(rec, G, E, dem.X_EG, []),
        on_task=partial(print_result, rec, as_json=args.json),  # before the plot is waited for
    )
