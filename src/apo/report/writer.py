"""The files of a recognised demonstration, written into an :class:`~apo.outputs.OutputSet`.

``task.json`` (:func:`apo.task.task_to_dict`), ``frames.csv`` (:func:`frames_csv`), ``dof.png``
(:func:`apo.report.plot.plot_dof`, drawn by a :class:`PlotWorker` while the rest is written)
and ``report.html`` (a callable, e.g. :func:`report_maker`). ``apo analyze`` and ``apo demo``
call :func:`write_recognition`; any program using the library can do the same::

    with OutputSet("out") as outs:
        rec = recognize_frames(G, E, times, X_EG, units="mm")
        written = write_recognition(outs, rec)
"""

from __future__ import annotations

import gc
import os
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from apo.outputs import sha256_file as sha256_of
from apo.workers import can_fork, run_parts

if TYPE_CHECKING:
    from apo.geometry import Polyhedron
    from apo.outputs import OutputSet
    from apo.recognition import Recognition
    from apo.task import ModelRef

ReportWriter = Callable[[Path, Mapping[str, Any], "str | TaskJson"], object]
"""``write(path, task_doc, task_json)``: writes ``report.html`` of a recognition to ``path``.

``task_json`` is the text of ``task.json`` or, from :func:`write_recognition`, the written
file (:class:`TaskJson`; ``task_doc`` then holds its top-level fields only, not the states).
"""

__all__ = [
    "PlotWorker",
    "ReportWriter",
    "TaskJson",
    "frames_csv",
    "frames_csv_chunks",
    "gc_paused",
    "model_ref",
    "model_ref_as",
    "report_maker",
    "sha256_of",
    "task_document",
    "write_recognition",
]


def model_ref(path: str | Path, out_dir: Path, name: str = "") -> ModelRef:
    """Return a ModelRef: path relative to ``out_dir`` when possible, and content hash."""
    from apo.task import ModelRef

    p = Path(path).resolve()
    try:
        rel = os.path.relpath(p, out_dir.resolve())
    except ValueError:  # different drives
        rel = str(p)
    return ModelRef(path=rel, sha256=sha256_of(p), name=name or p.name)


def model_ref_as(content: str | Path, path: str | Path, out_dir: Path, name: str = "") -> ModelRef:
    """Like :func:`model_ref` for a file that is at ``content`` now and will be at ``path``.

    For models written into an :class:`~apo.outputs.OutputSet`: hashed where they are written,
    referred to where they will be once the set is committed.
    """
    from apo.task import ModelRef

    p = Path(os.path.abspath(path))
    try:
        rel = os.path.relpath(p, Path(os.path.abspath(out_dir)))
    except ValueError:  # different drives
        rel = str(p)
    return ModelRef(path=rel, sha256=sha256_of(content), name=name or p.name)


