"""Bridging states: the state between two observed ones that cannot follow each other."""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence

import numpy as np

from apo.contact import ContactElement, ContactKind, ContactState
from apo.geometry import Polyhedron
from apo.recognition.candidates import dof_of
from apo.recognition.correction import correct_one
from apo.recognition.decoding import run_bounds
from apo.recognition.types import (
    BoolArray,
    CandidateState,
    FloatArray,
    IntArray,
    Scene,
    StateKey,
)

__all__ = ["Bridge", "bridge_candidates", "bridge_pose", "max_displacement", "meet_elements"]


Bridge = tuple[CandidateState, tuple[int, int], tuple[int, int]]
"""A bridging candidate, the frames it lies between, and the two candidates it joins."""


def bridge_candidates(
    scene: Scene,
    labels: IntArray,
    candidates: Sequence[CandidateState | None],
    feasible: BoolArray,
    index: Mapping[StateKey, int],
) -> list[Bridge]:
    """Candidate states bridging consecutive states that are not directly connected.

    For runs of ``labels`` ``k1`` then ``k2`` with no direct transition between them, the
    union of their elements (with :func:`meet_elements`: a corner that touched an edge in
    one and whose edge touched a corner in the other meet at the vertex-vertex contact) is
    imposed on the poses of the two boundary frames by the pose correction. Where it
    converges, the contact state found at the corrected pose (e.g. the vertex-vertex contact
    a sliding corner passes through between two frames) becomes a candidate, observed at no
    frame, provided it is near the observation (:func:`bridge_pose`). States already in
    ``index`` are not added again. Returns ``(candidate, (last frame of k1, first frame of
    k2), (k1, k2))`` triples.
    """
    out: list[Bridge] = []
    seen: set[tuple[int, int]] = set()
    new_keys: set[StateKey] = set()
    for (_a1, b1), (a2, _b2) in itertools.pairwise(run_bounds(labels)):
        k1, k2 = int(labels[b1]), int(labels[a2])
        if feasible[k1, k2] or (k1, k2) in seen:
            continue
        seen.add((k1, k2))
        c1, c2 = candidates[k1], candidates[k2]
        if c1 is None or c2 is None or not c1.state.elements or not c2.state.elements:
            continue
        best = bridge_pose(scene, c1.state, c2.state, (int(b1), int(a2)))
        if best is None:
            continue
        found = scene.exact.find(best[0])
        if not found.elements or found.key in index or found.key in new_keys:
            continue
        new_keys.add(found.key)
        cand = CandidateState(found.key, found, dof_of(found), best[1], best[0].copy(), True, 0)
        out.append((cand, (int(b1), int(a2)), (k1, k2)))
    return out


def bridge_pose(
    scene: Scene, s1: ContactState, s2: ContactState, frames: tuple[int, int]
) -> tuple[FloatArray, int] | None:
    """Pose where the elements of both states hold, corrected from one of two frames.

    The union of the elements (with meets) is imposed on the observed poses of the two
    frames; a correction counts if it converges, its residual at the observed pose is at
    most ``reach * theta`` and no vertex of G moved more than twice that residual plus
    ``theta`` (it did not wander off to a distant solution of the same equations). Of
    those, the one with the smallest initial residual; ``(X_EG, frame)`` or None.
    """
    G, E, X = scene.grasped, scene.environment, scene.X
    reach = scene.costs.reach * scene.unit
    union = ContactState(
        elements=meet_elements(G, E, s1.elements, s2.elements),
        touching=s1.touching | s2.touching,
    )
    best: tuple[float, FloatArray, int] | None = None
    for f in frames:
        Xc, before, _after, ok = correct_one(G, E, X[f], union, reach / 3.0)
        moved = max_displacement(G, X[f], Xc)
        near = before <= reach and moved <= 2.0 * before + reach / 3.0
        if ok and near and (best is None or before < best[0]):
            best = (before, Xc, f)
    return None if best is None else (best[1], best[2])


def _feature_vertices(poly: Polyhedron, feature: tuple[str, int]) -> set[int]:
    """Vertex ids of a feature: itself, an edge's ends, or a face's boundary vertices."""
    kind, i = feature
    if kind == "v":
        return {i}
    if kind == "e":
        return {int(v) for v in poly.edges[i]}
    loops = [poly.faces[i], *poly.face_holes[i]]
    return {int(v) for loop in loops for v in loop}


def meet_elements(
    grasped: Polyhedron,
    environment: Polyhedron,
    first: Sequence[ContactElement],
    second: Sequence[ContactElement],
) -> tuple[ContactElement, ...]:
    """Elements that hold in a state between ``first`` and ``second`` (union, with meets).

    A vertex of G touching an E feature in one state and a G feature touching an E vertex
    in the other, where the E vertex bounds the first E feature and the G vertex bounds the
    second G feature, meet at the vertex-vertex contact of the two vertices (a corner
    passing over a corner); that VV element replaces the two. The rest is the union.
    """
    chosen = {e.key: e for e in (*first, *second)}
    for a, b in itertools.chain(itertools.product(first, second), itertools.product(second, first)):
        if a.grasped[0] != "v" or b.environment[0] != "v":
            continue
        gv, ev = a.grasped[1], b.environment[1]
        if ev in _feature_vertices(environment, a.environment) and gv in _feature_vertices(
            grasped, b.grasped
        ):
            vv = ContactElement(
                ContactKind.VV,
                ("v", gv),
                ("v", ev),
                np.asarray(b.point, dtype=np.float64),
                np.asarray(a.normals, dtype=np.float64),
            )
            chosen.pop(a.key, None)
            chosen.pop(b.key, None)
            chosen[vv.key] = vv
    return tuple(chosen[k] for k in sorted(chosen))


def max_displacement(poly: Polyhedron, X0: FloatArray, X1: FloatArray) -> float:
    """Largest displacement (metres) of a vertex of ``poly`` between poses X0 and X1."""
    v = poly.vertices
    d = (v @ X1[:3, :3].T + X1[:3, 3]) - (v @ X0[:3, :3].T + X0[:3, 3])
    return float(np.linalg.norm(d, axis=1).max())
