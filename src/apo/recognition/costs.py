"""The cost of every candidate state at every frame (``docs/recognition.md``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from apo.recognition.bridges import Bridge
from apo.recognition.distances import DistanceCache
from apo.recognition.types import (
    BoolArray,
    CandidateState,
    FloatArray,
    IntArray,
    SegmentationCosts,
    StateKey,
)

__all__ = ["EmissionLayout", "candidate_costs", "emission_costs", "enclosed_frames"]


class EmissionLayout:
    """What :func:`emission_costs` needs of the candidates, whatever the frames.

    The element keys of every candidate (sorted), which elements each candidate claims
    (``member``, (U, K)) and which it covers (its own, and those whose feature pair touches
    in it: ``cover``), and the free candidates. Made once per segmentation pass, not per
    block of frames.
    """

    def __init__(
        self,
        keys: Sequence[StateKey],
        touching: Sequence[frozenset[tuple[tuple[str, int], tuple[str, int]]]],
    ) -> None:
        self.keys = keys
        self.ukeys = sorted({e for key in keys for e in key})
        self.free = [k for k, key in enumerate(keys) if not key]
        upos = {e: u for u, e in enumerate(self.ukeys)}
        self.cols = cols = [[upos[e] for e in key] for key in keys]
        self.member = np.zeros((len(self.ukeys), len(keys)))
        for k, c in enumerate(cols):
            self.member[c, k] = 1.0
        # the claimed elements of the candidates with some, one after another
        self.claiming = np.array([k for k, c in enumerate(cols) if c], dtype=np.int64)
        self.claimed = np.array([u for c in cols for u in c], dtype=np.int64)
        self.starts = np.cumsum([0, *[len(c) for c in cols if c][:-1]]).astype(np.int64)
        # Observed elements the candidate leaves out: evidence against it. An element whose
        # feature pair touches in the candidate (e.g. a vertex on an edge when the vertex
        # touches the edge's end vertex) is not left out.
        cover = self.member.copy()
        by_pair: dict[tuple[tuple[str, int], tuple[str, int]], list[int]] = {}
        for u, (_kind, gf, ef) in enumerate(self.ukeys):
            by_pair.setdefault((gf, ef), []).append(u)
        for k, pairs in enumerate(touching):
            rows = [u for pair in pairs for u in by_pair.get(pair, ())]
            cover[rows, k] = 1.0
        self.uncovered = 1.0 - cover


def emission_costs(
    dists: DistanceCache,
    layout: EmissionLayout,
    obs: IntArray,
    w: SegmentationCosts,
    enclosed: BoolArray | None = None,
) -> FloatArray:
    """Cost of every candidate at every frame (``docs/recognition.md``), shape (N, K).

    ``layout``: ``EmissionLayout(keys, touching)`` of the candidates (the same for every
    block of frames). ``enclosed`` (N,): the frames of :func:`enclosed_frames`, where the
    free state costs ``w.enclosed`` more.
    """
    lay = layout
    n = len(obs)
    emission = np.zeros((n, len(lay.keys)))
    if enclosed is not None and w.enclosed:
        emission[:, lay.free] += w.enclosed * enclosed[:, None]
    if not lay.ukeys:
        return emission
    dist = dists.get(lay.ukeys)
    # Claimed elements: the correction residual before correction, max_i |f_i| (paper
    # 4.3.1), of the candidate's elements at the observed pose.
    d2 = dist**2
    for k, cols in enumerate(lay.cols):
        if cols:
            emission[:, k] = w.claim * d2[:, cols].max(axis=1)
    k_obs = int(obs.max()) + 1
    seen = lay.member[:, :k_obs][:, obs].T  # (n, U): element observed at frame t
    missed = w.miss * seen * np.clip(1.0 - dist, 0.0, 1.0) ** 2
    emission += missed @ lay.uncovered
    return emission


def enclosed_frames(keys: Sequence[StateKey], labels: IntArray, outliers: BoolArray) -> BoolArray:
    """Frames observed in contact whose neighbours are too, shape (N,).

    ``labels`` index the observed states ``keys`` (the empty key: free); an outlier frame
    counts as in contact (it tells nothing). At such a frame nothing says G was away from
    E: the free state costs ``enclosed`` more there (:class:`SegmentationCosts`).
    """
    free = np.array([not key for key in keys], dtype=bool)
    contact = ~free[labels] | outliers
    out = contact.copy()
    out[1:] &= contact[:-1]
    out[:-1] &= contact[1:]
    return out & ~outliers


def candidate_costs(
    dists: DistanceCache,
    layout: EmissionLayout,
    candidates: Sequence[CandidateState | None],
    bridges: Sequence[Bridge],
    obs: IntArray,
    w: SegmentationCosts,
    start: int = 0,
    enclosed: BoolArray | None = None,
) -> FloatArray:
    """Cost of every analysed candidate at every frame, shape (N, K).

    :func:`emission_costs` with each candidate's touching set (``layout``: the
    :class:`EmissionLayout` of the candidates' keys and their states' touching pairs), plus:
    a bridging state costs no more at its two boundary frames than the observed state it
    joins there (it happens between them and holds that state's contacts too); a candidate
    whose correction converged at no frame costs ``fail`` more per frame; one not analysed
    is excluded. ``dists``, ``obs`` and ``enclosed`` may be a block of frames starting at
    frame ``start`` (the bridges' boundary frames are frame numbers of the whole sequence).
    """
    emission = emission_costs(dists, layout, obs, w, enclosed)
    k_obs = len(layout.keys) - len(bridges)
    for b, (_cand, (f1, f2), (k1, k2)) in enumerate(bridges, start=k_obs):
        for f, k in ((f1 - start, k1), (f2 - start, k2)):
            if 0 <= f < len(obs):
                emission[f, b] = min(emission[f, b], emission[f, k])
    unusable = np.array([c is None for c in candidates])
    failed = np.array([c is not None and not c.converged for c in candidates])
    out: FloatArray = emission + w.fail * failed[None, :] + np.where(unusable, np.inf, 0.0)[None, :]
    return out
