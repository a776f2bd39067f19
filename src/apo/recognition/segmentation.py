"""Segmentation block by block: costs and Viterbi passes in bounded working memory.

Stages 3 and 5 of ``docs/recognition.md``. The cost of every candidate at every frame
(:mod:`apo.recognition.costs`) is computed for one block of ``BLOCK_FRAMES`` frames at a
time and handed to a Viterbi decoder fed block by block
(:mod:`apo.recognition.decoding`), so the working arrays are ``block x elements`` and
``block x candidates`` whatever the length of the demonstration; the element distances
are computed over spans of ``DISTANCE_BLOCKS`` blocks and dropped after their span. What
is kept for the whole sequence is per frame and small: the first pass keeps the cost of
each frame's observed state (8 bytes a frame), one bit per frame and state, and the
distances of each frame's observed elements (8 bytes each); the second pass computes the
distances of the elements its candidates claim again, span by span, and keeps the costs
of the candidates it can choose from (8 bytes a frame per analysed candidate) and a
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
from apo.recognition.distances import FixedDistances, StreamedDistances
from apo.recognition.types import (
    BoolArray,
    CandidateState,
    FloatArray,
    IntArray,
    Scene,
)

__all__ = [
    "ObservedDistances",
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


#: Cost cells (frames x candidates) of a block at most: a block has ``BLOCK_FRAMES`` frames,
#: fewer where the candidates are many (a long noisy demonstration shows more observed
#: states: 227 at 30,000 synthetic frames, whose blocks of 1,024 frames made 1.9 MB arrays
#: of costs, several at once). The same numbers whatever the block (row by row).
BLOCK_CELLS = 64 * 1024

#: Frames of a block at least, however many the candidates.
MIN_BLOCK_FRAMES = 128


def cost_block(candidates: int) -> int:
    """Frames of a block of costs of ``candidates`` columns (``BLOCK_CELLS``).

    >>> cost_block(8), cost_block(227), cost_block(10_000)
    (1024, 288, 128)
    """
    fit = BLOCK_CELLS // max(1, candidates)
    return min(BLOCK_FRAMES, max(MIN_BLOCK_FRAMES, fit - fit % 32))


#: The distances are computed over spans of ``DISTANCE_BLOCKS`` cost blocks of frames
#: (:class:`~apo.recognition.distances.StreamedDistances`): a few numpy calls per element
#: and span, whatever its length.
DISTANCE_BLOCKS = 4


def distance_span() -> int:
    """Frames per span of the distances (read at each call, as ``BLOCK_FRAMES``)."""
    return max(1, DISTANCE_BLOCKS * BLOCK_FRAMES)


class ObservedDistances:
    """The distances of each frame's observed elements, kept from the first pass.

    What the second pass needs of the elements that no analysed candidate claims: their
    distances at the frames where they were observed (the cost of leaving an observed
    element out). One number per frame and observed element, in frame order and, within a
    frame, in the order of its observed state's columns (``EmissionLayout.cols``).
    """

    def __init__(self, layout: EmissionLayout, labels: IntArray) -> None:
        self.ukeys = layout.ukeys
        width = max((len(c) for c in layout.cols), default=0)
        self.cols = np.full((len(layout.cols), width), -1, dtype=np.int64)
        for k, c in enumerate(layout.cols):
            self.cols[k, : len(c)] = c
        counts = np.array([len(c) for c in layout.cols], dtype=np.int64)
        self.values = np.empty(int(counts[labels].sum()) if len(labels) else 0)
        self.filled = 0

    def where(self, lab: IntArray) -> tuple[IntArray, IntArray]:
        """Rows (frames of the block) and first-pass columns of the block's observed elements."""
        c = self.cols[lab]
        rows, j = np.nonzero(c >= 0)
        return rows, c[rows, j]

    def keep(self, lab: IntArray, dist: FloatArray) -> None:
        """Append the observed elements' distances of the next block (``dist``: all columns)."""
        rows, cols = self.where(lab)
        self.values[self.filled : self.filled + len(rows)] = dist[rows, cols]
        self.filled += len(rows)


