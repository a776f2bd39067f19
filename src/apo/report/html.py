"""The offline interactive report: one self-contained HTML file per recognised task.

The page is a static viewer shipped inside the package (``apo/report/viewer/``: an HTML
template, a stylesheet and a script) filled with the task's data as one JSON document, and
with the plotly.js bundle of the installed ``plotly`` package inlined: no CDN, no server,
every asset in the file. Writing it costs a read of the bundle and a :func:`json.dumps` of
the data; nothing is drawn in Python. The page itself draws, with plotly.js:

- a 3D replay of both objects (time slider, play button), the grasped object coloured by
  its contact state, the contact points with their separating normals (singular elements
  marked), the corrected pose beside the observed one, and further tracks (planned motion,
  simulated execution) where given;
- the DOF timeline (translation and rotation M, D, C, SM, SD, SC, restraining) with the
  state letters, linked to the slider;
- the state graph of the paper's Fig. 24/25 (eight numbers per state, arrows labelled with
  sub-skills and their directions, critical transitions marked, rejected runs crossed out
  with their reason);
- the tables of states, transitions and rejected runs, and the inputs.

Per-frame numbers travel as little-endian typed arrays in base64 (``{"dtype": "f4",
"shape": [n, 7], "b64": ...}``); a demonstration longer than :data:`MAX_REPLAY_FRAMES`
frames is decimated for the replay (every state keeps its first and last frame).
See ``docs/report.md``.
"""

from __future__ import annotations

import base64
import functools
import json
import mmap
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import numpy.typing as npt

from apo.arrays import unique
from apo.errors import ApoError
from apo.typing import BoolArray, FloatArray

if TYPE_CHECKING:
    from apo.geometry import Polyhedron
    from apo.task import TaskModel

__all__ = [
    "MAX_REPLAY_FRAMES",
    "FrameTrack",
    "MotionTrack",
    "pack_array",
    "plotly_js",
    "poses_to_rows",
    "read_report_data",
    "report_data",
    "report_html",
    "report_parts",
    "unpack_array",
    "write_report",
]


MAX_REPLAY_FRAMES = 6000
"""Frames of the replay at most; longer demonstrations are decimated (state ends kept)."""

SCHEMA = "apo.report/1"
"""Schema of the JSON document embedded in the page (``docs/report.md``)."""

_PLACEHOLDERS = ("__APO_TITLE__", "__APO_CSS__", "__APO_PLOTLY__", "__APO_DATA__", "__APO_JS__")


@dataclass(frozen=True)
class FrameTrack:
    """Per-frame data of the demonstration for the replay.

    Attributes
    ----------
    times : ndarray, shape (N,)
        Seconds.
    state_ids : sequence of str, length N
        Task state id of each frame.
    X_observed : ndarray, shape (N, 4, 4), metres, or None
        Observed poses of G in E.
    X_corrected : ndarray, shape (N, 4, 4), metres, or None
        Poses corrected so that the frame's contacts hold.
    residual_before, residual_after : ndarray, shape (N,), metres, or None
        Largest contact distance before and after the correction.
    converged, repaired : ndarray of bool, shape (N,), or None
    source : str
        Where the numbers came from (``"recognition"``, ``"frames.csv"``, ``"task states"``).
    """

    times: FloatArray
    state_ids: Sequence[str]
    X_observed: FloatArray | None = None
    X_corrected: FloatArray | None = None
    residual_before: FloatArray | None = None
    residual_after: FloatArray | None = None
    converged: BoolArray | None = None
    repaired: BoolArray | None = None
    source: str = "recognition"


@dataclass(frozen=True)
class MotionTrack:
    """A further replay track: a pose sequence of G in E with a label per sample.

    Attributes
    ----------
    name : str
        Shown in the track selector (``"planned motion"``, ``"simulated execution"``).
    kind : str
        ``"planned"`` or ``"executed"``.
    times : ndarray, shape (N,)
        Seconds.
    X_EG : ndarray, shape (N, 4, 4), metres
    labels : sequence of str, length N
        What each sample is (sub-skill, segment), shown beside the slider.
    note : str
        One line about the track (e.g. the replay's verdict).
    state_ids : sequence of str or None, length N, optional
        Task state the object is in at each sample (e.g. the primitive's ``from`` state);
        the page then shows that state's numbers and contacts.
    """

    name: str
    kind: str
    times: FloatArray
    X_EG: FloatArray
    labels: Sequence[str]
    note: str = ""
    state_ids: Sequence[str | None] = ()


