"""``apo analyze DEMO``: recognise a demonstration into ``task.json``, a table and a plot."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from apo.constants import UNITS
from apo.errors import InputFormatError
from apo.outputs import OutputSet
from apo.outputs import atomic_file as atomic_path
from apo.report.writer import (
    PlotWorker,
    TaskJson,
    frames_csv,
    model_ref,
    report_maker,
    sha256_of,
    task_document,
    write_recognition,
)

if TYPE_CHECKING:
    from apo.geometry import Polyhedron
    from apo.recognition import Recognition

# the names below were defined here before the library's apo.report.writer / apo.outputs
__all__ = [
    "PlotWorker",
    "atomic_path",
    "frames_csv",
    "model_ref",
    "outputs_part",
    "print_result",
    "print_written",
    "register",
    "report",
    "report_maker",
    "run",
    "sha256_of",
]

#: Inputs with at least this many frames get a progress bar (on stderr).
PROGRESS_MIN_FRAMES = 500

_UNITS = ("mm", *(u for u in UNITS if u != "mm"))  # apo.constants.UNITS, mm first


def register(subparsers: Any) -> None:
    """Add the ``analyze`` sub-command."""
    p = subparsers.add_parser(
        "analyze",
        help="recognise a demonstration (.pose.list, CSV or frames folder) into task.json",
        description=(
            "Recognise a demonstration: contact states, DOF, transitions, sub-skills and "
            "critical transitions. Prints the Fig. 25-style table and writes task.json, "
            "frames.csv and report.html (and with --plot dof.png) to --out. DEMO may also "
            "be a frames folder (see docs/perception.md): it is tracked first (as by apo "
            "track, which needs --grasped and --environment), and the poses are written "
            "to --out as poses.csv."
        ),
    )
    p.add_argument(
        "demo",
        metavar="DEMO",
        help="a .pose.list file, a CSV of poses, or a frames folder (camera.json, rgb/, depth/)",
    )
    p.add_argument("--out", metavar="DIR", help="output folder (default: <DEMO stem>-task)")
    p.add_argument("--json", action="store_true", help="print task.json instead of the table")
    p.add_argument("--grasped", metavar="MODEL", help="grasped model file (CSV or frames input)")
    p.add_argument(
        "--environment", metavar="MODEL", help="environment model file (CSV or frames input)"
    )
    p.add_argument(
        "--units", choices=_UNITS, default=None, help="length unit of the input (default: mm)"
    )
    p.add_argument(
        "--threshold",
        type=float,
        metavar="D",
        help="contact distance threshold in --units (default: scale-aware, and at least "
        "3.5 standard deviations of the pose noise)",
    )
    p.add_argument(
        "--noise",
        metavar="S[,DEG]",
        help="pose noise per axis: position standard deviation in --units and rotation in "
        "degrees (one number: both; default: estimated from the poses)",
    )
    p.add_argument(
        "--plot",
        dest="plot",
        action="store_true",
        default=False,
        help="also write dof.png, the DOF indices over time (matplotlib; report.html has the "
        "same timeline, interactive)",
    )
    p.add_argument(
        "--no-plot",
        dest="plot",
        action="store_false",
        help="do not write dof.png (the default; kept for scripts written before --plot)",
    )
    p.add_argument("--no-report", action="store_true", help="do not write report.html (apo report)")
    p.add_argument(
        "--jobs",
        type=_jobs,
        default=None,
        metavar="N",
        help="processes for the contact search and pose correction of long demonstrations "
        "(default: auto, the available cores; 1: one process; the results are the same)",
    )
    from apo.cli.track import add_tracking_options

    add_tracking_options(p)
    p.set_defaults(func=run)


def _jobs(text: str) -> int | None:
    """``--jobs``: a positive integer, or ``auto``."""
    if text.strip().lower() == "auto":
        return None
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer or auto, got {text!r}")
    return value


def parse_noise(text: str | None, unit: float) -> tuple[float, float] | None:
    """Parse ``--noise S`` or ``--noise S,DEG`` into (metres, radians) per axis."""
    if text is None:
        return None
    parts = text.split(",")
    try:
        vals = [float(v) for v in parts]
    except ValueError:
        vals = []
    if len(vals) not in (1, 2) or not all(math.isfinite(v) and v >= 0 for v in vals):
        raise InputFormatError(f"--noise: expected S or S,DEG (non-negative numbers), got {text!r}")
    pos, deg = vals[0], vals[-1]
    return pos * unit, math.radians(deg)


#: The progress bar appears once the work has taken this long (s): a fast run shows none.
PROGRESS_DELAY = 0.5

#: Least time between two drawings of the progress bar (s), as tqdm's ``mininterval``.
PROGRESS_INTERVAL = 0.1


def progress_bar(n: int, desc: str) -> tuple[Callable[[int, int], None] | None, Callable[[], None]]:
    """Return ``(progress, close)`` for a progress bar on stderr, or ``(None, noop)`` if short.

    The bar (:class:`ProgressBar`) is drawn from the first update after ``PROGRESS_DELAY``
    seconds, so a run that is over sooner prints nothing.
    """
    if n < PROGRESS_MIN_FRAMES:
        return None, lambda: None
    bar = ProgressBar(n, desc, sys.stderr, delay=PROGRESS_DELAY)
    return bar.update, bar.close


class ProgressBar:
    """A one-line progress bar on a text stream, redrawn in place and wiped at the end.

    Drawn as tqdm draws it: ``contacts:  47%|████▋     | 14080/29930 [00:01<00:01,
    10558.92frame/s]``. Not tqdm itself: importing it (with the ``multiprocessing``,
    ``email``, ``logging`` and ``importlib.metadata`` it loads) took 30 ms of CPU and
    5.5 MB of resident memory, a fixed cost that only long demonstrations paid
    (docs/recognition.md, "Session 7: memory").
    """

    def __init__(self, total: int, desc: str, file: Any, *, delay: float = 0.0) -> None:
        import time

        self.clock = time.monotonic
        self.total, self.desc, self.file = max(1, int(total)), desc, file
        self.start = self.clock()
        self.delay, self.drawn_at, self.width = delay, -1.0, 0

    def update(self, done: int, _total: int = 0) -> None:
        """Show ``done`` of the frames (drawn at most every ``PROGRESS_INTERVAL`` s)."""
        now = self.clock()
        if now - self.start < self.delay or now - self.drawn_at < PROGRESS_INTERVAL:
            return
        self.drawn_at = now
        line = self.line(min(int(done), self.total), now - self.start)
        self.file.write("\r" + line + " " * max(0, self.width - len(line)))
        self.file.flush()
        self.width = len(line)

    def line(self, done: int, elapsed: float) -> str:
        """Return the bar's text after ``done`` frames and ``elapsed`` seconds."""
        frac = done / self.total
        cells = frac * 10
        full = int(cells)
        bar = "\u2588" * full
        if full < 10:
            bar += " \u258f\u258e\u258d\u258c\u258b\u258a\u2589"[int((cells - full) * 8)]
        rate = done / elapsed if elapsed > 0 else 0.0
        left = _clock((self.total - done) / rate) if rate > 0 else "?"
        return (
            f"{self.desc}: {frac * 100:3.0f}%|{bar:<10}| {done}/{self.total} "
            f"[{_clock(elapsed)}<{left}, {rate:.2f}frame/s]"
        )

    def close(self) -> None:
        """Wipe the bar (if it was drawn)."""
        if self.width:
            self.file.write("\r" + " " * self.width + "\r")
            self.file.flush()
            self.width = 0


