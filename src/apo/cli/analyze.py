"""``apo analyze DEMO``: recognise a demonstration into ``task.json``, a table and a plot."""

from __future__ import annotations

import argparse
import hashlib
import importlib
import json
import os
import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from apo.errors import InputFormatError

if TYPE_CHECKING:
    from apo.geometry import Polyhedron
    from apo.recognition import Recognition
    from apo.task import ModelRef

#: Inputs with at least this many frames get a progress bar (on stderr).
PROGRESS_MIN_FRAMES = 500

_UNITS = ("mm", "cm", "m", "in")


def register(subparsers: Any) -> None:
    """Add the ``analyze`` sub-command."""
    p = subparsers.add_parser(
        "analyze",
        help="recognise a demonstration (.pose.list, CSV or frames folder) into task.json",
        description=(
            "Recognise a demonstration: contact states, DOF, transitions, sub-skills and "
            "critical transitions. Prints the Fig. 25-style table and writes task.json, "
            "frames.csv and dof.png to --out. DEMO may also be a frames folder (see "
            "docs/perception.md): it is tracked first (as by apo track, which needs "
            "--grasped and --environment), and the poses are written to --out as poses.csv."
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
        help="contact distance threshold in --units (default: scale-aware)",
    )
    p.add_argument("--no-plot", action="store_true", help="do not write dof.png")
    p.add_argument("--no-report", action="store_true", help="do not write report.html (apo report)")
    from apo.cli.track import add_tracking_options

    add_tracking_options(p)
    p.set_defaults(func=run)


def sha256_of(path: str | Path) -> str:
    """Return the hex SHA-256 of a file's content."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 16), b""):
            h.update(chunk)
    return h.hexdigest()


def model_ref(path: str | Path, out_dir: Path, name: str = "") -> ModelRef:
    """Return a ModelRef: path relative to ``out_dir`` when possible, and content hash."""
    from apo.task import ModelRef

    p = Path(path).resolve()
    try:
        rel = os.path.relpath(p, out_dir.resolve())
    except ValueError:  # different drives
        rel = str(p)
    return ModelRef(path=rel, sha256=sha256_of(p), name=name or p.name)


@contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it over ``path`` on success."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


class PlotWorker:
    """Draw ``dof.png`` in a forked process that imports matplotlib while the parent works.

    On a machine with two cores this hides matplotlib's import time (about a third of a
    second) behind the recognition. Where ``os.fork`` is missing, or ``APO_PLOT_WORKER=0``,
    or the worker fails, the plot is drawn in-process instead.
    """

    def __init__(self) -> None:
        self.pid: int | None = None
        self.wfd: int | None = None
        if not hasattr(os, "fork") or os.environ.get("APO_PLOT_WORKER", "1") == "0":
            return
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:  # pragma: no cover - the child
            os.close(w)
            code = 1
            try:
                import pickle

                from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: F401
                from matplotlib.figure import Figure  # noqa: F401

                from apo.report.plot import plot_dof  # and apo.task, for unpickling

                with os.fdopen(r, "rb") as fh:
                    data = fh.read()
                code = 0
                if data:
                    task, times, path, title = pickle.loads(data)
                    with atomic_path(Path(path)) as tmp:
                        plot_dof(task, tmp, times=times, title=title)
            except BaseException:
                code = 1
            finally:
                os._exit(code)
        os.close(r)
        self.pid, self.wfd = pid, w

    def plot(self, rec: Recognition, path: Path, title: str | None) -> bool:
        """Hand the plot to the worker and wait for it; return True if it wrote ``path``."""
        return self.submit(rec, path, title) and self.result(path)

    def submit(self, rec: Recognition, path: Path, title: str | None) -> bool:
        """Hand the plot to the worker without waiting; False if there is no worker."""
        if self.pid is None or self.wfd is None:
            return False
        import pickle

        try:
            with os.fdopen(self.wfd, "wb") as fh:
                self.wfd = None
                fh.write(pickle.dumps((rec.task, rec.times, str(path), title)))
        except OSError:
            pass
        return True

    def result(self, path: Path) -> bool:
        """Wait for a submitted plot; return True if the worker wrote ``path``."""
        return self._wait() and path.exists()

    def close(self) -> None:
        """Release the worker without a plot."""
        if self.wfd is not None:
            os.close(self.wfd)
            self.wfd = None
        self._wait()

    def _wait(self) -> bool:
        if self.pid is None:
            return False
        _, status = os.waitpid(self.pid, 0)
        self.pid = None
        return os.waitstatus_to_exitcode(status) == 0


def write_outputs(
    rec: Recognition,
    out_dir: Path,
    *,
    plot: bool = True,
    title: str | None = None,
    worker: PlotWorker | None = None,
    report: Callable[[Path], object] | None = None,
) -> dict[str, Path]:
    """Write ``task.json``, ``frames.csv`` (``dof.png``, ``report.html``) to ``out_dir`` atomically.

    ``report`` writes ``report.html`` to the path it is given (:func:`report_maker`).

    Each file is written to a temporary file in ``out_dir`` and renamed into place, so an
    interrupted run never leaves a half-written file. Returns the paths written.
    """
    from apo.task import task_to_dict

    out_dir.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    png = out_dir / "dof.png"
    want_plot = plot and bool(rec.task.states)
    # the worker draws while this process writes the other files
    submitted = want_plot and worker is not None and worker.submit(rec, png, title)
    data = task_to_dict(rec.task)
    target = out_dir / "task.json"
    with atomic_path(target) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    written["task"] = target
    frames = out_dir / "frames.csv"
    with atomic_path(frames) as tmp:
        tmp.write_text(frames_csv(rec), encoding="utf-8")
    written["frames"] = frames
    if want_plot:
        if not (submitted and worker is not None and worker.result(png)):
            from apo.report.plot import plot_dof

            with atomic_path(png) as tmp:
                plot_dof(rec.task, tmp, times=rec.times, title=title)
        written["plot"] = png
    if report is not None:
        html = out_dir / "report.html"
        with atomic_path(html) as tmp:
            report(tmp)
        written["report"] = html
    return written


def report_maker(
    rec: Recognition, G: Polyhedron, E: Polyhedron, X_observed: Any, inputs: list[Path]
) -> Callable[[Path], int]:
    """Return a callable that writes ``report.html`` of ``rec`` to a path (inputs: to hash)."""

    def write(path: Path) -> int:
        from apo.report.html import write_report
        from apo.report.sources import file_entry, recognition_report

        files = [file_entry("demonstration", p) for p in inputs if p.is_file()]
        doc = recognition_report(rec, grasped=G, environment=E, X_observed=X_observed, files=files)
        return write_report(path, doc)

    return write


def frames_csv(rec: Recognition) -> str:
    """Per-frame diagnostics as CSV text (lengths in the task's units)."""
    from apo.task import UNITS

    k = 1.0 / UNITS[rec.task.units]
    u = rec.task.units
    lines = [
        f"frame,time_s,state,observed,residual_before_{u},residual_after_{u},converged,repaired"
    ]
    for i, sid in enumerate(rec.state_of_frame):
        lines.append(
            f"{i},{rec.times[i]:.6f},{sid},{int(rec.observed[i])},"
            f"{rec.residual_before[i] * k:.6g},{rec.residual_after[i] * k:.6g},"
            f"{int(rec.converged[i])},{int(rec.repaired[i])}"
        )
    return "\n".join(lines) + "\n"


def progress_bar(n: int, desc: str) -> tuple[Callable[[int, int], None] | None, Callable[[], None]]:
    """Return ``(progress, close)`` for a tqdm bar on stderr, or ``(None, noop)`` if short."""
    if n < PROGRESS_MIN_FRAMES:
        return None, lambda: None
    from tqdm import tqdm

    bar = tqdm(total=n, desc=desc, unit="frame", file=sys.stderr, leave=False)

    def update(done: int, total: int) -> None:
        bar.update(done - bar.n)

    return update, bar.close


def report(rec: Recognition, written: dict[str, Path], *, as_json: bool) -> None:
    """Print the table (or the JSON) and where the outputs went."""
    if as_json:
        from apo.task import task_to_dict

        print(json.dumps(task_to_dict(rec.task), indent=2))
        return
    from apo.report.table import render_table

    print(render_table(rec.task))
    failed = int((~rec.converged).sum())
    n = len(rec.converged)
    print(
        f"{n} frames, {len(rec.task.states)} states, {len(rec.task.transitions)} transitions; "
        f"pose correction failed at {failed} frame(s); {int(rec.repaired.sum())} frame(s) "
        f"repaired"
    )
    for k, p in written.items():
        print(f"wrote {k}: {p}")


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


def run(args: argparse.Namespace) -> int:
    """Run ``apo analyze``; return the exit code."""
    demo = Path(args.demo)
    if not demo.is_file() and not demo.is_dir():
        raise InputFormatError(f"{demo}: file not found")
    worker = None if args.no_plot else PlotWorker()
    try:
        return _run(args, demo, worker)
    finally:
        if worker is not None:
            worker.close()


def _run(args: argparse.Namespace, demo: Path, worker: PlotWorker | None) -> int:
    poses = importlib.import_module("apo.io.poses")
    from apo.recognition import recognize_frames

    out = Path(args.out) if args.out else Path(demo.name.split(".")[0] + "-task")
    if demo.is_dir():  # a frames folder: track, then recognise the tracked poses
        from apo.cli.track import demonstration_from_frames

        G, E, gp, ep = _load_models(demo, args.grasped, args.environment, args.units, None)
        dem: Any = demonstration_from_frames(args, demo, gp, ep, out)
    else:
        from apo.cli.track import reject_tracking_options

        reject_tracking_options(args, demo)
        dem = poses.load_demonstration(
            demo, units=args.units, grasped=args.grasped, environment=args.environment
        )
        G, E, gp, ep = _load_models(demo, args.grasped, args.environment, args.units, dem)
    units = args.units or getattr(dem, "units", None) or "mm"
    from apo.task import UNITS

    threshold = None if args.threshold is None else args.threshold * UNITS[units]
    if threshold is not None and not threshold > 0:
        raise InputFormatError(f"--threshold must be positive, got {args.threshold}")
    progress, close = progress_bar(len(dem.X_EG), "contacts")
    try:
        rec = recognize_frames(
            G,
            E,
            dem.times,
            dem.X_EG,
            threshold=threshold,
            progress=progress,
            units=units,
            models=(model_ref(gp, out), model_ref(ep, out)),
            source=demo.name,
        )
    finally:
        close()
    written = write_outputs(
        rec,
        out,
        plot=not args.no_plot,
        title=f"DOF indices: {demo.name}",
        worker=worker,
        report=None if args.no_report else report_maker(rec, G, E, dem.X_EG, [demo]),
    )
    report(rec, written, as_json=args.json)
    return 0
