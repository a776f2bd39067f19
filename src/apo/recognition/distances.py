"""Distances between the two features of contact elements over a sequence of poses."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from apo.geometry import (
    Polyhedron,
    closest_point_on_segment,
    point_face_distance,
    segment_segment_closest,
)
from apo.recognition.types import ElementKey, FloatArray

__all__ = ["DistanceCache", "element_distances"]


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