class PlotWorker:
    """Draw ``dof.png`` in a forked process that imports matplotlib while the parent works.

    On a machine with two cores this hides matplotlib's import time (about a third of a
    second) behind the recognition. Where ``os.fork`` is missing, or ``APO_PLOT_WORKER=0``,
    or the worker fails, the plot is drawn in-process instead. The worker writes the path it
    is given (inside an output set's private folder), with the process's umask.
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
            os._exit(_plot_child(r))
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


def _plot_child(r: int) -> int:  # pragma: no cover - runs in the forked child
    """Import matplotlib, wait for a pickled plot request on ``r``, draw it; the exit code."""
    try:
        import pickle

        from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: F401
        from matplotlib.figure import Figure  # noqa: F401

        from apo.report.plot import plot_dof  # and apo.task, for unpickling

        with os.fdopen(r, "rb") as fh:
            data = fh.read()
        if data:
            task, times, path, title = pickle.loads(data)
            plot_dof(task, path, times=times, title=title)  # redrawn by the parent on failure
        return 0
    except BaseException:
        return 1


def _pose_columns(X: np.ndarray, k: float) -> np.ndarray:
    """``(N, 7)`` array: position times ``k``, quaternion ``(qw, qx, qy, qz)`` with qw >= 0."""
    from apo.spatial import quaternions_from_matrices

    return np.concatenate([X[:, :3, 3] * k, quaternions_from_matrices(X[:, :3, :3])], axis=1)


_POSE_FMT = ",{:.9g}" * 14


def frames_csv(rec: Recognition) -> str:
    """Per-frame diagnostics as CSV text (lengths in the task's units).

    Columns: ``frame, time_s, state, observed, residual_before_<u>, residual_after_<u>,
    converged, repaired``, then, when the recognition keeps its poses, the observed and the
    corrected pose ``obs_x_<u>, obs_y_<u>, obs_z_<u>, obs_qw, obs_qx, obs_qy, obs_qz,
    cor_x_<u> .. cor_qz`` (quaternions wxyz, ``qw >= 0``; ``<u>`` = the task's units).
    The text of :func:`frames_csv_chunks` joined.
    """
    return "".join(frames_csv_chunks(rec))


#: Frames per chunk of ``frames.csv`` formatted at once (:func:`frames_csv_chunks`).
CSV_BLOCK_FRAMES = 1024


def frames_csv_chunks(rec: Recognition, block: int = CSV_BLOCK_FRAMES) -> Iterator[str]:
    """``frames.csv`` (:func:`frames_csv`) as text chunks: the header, then ``block`` frames each.

    Only one block's rows are formatted at a time (plain floats: numpy scalars format
    slowly), so writing the file takes working memory of one block, not of the file.
    """
    from apo.task import UNITS

    u = rec.task.units
    k = 1.0 / UNITS[u]
    n = len(rec.state_of_frame)
    head = f"frame,time_s,state,observed,residual_before_{u},residual_after_{u},converged,repaired"
    Xo = np.asarray(getattr(rec, "X_observed", np.zeros((0, 4, 4))), dtype=np.float64)
    Xc = np.asarray(getattr(rec, "X_corrected", np.zeros((0, 4, 4))), dtype=np.float64)
    poses = n > 0 and Xo.shape == (n, 4, 4) and Xc.shape == (n, 4, 4)
    fmt = "{},{:.6f},{},{},{:.6g},{:.6g},{},{}"
    if poses:
        for p in ("obs", "cor"):
            head += "".join(f",{p}_{c}_{u}" for c in "xyz") + "".join(f",{p}_q{c}" for c in "wxyz")
        fmt += _POSE_FMT
    yield head + "\n"
    for a in range(0, n, max(1, block)):
        rows = slice(a, min(n, a + max(1, block)))
        obs, conv, rep = (
            np.asarray(v, dtype=np.int64)[rows].tolist()
            for v in (rec.observed, rec.converged, rec.repaired)
        )
        before, after = ((np.asarray(v, dtype=np.float64)[rows] * k).tolist() for v in
                         (rec.residual_before, rec.residual_after))  # fmt: skip
        times = np.asarray(rec.times, dtype=np.float64)[rows].tolist()
        cols: list[Any] = [range(rows.start, rows.stop), times, rec.state_of_frame[rows], obs,
                           before, after, conv, rep]  # fmt: skip
        if poses:  # one format call per line, on plain floats
            both = np.concatenate([_pose_columns(Xo[rows], k), _pose_columns(Xc[rows], k)], axis=1)
            cols += list(zip(*both.tolist(), strict=True))
        yield "\n".join(map(fmt.format, *cols)) + "\n"


def task_document(rec: Recognition) -> tuple[dict[str, Any], str]:
    """Return ``task.json`` of ``rec`` as a document and as its text (serialised once).

    The text is :func:`apo.outputs.json_text` of the document, two levels deep: one line
    per state, transition, rejected run and graph entry (as fast as ``json.dumps`` without
    an indent, ten times faster than ``json.dumps(indent=2)``). Both are whole in memory:
    :func:`write_recognition` writes the file block by block instead
    (:func:`apo.task.task_json_chunks`).
    """
    from apo.outputs import json_text
    from apo.task import task_to_dict

    with gc_paused():
        doc = task_to_dict(rec.task)
        return doc, json_text(doc, depth=TASK_JSON_DEPTH)


#: Top-level fields of ``task.json`` that grow with the task (:attr:`TaskJson.head` lacks them).
_LONG_FIELDS = ("states", "transitions", "rejected", "graph")


class TaskJson:
    """A written ``task.json``: its top-level fields, and its text read back in chunks.

    What :func:`write_recognition` hands to ``--json`` printing and to ``report.html``
    instead of the whole text: the file is written once, block by block, and read back a
    chunk at a time (the page cache holds it), so no copy of a long task's text is ever in
    memory whole.
    """

    #: Bytes read at a time (two chunks are held at once while the report is written).
    CHUNK = 1 << 18

    def __init__(self, path: Path, head: Mapping[str, Any]) -> None:
        self.path = Path(path)
        self.head = {k: v for k, v in head.items() if k not in _LONG_FIELDS}

    def text_chunks(self) -> Iterator[str]:
        """Yield the file's text (UTF-8) in chunks."""
        with open(self.path, encoding="utf-8", newline="") as fh:
            while chunk := fh.read(self.CHUNK):
                yield chunk

    def stripped_chunks(self) -> Iterator[bytes]:
        """Yield the file's bytes without leading and trailing whitespace, in chunks."""
        with open(self.path, "rb") as fh:
            size = fh.seek(0, os.SEEK_END)
            start, end = _stripped_span(fh, size)
            fh.seek(start)
            left = end - start
            while left > 0:
                chunk = fh.read(min(self.CHUNK, left))
                if not chunk:
                    break
                left -= len(chunk)
                yield chunk


def _stripped_span(fh: Any, size: int) -> tuple[int, int]:
    """``(start, end)`` of the bytes of the open file ``fh`` without surrounding whitespace."""
    space = b" \t\n\r\x0b\x0c"
    end = size
    while end > 0:
        fh.seek(max(0, end - 64))
        tail = fh.read(end - max(0, end - 64))
        kept = tail.rstrip(space)
        end -= len(tail) - len(kept)
        if kept:
            break
    start = 0
    while start < end:
        fh.seek(start)
        head = fh.read(min(64, end - start))
        kept = head.lstrip(space)
        start += len(head) - len(kept)
        if kept:
            break
    return start, end


@contextmanager
def gc_paused() -> Iterator[None]:
    """Pause Python's cyclic garbage collector while building large acyclic outputs.

    The task document of 30,000 frames is a million small lists and dicts: each batch of
    new objects triggers a collection that walks every object alive (the recognition's
    too), which doubled the time of building and writing the outputs. Nothing built here
    holds a reference cycle; reference counting frees it as before. Re-enabled after
    (unless it was off already).
    """
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


#: Levels of ``task.json`` laid out one item per line (:func:`apo.outputs.json_text`).
TASK_JSON_DEPTH = 2


#: Tasks of this many states or more have ``task.json`` written by a forked child while the
#: parent writes ``frames.csv`` (:func:`write_recognition`): about 0.1 ms a state, so from
#: here on it outweighs the fork (2-5 ms).
TASK_IN_CHILD_STATES = 100


def write_recognition(
    outs: OutputSet,
    rec: Recognition,
    *,
    plot: bool = True,
    title: str | None = None,
    worker: PlotWorker | None = None,
    report: ReportWriter | None = None,
    task: tuple[dict[str, Any], str] | None = None,
    on_task: Callable[[TaskJson], object] | None = None,
    jobs: int | None = None,
) -> dict[str, Path]:
    """Write ``task.json``, ``frames.csv`` (``dof.png``, ``report.html``) into ``outs``.

    ``task.json`` is written block by block (:func:`apo.task.task_json_chunks`) unless
    ``task`` (:func:`task_document` of ``rec``) is given; ``on_task(task_json)`` is called
    once it is written (e.g. to print it), before the rest. ``report(path, task_doc,
    task_json)`` writes ``report.html`` to ``path`` given the written task (a
    :class:`TaskJson`, embedded as is; see :func:`report_maker`); ``worker`` draws the plot
    while this process writes the rest. A task of ``TASK_IN_CHILD_STATES`` states or more
    is written by a forked child while this process writes ``frames.csv`` (unless ``jobs``
    is 1; :func:`apo.workers.can_fork`), the same bytes. Returns ``{what: final path}``
    (``task``, ``frames``, ``plot``, ``report``); the files appear there when ``outs`` commits.
    """
    from apo.task import task_head, task_json_chunks

    written: dict[str, Path] = {}
    want_plot = plot and bool(rec.task.states)
    png = outs.path("dof.png")
    submitted = want_plot and worker is not None and worker.submit(rec, png, title)
    frames = partial(outs.write_chunks, "frames.csv", frames_csv_chunks(rec))
    frames_done: Path | None = None
    with gc_paused():
        if task is not None:
            written_task = TaskJson(outs.path("task.json"), task[0])
            written["task"] = outs.write_text("task.json", task[1])
        else:
            written_task = TaskJson(outs.path("task.json"), task_head(rec.task))
            chunks = task_json_chunks(rec.task, depth=TASK_JSON_DEPTH)
            write_task = partial(outs.write_chunks, "task.json", chunks)
            if jobs != 1 and len(rec.task.states) >= TASK_IN_CHILD_STATES and can_fork():
                # task.json in a forked child while this process writes frames.csv (and
                # makes the report's data)
                prepare = getattr(report, "prepare", None)
                mine = partial(
                    _then, frames, partial(prepare, written_task.head) if prepare else None
                )
                frames_done, written["task"] = run_parts([mine, write_task])
            else:
                written["task"] = write_task()
    if on_task is not None:
        on_task(written_task)
    with gc_paused():
        written["frames"] = frames() if frames_done is None else frames_done
    if want_plot:
        if not (submitted and worker is not None and worker.result(png)):
            from apo.report.plot import plot_dof

            plot_dof(rec.task, png, times=rec.times, title=title)
        written["plot"] = outs.final("dof.png")
    if report is not None:
        with gc_paused():
            report(outs.path("report.html"), written_task.head, written_task)
        written["report"] = outs.final("report.html")
    return written


def _then(first: Callable[[], Path], then: Callable[[], object] | None) -> Path:
    """``first()``, then ``then()`` if given; ``first``'s result."""
    out = first()
    if then is not None:
        then()
    return out


def report_maker(
    rec: Recognition, G: Polyhedron, E: Polyhedron, X_observed: Any, inputs: list[Path]
) -> ReportWriter:
    """Return a :data:`ReportWriter` for ``report.html`` of ``rec`` (inputs: files to hash).

    It has a ``prepare(doc)`` method: the page's data made ahead,
    for the ``doc`` it will be called with (:func:`write_recognition` calls it while a
    forked child writes ``task.json``).
    """
    return _ReportMaker(rec, G, E, X_observed, inputs)


class _ReportMaker:
    """The :data:`ReportWriter` of :func:`report_maker`."""

    def __init__(
        self, rec: Recognition, G: Polyhedron, E: Polyhedron, X_observed: Any, inputs: list[Path]
    ) -> None:
        self.args = (rec, G, E, X_observed, inputs)
        self.ready: tuple[Mapping[str, Any], dict[str, Any]] | None = None

    def _data(self, doc: Mapping[str, Any]) -> dict[str, Any]:
        from apo.report.sources import file_entry, recognition_report

        rec, G, E, X_observed, inputs = self.args
        files = [file_entry("demonstration", p) for p in inputs if p.is_file()]
        return recognition_report(
            rec, grasped=G, environment=E, X_observed=X_observed, files=files, doc=doc
        )

    def prepare(self, doc: Mapping[str, Any]) -> None:
        """Make the page's data for ``doc`` ahead of the call (plotly.js is copied then).

        A failure here is left to the call, which makes them again (and raises there).
        """
        try:
            self.ready = (doc, self._data(doc))
        except Exception:
            self.ready = None

    def __call__(self, path: Path, doc: Mapping[str, Any], task_json: str | TaskJson) -> int:
        from apo.report.html import write_report

        ready, self.ready = self.ready, None
        if ready is not None and ready[0] is doc:
            return write_report(path, ready[1], task_json=task_json)
        return write_report(path, self._data(doc), task_json=task_json)
