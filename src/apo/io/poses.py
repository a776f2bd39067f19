r"""Pose files of a demonstration: the first author's ``.pose.list`` and a plain CSV.

Both readers return a :class:`Demonstration`: time stamps (s) and the poses ``X_EG`` of the
grasped object G in the environment frame E, in **metres** (converted from the file's units
here, at the boundary; ``docs/conventions.md``).

``.pose.list`` (the first author's format, camera frame C)::

    No of Models: 2
    .\\peg.step                      <- model 0: the grasped object G
    .\\hole.step                     <- model 1: the environment E
                                     <- blank line
    No of Scenes: 41
    2 -27.24 999.61 1429.92  -0.0497 0.0011 0.9988 3.1405   <- tag x y z ax ay az angle
    0 106.73 982.08 1437.27   0.0309 0.0013 -0.9995 3.1338
                                     <- blank line between scenes
    ...

Model paths are relative to the list file and may use Windows separators. In a scene the
i-th line is the pose ``X_C<i>`` of the i-th model: position in the file's units, rotation
as an axis (any non-zero length; normalised) and an angle in radians. The leading integer is
an id (tag) the tracker gave the object; it is kept (:attr:`Demonstration.tags`) but does not
decide which model a line belongs to. ``X_EG = inv(X_CE) @ X_CG`` per scene. The file has no
time stamps: frame ``k`` gets ``t = k / fps`` with ``fps = 1`` unless given.

CSV (written by :func:`write_pose_csv`, e.g. by apo's perception)::

    t,x,y,z,qw,qx,qy,qz[,extra,...]

one row per frame, the pose of G in E: position in the caller's units, unit quaternion
``(qw, qx, qy, qz)`` (normalised on reading). The header row is optional: a first row whose
first field is not a number is a header, and must begin with exactly those eight names; any
further columns are carried through by name (``Demonstration.extra``; without a header they
are named ``col8``, ``col9``, ...). Blank lines and lines starting with ``#`` are ignored.
Time stamps must strictly increase.

Every error is an :class:`apo.errors.InputFormatError` naming the file and the line.
"""

from __future__ import annotations

import csv
import io
import math
import re
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from apo.constants import UNITS
from apo.errors import InputFormatError
from apo.spatial import (
    matrices_from_quaternions,
    matrix_from_axis_angle,
    pose_defect,
    quaternion_from_matrix,
)
from apo.typing import FloatArray, IntArray

__all__ = [
    "CSV_COLUMNS",
    "DEFAULT_UNITS",
    "EXCERPT_CHARS",
    "QUATERNION_NORM_TOLERANCE",
    "UNITS",
    "Demonstration",
    "load_demonstration",
    "read_pose_csv",
    "read_pose_list",
    "write_pose_csv",
    "write_pose_list",
]


DEFAULT_UNITS = "mm"
"""Units assumed by :func:`load_demonstration` when none are given (the author's data)."""

CSV_COLUMNS = ("t", "x", "y", "z", "qw", "qx", "qy", "qz")
"""The required leading columns of a pose CSV, in order."""

_HEADER_MODELS = re.compile(r"^\s*No\s+of\s+Models\s*:\s*(\S+)\s*$", re.IGNORECASE)
_HEADER_SCENES = re.compile(r"^\s*No\s+of\s+Scenes\s*:\s*(\S+)\s*$", re.IGNORECASE)


@dataclass(frozen=True)
class Demonstration:
    """An observed demonstration: one pose of the grasped object per frame.

    Attributes
    ----------
    times : ndarray, shape (N,), seconds
        Strictly increasing time stamps (``k / fps`` for a ``.pose.list``).
    X_EG : ndarray, shape (N, 4, 4), metres
        Pose of the grasped object G in the environment frame E per frame.
    units : str
        Length unit of the source file (positions were converted from it to metres).
    source : Path or None
        The file read.
    grasped_path, environment_path : Path or None
        Model files of G and E (``.pose.list``: resolved against the list's directory;
        CSV: None unless given to :func:`load_demonstration`).
    model_paths : tuple of Path
        Every model listed (``.pose.list``), in order; G first, E second.
    X_C : ndarray, shape (N, n_models, 4, 4), metres, or None
        Raw camera-frame poses ``X_C<i>`` of every model (``.pose.list`` only).
    tags : ndarray of int, shape (N, n_models), or None
        The tracker's id at the start of each pose line (``.pose.list`` only).
    extra : dict of str to ndarray, shape (N,)
        Further CSV columns by name (e.g. ``"confidence"``).
    lines : ndarray of int, shape (N,)
        1-based line in the source of each frame's (first) pose line.
    fps : float or None
        Frame rate used to make ``times`` (``.pose.list``); None when the file had times.
    """

    times: FloatArray
    X_EG: FloatArray
    units: str
    source: Path | None = None
    grasped_path: Path | None = None
    environment_path: Path | None = None
    model_paths: tuple[Path, ...] = ()
    X_C: FloatArray | None = None
    tags: IntArray | None = None
    extra: Mapping[str, FloatArray] = field(default_factory=dict)
    lines: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    fps: float | None = None

    @property
    def n_frames(self) -> int:
        """Number of frames N."""
        return int(self.times.shape[0])

    @property
    def X_CG(self) -> FloatArray | None:
        """Camera-frame poses of G, shape (N, 4, 4), metres (``.pose.list`` only)."""
        return None if self.X_C is None else self.X_C[:, 0]

    @property
    def X_CE(self) -> FloatArray | None:
        """Camera-frame poses of E, shape (N, 4, 4), metres (``.pose.list`` only)."""
        return None if self.X_C is None else self.X_C[:, 1]


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def _scale(units: str, where: str) -> float:
    if units not in UNITS:
        raise InputFormatError(
            f"{where}: unknown units {units!r}; expected one of {', '.join(sorted(UNITS))}"
        )
    return UNITS[units]


