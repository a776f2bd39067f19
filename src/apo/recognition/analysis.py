"""Analysing the candidate states a segmentation needs, and their direct transitions.

Stage 4 of ``docs/recognition.md``: the states a first (unconstrained) segmentation uses
are analysed once each (:func:`apo.recognition.candidates.analyse_candidate`); where that
segmentation changes state in a way no sequence of analysed states can make directly, the
states observed around the change are analysed too; the direct-transition test is run for
pairs observed near each other; bridging states are added where two consecutive states
still cannot follow each other.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from apo.arrays import unique
from apo.contact import ContactState
from apo.recognition.bridges import Bridge, bridge_candidates
from apo.recognition.candidates import (
    analyse_candidate,
    correct_best,
    direct_possible,
    states_at,
)
from apo.recognition.contacts import Observations
from apo.recognition.decoding import near_pairs, reachable, run_bounds
from apo.recognition.types import (
    BoolArray,
    CandidateState,
    FloatArray,
    IntArray,
    Scene,
    StateKey,
)

__all__ = ["Analysis", "analyse", "analyse_needed"]


@dataclass
class Analysis:
    """The candidates analysed so far and the direct-transition tests between them.

    Attributes
    ----------
    keys : list of frozenset
        Contact-state keys: the observed states, then the bridging states.
    candidates : list of CandidateState or None
        Aligned with ``keys``; None where not analysed.
    feasible : ndarray of bool, shape (K, K)
        Direct-transition test results (diagonal True; False where untested).
    tested : ndarray of bool, shape (K, K)
        Pairs tested so far.
    bridges : list of Bridge
        The bridging candidates (their index is ``len(observed keys) + i``).
    """

    keys: list[StateKey]
    candidates: list[CandidateState | None]
    feasible: BoolArray
    tested: BoolArray
    bridges: list[Bridge] = field(default_factory=list)

    @classmethod
    def start(cls, keys: list[StateKey]) -> Analysis:
        """Nothing analysed yet."""
        k = len(keys)
        eye = np.eye(k, dtype=bool)
        return cls(list(keys), [None] * k, eye, eye.copy())

    def states(self, observed: Observations) -> list[ContactState]:
        """Each candidate's contact state: analysed, else as first observed."""
        return [
            c.state if c is not None else observed.states[k] for k, c in enumerate(self.candidates)
        ]


def analyse(
    scene: Scene,
    an: Analysis,
    observed: Observations,
    own: FloatArray,
    path0: IntArray,
    ks: Iterable[int],
) -> None:
    """Analyse candidates ``ks``, then test direct transitions between near analysed pairs.

    ``own`` is the cost of each frame's observed state there, shape (N,) (a state's best
    frames are the cheapest of those where it was observed).

    A pair is tested when both are observed (or, where a frame's observed state is not
    analysed, chosen by ``path0``) within ``window`` frames of each other.
    """
    obs = observed.labels
    pending = list(dict.fromkeys(k for k in ks if an.candidates[k] is None))
    corrected = {k: correct_best(scene, obs, k, observed.states[k], own) for k in pending}
    at = states_at(scene, corrected)  # the contact search at every corrected pose at once
    for k in pending:
        an.candidates[k] = analyse_candidate(
            scene,
            obs,
            k,
            an.keys[k],
            observed.states[k],
            own,
            neighbours=[observed.states[j] for j in neighbours(obs, path0, k)],
            corrected=corrected[k],
            at=at.get(k),
        )
    done = np.array([c is not None for c in an.candidates])
    labels = np.where(done[obs], obs, path0)
    todo = near_pairs(labels, len(an.keys), scene.costs.window) & ~an.tested
    todo &= done[:, None] & done[None, :]
    for i, j in zip(*np.nonzero(todo), strict=True):
        ci, cj = an.candidates[i], an.candidates[j]
        assert ci is not None and cj is not None
        an.feasible[i, j] = direct_possible(ci, cj)
        an.tested[i, j] = True


def neighbours(obs: IntArray, path0: IntArray, k: int) -> list[int]:
    """States of ``path0`` just before and after the runs where ``k`` is observed."""
    out: set[int] = set()
    for a, b in run_bounds(np.where(obs == k, -1, path0)):
        if obs[a] != k:
            continue
        if a > 0:
            out.add(int(path0[a - 1]))
        if b + 1 < len(path0):
            out.add(int(path0[b + 1]))
    out.discard(k)
    return sorted(out)


def analyse_needed(
    scene: Scene, observed: Observations, own: FloatArray, path0: IntArray
) -> Analysis:
    """Analyse what the segmentation needs: shortlist, states around gaps, bridges.

    ``path0`` is the unconstrained segmentation; the states it uses are the shortlist;
    ``own`` the cost of each frame's observed state (:func:`analyse`).
    """
    an = Analysis.start(observed.keys)
    shortlist = sorted({int(k) for k in unique(path0)})
    analyse(scene, an, observed, own, path0, shortlist)
    extra = states_around_gaps(scene, an, observed.labels, path0) - set(shortlist)
    if extra:
        analyse(scene, an, observed, own, path0, sorted(extra))
    add_bridges(scene, an, path0)
    return an


def states_around_gaps(scene: Scene, an: Analysis, obs: IntArray, path0: IntArray) -> set[int]:
    """Observed states near changes of ``path0`` that no analysed sequence can make directly.

    A short genuine state (a singular contact held for a few frames) may be the way through.
    """
    extra: set[int] = set()
    reach = reachable(an.feasible)
    w = scene.costs.window
    for (_a1, b1), (a2, _b2) in itertools.pairwise(run_bounds(path0)):
        if not reach[path0[b1], path0[a2]]:
            lo, hi = max(0, b1 - w), min(scene.n, a2 + w + 1)
            extra |= {int(k) for k in np.unique(obs[lo:hi])}
    return extra


def add_bridges(scene: Scene, an: Analysis, path0: IntArray) -> None:
    """Add bridging candidates (``apo.recognition.bridges``) and test their transitions.

    A bridge is tested against the states ``path0`` uses within ``window`` frames of its
    two boundary frames, and against the other bridges.
    """
    k_obs = len(an.keys)
    index = {key: k for k, key in enumerate(an.keys)}
    bridges = bridge_candidates(scene, path0, an.candidates, an.feasible, index)
    if not bridges:
        return
    for bridge, _frames, _pair in bridges:
        an.candidates.append(bridge)
        an.keys.append(bridge.key)
    k_count = len(an.candidates)
    grown = np.eye(k_count, dtype=bool)
    grown[:k_obs, :k_obs] = an.feasible
    an.feasible = grown
    an.bridges = bridges
    w = scene.costs.window
    for b, (cb, (f1, f2), _pair) in enumerate(bridges, start=k_obs):
        lo, hi = max(0, f1 - w), min(scene.n, f2 + w + 1)
        for j in {int(v) for v in path0[lo:hi]} | set(range(k_obs, k_count)):
            cj = an.candidates[j]
            if j == b or cj is None:
                continue
            an.feasible[b, j] = direct_possible(cb, cj)
            an.feasible[j, b] = direct_possible(cj, cb)
