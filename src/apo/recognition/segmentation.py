"""Segmentation block by block: costs and Viterbi passes in bounded working memory.

Stages 3 and 5 of ``docs/recognition.md``. The cost of every candidate at every frame
(:mod:`apo.recognition.costs`) is computed for one block of ``BLOCK_FRAMES`` frames at a
time and handed to a Viterbi decoder fed block by block
(:mod:`apo.recognition.decoding`), so the working arrays are ``block x elements`` and
``block x candidates`` whatever the length of the demonstration. What is kept for the
whole sequence is per frame and small: the first pass keeps the cost of each frame's
observed state (8 bytes a frame) and one bit per frame and state; the second keeps the
costs of the candidates it can choose from (8 bytes a frame per analysed candidate) and a
back-pointer of one byte per frame and candidate. The results are those of the
whole-sequence computation bit for bit (every value is computed by the same arithmetic,
row by row).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np

from apo.recognition.analysis import Analysis
from apo.recognition.candidates import canonical_ids
from apo.recognition.contacts import Observations
from apo.recognition.costs import (
    EmissionLayout,
    candidate_costs,
    emission_costs,
    enclosed_frames,
)
from apo.recognition.decoding import BLOCK_FRAMES, UniformViterbi, Viterbi
from apo.recognition.distances import DistanceCache, element_distances
from apo.recognition.types import (
    BoolArray,
    CandidateState,
    ElementKey,
    FloatArray,
    IntArray,
    Scene,
)

__all__ = [
    "BlockDistances",
    "Segmentation",
    "first_pass",
    "frame_blocks",
    "same_dof",
    "segment",
]


def frame_blocks(n: int, size: int | None = None) -> Iterator[tuple[int, int]]:
    """``(start, stop)`` of consecutive blocks of at most ``size`` frames covering ``n``.

    ``size`` defaults to the module's ``BLOCK_FRAMES`` (read at each call).

    >>> list(frame_blocks(10, 4))
    [(0, 4), (4, 8), (8, 10)]
    """
    size = max(1, BLOCK_FRAMES if size is None else size)
    for a in range(0, n, size):
        yield a, min(n, a + size)


class BlockDistances(DistanceCache):
    """The rows ``start:stop`` of a :class:`~apo.recognition.distances.DistanceCache`.

    ``get(keys)`` returns ``(stop - start, len(keys))``: the same values as the rows of the
    whole cache (each element's distances are computed once, over every frame, and kept
    there).
    """

    def __init__(self, whole: DistanceCache, start: int, stop: int) -> None:
        super().__init__(*whole.args, whole.theta)
        self.whole, self.start, self.stop = whole, start, stop

    def get(self, keys: Sequence[ElementKey]) -> FloatArray:
        """Distances (in thresholds) of ``keys`` at the block's frames."""
        cache = self.whole.cache
        missing = [k for k in dict.fromkeys(keys) if k not in cache]
        if missing:
            _fill(self.whole, missing)
        if not keys:
            return np.zeros((self.stop - self.start, 0))
        rows = slice(self.start, self.stop)
        return np.stack([cache[k][rows] for k in keys], axis=1)


def _fill(whole: DistanceCache, keys: list[ElementKey]) -> None:
    """Compute the distances of ``keys`` at every frame into ``whole``, a block at a time.

    One ``(frames x keys)`` array is made and filled block by block (the same values, row
    by row, as one pass over every frame); the cache keeps its columns.
    """
    G, E, X = whole.args
    out = np.empty((len(X), len(keys)))
    for a, b in frame_blocks(len(X), DISTANCE_BLOCKS * BLOCK_FRAMES):
        out[a:b] = element_distances(G, E, X[a:b], keys)
        out[a:b] /= whole.theta
    for j, k in enumerate(keys):
        whole.cache[k] = out[:, j]


#: The distances are computed ``DISTANCE_BLOCKS`` cost blocks at a time: a few numpy calls
#: per element and block, whatever its size.
DISTANCE_BLOCKS = 4


