"""Where the report's data comes from: a recognition in hand, or the files of an analysis.

``apo analyze`` and ``apo demo`` hand the :class:`~apo.recognition.Recognition` and the
observed poses to :func:`frames_from_recognition`; ``apo report task.json`` reads
``frames.csv`` beside ``task.json`` (:func:`read_frames_csv`), the models named in
``task.json`` (:func:`load_models`) and, with ``--motion``, ``motion.json``
(:func:`apo.report.motion.read_motion_tracks`).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from apo.errors import ApoError, InputFormatError
from apo.outputs import sha256_file
from apo.report.html import FrameTrack
from apo.typing import FloatArray

if TYPE_CHECKING:
    from apo.geometry import Polyhedron
    from apo.recognition import Recognition

__all__ = [
    "file_entry",
    "frames_from_recognition",
    "inputs_summary",
    "load_models",
    "read_frames_csv",
    "recognition_report",
]

_POSE_COLS = ("x", "y", "z", "qw", "qx", "qy", "qz")


def frames_from_recognition(
    rec: Recognition,
    X_observed: npt.ArrayLike | None = None,
    X_corrected: npt.ArrayLike | None = None,
) -> FrameTrack:
    """Per-frame track of a recognition: states, residuals, flags and the poses given.

    Parameters
    ----------
    rec : Recognition
    X_observed : array_like, shape (N, 4, 4), metres, optional
        The observed poses (default: ``rec.X_observed``).
    X_corrected : array_like, shape (N, 4, 4), metres, optional
        The corrected poses (default: ``rec.X_corrected``; observed where not converged).
    """
    if X_corrected is None:
        X_corrected = rec.X_corrected
    if X_observed is None:
        X_observed = rec.X_observed
    n = len(rec.state_of_frame)

    def poses(X: npt.ArrayLike | None) -> FloatArray | None:
        a = None if X is None else np.asarray(X, dtype=np.float64)
        return a if a is not None and a.shape == (n, 4, 4) else None  # (0, 4, 4): not kept

    return FrameTrack(
        times=np.asarray(rec.times, dtype=np.float64),
        state_ids=rec.state_of_frame,  # read only: no copy
        X_observed=poses(X_observed),
        X_corrected=poses(X_corrected),
        residual_before=np.asarray(rec.residual_before, dtype=np.float64),
        residual_after=np.asarray(rec.residual_after, dtype=np.float64),
        converged=np.asarray(rec.converged, dtype=bool),
        repaired=np.asarray(rec.repaired, dtype=bool),
        source="recognition",
    )


def _pose_block(
    rows: list[dict[str, str]], prefix: str, unit: str, k: float, where: str
) -> FloatArray | None:
    """Poses from columns ``<prefix>x_<unit> ... <prefix>qz``; None if the columns are absent."""
    from apo.spatial import pose_from_position_quaternion

    names = [f"{prefix}{c}_{unit}" if c in "xyz" else f"{prefix}{c}" for c in _POSE_COLS]
    if not rows or any(c not in rows[0] for c in names):
        return None
    vals = _floats(rows, names, where)
    X = np.empty((len(rows), 4, 4))
    for i, v in enumerate(vals):
        q = v[3:]
        nq = float(np.linalg.norm(q))
        if not nq > 0:
            raise InputFormatError(f"{where}: line {i + 2}: zero quaternion in {prefix}q*")
        X[i] = pose_from_position_quaternion(v[:3] * k, q / nq)
    return X


def _floats(rows: list[dict[str, str]], names: Sequence[str], where: str) -> Any:
    try:
        return np.array([[float(r[c]) for c in names] for r in rows], dtype=np.float64)
    except (TypeError, ValueError):
        for i, r in enumerate(rows):
            for c in names:
                try:
                    float(r[c])
                except (TypeError, ValueError):
                    raise InputFormatError(
                        f"{where}: line {i + 2}: column {c}: not a number: {r[c]!r}"
                    ) from None
        raise


def read_frames_csv(path: str | Path, *, units: str) -> FrameTrack:
    """Read ``frames.csv`` (written by ``apo analyze``) into a :class:`FrameTrack`.

    Columns are found by name: ``frame, time_s, state`` (required), ``residual_before_<u>,
    residual_after_<u>, converged, repaired`` and the poses ``obs_x_<u> .. obs_qz``,
    ``cor_x_<u> .. cor_qz`` where present (``<u>`` = ``units``, the task's).

    Raises
    ------
    InputFormatError
        Missing file or column, a value that is not a number, frames out of order.
    """
    from apo.task import UNITS

    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputFormatError(f"{p}: cannot read: {exc.strerror or exc}") from None
    rows = list(csv.DictReader(io.StringIO(text)))
    where = str(p)
    for col in ("frame", "time_s", "state"):
        if not rows or col not in rows[0]:
            raise InputFormatError(f"{where}: no column {col!r} (is this apo's frames.csv?)")
    frame = _floats(rows, ["frame"], where)[:, 0]
    if not np.array_equal(frame, np.arange(len(rows))):
        raise InputFormatError(f"{where}: frames must be 0, 1, 2, ... in order")
    k = UNITS[units]
    u = units

    def opt(col: str) -> Any:
        return _floats(rows, [col], where)[:, 0] if col in rows[0] else None

    before, after = opt(f"residual_before_{u}"), opt(f"residual_after_{u}")
    conv, rep = opt("converged"), opt("repaired")
    return FrameTrack(
        times=_floats(rows, ["time_s"], where)[:, 0],
        state_ids=[r["state"] for r in rows],
        X_observed=_pose_block(rows, "obs_", u, k, where),
        X_corrected=_pose_block(rows, "cor_", u, k, where),
        residual_before=None if before is None else before * k,
        residual_after=None if after is None else after * k,
        converged=None if conv is None else conv != 0,
        repaired=None if rep is None else rep != 0,
        source=p.name,
    )


def file_entry(
    role: str, path: str | Path, *, expected_sha256: str | None = None
) -> dict[str, Any]:
    """One row of the inputs panel: role, path, size, SHA-256 and whether it matches."""
    p = Path(path)
    entry: dict[str, Any] = {"role": role, "path": str(p), "expected_sha256": expected_sha256}
    if not p.is_file():
        entry.update(status="missing", sha256=None, bytes=None)
        return entry
    digest = sha256_file(p)
    status = "ok" if expected_sha256 in (None, digest) else "changed"
    entry.update(status=status, sha256=digest, bytes=p.stat().st_size)
    return entry


def load_models(
    task: Mapping[str, Any], base: str | Path, *, units: str | None = None
) -> tuple[Polyhedron | None, Polyhedron | None, list[dict[str, Any]], list[str]]:
    """Load the two models a ``task.json`` names (paths relative to ``base``).

    A missing or unreadable model is not fatal: the report is drawn without it and a note
    says why. Mesh files (STL, OBJ, PLY) are read in ``units`` (default: the task's units);
    STEP files in the unit they declare.

    Returns
    -------
    grasped, environment : Polyhedron or None
    entries : list of dict
        :func:`file_entry` of each model.
    notes : list of str
        Problems found (missing file, hash mismatch, unreadable model).
    """
    import warnings

    from apo.io.meshes import load_polyhedron

    base = Path(base)
    loaded: list[Polyhedron | None] = []
    entries: list[dict[str, Any]] = []
    notes: list[str] = []
    for role in ("grasped", "environment"):
        ref = task["models"][role]
        p = Path(ref["path"])
        p = p if p.is_absolute() else base / p
        entry = file_entry(f"{role} model", p, expected_sha256=ref.get("sha256"))
        entries.append(entry)
        if entry["status"] == "missing":
            notes.append(f"{role} model not found: {p} (the 3D view shows contacts only)")
            loaded.append(None)
            continue
        if entry["status"] == "changed":
            notes.append(f"{role} model {p} changed since the analysis (SHA-256 differs)")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                loaded.append(load_polyhedron(p, units=units or str(task["units"])))
        except ApoError as exc:
            notes.append(f"{role} model {p} could not be read: {exc}")
            loaded.append(None)
    return loaded[0], loaded[1], entries, notes


def inputs_summary(
    task: Mapping[str, Any], files: Sequence[Mapping[str, Any]] = ()
) -> dict[str, Any]:
    """Return the inputs panel: files with hashes, units, threshold, extras, version."""
    from apo import __version__

    extra = task.get("extra") or {}
    return {
        "source": task.get("source", ""),
        "units": task["units"],
        "frame": task.get("frame", "environment"),
        "threshold": task.get("threshold"),
        "n_frames": task.get("n_frames"),
        "noise": extra.get("noise") if isinstance(extra, Mapping) else None,
        "extra": extra,
        "apo_version": __version__,
        "written": _written(),
        "files": [dict(f) for f in files],
    }


def _written() -> str | None:
    """Time stamp of the page: only from ``SOURCE_DATE_EPOCH`` (reproducible builds), else None.

    Two identical runs must write identical bytes (docs/outputs.md), so the wall clock is
    never embedded.
    """
    import os
    from datetime import UTC, datetime

    epoch = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    if not epoch.isdigit():
        return None
    return datetime.fromtimestamp(int(epoch), UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def recognition_report(
    rec: Recognition,
    *,
    grasped: Polyhedron | None,
    environment: Polyhedron | None,
    X_observed: npt.ArrayLike | None = None,
    files: Sequence[Mapping[str, Any]] = (),
    doc: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Return the report document of a recognition (``apo analyze`` writes it as report.html).

    Write it with :func:`apo.report.html.write_report`. ``doc`` is ``task_to_dict(rec.task)``
    where the caller has it already, or its top-level fields only
    (:attr:`apo.report.writer.TaskJson.head`, the task's text then spliced in by
    ``write_report``). Costs the packing of the per-frame arrays: a few
    milliseconds (``docs/report.md``, ``benchmarks/report.py``).
    """
    from apo.report.html import report_data
    from apo.task import state_spans, task_to_dict

    if doc is None:
        doc = task_to_dict(rec.task)
    return report_data(
        doc,
        grasped=grasped,
        environment=environment,
        frames=frames_from_recognition(rec, X_observed),
        inputs=inputs_summary(doc, files),
        state_ids=None if "states" in doc else [s for s, _a, _b in state_spans(rec.task.states)],
    )
