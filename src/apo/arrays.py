"""numpy's ``unique`` and ``median`` without the import of ``numpy.ma`` they make.

numpy's plain ``np.unique(a)`` asks ``np.ma.is_masked(a)`` and ``np.median`` asks
``np.ma.isMaskedArray``: the first call imports ``numpy.ma``, 9 ms of CPU, about 3 % of a
41-frame ``apo analyze`` (docs/recognition.md, "Session 6: whole process"). These give the
same arrays without it, for the arrays apo passes (integer arrays to :func:`unique`, float
arrays to :func:`median`). A leaf module: numpy only.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["median", "unique"]


def unique(a: npt.ArrayLike, axis: int | None = None) -> np.ndarray[Any, Any]:
    """Return ``np.unique(a, axis=axis)`` (sorted distinct values or rows).

    Integer (and boolean) arrays go through numpy's sorting path (asked for the counts, which
    skips the masked-array test): the same values. Other arrays are handed to ``np.unique``
    as they are (a float array's ``-0.0`` and ``0.0`` could come out as either).
    """
    arr = np.asarray(a)
    if arr.dtype.kind not in "biu":
        return np.unique(arr, axis=axis)
    values: np.ndarray[Any, Any] = np.unique(arr, return_counts=True, axis=axis)[0]
    return values


def median(a: npt.ArrayLike, axis: int | None = None) -> Any:
    """Return ``np.median(a, axis=axis)`` of a float array, the same numbers and types.

    As numpy computes it: a partition at the middle (and the last place, where a NaN would
    go), the mean of the one or two middle values, NaN where the partition's last value is
    NaN.
    """
    arr = np.asarray(a)
    if arr.dtype.kind != "f":
        return np.median(arr, axis=axis)
    size = arr.size if axis is None else arr.shape[axis]
    half = size // 2
    kth = [half - 1, half, -1] if size % 2 == 0 else [half, -1]
    if size == 0:
        return np.median(arr, axis=axis)
    part = np.partition(arr, kth, axis=axis)
    if part.shape == ():
        return part.item()
    ax = 0 if axis is None else axis
    index = [slice(None)] * part.ndim
    mid = part.shape[ax] // 2
    index[ax] = slice(mid, mid + 1) if part.shape[ax] % 2 == 1 else slice(mid - 1, mid + 1)
    result = np.mean(part[tuple(index)], axis=ax)
    last = part.take(-1, axis=ax)
    nan = np.isnan(last)
    if not nan.any():
        return result
    if isinstance(result, np.generic):
        return last
    np.copyto(result, last, where=nan)
    return result