def first_pass(
    scene: Scene, observed: Observations, dists: StreamedDistances, block: int | None = None
) -> tuple[IntArray, FloatArray, ObservedDistances]:
    """Segment without the direct-transition test (every change costs ``switch``).

    Returns ``path0`` (the observed state chosen at each frame), ``own``, the cost of
    each frame's observed state there (what :func:`~apo.recognition.candidates.
    analyse_candidate` ranks a state's frames by), and the distances of each frame's
    observed elements (for :func:`segment`). Outlier frames cost nothing to any state.
    """
    w = scene.costs
    labels = observed.labels
    dec = UniformViterbi(len(observed.keys), w.switch)
    own = np.empty(scene.n)
    enc = enclosed_frames(observed.keys, labels, scene.outliers)
    lay = EmissionLayout(observed.keys, [s.touching for s in observed.states])
    seen = ObservedDistances(lay, labels)
    for a, b in frame_blocks(scene.n, cost_block(len(observed.keys)) if block is None else block):
        lab = labels[a:b]
        dist = dists.rows(a, b, lay.ukeys, distance_span())
        seen.keep(lab, dist)
        e = emission_costs(FixedDistances(lay.ukeys, dist), lay, lab, w, enc[a:b])
        own[a:b] = e[np.arange(b - a), lab]
        dec.feed(np.where(scene.outliers[a:b, None], 0.0, e))
    return dec.path()[0], own, seen


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
    dists: StreamedDistances,
    observed: Observations,
    seen: ObservedDistances,
    block: int | None = None,
) -> Segmentation:
    """Constrained segmentation over the analysed candidates, block by block.

    Only analysed candidates can be chosen (the others cost ``inf`` at every frame), so
    only their columns are decoded: the path is the whole-sequence Viterbi path over every
    candidate, the first of equal costs taken in the same order. ``seen``: the first
    pass's distances of the observed elements (:func:`first_pass`).
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
    blocks = _SecondPassDistances(dists, seen, lay, an)
    for a, b in frame_blocks(scene.n, cost_block(len(an.keys)) if block is None else block):
        e = candidate_costs(
            blocks.at(a, b, labels[a:b]), lay, an.candidates, an.bridges,
            labels[a:b], w, start=a, enclosed=enc[a:b],
        )[:, columns]  # fmt: skip
        e = np.where(scene.outliers[a:b, None] & np.isfinite(e), 0.0, e)
        costs[a:b] = e
        dec.feed(e)
    canon = canonical_ids(an.candidates)
    return Segmentation(canon[columns[dec.path()[0]]], canon[labels], columns, costs)


#: The distance (in thresholds) put where the second pass needs none: an element that no
#: candidate it costs claims, at a frame where it was not observed. At least 1, so that
#: such an element, were it counted as observed, would cost nothing either.
UNNEEDED = 2.0


class _SecondPassDistances:
    """The element distances of the second pass, block by block, exact where they count.

    The cost of an analysed candidate (and of the observed states that bridges join) at a
    frame reads the distances of its claimed elements and of the elements observed there,
    nothing else: those are computed again over their spans (the claimed ones) or taken
    from the first pass (the observed ones); the rest is ``UNNEEDED``. So the costs of the
    columns decoded are those of every distance kept from the first pass, bit for bit.
    """

    def __init__(
        self, dists: StreamedDistances, seen: ObservedDistances, lay: EmissionLayout, an: Analysis
    ) -> None:
        upos = {e: u for u, e in enumerate(lay.ukeys)}
        used = [k for k, c in enumerate(an.candidates) if c is not None]
        used += [k for _c, _f, pair in an.bridges for k in pair]
        claimed = sorted({e for k in used for e in an.keys[k]})
        self.claimed, self.claimed_at = claimed, [upos[e] for e in claimed]
        self.pos = np.array([upos[e] for e in seen.ukeys], dtype=np.int64)
        self.dists, self.seen, self.ukeys = dists, seen, lay.ukeys
        self.read = 0

    def at(self, a: int, b: int, lab: IntArray) -> FixedDistances:
        """Return the distances at frames ``a:b`` (observed states ``lab``), blocks in order."""
        dist = np.full((b - a, len(self.ukeys)), UNNEEDED)
        if self.claimed:
            dist[:, self.claimed_at] = self.dists.rows(a, b, self.claimed, distance_span())
        rows, cols = self.seen.where(lab)
        dist[rows, self.pos[cols]] = self.seen.values[self.read : self.read + len(rows)]
        self.read += len(rows)
        return FixedDistances(self.ukeys, dist)


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
