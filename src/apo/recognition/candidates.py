"""Analysing one candidate state: representative pose, contact state there, DOF.

A candidate is a distinct observed contact state (or a bridging state). It is analysed
once: its best observed frames are pose-corrected (paper 4.3.1), the first that converges
is its representative pose, its elements are re-evaluated there (the *closure*: every
element that holds at the corrected pose) and ``apo.dof`` gives its DOF.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from apo import dof
from apo.contact import ContactState
from apo.recognition.correction import correct_poses
from apo.recognition.hypotheses import rescue
from apo.recognition.types import (
    BoolArray,
    CandidateState,
    FloatArray,
    IntArray,
    Scene,
    StateKey,
)
from apo.transitions import direct_transition_possible

if TYPE_CHECKING:
    from apo.contact import ContactFinder

__all__ = [
    "Corrected",
    "analyse_candidate",
    "analysed_at",
    "canonical_ids",
    "correct_best",
    "direct_possible",
    "dof_of",
    "state_at",
    "states_at",
]


def dof_of(state: ContactState) -> Any:
    """``apo.dof.analyze`` of the state's elements (a ``DofResult``)."""
    points = list(state.elements)  # contact elements are DOF-analysis contact points
    return dof.analyze(points)


def state_at(
    finder: ContactFinder,
    exact: ContactFinder,
    X: FloatArray,
    key: StateKey,
    fallback: ContactState,
    at: tuple[ContactState, ContactState] | None = None,
) -> ContactState:
    """Return the contact state of ``key``'s elements re-evaluated at the corrected pose ``X``.

    The elements come from ``finder`` (the recognition threshold), restricted to ``key``;
    the touching pairs from ``exact`` (a tight threshold): at a corrected pose the contacts
    hold exactly, so only pairs that really touch enter Donald's inclusion test, not pairs
    that are merely near. ``at``: both finders' states at ``X`` if already searched
    (:func:`states_at`).
    """
    found = finder.find(X) if at is None else at[0]
    by_key = {e.key: e for e in found.elements}
    if not key <= set(by_key):
        return fallback
    held = exact.find(X) if at is None else at[1]
    closure = {e.key: e for e in held.elements}
    # every element that holds at the corrected pose: an observed subset of a contact (three
    # of a face's four vertices seen within the threshold) is the whole contact
    chosen = list(closure.values()) if key <= set(closure) else [by_key[k] for k in key]
    elements = tuple(sorted(chosen, key=lambda e: e.key))
    touching = held.touching | {(e.grasped, e.environment) for e in elements}
    return ContactState(elements=elements, touching=frozenset(touching))


def direct_possible(a: CandidateState, b: CandidateState) -> bool:
    """Run the direct-transition test (paper 4.3.2) between two analysed candidates."""
    return bool(direct_transition_possible(a.state, b.state, a.dof, b.dof))


def analysed_at(candidates: Sequence[CandidateState | None], k: int) -> CandidateState:
    """Return ``candidates[k]``, which must have been analysed."""
    c = candidates[k]
    if c is None:
        raise RuntimeError(f"candidate {k} was chosen but not analysed")
    return c


Corrected = tuple[IntArray, IntArray, FloatArray, BoolArray]
"""A candidate's frames, its best frames, their corrected poses and which converged."""


def correct_best(
    scene: Scene,
    labels: IntArray,
    k: int,
    observed: ContactState,
    cost: FloatArray,
    tries: int = 3,
) -> Corrected:
    """Correct the ``tries`` cheapest frames where candidate ``k`` is observed."""
    frames = np.flatnonzero(labels == k)
    best = frames[np.argsort(cost[frames], kind="stable")[:tries]]
    Xb, _before, _after, ok = correct_poses(
        scene.grasped, scene.environment, scene.X[best], observed.elements, threshold=scene.unit
    )
    return frames, best, Xb, ok


def states_at(
    scene: Scene, corrected: dict[int, Corrected]
) -> dict[int, tuple[ContactState, ContactState]]:
    """Both finders' states at each candidate's first converged pose, searched in one batch.

    One ``find_batch`` per finder instead of one single-pose ``find`` per candidate (the
    single-pose search is mostly per-call overhead: about 1.8 ms against 0.1 ms per pose).
    """
    ks = [k for k, (_f, _b, _X, ok) in corrected.items() if ok.any()]
    if not ks:
        return {}
    X = np.stack([corrected[k][2][int(np.argmax(corrected[k][3]))] for k in ks])
    found, held = scene.finder.find_batch(X), scene.exact.find_batch(X)
    return {k: (found[i], held[i]) for i, k in enumerate(ks)}


def analyse_candidate(
    scene: Scene,
    labels: IntArray,
    k: int,
    key: StateKey,
    observed: ContactState,
    cost: FloatArray,
    neighbours: Sequence[ContactState] = (),
    tries: int = 3,
    corrected: Corrected | None = None,
    at: tuple[ContactState, ContactState] | None = None,
) -> CandidateState:
    """Correct the best observed frames of candidate ``k``; analyse it at the first success.

    ``labels`` are the observed state of each frame, ``cost`` the candidate's cost at each
    frame (read where ``labels == k`` only): the ``tries`` cheapest frames where it was
    observed are corrected. If none converges, the other contact hypotheses near those
    frames are tried
    (:func:`apo.recognition.hypotheses.rescue`, with the states observed before and after,
    ``neighbours``); the state is then the one that holds at the rescued pose.
    ``corrected`` (:func:`correct_best`) and ``at`` (:func:`states_at`): already computed.
    """
    frames, best, Xb, ok = corrected or correct_best(scene, labels, k, observed, cost, tries)
    if ok.any():
        i = int(np.argmax(ok))
        f = int(best[i])
        state = state_at(scene.finder, scene.exact, Xb[i], key, observed, at)
        return CandidateState(key, state, dof_of(state), f, Xb[i].copy(), True, len(frames))
    found = rescue(scene, [int(f) for f in best], observed, neighbours)
    if found is not None:
        X_r, f, _moved = found
        state = scene.exact.find(X_r)
        return CandidateState(key, state, dof_of(state), f, X_r, True, len(frames))
    f = int(best[0])
    X0 = scene.X[f].copy()
    return CandidateState(key, observed, dof_of(observed), f, X0, False, len(frames))


def canonical_ids(candidates: Sequence[CandidateState | None]) -> IntArray:
    """Map each candidate to the first converged one with the same closure, shape (K,).

    Candidates observed with different subsets of one contact are the same state once
    their poses are corrected (their closures agree): one id for them all.
    """
    canon = np.arange(len(candidates))
    first_of: dict[StateKey, int] = {}
    for k, maybe in enumerate(candidates):
        if maybe is not None and maybe.converged:
            canon[k] = first_of.setdefault(maybe.state.key, k)
    return canon
