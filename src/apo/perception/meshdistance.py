"""Which points are inside a closed triangle mesh: ray parity, exact and cheap (numpy only).

The tracker's non-penetration rows and penetration share ask, at every ICP iteration, how
deep a few hundred samples of the grasped model are inside the environment model. Most of
them are not inside at all (a peg in a slot is in the slot's air), yet each one cost a k-d
tree query against the environment's 200,000 dense samples. For a closed mesh, a point is
inside when a ray from it crosses the surface an odd number of times: with the ray along
the ``z`` axis of a fixed oblique frame (no face of an axis-aligned model is parallel to
it, and a random sample lies on a projected edge with probability 0), each triangle is a 2-D
point-in-triangle test and a comparison with the height of its plane, both affine in the
point: two matrix products and a few comparisons for all (point, triangle) pairs. Only the
points inside are then queried.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from apo.typing import BoolArray, FloatArray

__all__ = ["ClosedMesh", "is_closed", "is_solid"]


def is_closed(vertices: npt.ArrayLike, triangles: npt.ArrayLike) -> bool:
    """Return whether every edge of the mesh belongs to exactly two triangles.

    Vertices at the same coordinates are one (an STL file repeats them per triangle).
    """
    return _closed(_welded(vertices, triangles))


def _welded(vertices: npt.ArrayLike, triangles: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """Return the triangles' corners as indices of the distinct vertex coordinates."""
    _, same = np.unique(np.asarray(vertices, dtype=np.float64), axis=0, return_inverse=True)
    return np.asarray(same.ravel()[np.asarray(triangles, dtype=np.int64)], dtype=np.int64)


def _closed(S: npt.NDArray[np.int64]) -> bool:
    """Whether every edge of the welded triangles ``S`` belongs to exactly two of them."""
    e = np.sort(np.concatenate([S[:, [0, 1]], S[:, [1, 2]], S[:, [2, 0]]]), axis=1)
    _, count = np.unique(e, axis=0, return_counts=True)
    return bool(len(S) > 0 and np.all(count == 2))


def is_solid(vertices: npt.ArrayLike, triangles: npt.ArrayLike) -> bool:
    """Return whether the mesh bounds a solid with its faces' normals pointing out.

    Closed (every edge in exactly two triangles), consistently oriented (the two triangles
    of an edge traverse it in opposite directions) and of positive signed volume (the
    right-hand normals point outwards). Seen from outside, such a mesh's faces turned away
    from the viewer are hidden behind the ones turned to it (back-face culling is exact).
    """
    V = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(triangles, dtype=np.int64)
    if len(T) == 0:
        return False
    S = _welded(V, T)
    if not _closed(S):
        return False
    directed = np.concatenate([S[:, [0, 1]], S[:, [1, 2]], S[:, [2, 0]]])
    if len(np.unique(directed, axis=0)) != len(directed):  # an edge twice the same way
        return False
    a, b, c = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
    return bool(np.einsum("ij,ij->", a, np.cross(b, c)) > 0.0)


def _oblique() -> FloatArray:
    """Return a fixed rotation whose ``z`` axis is oblique to the model's axes (the ray)."""
    z = np.array([0.1234, 0.2345, 1.0])
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    return np.array([x, np.cross(z, x), z])


class ClosedMesh:
    """The inside of a closed triangle mesh (model frame, metres)."""

    def __init__(self, vertices: npt.ArrayLike, triangles: npt.ArrayLike) -> None:
        self.R = _oblique()
        V = np.asarray(vertices, dtype=np.float64) @ self.R.T
        T = np.asarray(triangles, dtype=np.int64)
        a, b, c = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
        # Edge functions e_k(p) = W_k . p_xy + w_k of the edges ab, bc, ca (projected).
        W, w = [], []
        for p, q in ((a, b), (b, c), (c, a)):
            W.append(np.stack([-(q[:, 1] - p[:, 1]), q[:, 0] - p[:, 0]]))
            w.append((q[:, 1] - p[:, 1]) * p[:, 0] - (q[:, 0] - p[:, 0]) * p[:, 1])
        self.W = np.concatenate(W, axis=1)  # (2, 3T)
        self.w = np.concatenate(w)
        # Height of each triangle's plane over the projected point: z = G . p_xy + h.
        n = np.cross(b - a, c - a)
        flat = np.abs(n[:, 2]) > 0
        nz = np.where(flat, n[:, 2], 1.0)
        self.G = np.where(flat, -n[:, :2].T / nz, 0.0)  # (2, T)
        self.h = np.where(flat, np.einsum("ij,ij->i", n, a) / nz, np.inf)
        self.t = len(T)

    def inside(self, points: npt.ArrayLike) -> BoolArray:
        """Return True for each point inside the mesh (odd number of crossings above it)."""
        P = np.asarray(points, dtype=np.float64).reshape(-1, 3) @ self.R.T
        e = P[:, :2] @ self.W + self.w
        e0, e1, e2 = e[:, : self.t], e[:, self.t : 2 * self.t], e[:, 2 * self.t :]
        within = ((e0 > 0) & (e1 > 0) & (e2 > 0)) | ((e0 < 0) & (e1 < 0) & (e2 < 0))
        above = P[:, :2] @ self.G + self.h > P[:, 2:3]
        return np.asarray(np.count_nonzero(within & above, axis=1) % 2 == 1)