def _clock(seconds: float) -> str:
    """``mm:ss`` (``h:mm:ss`` from an hour), as tqdm writes times."""
    m, s = divmod(int(seconds), 60)
    h, m = divmod(m, 60)
    return f"{h:d}:{m:02d}:{s:02d}" if h else f"{m:02d}:{s:02d}"


def report(rec: Recognition, written: dict[str, Path], *, as_json: bool) -> None:
    """Print the table (or the JSON) and where the outputs went."""
    print_result(rec, as_json=as_json)
    print_written(written)


def print_result(
    rec: Recognition,
    task_json: TaskJson | None = None,
    *,
    as_json: bool,
    task_text: str | None = None,
) -> None:
    """Print the Fig. 25-style table and a summary, or ``task.json``.

    With ``as_json``: the written ``task_json`` (copied a chunk at a time), else
    ``task_text`` if given, else the task serialised here.
    """
    if as_json:
        if task_json is not None:
            sys.stdout.flush()
            for chunk in task_json.text_chunks():
                sys.stdout.write(chunk)
            sys.stdout.flush()
            return
        text = task_text if task_text is not None else task_document(rec)[1]
        print(text, end="", flush=True)
        return
    from apo.report.table import render_table

    print(render_table(rec.task))
    failed = int((~rec.converged).sum())
    n = len(rec.converged)
    print(
        f"{n} frames, {len(rec.task.states)} states, {len(rec.task.transitions)} transitions; "
        f"pose correction failed at {failed} frame(s); {int(rec.repaired.sum())} frame(s) "
        f"repaired",
        flush=True,
    )