EXCERPT_CHARS = 80
"""Longest piece of a file's line that an error message quotes."""

QUATERNION_NORM_TOLERANCE = 0.01
"""A CSV quaternion whose norm differs from 1 by more than this (1 %) is reported: it is
normalised as always, but a warning names the lines (a norm of 4 is a scaled or garbled
column, not rounding; six-decimal quaternions are within 1e-5)."""

# control characters that never occur in a text pose file (tab, CR, LF, FF, VT are fine)
_BINARY = re.compile(r"[\x00-\x08\x0e-\x1f\x7f]")


def _excerpt(text: str, limit: int = EXCERPT_CHARS, *, quote: bool = True) -> str:
    """``repr`` of ``text`` stripped and cut to ``limit`` characters (with the full length)."""
    t = text.strip()
    show = repr if quote else str
    if len(t) <= limit:
        return show(t)
    return f"{show(t[:limit])}... ({len(t)} characters)"


def _read_text(path: Path) -> str:
    """Return the file's text; binary content is blamed on the first line that holds it."""
    if not path.is_file():
        raise InputFormatError(f"{path}: file not found")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise InputFormatError(f"{path}: cannot read ({exc.strerror})") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise InputFormatError(
            f"{path}: line {line}: not a text file (byte 0x{raw[exc.start]:02x} is not UTF-8)"
        ) from None
    m = _BINARY.search(text)
    if m is not None:
        line = text.count("\n", 0, m.start()) + 1
        col = m.start() - (text.rfind("\n", 0, m.start()) + 1) + 1
        raise InputFormatError(
            f"{path}: line {line}: not a text file (control character {m.group()!r} at "
            f"column {col})"
        )
    return text


def _number(token: str, where: str, what: str) -> float:
    try:
        value = float(token)
    except ValueError:
        raise InputFormatError(f"{where}: {what} is not a number: {_excerpt(token)}") from None
    if not math.isfinite(value):
        raise InputFormatError(f"{where}: {what} is not finite: {_excerpt(token)}")
    return value


def _model_path(text: str, base: Path) -> Path:
    r"""Resolve a model path as written (``.\\peg.step``, ``models/peg.step``) against base."""
    rel = text.strip().replace("\\", "/")
    p = Path(rel)
    return p if p.is_absolute() else base / p


# --------------------------------------------------------------------------------------------
# .pose.list
# --------------------------------------------------------------------------------------------


def read_pose_list(
    path: str | Path,
    *,
    units: str = DEFAULT_UNITS,
    fps: float | None = None,
    camera_poses: bool = True,
) -> Demonstration:
    """Read the first author's ``.pose.list`` (camera-frame poses of every model per scene).

    Parameters
    ----------
    path : str or Path
        The list file.
    units : {"mm", "cm", "m", "in"}, optional
        Length unit of the positions in the file (the author's data: mm).
    fps : float, optional
        Frame rate giving ``times = k / fps`` (the format has no time stamps); 1 if None.
    camera_poses : bool
        Keep the raw poses and ids (``X_C``, ``tags``); False: None (``X_EG`` only, a
        third of the memory).

    Returns
    -------
    Demonstration
        ``X_EG = inv(X_CE) @ X_CG`` per scene (model 0 is G, model 1 is E), metres; the raw
        poses in ``X_C``, the ids in ``tags``, model paths resolved against the list's
        directory.

    Raises
    ------
    InputFormatError
        Missing file, a wrong header, fewer than two models, a count of models or scenes that
        differs from the header (expected vs found), a scene with the wrong number of lines,
        a line not of 8 fields, a malformed or non-finite number, a zero rotation axis with a
        non-zero angle, no scenes at all, or a non-positive ``fps``. The message names the
        file and the line.
    """
    path = Path(path)
    scale = _scale(units, str(path))
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise InputFormatError(f"{path}: fps must be positive, got {fps}")
    text = _read_text(path)
    read = _pose_list_in_blocks(path, text, scale, camera_poses)
    if read is None:  # something is wrong: the whole-text reader names it
        read = _pose_list_whole(path, text.splitlines(), scale)
    del text
    models, x_eg, first, tags, x_c = read
    n = len(x_eg)
    rate = 1.0 if fps is None else float(fps)
    return Demonstration(
        times=np.arange(n, dtype=np.float64) / rate,
        X_EG=x_eg,
        units=units,
        source=path,
        grasped_path=models[0],
        environment_path=models[1],
        model_paths=tuple(models),
        X_C=x_c if camera_poses else None,
        tags=tags if camera_poses else None,
        lines=first,
        fps=rate,
    )


_PoseList = tuple[list[Path], FloatArray, IntArray, IntArray | None, FloatArray | None]