def pack_array(a: npt.ArrayLike, dtype: str) -> dict[str, Any]:
    """Return ``{"dtype", "shape", "b64"}``: ``a`` as little-endian ``dtype`` bytes in base64.

    ``dtype`` is one of ``"f4"``, ``"f8"``, ``"u1"``, ``"u2"``, ``"u4"``, ``"i4"`` (the
    typed arrays of JavaScript).
    """
    arr = np.ascontiguousarray(np.asarray(a), dtype=np.dtype(dtype).newbyteorder("<"))
    return {
        "dtype": dtype,
        "shape": list(arr.shape),
        "b64": base64.b64encode(arr.data).decode("ascii"),  # the buffer itself: no copy
    }


def unpack_array(p: Mapping[str, Any]) -> npt.NDArray[Any]:
    """Inverse of :func:`pack_array`: the array of a ``{"dtype", "shape", "b64"}`` dict."""
    raw = base64.b64decode(p["b64"])
    dt = np.dtype(str(p["dtype"])).newbyteorder("<")
    return np.frombuffer(raw, dtype=dt).reshape([int(v) for v in p["shape"]])


def read_report_data(html: str) -> dict[str, Any]:
    """Return the JSON document embedded in a report page (for tests and tools)."""
    import re

    m = re.search(r'<script type="application/json" id="apo-data">(.*?)</script>', html, re.S)
    if m is None:
        raise ApoError("not an apo report: no embedded apo-data document")
    return dict(json.loads(m.group(1)))


def poses_to_rows(X: npt.ArrayLike, scale: float) -> FloatArray:
    """Return ``(N, 7)`` rows ``x y z qw qx qy qz`` of poses ``X`` (N, 4, 4), lengths * scale.

    Quaternions are unit with ``qw >= 0`` (``docs/conventions.md``).
    """
    from apo.spatial import quaternions_from_matrices

    X = np.asarray(X, dtype=np.float64).reshape(-1, 4, 4)
    rows = np.empty((X.shape[0], 7))
    rows[:, :3] = X[:, :3, 3] * scale
    if X.shape[0]:
        rows[:, 3:] = quaternions_from_matrices(X[:, :3, :3])
    return rows


def replay_indices(state_index: npt.ArrayLike, max_frames: int = MAX_REPLAY_FRAMES) -> Any:
    """Return the frame indices the replay keeps: all, or a regular subset with state ends.

    Every state run keeps its first and last frame, so no state disappears from the replay.
    """
    s = np.asarray(state_index)
    n = s.shape[0]
    if n <= max_frames:
        return np.arange(n)
    change = np.flatnonzero(np.diff(s) != 0)
    ends = np.concatenate([[0, n - 1], change, change + 1])
    budget = max(max_frames - ends.size, 2)
    regular = np.linspace(0, n - 1, budget).round().astype(np.int64)
    return unique(np.concatenate([regular, ends]))  # not np.unique: no numpy.ma import


def _mesh_data(poly: Polyhedron, scale: float) -> dict[str, Any]:
    """Triangles and feature edges of a model, vertices in the task's units."""
    tris = [np.asarray(t, dtype=np.int64).reshape(-1, 3) for t in poly.face_triangles]
    T = np.concatenate(tris) if tris else np.zeros((0, 3), dtype=np.int64)
    face_of = np.repeat(np.arange(len(tris)), [t.shape[0] for t in tris])
    return {
        "name": poly.name,
        "vertices": pack_array(np.asarray(poly.vertices) * scale, "f4"),
        "triangles": pack_array(T, "u4"),
        "triangle_face": pack_array(face_of, "u4"),
        "edges": pack_array(np.asarray(poly.edges).reshape(-1, 2), "u4"),
        "scale": float(poly.scale * scale),
    }


