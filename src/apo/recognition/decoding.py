"""Decoding a state sequence from per-frame costs: Viterbi passes and run helpers."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from apo.recognition.types import BoolArray, FloatArray, IntArray

__all__ = [
    "BLOCK_FRAMES",
    "UniformViterbi",
    "Viterbi",
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
    dec = Viterbi(transition)
    for a in range(0, len(emission), BLOCK_FRAMES):
        dec.feed(emission[a : a + BLOCK_FRAMES])
    return dec.path()


def viterbi_uniform(emission: FloatArray, switch: float) -> IntArray:
    """Minimum-cost path when every change costs ``switch``: O(N K) instead of O(N K^2).

    Equivalent to :func:`viterbi` with ``transition = switch`` off the diagonal.
    """
    dec = UniformViterbi(emission.shape[1], switch)
    for a in range(0, len(emission), BLOCK_FRAMES):
        dec.feed(emission[a : a + BLOCK_FRAMES])
    return dec.path()[0]


#: Frames per block of the block-wise stages (costs, decoding, ``frames.csv``): their
#: working arrays are ``BLOCK_FRAMES x states`` whatever the length of the demonstration.
BLOCK_FRAMES = 1024


def _small_int(k: int) -> type[np.signedinteger]:
    """Return the smallest signed integer type holding ``0 .. k - 1`` (back-pointers)."""
    return np.int8 if k <= 127 else np.int16 if k <= 32767 else np.int32


class Viterbi:
    """Minimum-cost path fed block by block: memory ``N x K`` small integers, no more.

    ``feed`` the emission ``(B, K)`` of consecutive frames, then ``path()``. The same
    arithmetic as a whole-sequence Viterbi, so the same path bit for bit whatever the
    blocks: for each frame the cheapest predecessor (first on ties) is kept as a
    back-pointer of 1 byte (K <= 127), 2 or 4.
    """

    def __init__(self, transition: FloatArray) -> None:
        self.trans = np.asarray(transition, dtype=np.float64)
        k = len(self.trans)
        self.acc: FloatArray | None = None
        self.back: list[npt.NDArray[np.signedinteger]] = []
        self.dtype = _small_int(k)
        self._tot = np.empty((k, k))

    def feed(self, emission: FloatArray) -> None:
        """Advance over the frames of ``emission`` (shape (B, K))."""
        e = np.asarray(emission, dtype=np.float64)
        back = np.zeros((len(e), len(self.trans)), dtype=self.dtype)
        acc, tot, trans = self.acc, self._tot, self.trans
        first = 0
        if acc is None and len(e):
            acc = e[0].copy()
            back[0] = np.arange(len(trans))
            first = 1
        if acc is not None:
            # the same operations as one frame at a time by index, with the row views made by
            # iterating and ``acc`` (updated in place) viewed as a column once
            col, add, lowest, argmin = acc[:, None], np.add, np.minimum.reduce, tot.argmin
            for row, et in zip(back[first:], e[first:], strict=True):
                add(col, trans, out=tot)
                row[...] = argmin(axis=0)
                lowest(tot, axis=0, out=acc)
                add(acc, et, out=acc)
        self.acc = acc
        self.back.append(back)

    def path(self) -> tuple[IntArray, float]:
        """Return the minimum-cost path over every frame fed, and its cost."""
        back = np.concatenate(self.back) if self.back else np.zeros((0, len(self.trans)))
        n = len(back)
        path = np.empty(n, dtype=np.int64)
        if n == 0 or self.acc is None:
            return path, 0.0
        path[-1] = int(np.argmin(self.acc))
        cost = float(self.acc[path[-1]])
        for t in range(n - 1, 0, -1):
            path[t - 1] = back[t, path[t]]
        return path, cost


class UniformViterbi:
    """Minimum-cost path when every change costs ``switch``, fed block by block.

    Per frame only the cheapest state (an integer) and whether each state was entered from
    it (one bit per state, packed) are kept: ``N x K / 8`` bytes of back-pointers.
    """

    def __init__(self, k: int, switch: float) -> None:
        self.k, self.switch = k, float(switch)
        self.acc: FloatArray | None = None
        self.best: list[npt.NDArray[np.int32]] = []
        self.moved: list[npt.NDArray[np.uint8]] = []

    def feed(self, emission: FloatArray) -> None:
        """Advance over the frames of ``emission`` (shape (B, K))."""
        e = np.asarray(emission, dtype=np.float64)
        best = np.zeros(len(e), dtype=np.int32)
        moved = np.zeros((len(e), self.k), dtype=bool)
        acc, s = self.acc, self.switch
        first = 0
        if acc is None and len(e):
            acc = e[0].copy()
            first = 1
        if acc is not None:
            # the same operations as one frame at a time by index (row views by iterating)
            less, minimum, add, argmin = np.less, np.minimum, np.add, acc.argmin
            for t, et, mt in zip(range(first, len(e)), e[first:], moved[first:], strict=True):
                j = argmin()
                m = acc[j] + s
                less(m, acc, out=mt)
                minimum(acc, m, out=acc)
                add(acc, et, out=acc)
                best[t] = j
        self.acc = acc
        self.best.append(best)
        self.moved.append(np.packbits(moved, axis=1))

    def path(self) -> tuple[IntArray, float]:
        """Return the minimum-cost path over every frame fed, and its cost."""
        best = np.concatenate(self.best) if self.best else np.zeros(0, dtype=np.int32)
        n = len(best)
        path = np.empty(n, dtype=np.int64)
        if n == 0 or self.acc is None:
            return path, 0.0
        moved = np.concatenate(self.moved)
        k = int(np.argmin(self.acc))
        cost = float(self.acc[k])
        path[-1] = k
        for t in range(n - 1, 0, -1):
            if (moved[t, k >> 3] >> (7 - (k & 7))) & 1:
                k = int(best[t])
            path[t - 1] = k
        return path, cost


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
    """Pairs of candidates observed within ``window`` frames of each other, shape (K, K).

    The frames are scanned in overlapping windows of ``window + step + 1`` frames
    (``step = window // 2``); working memory ``K x K`` whatever the number of frames.
    """
    n = len(obs)
    near = np.zeros((k_count, k_count), dtype=bool)
    step = max(1, window // 2)
    for a in range(0, n, step):
        present = obs[a : min(n, a + window + step + 1)]  # repeats set the same pairs
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