def print_written(written: dict[str, Path]) -> None:
    """Print ``wrote <what>: <path>`` per output file."""
    for k, p in written.items():
        print(f"wrote {k}: {p}")


def outputs_part(rec: Recognition) -> Recognition:
    """Return ``rec`` without what no output of ``apo analyze`` reads.

    The segmentation's costs (8 bytes a frame per analysed candidate), the candidates, the
    observed states, the candidates' keys and feasible transitions (a noisy demonstration
    shows more states the longer it is, each with its elements and touching set) are
    dropped before the outputs are written, where a long run peaks (docs/recognition.md,
    "Session 7: memory", "Session 8"); the task, the per-frame
    arrays and the poses stay.
    """
    from dataclasses import replace

    import numpy as np

    empty = np.zeros((len(rec.costs), 0))
    return replace(rec, costs=empty, cost_columns=np.zeros(0, dtype=np.int64), candidates=[],
                   observed_states=[], keys=[], feasible=np.zeros((0, 0), dtype=bool))  # fmt: skip


def _warn_scale(
    G: Polyhedron,
    E: Polyhedron,
    X_EG: Any,
    units: str,
    threshold: float | None,
    paths: tuple[Path, Path],
) -> None:
    """Print a warning if the poses do not fit the models' size (exit status unchanged)."""
    from apo.io.meshes import MESH_SUFFIXES
    from apo.io.plausibility import scale_warnings

    meshes = any(MESH_SUFFIXES.get(p.suffix.lower()) != "step" for p in paths)
    for line in scale_warnings(
        G, E, X_EG, units=units, threshold=threshold, models_follow_units=meshes
    ):
        print(f"apo analyze: warning: {line}", file=sys.stderr)


def _load_models(
    demo_path: Path, grasped: str | None, environment: str | None, units: str | None, dem: Any
) -> tuple[Polyhedron, Polyhedron, Path, Path]:
    from apo.cli import warnings_to_stderr
    from apo.io.meshes import load_polyhedron

    paths: list[Path] = []
    for given, attr, flag in (
        (grasped, "grasped_path", "--grasped"),
        (environment, "environment_path", "--environment"),
    ):
        p = given or getattr(dem, attr, None)
        if p is None:
            raise InputFormatError(f"{demo_path}: no {flag[2:]} model: pass {flag} MODEL")
        p = Path(p)  # paths from a .pose.list are already resolved against its folder
        if not p.exists():
            raise InputFormatError(f"{demo_path}: {flag[2:]} model file not found: {p}")
        paths.append(p)
    mu = units or getattr(dem, "model_units", None) or getattr(dem, "units", None) or "mm"
    with warnings_to_stderr("apo analyze"):
        G = load_polyhedron(paths[0], units=mu)
        E = load_polyhedron(paths[1], units=mu)
    return G, E, paths[0], paths[1]


#: Pose files from this size (bytes; about 700 frames) are read in a forked child while the
#: stages are imported (:func:`_read_inputs`). Below it, reading the file and the models costs
#: about as much as the fork and the pages it copies (72 M instructions of the 41 frames'
#: 1,529 M were moved off this process, against some 2,600 more page faults here).
READ_IN_CHILD_BYTES = 100_000


def _read_inputs(
    args: argparse.Namespace, demo: Path
) -> tuple[Any, Polyhedron, Polyhedron, Path, Path]:
    """Read the pose file and its models: ``(poses, G, E, G's path, E's path)``.

    A pose file of ``READ_IN_CHILD_BYTES`` or more (a long demonstration) is read in a
    forked child where that is possible (:func:`apo.workers.can_fork`, ``--jobs`` not 1),
    while this process imports the recognition stages (:func:`_import_stages`); the child
    sends back the poses as a plain namespace (``times``, ``X_EG``, ``units``: the reader's
    module is then never imported here) and the models, the same numbers.
    """
    from apo.workers import can_fork, run_parts

    read = partial(_read_poses_and_models, args, demo)
    if args.jobs == 1 or demo.stat().st_size < READ_IN_CHILD_BYTES or not can_fork():
        return read()
    parts: list[Callable[[], Any]] = [partial(_import_stages, args), read]
    got: tuple[Any, Polyhedron, Polyhedron, Path, Path] = run_parts(parts)[1]
    return got