def _frames_data(track: FrameTrack, state_ids: list[str], scale: float) -> dict[str, Any]:
    """Per-frame arrays of the demonstration track (decimated where long)."""
    index = {sid: i for i, sid in enumerate(state_ids)}
    try:
        ids = track.state_ids  # no list of a Python int per frame on the way
        s = np.fromiter((index[sid] for sid in ids), dtype=np.int64, count=len(ids))
    except KeyError as exc:
        raise ApoError(f"per-frame data name state {exc.args[0]!r}, which the task lacks") from None
    keep = replay_indices(s)
    out: dict[str, Any] = {
        "n_frames": len(s),
        "source": track.source,
        "frame": pack_array(keep, "u4"),
        "t": pack_array(np.asarray(track.times, dtype=np.float64)[keep], "f8"),
        "state": pack_array(s[keep], "u2"),
    }
    for key, X in (("observed", track.X_observed), ("corrected", track.X_corrected)):
        if X is not None:
            out[key] = pack_array(_kept_pose_rows(np.asarray(X), keep, scale), "f4")
    for key, v in (
        ("residual_before", track.residual_before),
        ("residual_after", track.residual_after),
    ):
        if v is not None:
            out[key] = pack_array(np.asarray(v, dtype=np.float64)[keep] * scale, "f4")
    for key, b in (("converged", track.converged), ("repaired", track.repaired)):
        if b is not None:
            out[key] = pack_array(np.asarray(b, dtype=bool)[keep], "u1")
    return out


#: Kept frames whose pose rows are made at a time (:func:`_kept_pose_rows`).
POSE_ROWS_BLOCK = 2048


def _kept_pose_rows(X: FloatArray, keep: Any, scale: float) -> npt.NDArray[np.float32]:
    """``poses_to_rows(X[keep], scale)`` as little-endian float32, ``POSE_ROWS_BLOCK`` at a time.

    The same numbers (each row is its pose's alone); the working arrays of a block, not of
    every kept frame (a long demonstration keeps two frames a state, 12,000 at 6,000 states).
    """
    out = np.empty((len(keep), 7), dtype=np.dtype("f4").newbyteorder("<"))
    for a in range(0, len(keep), POSE_ROWS_BLOCK):
        out[a : a + POSE_ROWS_BLOCK] = poses_to_rows(X[keep[a : a + POSE_ROWS_BLOCK]], scale)
    return out


NO_STATE = 0xFFFF
"""Per-sample state index of a track sample in no task state (``"state"`` arrays, u2)."""


def _motion_data(track: MotionTrack, scale: float, state_ids: list[str]) -> dict[str, Any]:
    labels = [str(v) for v in track.labels]
    names = list(dict.fromkeys(labels))
    pos = {v: i for i, v in enumerate(names)}
    keep = replay_indices(np.array([pos[v] for v in labels], dtype=np.int64))
    states: list[str | None] = [None] * len(names)
    for lab, sid in zip(labels, track.state_ids, strict=False):
        if states[pos[lab]] is None:
            states[pos[lab]] = sid
    index = {sid: i for i, sid in enumerate(state_ids)}
    per_sample = None
    if len(track.state_ids) == len(labels):
        per_sample = np.array(
            [index.get(str(v), NO_STATE) if v is not None else NO_STATE for v in track.state_ids]
        )
    return {
        "name": track.name,
        "kind": track.kind,
        "note": track.note,
        "state": None if per_sample is None else pack_array(per_sample[keep], "u2"),
        "t": pack_array(np.asarray(track.times, dtype=np.float64)[keep], "f8"),
        "pose": pack_array(poses_to_rows(np.asarray(track.X_EG)[keep], scale), "f4"),
        "labels": names,
        "label_states": states,
        "label": pack_array(np.array([pos[labels[i]] for i in keep]), "u2"),
    }


