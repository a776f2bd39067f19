"""Other contact hypotheses near an observed pose, when its own elements cannot be corrected.

Paper 4.3: the contacts found at one threshold are a rough estimate ("rough estimation
tends to find more elements"); where the correction of a candidate's observed elements
fails at every frame tried, the other hypotheses near the observed pose are tried:

- supersets: the elements found at larger thresholds (``RESCUE_SCALES`` times ``theta``);
- subsets: the observed elements less one;
- neighbours: the elements of the states observed just before and after the candidate.

Each is corrected with looser plausibility limits than an ordinary correction (a rough
estimate can be a few degrees off), and is accepted only if it *explains the observation*:
every feature pair observed within the threshold touches at the corrected pose. Of the
accepted ones, the one whose correction moves G least wins (largest vertex displacement).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from apo.contact import ContactElement, ContactFinder, ContactState
from apo.correction import ContactConstraints
from apo.recognition.correction import CORRECTION_MAX_ITER, CORRECTION_TOL
from apo.recognition.types import FloatArray, Scene

__all__ = [
    "RESCUE_MAX_ROTATION",
    "RESCUE_REACH",
    "RESCUE_SCALES",
    "Rescue",
    "hypotheses",
    "rescue",
]

#: Thresholds, in multiples of the recognition threshold, at which supersets are read.
RESCUE_SCALES = (1.5, 2.0, 3.0)
#: A hypothesis may move a vertex of G by at most this many thresholds.
RESCUE_REACH = 8.0
#: ... and turn G by at most this angle (radians).
RESCUE_MAX_ROTATION = math.radians(20.0)

Rescue = tuple[FloatArray, int, float]
"""Corrected pose, the frame it was corrected from, the largest vertex displacement (m)."""


def hypotheses(
    scene: Scene,
    X_EG: FloatArray,
    observed: ContactState,
    neighbours: Sequence[ContactState] = (),
) -> list[tuple[ContactElement, ...]]:
    """Contact hypotheses near the pose ``X_EG``, distinct, the observed elements first."""
    G, E = scene.grasped, scene.environment
    out: dict[frozenset[object], tuple[ContactElement, ...]] = {}

    def add(elements: Sequence[ContactElement]) -> None:
        if elements:
            out.setdefault(frozenset(e.key for e in elements), tuple(elements))

    add(observed.elements)
    for m in RESCUE_SCALES:
        add(ContactFinder(G, E, threshold=m * scene.theta).find(X_EG).elements)
    if len(observed.elements) > 1:
        for i in range(len(observed.elements)):
            add(observed.elements[:i] + observed.elements[i + 1 :])
    for s in neighbours:
        add(s.elements)
    return list(out.values())


def rescue(
    scene: Scene,
    frames: Sequence[int],
    observed: ContactState,
    neighbours: Sequence[ContactState] = (),
) -> Rescue | None:
    """Best converged hypothesis over ``frames`` that explains ``observed``, or None.

    Returns ``(X_EG corrected, frame, displacement)`` of the hypothesis whose correction
    moves G least, among those that converge within ``RESCUE_REACH`` thresholds and
    ``RESCUE_MAX_ROTATION`` and after which every touching pair of ``observed`` touches
    (``scene.exact``).
    """
    best: Rescue | None = None
    for f in frames:
        X0 = scene.X[f]
        for elements in hypotheses(scene, X0, observed, neighbours):
            found = _correct(scene, X0, elements)
            if found is None or (best is not None and found[1] >= best[2]):
                continue
            if _explains(scene, found[0], observed):
                best = (found[0], int(f), found[1])
    return best


def _correct(
    scene: Scene, X0: FloatArray, elements: Sequence[ContactElement]
) -> tuple[FloatArray, float] | None:
    """Correct ``X0`` under ``elements`` with the rescue limits; (pose, displacement)."""
    res = ContactConstraints(scene.grasped, scene.environment, elements).correct(
        X0[None],
        max_iter=CORRECTION_MAX_ITER,
        tol=CORRECTION_TOL,
        max_rotation=RESCUE_MAX_ROTATION,
        max_displacement=RESCUE_REACH * scene.theta,
    )
    if not bool(res.converged[0]) or bool(res.flagged[0]):
        return None
    return np.asarray(res.X_EG[0], dtype=np.float64), float(res.displacement[0])


def _explains(scene: Scene, X: FloatArray, observed: ContactState) -> bool:
    """Return True if every feature pair of the observed elements touches at ``X``."""
    touching = scene.exact.find(X).touching
    return all((e.grasped, e.environment) in touching for e in observed.elements)
