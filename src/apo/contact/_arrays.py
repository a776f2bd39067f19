"""Small vectorised array helpers of the contact search (rows of 3-vectors, CSR rows)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from apo.spatial import perpendicular_basis
from apo.typing import BoolArray, FloatArray, IntArray

_EMPTY_I = np.zeros(0, dtype=np.int64)
_EMPTY_F = np.zeros(0, dtype=np.float64)
_EMPTY_3 = np.zeros((0, 3), dtype=np.float64)


def _csr(arrays: Sequence[FloatArray]) -> tuple[IntArray, IntArray, FloatArray]:
    """Row counts, row pointers and stacked rows of a list of (k, 3) arrays."""
    n = np.fromiter((len(a) for a in arrays), dtype=np.int64, count=len(arrays))
    ptr = np.concatenate([[0], np.cumsum(n)[:-1]]).astype(np.int64) if len(n) else _EMPTY_I
    flat = np.concatenate([np.reshape(a, (-1, 3)) for a in arrays]) if len(n) else _EMPTY_3
    return n, ptr, np.asarray(flat, dtype=np.float64)


def _cross3(a: FloatArray, b: FloatArray) -> FloatArray:
    """Cross product of two 3-vectors (much cheaper than ``np.cross`` for one pair)."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


_plane_basis = perpendicular_basis  # the one basis of the plane perpendicular to a unit vector


def _dedupe(
    rays: FloatArray, angle: float, priority: npt.NDArray[np.int64] | None = None
) -> FloatArray:
    """Greedy clustering of unit rays closer than ``angle``.

    Each cluster is represented by its member of highest ``priority`` (the first such), or by
    the normalised mean when no priorities are given.
    """
    if len(rays) <= 1:
        return rays.reshape(-1, 3)
    cos_a = math.cos(angle)
    out: list[FloatArray] = []
    used = np.zeros(len(rays), dtype=bool)
    G = rays @ rays.T
    for i in range(len(rays)):
        if used[i]:
            continue
        members = (~used) & (G[i] >= cos_a)
        members[i] = True
        used |= members
        if priority is None:
            m = rays[members].sum(axis=0)
            out.append(m / np.linalg.norm(m))
        else:
            idx = np.flatnonzero(members)
            out.append(rays[idx[int(np.argmax(priority[idx]))]])
    return np.asarray(out)


def _dot(x: FloatArray, y: FloatArray) -> FloatArray:
    return np.asarray(np.einsum("ij,ij->i", x, y), dtype=np.float64)


def _norm(x: FloatArray) -> FloatArray:
    """Row norms of an (n, 3) array (faster than ``np.linalg.norm(x, axis=1)``)."""
    return np.asarray(np.sqrt(x[:, 0] ** 2 + x[:, 1] ** 2 + x[:, 2] ** 2), dtype=np.float64)


def _cross_rows(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise cross products of (n, 3) arrays (cheaper than ``np.cross``)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _sq_dist(P: FloatArray, C: FloatArray) -> FloatArray:
    """Squared distances (n, m) between the rows of P (n, 3) and C (m, 3), to a few ulps.

    One matrix product ``[P, |P|^2, 1] @ [-2 C, 1, |C|^2]^T`` (``|p|^2 + |c|^2 - 2 p.c``):
    much faster than the differences, and off by at most a few ulps of ``|p|^2 + |c|^2``
    (:func:`_sq_dist_slack`), which the callers' prefilters allow for.
    """
    A = np.empty((len(P), 5))
    A[:, :3] = P
    A[:, 3] = np.einsum("ij,ij->i", P, P)
    A[:, 4] = 1.0
    B = np.empty((5, len(C)))
    B[:3] = -2.0 * C.T
    B[3] = 1.0
    B[4] = np.einsum("ij,ij->i", C, C)
    out: FloatArray = A @ B
    return out


def _sq_dist_slack(P: FloatArray, C: FloatArray) -> float:
    """Return a bound of the rounding error of :func:`_sq_dist` (squared metres)."""
    big = float(np.max(np.abs(P), initial=0.0)) + float(np.max(np.abs(C), initial=0.0))
    return 64 * np.finfo(np.float64).eps * 3 * big * big


def _pairs_from_ball(lists: Any, rows: IntArray) -> tuple[IntArray, IntArray]:
    counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
    if counts.sum() == 0:
        return _EMPTY_I, _EMPTY_I
    i = np.repeat(rows, counts)
    j = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(counts.sum()))
    return i, j


def _expand(ptr: IntArray, cnt: IntArray) -> tuple[IntArray, IntArray, IntArray]:
    """Entries of CSR rows ``ptr[k] : ptr[k] + cnt[k]``: (row k, flat index, slot in row)."""
    total = int(cnt.sum())
    rep = np.repeat(np.arange(len(cnt), dtype=np.int64), cnt)
    slot = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    return rep, ptr[rep] + slot, slot


def _padded(flat: FloatArray, ptr: IntArray, cnt: IntArray) -> FloatArray:
    """CSR rows as a zero-padded array (n, max(cnt), 3)."""
    out = np.zeros((len(cnt), max(int(cnt.max(initial=0)), 1), 3))
    rep, idx, slot = _expand(ptr, cnt)
    out[rep, slot] = flat[idx]
    return out


def _rotate(R: FloatArray, v: FloatArray) -> FloatArray:
    """``R[k] @ v[k]`` for each k."""
    return np.asarray(np.einsum("kij,kj->ki", R, v), dtype=np.float64)


def _member(x: IntArray, sorted_set: IntArray) -> BoolArray:
    """``np.isin(x, sorted_set)`` for a sorted ``sorted_set`` (a binary search per entry)."""
    if len(sorted_set) == 0:
        return np.zeros(len(x), dtype=bool)
    i = np.minimum(np.searchsorted(sorted_set, x), len(sorted_set) - 1)
    return np.asarray(sorted_set[i] == x, dtype=bool)