def report_data(
    task: TaskModel | Mapping[str, Any],
    *,
    grasped: Polyhedron | None = None,
    environment: Polyhedron | None = None,
    frames: FrameTrack | None = None,
    tracks: Sequence[MotionTrack] = (),
    inputs: Mapping[str, Any] | None = None,
    notes: Sequence[str] = (),
    state_ids: Sequence[str] | None = None,
) -> dict[str, Any]:
    """Return the JSON document the viewer draws (schema ``"apo.report/1"``).

    Parameters
    ----------
    task : TaskModel or dict
        The task, or its ``task.json`` form (``apo.task.task_to_dict``), which is embedded
        as is.
    grasped, environment : Polyhedron, optional
        The models (metres); without them the 3D view shows contacts and paths only.
    frames : FrameTrack, optional
        Per-frame poses and diagnostics; default: each state's pose over its frames.
    tracks : sequence of MotionTrack
        Planned motion and simulated execution.
    inputs : dict, optional
        Shown in the inputs panel (files with hashes, apo version, ...).
    notes : sequence of str
        Warnings shown at the top of the page (a model not found, a hash mismatch).
    state_ids : sequence of str, optional
        The task's state ids, for a ``task`` dictionary without its ``states`` (the
        top-level fields of a task whose text is spliced in by :func:`write_report`).
    """
    from apo import __version__
    from apo.task import UNITS, task_to_dict

    doc = dict(task) if isinstance(task, Mapping) else task_to_dict(task)
    units = str(doc["units"])
    scale = 1.0 / UNITS[units]
    ids = [str(s["id"]) for s in doc["states"]] if state_ids is None else list(state_ids)
    if frames is None:
        frames = frames_from_task_dict(doc)
    return {
        "schema": SCHEMA,
        "apo_version": __version__,
        "task": doc,
        "models": {
            "grasped": None if grasped is None else _mesh_data(grasped, scale),
            "environment": None if environment is None else _mesh_data(environment, scale),
        },
        "frames": _frames_data(frames, ids, scale),
        "tracks": [_motion_data(t, scale, ids) for t in tracks],
        "inputs": dict(inputs or {}),
        "notes": list(notes),
    }


def frames_from_task_dict(doc: Mapping[str, Any]) -> FrameTrack:
    """Per-frame track from a ``task.json`` document alone: each state's pose held.

    Times are interpolated linearly within each state's ``times``.
    """
    from apo.spatial import pose_from_position_quaternion
    from apo.task import UNITS

    k = UNITS[str(doc["units"])]
    states = doc["states"]
    n = int(states[-1]["frames"][1]) + 1 if states else 0
    n = max(n, int(doc.get("n_frames", 0) or 0))
    times = np.zeros(n)
    ids = [""] * n
    X = np.tile(np.eye(4), (n, 1, 1))
    for s in states:
        a, b = (int(v) for v in s["frames"])
        times[a : b + 1] = np.linspace(float(s["times"][0]), float(s["times"][1]), b - a + 1)
        ids[a : b + 1] = [str(s["id"])] * (b - a + 1)
        pose = s["pose"]
        X[a : b + 1] = pose_from_position_quaternion(
            np.asarray(pose["position"], dtype=float) * k, np.asarray(pose["quaternion"])
        )
    if states and any(not v for v in ids):  # frames after the last state (never, by schema)
        ids = [v or str(states[-1]["id"]) for v in ids]
    return FrameTrack(times=times, state_ids=ids, X_corrected=X, source="task states")


_VIEWER = Path(__file__).resolve().parent / "viewer"


@functools.cache
def _asset(name: str) -> bytes:
    """Return a file of the viewer (``apo/report/viewer/``) as bytes, ``</script`` escaped."""
    return (_VIEWER / name).read_bytes().replace(b"</script", b"<\\/script")


@functools.cache
def plotly_js() -> bytes:
    """Return the plotly.js bundle of the installed ``plotly`` package (UTF-8, for inlining).

    The file is found without importing plotly (``importlib.util.find_spec``).

    Raises
    ------
    ApoError
        If the ``plotly`` package is not installed or lacks its bundle.
    """
    return _plotly_bundle().read_bytes().replace(b"</script", b"<\\/script")


def _plotly_bundle() -> Path:
    """Return the file of :func:`plotly_js` (raise its error if there is none)."""
    import importlib.util

    spec = importlib.util.find_spec("plotly")
    locations = list(spec.submodule_search_locations or []) if spec is not None else []
    for folder in locations:
        bundle = Path(folder) / "package_data" / "plotly.min.js"
        if bundle.is_file():
            return bundle
    raise ApoError(
        "the HTML report needs the plotly package and its bundled plotly.min.js "
        "(pip install plotly)"
    )


class _FileCopy(NamedTuple):
    """A piece of the page that is a file's bytes as they are (copied by the kernel)."""

    path: Path
    size: int


