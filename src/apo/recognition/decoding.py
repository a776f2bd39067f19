"""Decoding a state sequence from per-frame costs: Viterbi passes and run helpers."""

from __future__ import annotations

import numpy as np

from apo.recognition.types import BoolArray, FloatArray, IntArray

__all__ = [
    "constrained_path",
    "near_pairs",
    "reachable",
    "run_bounds",
    "viterbi",
    "viterbi_uniform",
]


def viterbi(emission: FloatArray, transition: FloatArray) -> tuple[IntArray, float]:
    """Minimum-cost state path.

    Parameters
    ----------
    emission : ndarray, shape (N, K)
        Cost of state k at frame t.
    transition : ndarray, shape (K, K)
        Cost of going from state i (row) to state j (column); 0 on the diagonal.

    Returns
    -------
    path : ndarray of int, shape (N,)
    cost : float

    Examples
    --------
    Frame 1 prefers state 1 by 3; two switches cost 2, so the path visits it:

    >>> e = np.array([[0.0, 5], [3, 0], [0, 5]])
    >>> path, cost = viterbi(e, np.array([[0.0, 1], [1, 0]]))
    >>> path.tolist(), cost
    ([0, 1, 0], 2.0)

    With switches costing 2 each, staying in state 0 (cost 3) is cheaper than 4:

    >>> path, cost = viterbi(e, np.array([[0.0, 2], [2, 0]]))
    >>> path.tolist(), cost
    ([0, 0, 0], 3.0)
    """
    n, k = emission.shape
    back = np.empty((n, k), dtype=np.int64)
    acc = emission[0].copy()
    back[0] = np.arange(k)
    for t in range(1, n):
        tot = acc[:, None] + transition
        arg = np.argmin(tot, axis=0)
        back[t] = arg
        acc = tot[arg, np.arange(k)] + emission[t]
    path = np.empty(n, dtype=np.int64)
    path[-1] = int(np.argmin(acc))
    cost = float(acc[path[-1]])
    for t in range(n - 1, 0, -1):
        path[t - 1] = back[t, path[t]]
    return path, cost


def viterbi_uniform(emission: FloatArray, switch: float) -> IntArray:
    """Minimum-cost path when every change costs ``switch``: O(N K) instead of O(N K^2).

    Equivalent to :func:`viterbi` with ``transition = switch`` off the diagonal.
    """
    n, k = emission.shape
    back = np.empty((n, k), dtype=np.int64)
    acc = emission[0].copy()
    back[0] = np.arange(k)
    ar = np.arange(k)
    for t in range(1, n):
        j = int(np.argmin(acc))
        move = acc[j] + switch < acc
        back[t] = np.where(move, j, ar)
        acc = np.where(move, acc[j] + switch, acc) + emission[t]
    path = np.empty(n, dtype=np.int64)
    path[-1] = int(np.argmin(acc))
    for t in range(n - 1, 0, -1):
        path[t - 1] = back[t, path[t]]
    return path


# --------------------------------------------------------------------------------------------
# Adapters to the contact, correction, DOF and transition modules


def reachable(feasible: BoolArray) -> BoolArray:
    """Transitive closure of the direct-transition relation (i can reach j), shape (K, K)."""
    r = feasible.copy()
    k = len(r)
    for m in range(k):
        r |= r[:, m : m + 1] & r[m : m + 1, :]
    return r


def near_pairs(obs: IntArray, k_count: int, window: int) -> BoolArray:
    """Pairs of candidates observed within ``window`` frames of each other, shape (K, K)."""
    n = len(obs)
    near = np.zeros((k_count, k_count), dtype=bool)
    # Candidates present in each window of frames [t, t + window].
    onehot = np.zeros((n + 1, k_count))
    onehot[np.arange(n) + 1, obs] = 1.0
    cum = np.cumsum(onehot, axis=0)
    step = max(1, window // 2)
    for a in range(0, n, step):
        b = min(n, a + window + step + 1)
        present = np.flatnonzero(cum[b] - cum[a] > 0)
        near[np.ix_(present, present)] = True
    return near


def run_bounds(labels: IntArray) -> list[tuple[int, int]]:
    """(first, last) of each run of equal consecutive values."""
    n = len(labels)
    starts = np.flatnonzero(np.r_[True, labels[1:] != labels[:-1]])
    ends = np.r_[starts[1:] - 1, n - 1]
    return [(int(a), int(b)) for a, b in zip(starts, ends, strict=True)]


def constrained_path(
    emission: FloatArray,
    feasible: BoolArray,
    switch: float,
    jump: float,
    same: BoolArray | None = None,
    same_cost: float = 0.0,
) -> IntArray:
    """Viterbi path where a change costs ``switch``, plus ``jump`` if it is not direct.

    Where ``same[i, j]`` (a change that keeps every DOF number), ``same_cost`` is added.
    """
    trans = np.where(feasible, switch, switch + jump)
    if same is not None:
        trans = trans + same_cost * same
    np.fill_diagonal(trans, 0.0)
    path, _cost = viterbi(emission, trans)
    return path