def _pose_list_whole(path: Path, lines: list[str], scale: float) -> _PoseList:
    """Read a pose list from all its lines at once; raise on the first problem, naming it."""
    models, n_scenes, i = _pose_list_header(path, lines)
    scenes = _scene_lines(path, lines, i, n_scenes)
    first = np.array([scene[0] + 1 for scene in scenes], dtype=np.int64)
    parsed = _scene_poses_fast(lines, scenes, len(models), scale)
    if parsed is None:  # something is wrong: the line-by-line reader names it
        parsed = _scene_poses(lines, scenes, len(models), scale, lambda j: _where(path, j))
    tags, x_c = parsed
    return models, _poses_in_e(x_c), first, tags, x_c


def _poses_in_e(x_c: FloatArray) -> FloatArray:
    """``inv(X_CE) @ X_CG`` of scenes ``x_c`` (n, models, 4, 4), a block at a time."""
    n = len(x_c)
    x_eg = np.empty((n, 4, 4))
    for a in range(0, n, POSE_BLOCK):
        b = min(n, a + POSE_BLOCK)
        x_eg[a:b] = np.einsum("nij,njk->nik", _invert_all(x_c[a:b, 1]), x_c[a:b, 0])
    return x_eg


#: Characters of a pose list split into lines at a time (:func:`_pose_list_in_blocks`).
POSE_CHUNK_CHARS = 1 << 18


def _line_chunks(text: str, size: int, first: int = 0) -> Iterator[list[str]]:
    """Yield the lines of ``text`` (as ``text.splitlines()``), ``size`` characters at a time.

    The first chunk has at least ``first`` characters (the header). Each chunk ends just
    after a newline, which ends a line wherever the text is cut.
    """
    for chunk in _text_chunks(text, size, first):
        yield chunk.splitlines()


#: The least length of the first chunk of a pose list, where its header is read.
POSE_HEADER_CHARS = 1 << 16


def _pose_list_in_blocks(
    path: Path, text: str, scale: float, camera_poses: bool
) -> _PoseList | None:
    """Read a valid pose list a chunk of lines at a time; None at anything unusual.

    No Python string is kept per line: each chunk's complete scenes are parsed by numpy and
    their poses in E written into arrays of the announced number of scenes. A file with
    any problem (or a header longer than ``POSE_HEADER_CHARS``) gives None: :func:`_pose_list_whole`
    then reads it and names the problem as it always did.
    """
    chunks = _line_chunks(text, POSE_CHUNK_CHARS, POSE_HEADER_CHARS)
    head = next(chunks, [])
    try:
        models, n_scenes, i = _pose_list_header(path, head)
    except InputFormatError:
        return None
    m = len(models)
    if not 0 < n_scenes * m <= text.count("\n") + 1:
        return None
    out = _SceneArrays(n_scenes, m, camera_poses)
    scenes = _Scenes(m)
    done = scenes.take(head[i:], i) if i < len(head) else ([], [])
    offset = len(head)  # index of the next chunk's first line in the whole text
    del head
    while scenes.ok and out.add(done, scale):
        lines = next(chunks, None)
        if lines is None:
            break
        done = scenes.take(lines, offset)
        offset += len(lines)
        del lines  # one chunk's lines at a time
    else:
        return None
    done = scenes.take([], offset, last=True)  # the last scene ends with the text
    if not (scenes.ok and out.add(done, scale)) or out.done != n_scenes:
        return None
    return models, out.x_eg, out.first, out.tags, out.x_c


class _Scenes:
    """Scenes (runs of non-blank lines) of a text read a chunk of lines at a time."""

    def __init__(self, n_models: int) -> None:
        self.m = n_models
        self.open: list[str] = []  # the lines of the scene that the last chunk ended in
        self.ok = True  # every complete scene has one line per model

    def take(
        self, lines: list[str], offset: int, last: bool = False
    ) -> tuple[list[str], list[int]]:
        """Return the lines and first lines (numbered from 1) of the scenes that end here.

        ``lines`` start at line ``offset`` (0-based) of the text; a scene running to their
        end is kept open for the next chunk, unless ``last``.
        """
        kept = [j for j, line in enumerate(lines) if line.strip()]
        rows = self.open + [lines[j] for j in kept]
        if not rows:
            return [], []
        # line indices relative to this chunk: the open scene's lines end just before it
        at = np.concatenate([np.arange(-len(self.open), 0), np.array(kept, dtype=np.int64)])
        starts = np.flatnonzero(np.diff(at, prepend=at[0] - 2) != 1)
        cut = len(rows)
        if not last and at[-1] == len(lines) - 1:  # the last scene may go on
            cut = int(starts[-1])
            starts = starts[:-1]
        self.open = rows[cut:]
        self.ok &= bool(np.all(np.diff(np.append(starts, cut)) == self.m))
        return rows[:cut], (offset + at[starts] + 1).tolist()


class _SceneArrays:
    """The poses in E (and optionally the raw poses and ids) of the scenes read so far."""

    def __init__(self, n: int, n_models: int, camera_poses: bool) -> None:
        self.m, self.done = n_models, 0
        self.x_eg = np.empty((n, 4, 4))
        self.first = np.empty(n, dtype=np.int64)
        self.x_c = np.empty((n, n_models, 4, 4)) if camera_poses else None
        self.tags = np.empty((n, n_models), dtype=np.int64) if camera_poses else None

    def add(self, scenes: tuple[list[str], list[int]], scale: float) -> bool:
        """Parse and store complete scenes; False if they do not parse or are too many."""
        rows, firsts = scenes
        a, k = self.done, len(firsts)
        if not k:
            return True
        parsed = _rows_poses(rows, k, self.m, scale) if a + k <= len(self.first) else None
        if parsed is None:
            return False
        tags, x = parsed
        self.first[a : a + k] = firsts
        self.x_eg[a : a + k] = _poses_in_e(x)
        if self.x_c is not None and self.tags is not None:
            self.x_c[a : a + k], self.tags[a : a + k] = x, tags
        self.done += k
        return True


