"""Distances between the two features of contact elements over a sequence of poses."""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import numpy as np
import numpy.typing as npt

from apo.geometry import (
    Polyhedron,
    closest_point_on_segment,
    point_face_distance,
    segment_segment_closest,
)
from apo.recognition.types import ElementKey, FloatArray
from apo.workers import run_parts, shared_zeros, workers_for

__all__ = [
    "DistanceCache",
    "FixedDistances",
    "StreamedDistances",
    "element_distances",
    "split_distances",
]


def element_distances(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG_seq: npt.ArrayLike,
    keys: Sequence[ElementKey],
) -> FloatArray:
    """Distances between the features of each element key at every pose.

    Parameters
    ----------
    grasped, environment : Polyhedron
        Models G and E (metres, own frames).
    X_EG_seq : array_like, shape (N, 4, 4)
        Poses of G in E.
    keys : sequence of (kind, grasped feature, environment feature)
        ``ContactElement.key`` values.

    Returns
    -------
    ndarray, shape (N, len(keys))
        Euclidean distance (metres) between the two closed features: vertex, edge segment,
        face polygon.
    """
    X = np.asarray(X_EG_seq, dtype=np.float64)
    R, p = X[:, :3, :3], X[:, :3, 3]
    out = np.empty((X.shape[0], len(keys)))
    G, E = grasped, environment
    for j, (_kind, (gk, gi), (ek, ei)) in enumerate(keys):

        def g_pts(v: FloatArray) -> FloatArray:
            out_: FloatArray = np.einsum("nij,j->ni", R, v) + p
            return out_

        def e_in_g(v: FloatArray) -> FloatArray:
            out_: FloatArray = np.einsum("nji,nj->ni", R, v[None, :] - p)
            return out_

        if gk == "v" and ek == "f":
            out[:, j] = point_face_distance(E, ei, g_pts(G.vertices[gi]))[0]
        elif gk == "f" and ek == "v":
            out[:, j] = point_face_distance(G, gi, e_in_g(E.vertices[ei]))[0]
        elif gk == "e" and ek == "e":
            a, b = G.edges[gi]
            c, d = E.edges[ei]
            r = segment_segment_closest(
                g_pts(G.vertices[a]), g_pts(G.vertices[b]), E.vertices[c], E.vertices[d]
            )
            out[:, j] = r.distance
        elif gk == "v" and ek == "e":
            c, d = E.edges[ei]
            q = g_pts(G.vertices[gi])
            cl, _ = closest_point_on_segment(q, E.vertices[c], E.vertices[d])
            out[:, j] = np.linalg.norm(q - cl, axis=1)
        elif gk == "e" and ek == "v":
            a, b = G.edges[gi]
            q = e_in_g(E.vertices[ei])
            cl, _ = closest_point_on_segment(q, G.vertices[a], G.vertices[b])
            out[:, j] = np.linalg.norm(q - cl, axis=1)
        elif gk == "v" and ek == "v":
            out[:, j] = np.linalg.norm(g_pts(G.vertices[gi]) - E.vertices[ei], axis=1)
        else:
            raise ValueError(f"unsupported feature pair {(gk, ek)} in element key")
    return out


#: Least ``frames x keys`` whose distances :func:`split_distances` splits over processes
#: (auto): the distances of one key cost some 0.15-0.2 us a frame, a fork 2-5 ms of the
#: parent's time and about 10 ms of CPU of both processes together (the synthetic 3,000
#: frames' 63 keys, 189,000: split; the jittered 2,993 frames' 30 keys, 89,790: not).
SPLIT_MIN_KEY_FRAMES = 100_000


def split_distances(
    grasped: Polyhedron,
    environment: Polyhedron,
    X: FloatArray,
    keys: Sequence[ElementKey],
    jobs: int | None = 1,
) -> FloatArray:
    """:func:`element_distances`, the keys dealt over ``jobs`` processes (:mod:`apo.workers`).

    Each key's column is computed on its own from the same poses (the loop of
    :func:`element_distances`), so the columns are the same bit for bit whichever process
    computes them; key ``j`` goes to process ``j % k``, and each writes its columns into a
    shared array (nothing is sent back). ``jobs``: None for auto (from 768 frames and
    ``SPLIT_MIN_KEY_FRAMES``), 1 for this process only.
    """
    k = workers_for(jobs, len(X))
    if jobs is None and len(X) * len(keys) < SPLIT_MIN_KEY_FRAMES:
        k = 1
    k = min(k, len(keys))
    if k <= 1:
        return element_distances(grasped, environment, X, keys)
    out = shared_zeros((len(X), len(keys)), np.float64, True)
    keys = list(keys)

    def part(i: int) -> None:
        out[:, i::k] = element_distances(grasped, environment, X, keys[i::k])

    run_parts([partial(part, i) for i in range(k)])
    return out