def _bundle_piece(plotly: bytes | None, copy: bool) -> Iterator[bytes | _FileCopy]:
    """Yield the page's plotly.js: ``plotly`` if read already, else the bundle's file.

    With ``copy`` and a bundle that needs no escaping (no ``</script``, looked for in the
    file mapped, not read: :func:`_file_lacks`), the file itself (:func:`write_report`
    copies it with ``os.sendfile``: no 4.8 MB read into this process and written back, 3 ms
    of a cold start); else its escaped bytes.
    """
    if plotly is not None:
        yield plotly
        return
    if copy:
        path = _plotly_bundle()
        try:
            clean, size = _file_lacks(path, b"</script")
        except (OSError, ValueError):
            clean, size = False, 0
        if clean:
            yield _FileCopy(path, size)
            return
    yield plotly_js()


#: Bytes of a file mapped at a time by :func:`_file_lacks` (a multiple of mmap's granularity).
SCAN_WINDOW = 1 << 20


def _file_lacks(path: Path, needle: bytes) -> tuple[bool, int]:
    """Return whether the file at ``path`` does not contain ``needle``, and its size.

    Mapped ``SCAN_WINDOW`` bytes at a time (each window overlapping the next by the
    needle's length less one): the pages mapped count in the resident memory, and the
    whole bundle mapped at once was 4.8 MB at the end of a run, where a long run peaks
    (the same CPU time).
    """
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        for start in range(0, size, SCAN_WINDOW):
            length = min(SCAN_WINDOW + len(needle) - 1, size - start)
            with mmap.mmap(fh.fileno(), length, access=mmap.ACCESS_READ, offset=start) as m:
                if m.find(needle) >= 0:
                    return False, size
    return True, size


def _copy_into(fh: Any, piece: _FileCopy) -> int:
    """Append the file of ``piece`` to the open file ``fh`` (``os.sendfile``); bytes written."""
    fh.flush()
    start = fh.tell()
    done = 0
    try:
        with open(piece.path, "rb") as src:
            while done < piece.size:
                sent = os.sendfile(fh.fileno(), src.fileno(), done, piece.size - done)
                if sent == 0:
                    raise OSError("the file ended early")
                done += sent
    except OSError:  # no sendfile here: the bytes written as they are
        fh.seek(start)
        fh.truncate()
        data = piece.path.read_bytes()
        fh.write(data)
        return len(data)
    fh.seek(0, os.SEEK_END)
    return done


def _json_for_script(data: Mapping[str, Any], task_json: str | None = None) -> bytes:
    """JSON safe inside ``<script type="application/json">`` (no ``</``, no ``<!--``).

    With ``task_json`` (the text of ``task.json``, the same document as ``data["task"]``),
    that text is spliced in as ``"task"`` instead of serialising the task a second time.
    """
    return b"".join(_script_pieces(data, task_json))


def _script_pieces(data: Mapping[str, Any], task_json: Any = None) -> Iterator[bytes]:
    """:func:`_json_for_script` in pieces; ``task_json`` may also be a written task file.

    A written file (:class:`apo.report.writer.TaskJson`: ``stripped_chunks()``) is spliced
    chunk by chunk: a long task's text is never in memory whole. The escapes replace single
    ASCII characters, so escaping chunk by chunk gives the same bytes.
    """
    if task_json is None:
        text = json.dumps(data, separators=(",", ":"), allow_nan=False)
        yield _escape_script(text.encode("utf-8"))
        return
    rest = {k: v for k, v in data.items() if k != "task"}
    for piece in _json_pieces(rest, SCRIPT_SPLIT_DEPTH, last=False):  # the task follows
        for a in range(0, len(piece), SCRIPT_CHUNK_CHARS):  # no whole copy of the text
            yield _escape_script(piece[a : a + SCRIPT_CHUNK_CHARS].encode("utf-8"))
    yield b',"task":'
    if isinstance(task_json, str):
        yield _escape_script(task_json.strip().encode("utf-8"))
    else:
        for chunk in task_json.stripped_chunks():
            yield _escape_script(chunk)
    yield b"}"


#: Characters of the report's data (all but the task) encoded and escaped at a time.
SCRIPT_CHUNK_CHARS = 1 << 18

#: Levels of the report's data whose objects are written member by member
#: (:func:`_json_pieces`): ``frames`` -> ``observed`` -> its ``b64`` text, alone.
SCRIPT_SPLIT_DEPTH = 3