def _where(path: Path, i: int) -> str:
    return f"{path}: line {i + 1}"


def _expect_header(
    path: Path, lines: list[str], i: int, pattern: re.Pattern[str], name: str
) -> tuple[int, int]:
    """Parse the ``name: N`` header at or after line ``i``; return N and the next line."""
    n_lines = len(lines)
    while i < n_lines and not lines[i].strip():
        i += 1
    if i >= n_lines:
        raise InputFormatError(f"{path}: line {i + 1}: expected '{name}: N', found end of file")
    m = pattern.match(lines[i])
    if m is None:
        raise InputFormatError(f"{_where(path, i)}: expected '{name}: N', got {_excerpt(lines[i])}")
    try:
        n = int(m.group(1))
    except ValueError:
        raise InputFormatError(
            f"{_where(path, i)}: '{name}' must be a whole number, got {m.group(1)!r}"
        ) from None
    if n < 0:
        raise InputFormatError(f"{_where(path, i)}: '{name}' must not be negative, got {n}")
    return n, i + 1


def _pose_list_header(path: Path, lines: list[str]) -> tuple[list[Path], int, int]:
    """Return the model paths, the announced number of scenes and the next line."""
    n_lines = len(lines)
    n_models, i = _expect_header(path, lines, 0, _HEADER_MODELS, "No of Models")
    if n_models < 2:
        raise InputFormatError(
            f"{_where(path, i - 1)}: need at least 2 models (grasped, environment), got {n_models}"
        )
    models: list[Path] = []
    while len(models) < n_models:
        if i >= n_lines or not lines[i].strip() or _HEADER_SCENES.match(lines[i]):
            raise InputFormatError(
                f"{_where(path, min(i, n_lines - 1))}: expected {n_models} model paths, found "
                f"{len(models)}"
            )
        models.append(_model_path(lines[i], path.parent))
        i += 1
    if i < n_lines and lines[i].strip() and not _HEADER_SCENES.match(lines[i]):
        raise InputFormatError(
            f"{_where(path, i)}: expected {n_models} model paths, found more: {_excerpt(lines[i])}"
        )
    n_scenes, i = _expect_header(path, lines, i, _HEADER_SCENES, "No of Scenes")
    return models, n_scenes, i


def _scene_lines(path: Path, lines: list[str], i: int, n_scenes: int) -> list[list[int]]:
    """Return the scenes from line ``i`` on (runs of non-blank lines), as many as announced."""
    n_lines = len(lines)
    scenes: list[list[int]] = []
    current: list[int] = []
    for j in range(i, n_lines):
        if lines[j].strip():
            current.append(j)
        elif current:
            scenes.append(current)
            current = []
    if current:
        scenes.append(current)
    if not scenes:
        raise InputFormatError(
            f"{path}: no scenes (empty sequence): a demonstration needs at least one"
            + (f"; the header announced {n_scenes}" if n_scenes else "")
        )
    if len(scenes) != n_scenes:
        raise InputFormatError(
            f"{_where(path, scenes[-1][0] if len(scenes) > n_scenes else n_lines - 1)}: "
            f"expected {n_scenes} scenes ('No of Scenes: {n_scenes}'), found {len(scenes)}"
        )
    return scenes


def _scene_poses(
    lines: list[str], scenes: list[list[int]], n_models: int, scale: float, where: Any
) -> tuple[IntArray, FloatArray]:
    """Parse every scene's pose lines one by one; raise on the first bad one."""
    n = len(scenes)
    x_c = np.zeros((n, n_models, 4, 4))
    tags = np.zeros((n, n_models), dtype=np.int64)
    for k, scene in enumerate(scenes):
        if len(scene) != n_models:
            raise InputFormatError(
                f"{where(scene[0])}: scene {k + 1} has {len(scene)} pose lines, expected "
                f"{n_models} (one per model)"
            )
        for m, j in enumerate(scene):
            tags[k, m], x_c[k, m] = _pose_line(lines[j], where(j), scale)
    return tags, x_c


def _scene_poses_fast(
    lines: list[str], scenes: list[list[int]], n_models: int, scale: float
) -> tuple[IntArray, FloatArray] | None:
    """Parse all pose lines at once (numpy); None if anything is off (then read line by line).

    Same result as :func:`_scene_poses` on a valid file: tags, and the poses from the
    axis-angle rotation (Rodrigues' formula, vectorised) and the position times ``scale``.
    """
    if any(len(scene) != n_models for scene in scenes):
        return None
    return _rows_poses([lines[j] for scene in scenes for j in scene], len(scenes), n_models, scale)


