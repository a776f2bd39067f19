"""Other contact hypotheses near an observed pose, when its own elements cannot be corrected.

Paper 4.3: the contacts found at one threshold are a rough estimate ("rough estimation
tends to find more elements"); where the correction of a candidate's observed elements
fails at every frame tried, the other hypotheses near the observed pose are tried:

- supersets: the elements found at larger thresholds (``RESCUE_SCALES`` times ``theta``);
- subsets: the observed elements less one;
- neighbours: the elements of the states observed just before and after the candidate;
- faces: each vertex-edge (edge-vertex) element replaced by the vertex on the face next to
  the edge that it is closest to (a vertex seen near a face's boundary edge under noise is
  often simply on the face).

Each is corrected with looser plausibility limits than an ordinary correction (a rough
estimate can be a few degrees off), and is accepted only if it *explains the observation*:
every feature pair observed within the threshold is still within the threshold at the
corrected pose. Of the accepted ones, the one that makes most observed pairs touch exactly
wins, then the one whose correction moves G least (largest vertex displacement).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from apo.contact import ContactElement, ContactFinder, ContactKind, ContactState
from apo.correction import ContactConstraints
from apo.geometry import Polyhedron
from apo.recognition.correction import CORRECTION_MAX_ITER, CORRECTION_TOL
from apo.recognition.distances import element_distances
from apo.recognition.types import FloatArray, Scene

__all__ = [
    "RESCUE_MAX_ROTATION",
    "RESCUE_REACH",
    "RESCUE_SCALES",
    "Rescue",
    "hypotheses",
    "on_faces",
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
        add(ContactFinder(G, E, threshold=m * scene.unit).find(X_EG).elements)
    if len(observed.elements) > 1:
        for i in range(len(observed.elements)):
            add(observed.elements[:i] + observed.elements[i + 1 :])
    for s in neighbours:
        add(s.elements)
    add(on_faces(G, E, X_EG, observed.elements))
    return list(out.values())


def on_faces(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG: FloatArray,
    elements: Sequence[ContactElement],
) -> tuple[ContactElement, ...]:
    """Replace each VE (EV) element by the VF (FV) of the closest face next to its edge."""
    R, p = X_EG[:3, :3], X_EG[:3, 3]
    out: list[ContactElement] = []
    for e in elements:
        if e.kind is ContactKind.VE:
            q = R @ grasped.vertices[e.grasped[1]] + p  # G's vertex in E
            f = _closest_face(environment, e.environment[1], q)
            n = environment.face_normals[f]
            out.append(ContactElement(ContactKind.VF, e.grasped, ("f", f), q, n[None, :]))
        elif e.kind is ContactKind.EV:
            q = R.T @ (environment.vertices[e.environment[1]] - p)  # E's vertex in G
            f = _closest_face(grasped, e.grasped[1], q)
            n = -(R @ grasped.face_normals[f])
            point = environment.vertices[e.environment[1]]
            out.append(ContactElement(ContactKind.FV, ("f", f), e.environment, point, n[None, :]))
        else:
            out.append(e)
    return tuple(out)


def _closest_face(poly: Polyhedron, edge: int, q: FloatArray) -> int:
    """Return the face next to ``edge`` whose plane is closest to ``q``."""
    faces = [int(f) for f in poly.edge_faces[edge] if f >= 0]
    heights = [abs(float(poly.face_normals[f] @ q - poly.face_offsets[f])) for f in faces]
    return faces[int(np.argmin(heights))]


def rescue(
    scene: Scene,
    frames: Sequence[int],
    observed: ContactState,
    neighbours: Sequence[ContactState] = (),
) -> Rescue | None:
    """Best converged hypothesis over ``frames`` that explains ``observed``, or None.

    Returns ``(X_EG corrected, frame, displacement)`` of the hypothesis that makes most
    observed pairs touch, then moves G least, among those that converge within
    ``RESCUE_REACH`` thresholds and ``RESCUE_MAX_ROTATION`` and after which every observed
    pair is still within the threshold.
    """
    best: tuple[int, float, FloatArray, int] | None = None
    for f in frames:
        X0 = scene.X[f]
        for elements in hypotheses(scene, X0, observed, neighbours):
            found = _correct(scene, X0, elements)
            if found is None:
                continue
            touched = _explains(scene, found[0], observed)
            if touched < 0:
                continue
            rank = (-touched, found[1])
            if best is None or rank < (best[0], best[1]):
                best = (-touched, found[1], found[0], int(f))
        if best is not None:  # frames come best first: the first that gives one decides
            break
    return None if best is None else (best[2], best[3], best[1])


def _correct(
    scene: Scene, X0: FloatArray, elements: Sequence[ContactElement]
) -> tuple[FloatArray, float] | None:
    """Correct ``X0`` under ``elements`` with the rescue limits; (pose, displacement)."""
    res = ContactConstraints(scene.grasped, scene.environment, elements).correct(
        X0[None],
        max_iter=CORRECTION_MAX_ITER,
        tol=CORRECTION_TOL,
        max_rotation=RESCUE_MAX_ROTATION,
        max_displacement=RESCUE_REACH * scene.unit,
    )
    if not bool(res.converged[0]) or bool(res.flagged[0]):
        return None
    return np.asarray(res.X_EG[0], dtype=np.float64), float(res.displacement[0])


def _explains(scene: Scene, X: FloatArray, observed: ContactState) -> int:
    """Count the observed pairs that touch at ``X``; -1 if some pair is no longer near.

    Near: the two features within the recognition threshold; touching: within the tight
    threshold of ``scene.exact`` (feature distances, ``element_distances``).
    """
    if not observed.elements:
        return 0
    keys = [e.key for e in observed.elements]
    d = element_distances(scene.grasped, scene.environment, X[None], keys)[0]
    if (d > scene.unit).any():
        return -1
    return int((d <= float(scene.exact.threshold)).sum())
