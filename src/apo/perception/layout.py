"""Numbered image folders and ``timestamps.txt``: the layout shared by frames and stereo folders.

``NAME/000000.png, NAME/000001.png, ...`` (six digits, from 000000 without gaps) and an
optional ``timestamps.txt`` (one increasing time in seconds per frame; blank lines and
``#`` comments skipped). Used by :mod:`apo.perception.frames` and :mod:`apo.perception.stereo`.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from apo.errors import InputFormatError
from apo.typing import FloatArray

__all__ = ["check_numbering", "frame_indices", "read_times"]

_FRAME_NAME = re.compile(r"^(\d{6})\.png$")


def frame_indices(folder: Path) -> list[int]:
    """Return the sorted frame numbers of ``folder/NNNNNN.png`` (other PNG names: error)."""
    if not folder.is_dir():
        raise InputFormatError(f"{folder}: folder not found (expected {folder.name}/NNNNNN.png)")
    indices = []
    for entry in folder.iterdir():
        m = _FRAME_NAME.match(entry.name)
        if m:
            indices.append(int(m.group(1)))
        elif entry.suffix.lower() == ".png":
            raise InputFormatError(
                f"{entry}: frame files must be named with six digits, e.g. 000000.png"
            )
    return sorted(indices)


def read_times(path: Path, n: int) -> FloatArray:
    """Read ``timestamps.txt``: ``n`` finite, increasing times in seconds."""
    times: list[float] = []
    for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        try:
            times.append(float(s))
        except ValueError:
            raise InputFormatError(
                f"{path}:{lineno}: expected one time in seconds, got {s!r}"
            ) from None
    t = np.asarray(times, dtype=np.float64)
    if len(t) != n:
        raise InputFormatError(f"{path}: {len(t)} times for {n} frames; expected one per frame")
    if not np.all(np.isfinite(t)):
        raise InputFormatError(f"{path}: times must be finite")
    bad = np.nonzero(np.diff(t) <= 0)[0]
    if len(bad):
        raise InputFormatError(f"{path}: times must increase; frame {bad[0] + 1} does not")
    return t


def check_numbering(root: Path, name: str, indices: Sequence[int]) -> None:
    """Raise unless ``indices`` are 0, 1, 2, ... (frames of ``root/name``)."""
    if not indices:
        raise InputFormatError(f"{root / name}: no frames (expected {name}/000000.png, ...)")
    for expected, got in enumerate(indices):
        if got != expected:
            raise InputFormatError(
                f"{root / name / f'{expected:06d}.png'}: missing; frames must be numbered "
                f"from 000000 without gaps"
            )