class DistanceCache:
    """Distances (in thresholds) of element keys at every observed pose, computed once."""

    def __init__(
        self, grasped: Polyhedron, environment: Polyhedron, X: FloatArray, theta: float
    ) -> None:
        self.args = (grasped, environment, X)
        self.theta = theta
        self.cache: dict[ElementKey, FloatArray] = {}

    def get(self, keys: Sequence[ElementKey]) -> FloatArray:
        """Distances (in thresholds) of ``keys`` at every pose, shape (N, len(keys))."""
        missing = [k for k in dict.fromkeys(keys) if k not in self.cache]
        if missing:
            d = element_distances(*self.args, missing) / self.theta
            for j, k in enumerate(missing):
                self.cache[k] = d[:, j]
        n = self.args[2].shape[0]
        if not keys:
            return np.zeros((n, 0))
        return np.stack([self.cache[k] for k in keys], axis=1)


class StreamedDistances:
    """Distances (in thresholds) of element keys, one span of ``span`` frames at a time.

    The spans are ``[0, span), [span, 2 span), ...``: each element's distances over a span
    are computed in one call of :func:`element_distances` (a few numpy calls per element,
    whatever the span's length) and kept only while frames of that span are asked for, so
    the working memory is ``span x elements`` whatever the length of the demonstration.
    A frame's distance is the same value whichever keys are asked for with it (each key is
    computed on its own, over the same span): :func:`apo.recognition.segmentation.segment`
    computes again the distances the first pass computed and dropped. ``jobs``: processes a
    span's keys are split over (:func:`split_distances`; the same numbers whatever ``jobs``).
    """

    def __init__(
        self,
        grasped: Polyhedron,
        environment: Polyhedron,
        X: FloatArray,
        theta: float,
        jobs: int | None = 1,
    ) -> None:
        self.args = (grasped, environment, X)
        self.theta = theta
        self.jobs = jobs
        self.at: tuple[int, int] = (0, 0)
        self.cols: dict[ElementKey, FloatArray] = {}

    def rows(self, a: int, b: int, keys: Sequence[ElementKey], span: int) -> FloatArray:
        """Distances of ``keys`` at frames ``a:b``, shape ``(b - a, len(keys))``."""
        n = len(self.args[2])
        if not keys:
            return np.zeros((b - a, 0))
        parts = []
        for s0 in range((a // span) * span, b, span):  # the spans that frames a:b meet
            s1 = min(n, s0 + span)
            cols = self._span(s0, s1, keys)
            lo, hi = max(a, s0) - s0, min(b, s1) - s0
            parts.append(np.stack([cols[k][lo:hi] for k in keys], axis=1))
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def _span(self, s0: int, s1: int, keys: Sequence[ElementKey]) -> dict[ElementKey, FloatArray]:
        """Return the columns of the span ``s0:s1``, its missing ``keys`` computed (once)."""
        if self.at != (s0, s1):
            self.at, self.cols = (s0, s1), {}
        missing = [k for k in dict.fromkeys(keys) if k not in self.cols]
        if missing:
            G, E, X = self.args
            d = split_distances(G, E, X[s0:s1], missing, self.jobs)
            d /= self.theta
            for j, k in enumerate(missing):
                self.cols[k] = d[:, j]
        return self.cols


class FixedDistances(DistanceCache):
    """Distances already computed for one block of frames, handed out as a DistanceCache."""

    def __init__(self, keys: Sequence[ElementKey], dist: FloatArray) -> None:
        self.keys, self.dist = list(keys), dist

    def get(self, keys: Sequence[ElementKey]) -> FloatArray:
        """Return the block's distances; ``keys`` must be those it was made with."""
        if list(keys) != self.keys:
            raise ValueError("FixedDistances: asked for other keys than it holds")
        return self.dist