def first_pass(
    scene: Scene, observed: Observations, dists: DistanceCache, block: int | None = None
) -> tuple[IntArray, FloatArray]:
    """Segment without the direct-transition test (every change costs ``switch``).

    Returns ``path0`` (the observed state chosen at each frame) and ``own``, the cost of
    each frame's observed state there (what :func:`~apo.recognition.candidates.
    analyse_candidate` ranks a state's frames by). Outlier frames cost nothing to any state.
    """
    w = scene.costs
    labels = observed.labels
    dec = UniformViterbi(len(observed.keys), w.switch)
    own = np.empty(scene.n)
    enc = enclosed_frames(observed.keys, labels, scene.outliers)
    lay = EmissionLayout(observed.keys, [s.touching for s in observed.states])
    for a, b in frame_blocks(scene.n, block):
        lab = labels[a:b]
        bd = BlockDistances(dists, a, b)
        e = emission_costs(bd, lay, lab, w, enc[a:b])
        own[a:b] = e[np.arange(b - a), lab]
        dec.feed(np.where(scene.outliers[a:b, None], 0.0, e))
    return dec.path()[0], own


class Segmentation:
    """The constrained segmentation: chosen and observed candidate per frame, and costs.

    Attributes
    ----------
    path, observed : ndarray of int, shape (N,)
        Chosen and observed candidate of each frame, candidates of the same closure
        identified (:func:`~apo.recognition.candidates.canonical_ids`).
    columns : ndarray of int, shape (U,)
        The candidates the segmentation could choose (analysed ones), ascending.
    costs : ndarray, shape (N, U)
        Their cost at every frame (``docs/recognition.md``; 0 at outlier frames).
    """

    def __init__(
        self, path: IntArray, observed: IntArray, columns: IntArray, costs: FloatArray
    ) -> None:
        self.path, self.observed, self.columns, self.costs = path, observed, columns, costs


def segment(
    scene: Scene,
    an: Analysis,
    dists: DistanceCache,
    observed: Observations,
    block: int | None = None,
) -> Segmentation:
    """Constrained segmentation over the analysed candidates, block by block.

    Only analysed candidates can be chosen (the others cost ``inf`` at every frame), so
    only their columns are decoded: the path is the whole-sequence Viterbi path over every
    candidate, the first of equal costs taken in the same order.
    """
    w = scene.costs
    states = an.states(observed)
    columns = np.flatnonzero([c is not None for c in an.candidates])
    trans = np.where(an.feasible, w.switch, w.switch + w.jump)
    trans = trans + w.same * same_dof(an.candidates)
    np.fill_diagonal(trans, 0.0)
    dec = Viterbi(trans[np.ix_(columns, columns)])
    costs = np.empty((scene.n, len(columns)))
    labels = observed.labels
    enc = enclosed_frames(observed.keys, labels, scene.outliers)
    lay = EmissionLayout(an.keys, [s.touching for s in states])
    for a, b in frame_blocks(scene.n, block):
        e = candidate_costs(
            BlockDistances(dists, a, b), lay, an.candidates, an.bridges,
            labels[a:b], w, start=a, enclosed=enc[a:b],
        )[:, columns]  # fmt: skip
        e = np.where(scene.outliers[a:b, None] & np.isfinite(e), 0.0, e)
        costs[a:b] = e
        dec.feed(e)
    canon = canonical_ids(an.candidates)
    return Segmentation(canon[columns[dec.path()[0]]], canon[labels], columns, costs)


def same_dof(candidates: Sequence[CandidateState | None]) -> BoolArray:
    """Pairs of analysed candidates with the same DOF numbers (six per space), (K, K)."""
    sig = [
        None if c is None else (c.dof.six("translation"), c.dof.six("rotation")) for c in candidates
    ]
    k = len(sig)
    out = np.zeros((k, k), dtype=bool)
    for i in range(k):
        for j in range(i + 1, k):
            if sig[i] is not None and sig[i] == sig[j]:
                out[i, j] = out[j, i] = True
    return out