def _read_poses_and_models(
    args: argparse.Namespace, demo: Path
) -> tuple[Any, Polyhedron, Polyhedron, Path, Path]:
    """Read a pose file and its models; the poses as ``times``, ``X_EG`` and ``units``."""
    from types import SimpleNamespace

    from apo.cli import warnings_to_stderr
    from apo.io import poses

    with warnings_to_stderr("apo analyze"):
        dem = poses.load_demonstration(
            demo,
            units=args.units,
            grasped=args.grasped,
            environment=args.environment,
            camera_poses=False,  # not needed: X_EG only
        )
    G, E, gp, ep = _load_models(demo, args.grasped, args.environment, args.units, dem)
    plain = SimpleNamespace(times=dem.times, X_EG=dem.X_EG, units=getattr(dem, "units", None))
    return plain, G, E, gp, ep


def _import_stages(args: argparse.Namespace) -> None:
    """Import the modules recognition and the outputs will use (while a child reads)."""
    import highspy  # noqa: F401 - the DOF analyses' LPs

    import apo.io.plausibility
    import apo.recognition.pipeline

    if not args.no_report:
        import apo.report.html
        import apo.report.sources  # noqa: F401


def run(args: argparse.Namespace) -> int:
    """Run ``apo analyze``; return the exit code."""
    demo = Path(args.demo)
    if not demo.is_file() and not demo.is_dir():
        raise InputFormatError(f"{demo}: file not found")
    out = Path(args.out) if args.out else Path(demo.name.split(".")[0] + "-task")
    worker = PlotWorker() if args.plot else None
    try:
        with OutputSet(out, label="--out") as outs:  # checked and locked before the work
            written = _run(args, demo, outs, worker)
    finally:
        if worker is not None:
            worker.close()
    print_written(written)
    return 0


def _run(
    args: argparse.Namespace, demo: Path, outs: OutputSet, worker: PlotWorker | None
) -> dict[str, Path]:
    out = outs.given
    floor_share = None
    if demo.is_dir():  # a frames folder: track, then recognise the tracked poses
        from apo.cli.track import demonstration_from_frames
        from apo.recognition.pipeline import TRACKED_FLOOR_SHARE

        floor_share = TRACKED_FLOOR_SHARE
        G, E, gp, ep = _load_models(demo, args.grasped, args.environment, args.units, None)
        dem: Any = demonstration_from_frames(args, demo, gp, ep, outs)
    else:
        from apo.cli.track import reject_tracking_options

        reject_tracking_options(args, demo)
        dem, G, E, gp, ep = _read_inputs(args, demo)
    units = args.units or getattr(dem, "units", None) or "mm"
    from apo.task import UNITS

    threshold = None if args.threshold is None else args.threshold * UNITS[units]
    if threshold is not None and not threshold > 0:
        raise InputFormatError(f"--threshold must be positive, got {args.threshold}")
    noise = parse_noise(args.noise, UNITS[units])
    _warn_scale(G, E, dem.X_EG, units, threshold, (gp, ep))
    from apo.recognition import recognize_frames

    progress, close = progress_bar(len(dem.X_EG), "contacts")
    try:
        rec = recognize_frames(
            G,
            E,
            dem.times,
            dem.X_EG,
            threshold=threshold,
            noise=noise,
            floor_share=floor_share,
            progress=progress,
            units=units,
            models=(model_ref(gp, out), model_ref(ep, out)),
            source=demo.name,
            jobs=args.jobs,
            keep_costs=False,  # no output reads them (outputs_part)
        )
    finally:
        close()
    rec = outputs_part(rec)
    return write_recognition(
        outs,
        rec,
        plot=args.plot,
        title=f"DOF indices: {demo.name}",
        worker=worker,
        report=None if args.no_report else report_maker(rec, G, E, dem.X_EG, [demo]),
        on_task=partial(print_result, rec, as_json=args.json),  # before the plot is waited for
        jobs=args.jobs,
    )