def _json_pieces(value: Any, depth: int, *, last: bool = True) -> Iterator[str]:
    """Yield ``json.dumps(value, separators=(",", ":"), allow_nan=False)`` in pieces.

    Objects (string keys) down to ``depth`` levels are written member by member, so that
    the text of the report's data is never made whole (a long demonstration's packed
    frames are megabytes) besides the data itself; the same text, joined. ``last=False``
    leaves out the outer object's closing brace.

    >>> d = {"a": {"b": [1, 2.5], "c": {"d": "x"}}, "e": None}
    >>> "".join(_json_pieces(d, 2)) == json.dumps(d, separators=(",", ":"))
    True
    """
    if depth <= 0 or not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        yield json.dumps(value, separators=(",", ":"), allow_nan=False)
        return
    yield "{"
    for i, (k, v) in enumerate(value.items()):
        yield ("," if i else "") + json.dumps(k) + ":"
        yield from _json_pieces(v, depth - 1)
    if last:
        yield "}"


def _escape_script(b: bytes) -> bytes:
    """Escape ``<``, ``>`` and ``&`` of UTF-8 JSON text as unicode escapes (script-safe)."""
    return b.replace(b"<", b"\\u003c").replace(b">", b"\\u003e").replace(b"&", b"\\u0026")


def report_parts(
    data: Mapping[str, Any], *, title: str | None = None, task_json: Any = None
) -> list[bytes]:
    """Return the page of a :func:`report_data` document as a list of UTF-8 byte strings.

    Joined, they are the HTML file; :func:`write_report` writes them without joining (the
    plotly.js bundle, most of the page, is never decoded or copied). ``task_json``: the
    text of ``task.json`` for ``data["task"]`` (or the written file, a
    :class:`apo.report.writer.TaskJson`), embedded as is (:func:`_json_for_script`).
    """
    return [p for p in _page_pieces(data, title=title, task_json=task_json) if isinstance(p, bytes)]


def _page_pieces(
    data: Mapping[str, Any],
    *,
    title: str | None = None,
    task_json: Any = None,
    plotly: bytes | None = None,
    copy: bool = False,
) -> Iterator[bytes | _FileCopy]:
    """Yield the pieces of :func:`report_parts`, the task's text read while they are written.

    ``plotly``: :func:`plotly_js` read already. With ``copy``, the bundle may come as a
    file to copy (:func:`_bundle_piece`).
    """
    src = str(data["task"].get("source") or "demonstration")
    text = title or f"apo report: {src}"  # escaped by hand: importing html costs 15 ms
    text = text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
    parts: dict[bytes, Callable[[], Iterator[bytes | _FileCopy]]] = {
        b"__APO_TITLE__": lambda: iter([text.encode("utf-8")]),
        b"__APO_CSS__": lambda: iter([_asset("report.css")]),
        b"__APO_PLOTLY__": lambda: _bundle_piece(plotly, copy),
        b"__APO_DATA__": lambda: _script_pieces(data, task_json),
        b"__APO_JS__": lambda: iter([_asset("report.js")]),
    }
    rest = (_VIEWER / "report.html").read_bytes()
    for key in _PLACEHOLDERS:
        head, sep, rest = rest.partition(key.encode("ascii"))
        if not sep:
            raise ApoError(f"report template: placeholder {key} missing")
        yield head
        yield from parts[sep]()
    yield rest


def report_html(data: Mapping[str, Any], *, title: str | None = None) -> str:
    """Return the self-contained HTML page of a :func:`report_data` document."""
    return b"".join(report_parts(data, title=title)).decode("utf-8")


def write_report(
    path: str | Path,
    data: Mapping[str, Any],
    *,
    title: str | None = None,
    task_json: Any = None,
    plotly: bytes | None = None,
) -> int:
    """Write the page of a :func:`report_data` document to ``path``; return its size in bytes.

    ``task_json``: the text of ``task.json`` or the written file
    (:class:`apo.report.writer.TaskJson`), spliced in as the document's task. ``plotly``:
    :func:`plotly_js`, if read already. Not atomic by itself: callers write into an
    :class:`apo.outputs.OutputSet` or through :func:`apo.outputs.atomic_file`.
    """
    size = 0
    with open(path, "wb") as fh:
        for piece in _page_pieces(data, title=title, task_json=task_json, plotly=plotly, copy=True):
            if isinstance(piece, _FileCopy):
                size += _copy_into(fh, piece)
            else:
                fh.write(piece)
                size += len(piece)
    return size
