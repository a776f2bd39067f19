"""Robot-motion tracks for the report: the planned trajectory and the simulated execution.

``apo report task.json --motion motion.json`` reads, beside ``motion.json`` (schema
``apo.motion/1``, ``docs/motion.md``):

- ``motion.csv``: the planned pose trajectory of the grasped object, columns
  ``t, x, y, z, qw, qx, qy, qz`` (seconds, the motion's units, environment frame) and,
  where present, ``primitive`` (index into ``motion.json`` ``primitives``): each sample is
  labelled with its primitive (``"2 push_to translation"``);
- ``replay.csv`` and ``replay.json`` (written by ``apo replay --out DIR``), where present
  beside it (or given by ``apo report --replay``): the executed trajectory in the simulator,
  labelled with the primitive running and coloured by the contact state the simulation
  reached (``visits``), with the verdict.

Without ``motion.csv`` the planned track is the start pose followed by each primitive's
target pose (one sample per primitive, one second apart).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from apo.errors import InputFormatError
from apo.io.jsonfile import read_json
from apo.report.html import MotionTrack

__all__ = ["read_motion_tracks", "read_pose_track_csv", "read_replay_track"]

_COLS = ("t", "x", "y", "z", "qw", "qx", "qy", "qz")


def _primitive_label(p: Mapping[str, Any]) -> str:
    parts = [str(p.get("index", "?")), str(p.get("kind", "?"))]
    if p.get("space"):
        parts.append(str(p["space"]))
    if p.get("type"):
        parts.append(f"({p['type']})")
    if p.get("to"):
        parts.append(f"-> {p['to']}")
    return " ".join(parts)


def read_pose_track_csv(
    path: str | Path, *, units: str, labels: Sequence[str] = ()
) -> tuple[np.ndarray, np.ndarray, list[str], list[int | None]]:
    """Read a ``t,x,y,z,qw,qx,qy,qz[,primitive]`` CSV.

    Returns times, poses (metres), a label per sample and its primitive index (or None).

    Raises
    ------
    InputFormatError
        Missing columns, values that are not numbers, zero quaternions, times going back.
    """
    from apo.spatial import pose_from_position_quaternion
    from apo.task import UNITS

    p = Path(path)
    try:
        rows = list(csv.DictReader(io.StringIO(p.read_text(encoding="utf-8"))))
    except OSError as exc:
        raise InputFormatError(f"{p}: cannot read: {exc.strerror or exc}") from None
    if not rows:
        raise InputFormatError(f"{p}: no samples")
    missing = [c for c in _COLS if c not in rows[0]]
    if missing:
        raise InputFormatError(f"{p}: missing column(s) {', '.join(missing)}")
    vals = np.empty((len(rows), 8))
    for i, r in enumerate(rows):
        try:
            vals[i] = [float(r[c]) for c in _COLS]
        except (TypeError, ValueError):
            raise InputFormatError(f"{p}: line {i + 2}: not a number in {r}") from None
    if np.any(np.diff(vals[:, 0]) < 0):
        raise InputFormatError(f"{p}: times go backwards")
    k = UNITS[units]
    X = np.empty((len(rows), 4, 4))
    for i, v in enumerate(vals):
        n = float(np.linalg.norm(v[4:]))
        if not n > 0:
            raise InputFormatError(f"{p}: line {i + 2}: zero quaternion")
        X[i] = pose_from_position_quaternion(v[1:4] * k, v[4:] / n)
    prims = [_primitive_index(r.get("primitive"), len(labels)) for r in rows]
    out_labels = [
        labels[k] if k is not None else (r.get("primitive") or "").strip() or p.stem
        for k, r in zip(prims, rows, strict=True)
    ]
    return vals[:, 0], X, out_labels, prims


def _primitive_index(value: str | None, n: int) -> int | None:
    """Primitive of a sample (column ``primitive``: an index, "3" or "3.0"), None if none."""
    try:
        k = float((value or "").strip())
    except ValueError:
        return None
    return int(k) if k.is_integer() and 0 <= k < n else None


def _targets_track(doc: Mapping[str, Any], k: float, labels: list[str]) -> MotionTrack:
    from apo.spatial import pose_from_position_quaternion

    poses = [doc["start_pose"]] + [p["target"]["pose"] for p in doc["primitives"]]
    X = np.array(
        [
            pose_from_position_quaternion(
                np.asarray(q["position"], dtype=float) * k, np.asarray(q["quaternion"])
            )
            for q in poses
        ]
    )
    return MotionTrack(
        name="planned motion (targets)",
        kind="planned",
        times=np.arange(len(poses), dtype=float),
        X_EG=X,
        labels=["start", *labels],
        note="no motion.csv: start pose and each primitive's target pose",
    )


def read_motion_tracks(
    path: str | Path, *, units: str
) -> tuple[list[MotionTrack], list[dict[str, Any]]]:
    """Read the planned (and, where present, executed) tracks of ``motion.json``.

    Parameters
    ----------
    path : str or Path
        ``motion.json`` (schema ``apo.motion/1``).
    units : str
        The task's units (the tracks are returned in metres whatever the file's).

    Returns
    -------
    tracks : list of MotionTrack
    files : list of dict
        Inputs-panel entries of the further files read (``motion.csv``, ``replay.csv``).
    """
    from apo.report.sources import file_entry
    from apo.task import UNITS

    p = Path(path)
    doc = read_json(p)
    if not isinstance(doc, dict) or doc.get("schema") != "apo.motion/1":
        raise InputFormatError(f"{p}: not a motion.json (schema apo.motion/1 expected)")
    try:
        munits = str(doc["units"])
        k = UNITS[munits]
        labels = [_primitive_label(q) for q in doc["primitives"]]
        from_states = [q.get("from") for q in doc["primitives"]]
    except (KeyError, TypeError, AttributeError) as exc:
        raise InputFormatError(f"{p}: missing or bad field {exc}") from None
    del units  # the tracks are in metres; the page converts to the task's units
    tracks: list[MotionTrack] = []
    files: list[dict[str, Any]] = []
    csv_path = p.with_name("motion.csv")
    if csv_path.is_file():
        t, X, lab, prim = read_pose_track_csv(csv_path, units=munits, labels=labels)
        sids = [None if q is None else from_states[q] for q in prim]
        tracks.append(MotionTrack("planned motion", "planned", t, X, lab, state_ids=sids))
        files.append(file_entry("planned trajectory", csv_path))
    else:
        try:
            tracks.append(_targets_track(doc, k, labels))
        except (KeyError, TypeError) as exc:
            raise InputFormatError(f"{p}: missing or bad field {exc}") from None
    if p.with_name("replay.json").is_file() or p.with_name("replay.csv").is_file():
        track, rfiles = read_replay_track(p.parent, units=munits)
        tracks.append(track)
        files += rfiles
    return tracks, files


def _at(t: np.ndarray, spans: Sequence[Mapping[str, Any]], key: str) -> list[Any]:
    """For each time in ``t``: ``span[key]`` of the span whose ``t: [a, b]`` contains it."""
    out: list[Any] = [None] * len(t)
    for sp in spans:
        a, b = (float(v) for v in sp["t"])
        for i in np.flatnonzero((t >= a - 1e-9) & (t <= b + 1e-9)):
            if out[i] is None:
                out[i] = sp.get(key)
    return out


def read_replay_track(path: str | Path, *, units: str) -> tuple[MotionTrack, list[dict[str, Any]]]:
    """Read the simulated execution written by ``apo replay --out DIR``.

    Parameters
    ----------
    path : str or Path
        ``replay.json``, ``replay.csv`` or the folder holding them.
    units : str
        Units of ``replay.csv`` when ``replay.json`` does not say (its ``"units"``).

    Returns
    -------
    track : MotionTrack
        Samples labelled with the primitive running (``"3 slide (reached)"``) and the
        contact state the simulation was in (``replay.json`` ``visits``), the verdict as note.
    files : list of dict
        Inputs-panel entries of the files read.
    """
    from apo.report.sources import file_entry

    p = Path(path)
    folder = p if p.is_dir() else p.parent
    csv_path, json_path = folder / "replay.csv", folder / "replay.json"
    if not csv_path.is_file():
        raise InputFormatError(f"{csv_path}: file not found (written by apo replay --out DIR)")
    verdict: Mapping[str, Any] = {}
    files = []
    if json_path.is_file():
        doc = read_json(json_path)
        if not isinstance(doc, dict):
            raise InputFormatError(f"{json_path}: expected a JSON object")
        verdict = doc
        files.append(file_entry("replay verdict", json_path))
    t, X, _lab, _prim = read_pose_track_csv(csv_path, units=str(verdict.get("units") or units))
    files.append(file_entry("executed trajectory", csv_path))
    try:
        prims = _at(t, verdict.get("primitives") or [], "index")
        kinds = {int(q["index"]): q for q in verdict.get("primitives") or []}
        states = _at(t, verdict.get("visits") or [], "state")
    except (KeyError, TypeError, ValueError) as exc:
        raise InputFormatError(f"{json_path}: bad primitives/visits: {exc}") from None
    labels = []
    for k in prims:
        q = kinds.get(int(k)) if k is not None else None
        labels.append(
            f"{q['index']} {q.get('kind', '?')} ({q.get('outcome', '?')})" if q else "executed"
        )
    note = str(verdict.get("verdict") or verdict.get("summary") or "")
    return (
        MotionTrack(
            "simulated execution",
            "executed",
            t,
            X,
            labels,
            note=note,
            state_ids=[None if v is None else str(v) for v in states],
        ),
        files,
    )