def _rows_poses(
    rows: list[str], n: int, n_models: int, scale: float
) -> tuple[IntArray, FloatArray] | None:
    """Parse ``n`` scenes' pose lines ``rows`` at once (numpy); None if anything is off."""
    try:  # numpy's C parser: no Python string per number (correctly rounded, as float())
        table = np.loadtxt(rows, dtype=np.float64, comments=None, ndmin=2)
    except ValueError:  # ragged rows or a token that is not a number
        return None
    if table.ndim != 2 or table.shape[1] != 8 or not np.isfinite(table).all():
        return None
    tags = table[:, 0]
    if not all(r.split(None, 1)[0].lstrip("+-").isdigit() for r in rows):
        return None
    x = np.zeros((len(table), 4, 4))
    for a in range(0, len(table), POSE_BLOCK):  # working arrays of one block
        if not _axis_angle_poses(table[a : a + POSE_BLOCK], scale, x[a : a + POSE_BLOCK]):
            return None
    return tags.astype(np.int64).reshape(n, n_models), x.reshape(n, n_models, 4, 4)


#: Pose lines converted to matrices at once (the working arrays of one block).
POSE_BLOCK = 4096


def _axis_angle_poses(table: FloatArray, scale: float, x: FloatArray) -> bool:
    """Fill ``x`` (n, 4, 4) with the poses of rows ``tag x y z ax ay az angle``.

    Rodrigues' formula, vectorised; False (``x`` partly filled) where an axis is zero and
    its angle is not.
    """
    axis, angle = table[:, 4:7], table[:, 7]
    norm = np.linalg.norm(axis, axis=1)
    if np.any((norm < 1e-12) & (np.abs(angle) > 1e-12)):
        return False
    k = axis / np.where(norm < 1e-12, 1.0, norm)[:, None]
    K = np.zeros((len(k), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    x[:, :3, :3] = np.eye(3) + s * K + (1.0 - c) * (K @ K)
    x[:, :3, 3] = table[:, 1:4] * scale
    x[:, 3, 3] = 1.0
    return True


def _pose_line(line: str, where: str, scale: float) -> tuple[int, FloatArray]:
    """Parse ``tag x y z ax ay az angle``; return the tag and the pose (metres)."""
    tokens = line.split()
    if len(tokens) != 8:
        raise InputFormatError(
            f"{where}: expected 8 fields 'tag x y z ax ay az angle', got {len(tokens)}: "
            f"{_excerpt(line)}"
        )
    try:
        tag = int(tokens[0])
    except ValueError:
        raise InputFormatError(f"{where}: tag is not an integer: {_excerpt(tokens[0])}") from None
    names = ("x", "y", "z", "ax", "ay", "az", "angle")
    vals = [_number(t, where, nm) for t, nm in zip(tokens[1:], names, strict=True)]
    axis = np.array(vals[3:6])
    angle = vals[6]
    if float(np.linalg.norm(axis)) < 1e-12 and abs(angle) > 1e-12:
        raise InputFormatError(f"{where}: rotation axis is zero but the angle is {angle}")
    x = np.eye(4)
    x[:3, :3] = matrix_from_axis_angle(axis, angle)
    x[:3, 3] = np.array(vals[:3]) * scale
    return tag, x


def _invert_all(x: FloatArray) -> FloatArray:
    out = np.zeros_like(x)
    out[:, :3, :3] = np.swapaxes(x[:, :3, :3], 1, 2)
    out[:, :3, 3] = -np.einsum("nji,nj->ni", x[:, :3, :3], x[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


# --------------------------------------------------------------------------------------------
# CSV
# --------------------------------------------------------------------------------------------


def read_pose_csv(path: str | Path, *, units: str) -> Demonstration:
    """Read a pose CSV ``t,x,y,z,qw,qx,qy,qz[,extra...]`` (G in E; see the module docstring).

    Parameters
    ----------
    path : str or Path
        The CSV file.
    units : {"mm", "cm", "m", "in"}
        Length unit of ``x, y, z`` in the file.

    Returns
    -------
    Demonstration
        Times (s) as written, ``X_EG`` in metres, extra columns in ``extra``.

    Raises
    ------
    InputFormatError
        Missing file, a header not beginning with ``t,x,y,z,qw,qx,qy,qz`` (or with repeated
        names), a row with a different number of fields than the first, fewer than 8
        columns, a malformed or non-finite number (extra columns may hold ``nan``), a zero
        quaternion, a time stamp not greater than the previous one, or no rows. The message
        names the file and the line.
    """
    path = Path(path)
    scale = _scale(units, str(path))
    fast = _csv_fast(path)
    if fast is not None:
        names, table, lines = fast
    else:
        names, rows = _csv_header(path, _csv_rows(path))
        quick = _csv_table(rows, len(names))
        # something is wrong: the row-by-row reader names it
        table = _csv_table_checked(path, rows, names) if quick is None else quick
        lines = np.array([lineno for lineno, _ in rows], dtype=np.int64)
    width = len(names)
    q = table[:, 4:8]
    _warn_quaternion_norms(path, np.linalg.norm(q, axis=1), lines)
    x_eg = np.zeros((len(table), 4, 4))
    for a in range(0, len(table), POSE_BLOCK):  # the working arrays of one block
        b = a + POSE_BLOCK
        x_eg[a:b, :3, :3] = matrices_from_quaternions(q[a:b])
        x_eg[a:b, :3, 3] = table[a:b, 1:4] * scale
    x_eg[:, 3, 3] = 1.0
    return Demonstration(
        times=table[:, 0].copy(),
        X_EG=x_eg,
        units=units,
        source=path,
        extra={names[j]: table[:, j].copy() for j in range(8, width)},
        lines=lines,
    )


def _csv_fast(path: Path) -> tuple[list[str], FloatArray, IntArray] | None:
    """Return names, table and line numbers of a plain CSV file read by numpy, else None.

    Plain: no quotes, no ``#`` and no carriage return but in CR LF line ends (so that
    lines are records and fields are split at every comma, as :func:`_csv_rows` splits
    them), every data row of the header's width, and every check of :func:`_csv_table`
    passed. Numbers are parsed by ``np.loadtxt`` (correctly rounded, as ``float``) without a
    Python string per field, a chunk of ``POSE_CHUNK_CHARS`` characters at a time (no
    string is kept per line). Anything else (and every error) goes to the careful reader,
    which names the line.
    """
    text = _read_text(path)
    if '"' in text or "#" in text or text.count("\r") != text.count("\r\n"):
        return None
    out = _CsvTable(text.count("\n") + 1)
    for chunk in _text_chunks(text, POSE_CHUNK_CHARS):
        if not out.add(path, chunk.replace("\r\n", "\n")):
            return None
    del text
    if out.names is None or out.n + out.header < 2:  # fewer than two lines not blank
        return None
    table, lines = out.table[: out.n], out.lines[: out.n]
    if not np.isfinite(table[:, :8]).all():
        return None
    if np.any(np.linalg.norm(table[:, 4:8], axis=1) < 1e-9) or np.any(np.diff(table[:, 0]) <= 0):
        return None
    return out.names, table, lines


def _text_chunks(text: str, size: int, first: int = 0) -> Iterator[str]:
    """Yield ``text`` about ``size`` characters at a time, each chunk ending after a newline.

    The first chunk has at least ``first`` characters.
    """
    start, n = 0, len(text)
    while start < n:
        stop = text.find("\n", min(n, start + max(1, size, first if start == 0 else 0)) - 1)
        stop = n if stop < 0 else stop + 1
        yield text[start:stop]
        start = stop


class _CsvTable:
    """The data rows of a plain CSV file, parsed a chunk of lines at a time."""

    def __init__(self, most: int) -> None:
        self.most = most  # rows at most: the file's lines
        self.names: list[str] | None = None
        self.header = False
        self.head_line = 0
        self.table = np.empty((0, 0))
        self.lines = np.empty(most, dtype=np.int64)
        self.n = 0  # data rows so far
        self.lineno = 0  # lines so far

    def add(self, path: Path, chunk: str) -> bool:
        """Parse the next chunk of text (whole lines); False where numpy cannot read it."""
        pieces = chunk.split("\n")
        if chunk.endswith("\n"):
            pieces.pop()  # the next chunk starts a new line
        numbered = [
            (i, line) for i, line in enumerate(pieces, start=self.lineno + 1)
            if line.replace(",", "").strip()
        ]  # fmt: skip
        self.lineno += len(pieces)
        if numbered and self.names is None:
            head_line, head = numbered[0]
            names, rest = _csv_header(
                path, [(head_line, [f.strip() for f in head.split(",")]), (0, [])]
            )
            self.names, self.header = names, rest[0][0] == 0
            self.table = np.empty((self.most, len(names)))
            if self.header:
                numbered = numbered[1:]
        return self._rows(numbered)

    def _rows(self, data: list[tuple[int, str]]) -> bool:
        """Parse data lines ``(line number, text)`` into the table."""
        if not data or self.names is None:
            return True
        try:
            part = np.loadtxt([line for _i, line in data], delimiter=",", dtype=np.float64,
                              comments=None, ndmin=2)  # fmt: skip
        except ValueError:
            return False
        if part.shape != (len(data), len(self.names)):
            return False
        a, b = self.n, self.n + len(data)
        self.table[a:b] = part
        self.lines[a:b] = [i for i, _line in data]
        self.n = b
        return True


def _csv_rows(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, stripped fields) of every row that is not blank or a ``#`` comment."""
    rows: list[tuple[int, list[str]]] = []
    for lineno, fields in enumerate(csv.reader(io.StringIO(_read_text(path))), start=1):
        if not fields or all(not f.strip() for f in fields) or fields[0].lstrip().startswith("#"):
            continue
        rows.append((lineno, [f.strip() for f in fields]))
    if not rows:
        raise InputFormatError(f"{path}: no rows (empty sequence)")
    return rows


def _csv_header(
    path: Path, rows: list[tuple[int, list[str]]]
) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """Return the column names (the header's, or ``t..qz, col8, ...``) and the data rows."""
    head_line, head = rows[0]
    try:
        float(head[0])
    except ValueError:  # a header
        names = [h.lower() for h in head]
        if tuple(names[:8]) != CSV_COLUMNS:
            raise InputFormatError(
                f"{path}: line {head_line}: header must begin with {','.join(CSV_COLUMNS)}, "
                f"got {_excerpt(','.join(head))}"
            ) from None
        names = names[:8] + head[8:]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise InputFormatError(
                f"{path}: line {head_line}: repeated column names "
                f"{_excerpt(str(sorted(dup)), quote=False)}"
            ) from None
        if len(rows) == 1:
            raise InputFormatError(f"{path}: header only, no rows (empty sequence)") from None
        return names, rows[1:]
    if len(head) < 8:
        raise InputFormatError(
            f"{path}: line {head_line}: expected at least 8 columns "
            f"{','.join(CSV_COLUMNS)}, got {len(head)}"
        )
    return [*CSV_COLUMNS, *(f"col{j}" for j in range(8, len(head)))], rows


def _csv_table(rows: list[tuple[int, list[str]]], width: int) -> FloatArray | None:
    """Every row as floats (N, width) in one numpy pass; None if anything is off.

    Off: a row of another width, a field that is not a number, a non-finite number among
    the first 8 columns, a zero quaternion, or time stamps that do not strictly increase.
    """
    if any(len(fields) != width for _, fields in rows):
        return None
    try:
        table = np.array([fields for _, fields in rows], dtype=np.float64)
    except ValueError:
        return None
    if not np.isfinite(table[:, :8]).all():
        return None
    if np.any(np.linalg.norm(table[:, 4:8], axis=1) < 1e-9) or np.any(np.diff(table[:, 0]) <= 0):
        return None
    return table.reshape(len(rows), width)


def _csv_table_checked(
    path: Path, rows: list[tuple[int, list[str]]], names: list[str]
) -> FloatArray:
    """Every row as floats, row by row; raise on the first bad field, naming the line."""
    width = len(names)
    table = np.zeros((len(rows), width))
    for k, (lineno, fields) in enumerate(rows):
        where = f"{path}: line {lineno}"
        if len(fields) != width:
            raise InputFormatError(f"{where}: expected {width} fields, got {len(fields)}")
        vals = [_number(f, where, nm) for f, nm in zip(fields[:8], CSV_COLUMNS, strict=True)]
        for j in range(8, width):
            try:
                table[k, j] = float(fields[j])
            except ValueError:
                raise InputFormatError(
                    f"{where}: column {_excerpt(names[j])} is not a number: {_excerpt(fields[j])}"
                ) from None
        if float(np.linalg.norm(vals[4:8])) < 1e-9:
            raise InputFormatError(f"{where}: quaternion (qw, qx, qy, qz) is zero")
        if k and not vals[0] > table[k - 1, 0]:
            raise InputFormatError(
                f"{where}: time stamps must strictly increase: t = {vals[0]} after "
                f"{table[k - 1, 0]}"
            )
        table[k, :8] = vals
    return table


def _warn_quaternion_norms(path: Path, norms: FloatArray, lines: IntArray) -> None:
    """Warn once, naming the lines, if quaternion norms differ from 1 beyond the tolerance."""
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUATERNION_NORM_TOLERANCE)
    if not bad.size:
        return
    shown = ", ".join(f"line {int(lines[i])} (norm {norms[i]:.4g})" for i in bad[:5])
    more = f", ... ({bad.size - 5} more)" if bad.size > 5 else ""
    warnings.warn(
        f"{path}: {bad.size} line(s) have a quaternion of norm far from 1 (by more than "
        f"{QUATERNION_NORM_TOLERANCE:g}), normalised: {shown}{more}",
        UserWarning,
        stacklevel=3,
    )


def _check_rotations(path: Path, x: FloatArray) -> FloatArray:
    """Return the 3x3 blocks of poses ``x`` (N, 4, 4) that pass the one pose rule.

    The rule is :func:`apo.spatial.pose_defect` (``tol.rotation``); a failing pose raises
    ``InputFormatError`` naming the file and the pose.
    """
    defect = pose_defect(x)
    if defect is not None:
        k, what, description = defect
        problem = "has no rotation in its 3x3 block" if what == "rotation" else description
        raise InputFormatError(f"{path}: X_EG[{k}] {problem}")
    return x[:, :3, :3]


def write_pose_csv(
    path: str | Path,
    times: npt.ArrayLike,
    X_EG: npt.ArrayLike,
    *,
    units: str,
    extra: Mapping[str, npt.ArrayLike] | None = None,
) -> Path:
    """Write poses of G in E as a pose CSV with a header (read back by :func:`read_pose_csv`).

    Parameters
    ----------
    path : str or Path
        Output file (overwritten).
    times : array_like, shape (N,), seconds
        Strictly increasing time stamps.
    X_EG : array_like, shape (N, 4, 4), metres
        Poses of G in E.
    units : {"mm", "cm", "m", "in"}
        Length unit to write positions in.
    extra : mapping of str to array_like, shape (N,), optional
        Further columns, written after the pose in the mapping's order.

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    InputFormatError
        Mismatched shapes, no frames, non-finite values, non-increasing times, a rotation part
        that is not a rotation, or a bad extra column name (empty, a pose column, or containing
        a comma, quote or line break).

    Notes
    -----
    Numbers are written with ``repr`` (shortest round-trip form); quaternions with
    ``qw >= 0``. Positions round-trip exactly up to the units conversion, rotations to
    about 1e-15.
    """
    path = Path(path)
    scale = _scale(units, str(path))
    t = np.asarray(times, dtype=np.float64)
    x = np.asarray(X_EG, dtype=np.float64)
    if t.ndim != 1 or t.shape[0] == 0:
        raise InputFormatError(f"{path}: times must have shape (N,) with N > 0, got {t.shape}")
    n = t.shape[0]
    if x.shape != (n, 4, 4):
        raise InputFormatError(f"{path}: X_EG must have shape ({n}, 4, 4), got {x.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(x))):
        raise InputFormatError(f"{path}: times and X_EG must be finite")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise InputFormatError(
            f"{path}: times must strictly increase: frame {k} has t = {t[k]} after {t[k - 1]}"
        )
    r = _check_rotations(path, x)
    cols: list[tuple[str, FloatArray]] = []
    for name, values in (extra or {}).items():
        if not name or name.lower() in CSV_COLUMNS or any(c in name for c in ',"\r\n'):
            raise InputFormatError(f"{path}: bad extra column name {name!r}")
        arr = np.asarray(values, dtype=np.float64)
        if arr.shape != (n,):
            raise InputFormatError(
                f"{path}: extra column {name!r} must have shape ({n},), got {arr.shape}"
            )
        cols.append((name, arr))
    out = [",".join([*CSV_COLUMNS, *(c for c, _ in cols)])]
    for k in range(n):
        q = quaternion_from_matrix(r[k])
        p = x[k, :3, 3] / scale
        vals = [t[k], *p, *q, *(a[k] for _, a in cols)]
        out.append(",".join(repr(float(v)) for v in vals))
    path.write_text("\n".join(out) + "\n", encoding="utf-8")
    return path


# --------------------------------------------------------------------------------------------
# Any demonstration file
# --------------------------------------------------------------------------------------------


def load_demonstration(
    path: str | Path,
    *,
    units: str | None = None,
    grasped: str | Path | None = None,
    environment: str | Path | None = None,
    fps: float | None = None,
    camera_poses: bool = True,
) -> Demonstration:
    """Read a demonstration from a ``.pose.list`` or a pose CSV, chosen by the file name.

    Parameters
    ----------
    path : str or Path
        ``*.list`` (``.pose.list``) or ``*.csv``.
    units : {"mm", "cm", "m", "in"}, optional
        Length unit of the file; :data:`DEFAULT_UNITS` (mm) if None.
    grasped, environment : str or Path, optional
        Model files overriding those the file names (used as given).
    fps : float, optional
        Frame rate for a ``.pose.list`` (see :func:`read_pose_list`); ignored for CSV.
    camera_poses : bool
        Keep a ``.pose.list``'s raw camera poses and ids (see :func:`read_pose_list`).

    Returns
    -------
    Demonstration

    Raises
    ------
    InputFormatError
        An unknown suffix, or any error of the reader.
    """
    path = Path(path)
    u = DEFAULT_UNITS if units is None else units
    suffix = path.suffix.lower()
    if suffix == ".list":
        dem = read_pose_list(path, units=u, fps=fps, camera_poses=camera_poses)
    elif suffix == ".csv":
        dem = read_pose_csv(path, units=u)
    else:
        raise InputFormatError(
            f"{path}: unknown demonstration format {suffix!r}; expected .pose.list or .csv"
        )
    if grasped is None and environment is None:
        return dem
    return replace(
        dem,
        grasped_path=dem.grasped_path if grasped is None else Path(grasped),
        environment_path=dem.environment_path if environment is None else Path(environment),
    )


def write_pose_list(
    path: str | Path,
    X_EG: npt.ArrayLike,
    *,
    units: str,
    models: tuple[str | Path, str | Path],
    tags: tuple[int, int] = (0, 1),
) -> Path:
    r"""Write poses of G in E as a ``.pose.list`` (the exact inverse of :func:`read_pose_list`).

    The camera frame of the file is the environment frame: each scene has the pose of G
    (``X_EG``) and the identity for E, so that ``inv(X_CE) @ X_CG`` gives ``X_EG`` back.

    Parameters
    ----------
    path : str or Path
        Output file (overwritten).
    X_EG : array_like, shape (N, 4, 4), metres
        Poses of G in E, one per scene (``N >= 1``).
    units : {"mm", "cm", "m", "in"}
        Length unit to write positions in.
    models : (str or Path, str or Path)
        Model files of G and E as the list should name them: relative to the folder of
        ``path`` (as the reader resolves them) or absolute.
    tags : (int, int)
        Ids written at the start of the pose lines of G and E.

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    InputFormatError
        Wrong shape, no scene, non-finite values, a rotation part that is not a rotation,
        an empty model path or one with a line break.

    Notes
    -----
    Rotations are written as a unit axis and an angle in ``[0, pi]`` (axis ``1 0 0`` for
    the identity); numbers with ``repr``, so a read gives back the poses to about 1e-15.
    """
    path = Path(path)
    scale = _scale(units, str(path))
    x = np.asarray(X_EG, dtype=np.float64)
    if x.ndim != 3 or x.shape[1:] != (4, 4) or x.shape[0] == 0:
        raise InputFormatError(f"{path}: X_EG must have shape (N, 4, 4), N > 0, got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise InputFormatError(f"{path}: X_EG must be finite")
    r = _check_rotations(path, x)
    names = [str(m) for m in models]
    if len(names) != 2 or any(not m.strip() or "\n" in m or "\r" in m for m in names):
        raise InputFormatError(f"{path}: need two model paths without line breaks, got {names}")
    from scipy.spatial.transform import Rotation

    rotvec = Rotation.from_matrix(r).as_rotvec()
    out = ["No of Models: 2", *names, "", f"No of Scenes: {x.shape[0]}"]
    identity = f"{int(tags[1])} 0.0 0.0 0.0 1.0 0.0 0.0 0.0"
    for k in range(x.shape[0]):
        angle = float(np.linalg.norm(rotvec[k]))
        axis = rotvec[k] / angle if angle > 0 else np.array([1.0, 0.0, 0.0])
        vals = [*(x[k, :3, 3] / scale), *axis, angle]
        out.append(f"{int(tags[0])} " + " ".join(repr(float(v)) for v in vals))
        out.append(identity)
        out.append("")
    path.write_text("\n".join(out), encoding="utf-8")
    return path
