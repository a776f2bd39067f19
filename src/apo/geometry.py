"""Polyhedral models: polygonal faces, edges with convexity, outward normals (no I/O).

A :class:`Polyhedron` is built from a closed triangle mesh by
:func:`polyhedron_from_triangles`: duplicate vertices are merged, coplanar adjacent triangles
become one polygonal face (possibly non-convex, possibly with holes), flat edges and vertices
that are not corners disappear, and every remaining edge is flagged convex or concave.

The module also holds the pure geometric helpers the contact finder needs: distances from
points to faces and segments, closest points between segments, and the local solid at a
vertex, edge or face split into convex pieces (:func:`local_solid`).

Everything is in the model frame, in metres; normals point out of the solid and face loops
are counter-clockwise seen from outside (``docs/conventions.md``).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from apo.arrays import unique
from apo.constants import tol
from apo.errors import GeometryError
from apo.typing import BoolArray, FloatArray, IntArray

__all__ = [
    "LocalSolid",
    "Polyhedron",
    "SegmentClosest",
    "closest_point_on_segment",
    "local_solid",
    "point_face_distance",
    "polyhedron_from_triangles",
    "segment_segment_closest",
    "transformed",
    "triangulate_polygon",
]


@dataclass(frozen=True, eq=False)
class Polyhedron:
    """A closed polyhedron with merged coplanar faces, in its own frame (metres).

    Feature ids are indices into these arrays; they are deterministic for a given input mesh,
    so contact states computed at different frames can be compared by feature ids.
    Build one with :func:`polyhedron_from_triangles` (or ``apo.io.load_polyhedron``,
    ``apo.shapes``).

    Attributes
    ----------
    name : str
        Where it came from (file name or builder name), used in messages.
    vertices : ndarray, shape (V, 3)
        Vertex positions, metres, model frame. Only vertices that are corners of the polyhedron
        (incident to at least one non-flat edge) are kept.
    faces : tuple of ndarray
        ``faces[f]`` is the outer boundary loop of face f as vertex indices, counter-clockwise
        seen from outside (right-hand rule gives the outward normal).
    face_holes : tuple of tuple of ndarray
        ``face_holes[f]`` are the inner boundary loops (holes) of face f, clockwise seen from
        outside; usually empty.
    face_normals : ndarray, shape (F, 3)
        Outward unit normals.
    face_offsets : ndarray, shape (F,)
        Plane offsets: points x of face f satisfy ``face_normals[f] @ x == face_offsets[f]``.
    face_triangles : tuple of ndarray
        ``face_triangles[f]`` has shape (T_f, 3): a triangulation of face f (vertex indices),
        for point-in-face tests and distances.
    edges : ndarray, shape (E, 2)
        Vertex index pairs ``(a, b)`` with ``a < b``; only edges between two faces that are not
        coplanar (flat edges between coplanar triangles are removed).
    edge_faces : ndarray, shape (E, 2)
        The two faces meeting at each edge: ``edge_faces[e, 0]`` is the face whose outer or
        inner loop traverses the edge from ``edges[e, 0]`` to ``edges[e, 1]``.
    edge_convex : ndarray of bool, shape (E,)
        True for a convex edge (dihedral angle < 180 deg inside the solid), False for concave.
    vertex_edges : tuple of ndarray
        Edge ids incident to each vertex.
    vertex_faces : tuple of ndarray
        Face ids incident to each vertex, in cyclic order around the vertex where possible.
    scale : float
        Length of the bounding-box diagonal (metres), for scale-aware tolerances.

    Notes
    -----
    ``vertex_faces[v]`` is counter-clockwise seen from outside the solid, i.e. the right-hand
    rule about the outward direction at ``v``; a face that touches ``v`` twice is listed once.
    """

    name: str
    vertices: FloatArray
    faces: tuple[IntArray, ...]
    face_holes: tuple[tuple[IntArray, ...], ...]
    face_normals: FloatArray
    face_offsets: FloatArray
    face_triangles: tuple[IntArray, ...]
    edges: IntArray
    edge_faces: IntArray
    edge_convex: npt.NDArray[np.bool_]
    vertex_edges: tuple[IntArray, ...]
    vertex_faces: tuple[IntArray, ...]
    scale: float

    def __repr__(self) -> str:
        return (
            f"Polyhedron(name={self.name!r}, vertices={len(self.vertices)}, "
            f"edges={len(self.edges)}, faces={len(self.faces)}, "
            f"concave_edges={self.n_concave_edges}, scale={self.scale:.6g} m)"
        )

    @property
    def n_concave_edges(self) -> int:
        """Number of concave edges."""
        return int(np.count_nonzero(~self.edge_convex))

    @cached_property
    def edge_vectors(self) -> FloatArray:
        """Edge vectors ``vertices[b] - vertices[a]``, shape (E, 3), metres."""
        return self.vertices[self.edges[:, 1]] - self.vertices[self.edges[:, 0]]

    @cached_property
    def edge_lengths(self) -> FloatArray:
        """Edge lengths, shape (E,), metres."""
        lengths: FloatArray = np.linalg.norm(self.edge_vectors, axis=1)
        return lengths

    @cached_property
    def edge_directions(self) -> FloatArray:
        """Unit edge directions from ``edges[e, 0]`` to ``edges[e, 1]``, shape (E, 3)."""
        return self.edge_vectors / self.edge_lengths[:, None]

    @cached_property
    def face_areas(self) -> FloatArray:
        """Face areas, shape (F,), square metres (holes subtracted)."""
        out = np.empty(len(self.faces))
        for f, tris in enumerate(self.face_triangles):
            p = self.vertices[tris]
            out[f] = 0.5 * float(
                np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
            )
        return out

    @cached_property
    def volume(self) -> float:
        """Enclosed volume, cubic metres (positive: normals point outward)."""
        tris = np.concatenate(self.face_triangles)
        p = self.vertices[tris] - self.vertices.mean(axis=0)
        return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)

    @cached_property
    def face_boundary_segments(self) -> tuple[IntArray, ...]:
        """Per face, the directed boundary segments of all its loops, shape (S_f, 2) each.

        Outer loop first (counter-clockwise seen from outside), then the holes (clockwise).
        """
        flat, face, _, nxt = _flatten_loops(self.faces, self.face_holes)
        segs = np.stack([flat, flat[nxt]], axis=1)
        split = np.searchsorted(face, np.arange(len(self.faces) + 1))
        return tuple(segs[split[f] : split[f + 1]] for f in range(len(self.faces)))

    @cached_property
    def vertex_corners(self) -> tuple[IntArray, ...]:
        """Per vertex, its face corners in counter-clockwise order seen from outside.

        ``vertex_corners[v]`` has shape (K, 3); row ``(f, u, w)`` is a corner of face f at
        ``v`` whose boundary arrives from vertex u and leaves towards vertex w. Consecutive
        rows share an edge: the edge ``{v, u}`` of row k is the edge ``{v, w}`` of row k + 1.
        """
        return _vertex_corners(self.faces, self.face_holes, len(self.vertices))


# --------------------------------------------------------------------------------------------
# Construction
# --------------------------------------------------------------------------------------------


def polyhedron_from_triangles(
    vertices: npt.ArrayLike, triangles: npt.ArrayLike, *, name: str = ""
) -> Polyhedron:
    """Build a :class:`Polyhedron` from a closed, consistently oriented triangle mesh.

    Parameters
    ----------
    vertices : array_like, shape (N, 3)
        Vertex positions, metres, model frame. Unreferenced vertices are ignored.
    triangles : array_like of int, shape (T, 3)
        Vertex indices of each triangle. Counter-clockwise seen from outside is expected; a
        mesh that is consistently oriented but inside-out (negative volume) is flipped with a
        warning.
    name : str, optional
        Name of the model, used in messages and stored in ``Polyhedron.name``.

    Returns
    -------
    Polyhedron
        Faces, edges and vertices re-indexed deterministically: vertices keep the order of
        their first occurrence in ``vertices``, faces the order of their first triangle, edges
        are sorted by ``(a, b)``.

    Raises
    ------
    GeometryError
        Empty mesh, wrong array shapes, indices out of range, non-finite coordinates, open
        mesh (boundary edges), non-manifold edges or vertices, inconsistently oriented
        triangles, zero volume or zero-area faces. The message starts with ``name``.

    Warns
    -----
    UserWarning
        When triangles collapse after merging vertices closer than ``tol.merge`` times the
        bounding diagonal, when zero-area (sliver) triangles are absorbed into a neighbouring
        face, and when an inside-out mesh is flipped. The result is then still exact up to
        the tolerances.

    Notes
    -----
    Steps: merge vertices closer than ``tol.merge * scale`` (``scale`` = bounding-box
    diagonal); check that every edge has exactly two triangles traversing it in opposite
    directions and that the triangles around each vertex form one fan; join adjacent
    triangles whose normals differ by less than ``tol.coplanar_angle`` or whose far vertex
    lies within ``tol.coplanar_distance * scale`` of the other's plane; trace the boundary
    loops of each face; keep only corner vertices (a vertex inside a face or in the middle of
    a straight edge is dropped); re-triangulate each face from its loops. An edge from ``a``
    to ``b`` traversed in that direction by face ``f0`` with outward normal ``n0`` and by the
    other face ``f1`` (normal ``n1``) is convex iff ``(n0 x n1) . (b - a) > 0``.

    Examples
    --------
    >>> import numpy as np
    >>> v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    >>> t = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    >>> p = polyhedron_from_triangles(v, t, name="tetra")
    >>> len(p.vertices), len(p.edges), len(p.faces), bool(p.edge_convex.all())
    (4, 6, 4, True)
    """
    label = name or "mesh"
    V, T = _check_mesh_arrays(vertices, triangles, label)

    # Keep referenced vertices only (order of first index), then merge close ones.
    used = unique(T)
    V = V[used]
    T = np.searchsorted(used, T).astype(np.int64)
    lo, hi = V.min(axis=0), V.max(axis=0)
    scale = float(np.linalg.norm(hi - lo))
    if not scale > 0.0:
        raise GeometryError(f"{label}: degenerate mesh: all vertices coincide")
    merge_dist = tol.merge * scale
    V, T = _merge_vertices(V, T, merge_dist)
    collapsed = (T[:, 0] == T[:, 1]) | (T[:, 1] == T[:, 2]) | (T[:, 2] == T[:, 0])
    if collapsed.any():
        warnings.warn(
            f"{label}: dropped {int(collapsed.sum())} triangle(s) that collapsed when merging "
            f"vertices closer than {merge_dist:.3g} m",
            stacklevel=2,
        )
        T = T[~collapsed]
        if len(T) == 0:
            raise GeometryError(f"{label}: degenerate mesh: every triangle collapsed")

    twin = _check_closed_manifold(V, T, label)
    volume = _signed_volume(V, T)
    if abs(volume) <= tol.merge * scale**3:
        raise GeometryError(f"{label}: degenerate mesh: zero volume ({volume:.3g} m^3)")
    if volume < 0.0:
        warnings.warn(
            f"{label}: the mesh is inside-out (negative volume {volume:.3g} m^3); "
            "flipped all triangles so that normals point outward",
            stacklevel=2,
        )
        T = T[:, ::-1].copy()
        twin = _check_closed_manifold(V, T, label)

    groups, n_absorbed = _coplanar_groups(V, T, twin, scale, label)
    if n_absorbed:
        warnings.warn(
            f"{label}: absorbed {n_absorbed} zero-area triangle(s) (height below "
            f"{merge_dist:.3g} m) into neighbouring faces",
            stacklevel=2,
        )
    return _assemble(V, T, twin, groups, scale, label)


def _check_mesh_arrays(
    vertices: npt.ArrayLike, triangles: npt.ArrayLike, label: str
) -> tuple[FloatArray, IntArray]:
    try:
        V = np.asarray(vertices, dtype=np.float64)
        T_raw = np.asarray(triangles)
    except (TypeError, ValueError) as exc:
        raise GeometryError(
            f"{label}: vertices or triangles are not numeric arrays: {exc}"
        ) from exc
    if V.size == 0 or T_raw.size == 0:
        raise GeometryError(
            f"{label}: empty mesh ({V.size // 3} vertices, {T_raw.size // 3} triangles)"
        )
    if V.ndim != 2 or V.shape[1] != 3:
        raise GeometryError(f"{label}: vertices must have shape (N, 3), got {V.shape}")
    if T_raw.ndim != 2 or T_raw.shape[1] != 3:
        raise GeometryError(f"{label}: triangles must have shape (T, 3), got {T_raw.shape}")
    if not np.issubdtype(T_raw.dtype, np.integer) and (
        not np.all(np.isfinite(T_raw)) or np.any(T_raw != np.round(T_raw))
    ):
        raise GeometryError(f"{label}: triangle indices must be integers")
    T = T_raw.astype(np.int64)
    if T.min() < 0 or T.max() >= len(V):
        raise GeometryError(
            f"{label}: triangle indices out of range [0, {len(V)}): "
            f"min {int(T.min())}, max {int(T.max())}"
        )
    bad = ~np.isfinite(V[unique(T)])
    if bad.any():
        raise GeometryError(
            f"{label}: {int(bad.any(axis=1).sum())} vertex coordinate row(s) are NaN or infinite"
        )
    return V, T


#: Meshes with at most this many vertices find their close pairs by all-pairs distances
#: (numpy), larger ones with a k-d tree (scipy, imported then: 0.1-0.3 s).
_DENSE_MERGE = 2048


def _close_pairs(V: FloatArray, dist: float) -> IntArray:
    """Pairs ``(i, j)``, ``i < j``, of points within ``dist``, sorted (``cKDTree.query_pairs``)."""
    if len(V) > _DENSE_MERGE:
        from scipy.spatial import cKDTree

        pairs = cKDTree(V).query_pairs(dist, output_type="ndarray")
        return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))] if len(pairs) else pairs
    d2 = np.sum((V[:, None, :] - V[None, :, :]) ** 2, axis=2)
    i, j = np.nonzero(np.triu(d2 <= dist * dist, 1))
    return np.stack([i, j], axis=1).astype(np.int64)


def connected_components(n: int, a: IntArray, b: IntArray) -> tuple[int, IntArray]:
    """Return the connected components of the graph on ``n`` nodes with edges ``(a[k], b[k])``.

    Returns the count and each node's label, labels numbered in the order of each
    component's smallest node (as ``scipy.sparse.csgraph.connected_components`` numbers
    them, also for ``directed=True, connection="weak"``). Numpy only: min-label
    propagation with pointer jumping, so loading a model does not import scipy.

    Examples
    --------
    >>> connected_components(5, np.array([3, 1]), np.array([4, 0]))[1].tolist()
    [0, 0, 1, 2, 2]
    """
    lab = np.arange(n, dtype=np.int64)
    a, b = np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64)
    while len(a):
        la, lb = lab[a], lab[b]
        if np.array_equal(la, lb):
            break
        m = np.minimum(la, lb)
        np.minimum.at(lab, la, m)  # hook each root onto the smaller label
        np.minimum.at(lab, lb, m)
        while True:  # pointer jumping: every node to its root
            nxt = lab[lab]
            if np.array_equal(nxt, lab):
                break
            lab = nxt
    roots, labels = np.unique(lab, return_inverse=True)
    return len(roots), labels.reshape(-1).astype(np.int64)


def _merge_vertices(V: FloatArray, T: IntArray, dist: float) -> tuple[FloatArray, IntArray]:
    """Merge vertices closer than ``dist`` (transitively); keep the first one's position."""
    pairs = _close_pairs(V, dist)
    if len(pairs) == 0:
        return V, T
    _, labels = connected_components(len(V), pairs[:, 0], pairs[:, 1])
    # Relabel by first occurrence so that the order is that of the input.
    _, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    new_index = rank[inverse]
    return V[first[order]], new_index[T].astype(np.int64)


def _half_edges(T: IntArray) -> IntArray:
    """Half-edges ``(u, v)`` of the triangles, shape (3T, 2); half-edge h is in triangle h//3."""
    return T[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)


def _check_closed_manifold(V: FloatArray, T: IntArray, label: str) -> IntArray:
    """Return the twin half-edge of each half-edge; raise if not closed, manifold, oriented."""
    he = _half_edges(T)
    n = np.int64(len(V))
    lo = np.minimum(he[:, 0], he[:, 1])
    hi = np.maximum(he[:, 0], he[:, 1])
    key = lo * n + hi
    order = np.argsort(key, kind="stable")
    uniq, start, counts = np.unique(key[order], return_index=True, return_counts=True)

    def where(k: np.int64) -> str:
        a, b = divmod(int(k), int(n))
        return f"between {V[a].tolist()} and {V[b].tolist()}"

    if np.any(counts == 1):
        bad = uniq[counts == 1]
        raise GeometryError(
            f"{label}: mesh is not closed: {len(bad)} boundary edge(s), e.g. {where(bad[0])}"
        )
    if np.any(counts > 2):
        bad = uniq[counts > 2]
        raise GeometryError(
            f"{label}: non-manifold mesh: {len(bad)} edge(s) shared by more than two "
            f"triangles, e.g. {where(bad[0])}"
        )
    h0 = order[start]
    h1 = order[start + 1]
    same = he[h0, 0] == he[h1, 0]
    if same.any():
        raise GeometryError(
            f"{label}: inconsistent orientation: {int(same.sum())} edge(s) traversed in the "
            f"same direction by both triangles, e.g. {where(uniq[same][0])}"
        )
    twin = np.empty(len(he), dtype=np.int64)
    twin[h0] = h1
    twin[h1] = h0

    # One fan per vertex: corner c (triangle corner at u with outgoing half-edge c) maps to
    # the corner whose outgoing half-edge is the twin of c's incoming half-edge.
    incoming = (np.arange(len(he)) // 3) * 3 + (np.arange(len(he)) + 2) % 3
    nxt = twin[incoming]
    n_cycles, cyc = connected_components(len(he), np.arange(len(he)), nxt)
    n_used = len(unique(T))
    if n_cycles != n_used:
        per_vertex = np.zeros(len(V), dtype=np.int64)
        first_of_cycle = np.unique(cyc, return_index=True)[1]
        np.add.at(per_vertex, he[first_of_cycle, 0], 1)
        v = int(np.argmax(per_vertex))
        raise GeometryError(
            f"{label}: non-manifold vertex at {V[v].tolist()}: {int(per_vertex[v])} separate "
            "fans of triangles meet there"
        )
    return twin


def _signed_volume(V: FloatArray, T: IntArray) -> float:
    p = V[T] - V.mean(axis=0)
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


def _coplanar_groups(
    V: FloatArray, T: IntArray, twin: IntArray, scale: float, label: str
) -> tuple[IntArray, int]:
    """Label each triangle with its face (connected, coplanar); return labels, #absorbed."""
    p = V[T]
    e = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 1], p[:, 0] - p[:, 2]], axis=1)
    cross = np.cross(e[:, 0], -e[:, 2])
    area2 = np.linalg.norm(cross, axis=1)
    longest = np.linalg.norm(e, axis=2).max(axis=1)
    degenerate = area2 <= tol.merge * scale * longest
    normals = np.zeros_like(cross)
    normals[~degenerate] = cross[~degenerate] / area2[~degenerate, None]

    m = len(twin)
    h = np.arange(m)
    keep = h < twin
    h, g = h[keep], twin[keep]
    t1, t2 = h // 3, g // 3
    ok = ~degenerate[t1] & ~degenerate[t2]
    h, g, t1, t2 = h[ok], g[ok], t1[ok], t2[ok]
    n1, n2 = normals[t1], normals[t2]
    dots = np.einsum("ij,ij->i", n1, n2)
    # Far vertices: the corner opposite the shared half-edge.
    far1 = T[t1, (h % 3 + 2) % 3]
    far2 = T[t2, (g % 3 + 2) % 3]
    a = T[t1, h % 3]
    d12 = np.abs(np.einsum("ij,ij->i", n1, V[far2] - V[a]))
    d21 = np.abs(np.einsum("ij,ij->i", n2, V[far1] - V[a]))
    same = (dots >= math.cos(tol.coplanar_angle)) | (
        (dots > 0.5) & (np.minimum(d12, d21) <= tol.coplanar_distance * scale)
    )
    n_tri = len(T)
    _, labels = connected_components(n_tri, t1[same], t2[same])

    n_absorbed = int(degenerate.sum())
    if n_absorbed:
        if n_absorbed == n_tri:
            raise GeometryError(f"{label}: degenerate mesh: every triangle has zero area")
        assigned = ~degenerate
        # Absorb each zero-area triangle into the neighbour across its longest edge that is
        # already assigned; repeat for chains of slivers.
        edge_len = np.linalg.norm(e, axis=2)
        pending = list(np.flatnonzero(degenerate))
        while pending:
            rest = []
            for t in pending:
                for k in np.argsort(-edge_len[t], kind="stable"):
                    nb = int(twin[3 * t + k] // 3)
                    if assigned[nb]:
                        labels[t] = labels[nb]
                        assigned[t] = True
                        break
                else:
                    rest.append(t)
            if len(rest) == len(pending):
                raise GeometryError(
                    f"{label}: degenerate mesh: a connected patch of zero-area triangles "
                    f"near {V[T[rest[0], 0]].tolist()}"
                )
            pending = rest
    # Relabel by first triangle.
    _, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[inverse].astype(np.int64), n_absorbed


def _plane_basis(normal: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors ``(u, w)`` with ``(u, w, normal)`` right-handed and orthonormal."""
    k = int(np.argmin(np.abs(normal)))
    axis = np.zeros(3)
    axis[k] = 1.0
    u = np.cross(axis, normal)
    u /= np.linalg.norm(u)
    w = np.cross(normal, u)
    return u, w


def _loop_area2d(xy: FloatArray) -> float:
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def _trace_loops(
    V: FloatArray,
    he: IntArray,
    boundary: IntArray,
    normal: FloatArray,
    label: str,
) -> list[IntArray]:
    """Chain the boundary half-edges of one face into closed loops (vertex index arrays)."""
    out_of: dict[int, list[int]] = {}
    for b in boundary:
        out_of.setdefault(int(he[b, 0]), []).append(int(b))
    used: set[int] = set()
    loops: list[IntArray] = []
    for b0 in boundary:
        b0 = int(b0)
        if b0 in used:
            continue
        loop = []
        b = b0
        while True:
            used.add(b)
            u, v = int(he[b, 0]), int(he[b, 1])
            loop.append(u)
            cands = [c for c in out_of.get(v, []) if c not in used or c == b0]
            if not cands:
                raise GeometryError(f"{label}: could not close a face boundary at {V[v].tolist()}")
            if len(cands) > 1:
                # The face touches itself at v: take the outgoing edge that makes the
                # smallest clockwise turn from the reversed incoming edge (keeps regions apart).
                uu, ww = _plane_basis(normal)
                back = V[u] - V[v]
                ang_back = math.atan2(float(back @ ww), float(back @ uu))
                best, best_ang = cands[0], 10.0
                for c in cands:
                    d = V[he[c, 1]] - V[v]
                    ang = (ang_back - math.atan2(float(d @ ww), float(d @ uu))) % (2 * math.pi)
                    if ang == 0.0:
                        ang = 2 * math.pi
                    if ang < best_ang:
                        best, best_ang = c, ang
                b = best
            else:
                b = cands[0]
            if b == b0:
                break
        loops.append(np.asarray(loop, dtype=np.int64))
    return loops


def _face_normals(
    V: FloatArray, T: IntArray, groups: IntArray, n_faces: int, scale: float, label: str
) -> FloatArray:
    """Return unit face normals: area-weighted mean of the triangle normals (sliver-robust)."""
    p = V[T]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    fn = np.zeros((n_faces, 3))
    np.add.at(fn, groups, cross)
    fn_norm = np.linalg.norm(fn, axis=1)
    face_area = 0.5 * fn_norm
    min_area = (tol.merge * scale) ** 2
    if np.any(face_area <= min_area):
        f = int(np.argmin(face_area))
        raise GeometryError(f"{label}: degenerate face of zero area near {V[T[groups == f][0, 0]]}")
    fn /= fn_norm[:, None]
    return fn


def _corner_vertices(V: FloatArray, feature_edges: IntArray) -> BoolArray:
    """Mark corner vertices: on >= 3 feature edges, or on 2 that are not collinear."""
    fe = unique(np.sort(feature_edges, axis=1), axis=0)
    nbrs: dict[int, list[int]] = {}
    for a, b in fe:
        nbrs.setdefault(int(a), []).append(int(b))
        nbrs.setdefault(int(b), []).append(int(a))
    corner = np.zeros(len(V), dtype=bool)
    for v, nb in nbrs.items():
        if len(nb) != 2:
            corner[v] = True
            continue
        d1 = V[nb[0]] - V[v]
        d2 = V[nb[1]] - V[v]
        s = np.linalg.norm(np.cross(d1, d2)) / (np.linalg.norm(d1) * np.linalg.norm(d2))
        corner[v] = not (s <= tol.coplanar_angle and float(d1 @ d2) < 0.0)
    return corner


def _face_outline(
    f: int,
    loops: list[IntArray],
    corner: BoolArray,
    new_index: IntArray,
    verts: FloatArray,
    basis: FloatArray,
    V: FloatArray,
    label: str,
) -> tuple[IntArray, tuple[IntArray, ...]]:
    """Return the outer boundary and holes of face ``f`` (corner-vertex ids, lowest first)."""
    if len(loops) == 1 and len(loops[0]) == 3 and corner[loops[0]].all():
        kept = new_index[loops[0]]
        return np.roll(kept, -int(np.argmin(kept))), ()
    outer: list[IntArray] = []
    inner: list[IntArray] = []
    for loop in loops:
        kept = new_index[loop[corner[loop]]]
        if len(kept) < 3:
            raise GeometryError(
                f"{label}: degenerate face boundary with {len(kept)} corner(s) near "
                f"{V[loop[0]].tolist()}"
            )
        kept = np.roll(kept, -int(np.argmin(kept)))
        if len(loops) == 1:
            outer.append(kept)
            continue
        xy = verts[kept] @ basis.T
        (outer if _loop_area2d(xy) > 0.0 else inner).append(kept)
    if len(outer) != 1:
        raise GeometryError(
            f"{label}: face {f} has {len(outer)} outer boundaries (expected one); "
            "the mesh may self-intersect"
        )
    return outer[0], tuple(sorted(inner, key=lambda lp: int(lp[0])))


def _pair_edges(
    flat: IntArray, flat_face: IntArray, flat_next: IntArray, n_verts: int, label: str
) -> tuple[IntArray, IntArray]:
    """Pair the directed boundary segments into edges (v0 < v1) and their two faces."""
    segs = np.stack([flat, flat[flat_next], flat_face], axis=1)
    lo = np.minimum(segs[:, 0], segs[:, 1])
    hi = np.maximum(segs[:, 0], segs[:, 1])
    key = lo * np.int64(n_verts) + hi
    order = np.lexsort((segs[:, 0] > segs[:, 1], key))
    key_s = key[order]
    if len(key_s) % 2 or np.any(key_s[0::2] != key_s[1::2]) or np.any(key_s[1:-1:2] == key_s[2::2]):
        raise GeometryError(f"{label}: could not pair face boundaries into edges")
    forward = segs[order[0::2]]
    backward = segs[order[1::2]]
    if np.any(forward[:, 0] > forward[:, 1]) or np.any(backward[:, 0] < backward[:, 1]):
        raise GeometryError(f"{label}: face boundaries do not pair up into oriented edges")
    edges = forward[:, :2].copy()
    edge_faces = np.stack([forward[:, 2], backward[:, 2]], axis=1)
    return edges, edge_faces


def _vertex_edge_lists(edges: IntArray, n_v: int) -> tuple[IntArray, ...]:
    """Return the edge ids incident to each vertex, in increasing order."""
    inc = np.concatenate([edges[:, 0], edges[:, 1]])
    eid = np.concatenate([np.arange(len(edges)), np.arange(len(edges))])
    order = np.lexsort((eid, inc))
    vsplit = np.searchsorted(inc[order], np.arange(n_v + 1))
    eid_sorted = eid[order].astype(np.int64)
    return tuple(eid_sorted[vsplit[v] : vsplit[v + 1]] for v in range(n_v))


def _face_triangulations(
    faces: tuple[IntArray, ...],
    holes: tuple[tuple[IntArray, ...], ...],
    verts: FloatArray,
    bases: FloatArray,
) -> tuple[IntArray, ...]:
    """Triangulate each polygonal face (with its holes), in vertex indices."""
    face_triangles: list[IntArray] = []
    tri3 = np.array([[0, 1, 2]], dtype=np.int64)
    for f in range(len(faces)):
        loops_f = (faces[f], *holes[f])
        if len(loops_f) == 1 and len(loops_f[0]) == 3:
            face_triangles.append(loops_f[0][tri3])
            continue
        xy = [verts[lp] @ bases[f].T for lp in loops_f]
        local = triangulate_polygon(xy[0], xy[1:])
        face_triangles.append(np.concatenate(loops_f)[local].astype(np.int64))
    return tuple(face_triangles)


def _assemble(
    V: FloatArray, T: IntArray, twin: IntArray, groups: IntArray, scale: float, label: str
) -> Polyhedron:
    he = _half_edges(T)
    n_faces = int(groups.max()) + 1
    tri_of = np.arange(len(he)) // 3
    is_boundary = groups[tri_of] != groups[tri_of[twin]]
    fn = _face_normals(V, T, groups, n_faces, scale, label)

    # Boundary loops of each face, in merged-vertex indices.
    b_idx = np.flatnonzero(is_boundary)
    b_face = groups[tri_of[b_idx]]
    order = np.argsort(b_face, kind="stable")
    b_idx, b_face = b_idx[order], b_face[order]
    splits = np.searchsorted(b_face, np.arange(n_faces + 1))
    face_loops = [
        _trace_loops(V, he, b_idx[splits[f] : splits[f + 1]], fn[f], label) for f in range(n_faces)
    ]

    corner = _corner_vertices(V, he[b_idx])
    new_index = np.full(len(V), -1, dtype=np.int64)
    new_index[corner] = np.arange(int(corner.sum()))
    verts = V[corner]
    bases = _plane_bases(fn)
    outlines = [
        _face_outline(f, face_loops[f], corner, new_index, verts, bases[f], V, label)
        for f in range(n_faces)
    ]
    faces_t = tuple(o[0] for o in outlines)
    holes_t = tuple(o[1] for o in outlines)
    flat, flat_face, _, flat_next = _flatten_loops(faces_t, holes_t)

    face_offsets = np.zeros(n_faces)
    np.add.at(face_offsets, flat_face, np.einsum("ij,ij->i", verts[flat], fn[flat_face]))
    face_offsets /= np.bincount(flat_face, minlength=n_faces)

    edges, edge_faces = _pair_edges(flat, flat_face, flat_next, len(verts), label)
    d = verts[edges[:, 1]] - verts[edges[:, 0]]
    edge_convex = np.einsum("ij,ij->i", np.cross(fn[edge_faces[:, 0]], fn[edge_faces[:, 1]]), d) > 0
    corners = _vertex_corners(faces_t, holes_t, len(verts))

    poly = Polyhedron(
        name=label,
        vertices=verts,
        faces=faces_t,
        face_holes=holes_t,
        face_normals=fn,
        face_offsets=face_offsets,
        face_triangles=_face_triangulations(faces_t, holes_t, verts, bases),
        edges=edges,
        edge_faces=edge_faces.astype(np.int64),
        edge_convex=edge_convex,
        vertex_edges=_vertex_edge_lists(edges, len(verts)),
        vertex_faces=tuple(_unique_in_order(c[:, 0]) for c in corners),
        scale=scale,
    )
    poly.__dict__["vertex_corners"] = corners
    return poly


def _flatten_loops(
    faces: tuple[IntArray, ...], face_holes: tuple[tuple[IntArray, ...], ...]
) -> tuple[IntArray, IntArray, IntArray, IntArray]:
    """All loop vertices in one array, with their face and previous / next positions."""
    loops = [lp for outer, holes in zip(faces, face_holes, strict=True) for lp in (outer, *holes)]
    face_of = np.repeat(np.arange(len(faces)), [1 + len(h) for h in face_holes])
    lengths = np.fromiter((len(lp) for lp in loops), dtype=np.int64, count=len(loops))
    flat = np.concatenate(loops).astype(np.int64)
    start = np.repeat(np.cumsum(lengths) - lengths, lengths)
    size = np.repeat(lengths, lengths)
    pos = np.arange(len(flat)) - start
    nxt = start + (pos + 1) % size
    prv = start + (pos - 1) % size
    return flat, np.repeat(face_of, lengths).astype(np.int64), prv, nxt


def _unique_in_order(a: IntArray) -> IntArray:
    _, first = np.unique(a, return_index=True)
    return a[np.sort(first)].astype(np.int64)


def _vertex_corners(
    faces: tuple[IntArray, ...], face_holes: tuple[tuple[IntArray, ...], ...], n_vertices: int
) -> tuple[IntArray, ...]:
    """Face corners ``(f, u, w)`` around each vertex, counter-clockwise seen from outside."""
    flat, face, prv, nxt = _flatten_loops(faces, face_holes)
    allc = np.stack([flat, face, flat[prv], flat[nxt]], axis=1)
    order = np.lexsort((allc[:, 3], allc[:, 0]))
    allc = allc[order]
    n = np.int64(n_vertices)
    # Next corner counter-clockwise: the one leaving along the edge this one arrived on,
    # i.e. the corner at the same vertex whose outgoing neighbour is this one's incoming one.
    key_out = allc[:, 0] * n + allc[:, 3]
    want = allc[:, 0] * n + allc[:, 2]
    j = np.searchsorted(key_out, want)
    j = np.minimum(j, len(key_out) - 1)
    succ = np.where(key_out[j] == want, j, -1).tolist()
    split = np.searchsorted(allc[:, 0], np.arange(n_vertices + 1)).tolist()
    out = []
    for v in range(n_vertices):
        lo, hi = split[v], split[v + 1]
        seq = [lo]
        seen = {lo}
        k = succ[lo]
        while k >= 0 and k not in seen:
            seq.append(k)
            seen.add(k)
            k = succ[k]
        if len(seq) < hi - lo:
            seq += [k for k in range(lo, hi) if k not in seen]
        out.append(allc[seq, 1:])
    return tuple(out)


def _plane_bases(normals: FloatArray) -> FloatArray:
    """Per normal, rows ``(u, w)`` with ``(u, w, n)`` right-handed orthonormal, shape (F, 2, 3)."""
    k = np.argmin(np.abs(normals), axis=1)
    axis = np.zeros_like(normals)
    axis[np.arange(len(normals)), k] = 1.0
    u = np.cross(axis, normals)
    u /= np.linalg.norm(u, axis=1)[:, None]
    w = np.cross(normals, u)
    return np.stack([u, w], axis=1)


def transformed(poly: Polyhedron, X_NM: npt.ArrayLike) -> Polyhedron:
    """Express the polyhedron in another frame; feature ids are unchanged.

    Parameters
    ----------
    poly : Polyhedron
        Model in its frame M.
    X_NM : array_like, shape (4, 4)
        Pose of frame M in frame N (rigid: rotation and translation, metres), so that
        ``p_N = X_NM @ p_M``.

    Returns
    -------
    Polyhedron
        Vertices, normals and offsets in frame N; topology, convexity and scale shared.

    Raises
    ------
    ValueError
        If ``X_NM`` is not a 4x4 rigid transform.

    Examples
    --------
    >>> from apo.shapes import box
    >>> X = np.eye(4)
    >>> X[:3, 3] = [0.0, 0.0, 1.0]
    >>> float(transformed(box(), X).vertices[:, 2].min())
    0.5
    """
    X = np.asarray(X_NM, dtype=np.float64)
    if X.shape != (4, 4):
        raise ValueError(f"expected a pose of shape (4, 4), got shape {X.shape}")
    R, p = X[:3, :3], X[:3, 3]
    if (
        not np.all(np.isfinite(X))
        or not np.allclose(R.T @ R, np.eye(3), atol=tol.rigid_transform)
        or np.linalg.det(R) <= 0
        or not np.allclose(X[3], [0.0, 0.0, 0.0, 1.0])
    ):
        raise ValueError("X_NM is not a rigid transform (rotation with det +1 and translation)")
    normals = poly.face_normals @ R.T
    moved = Polyhedron(
        name=poly.name,
        vertices=poly.vertices @ R.T + p,
        faces=poly.faces,
        face_holes=poly.face_holes,
        face_normals=normals,
        face_offsets=poly.face_offsets + normals @ p,
        face_triangles=poly.face_triangles,
        edges=poly.edges,
        edge_faces=poly.edge_faces,
        edge_convex=poly.edge_convex,
        vertex_edges=poly.vertex_edges,
        vertex_faces=poly.vertex_faces,
        scale=poly.scale,
    )
    moved.__dict__["vertex_corners"] = poly.vertex_corners
    return moved


# --------------------------------------------------------------------------------------------
# Polygon triangulation
# --------------------------------------------------------------------------------------------


def _cross2(o: FloatArray, a: FloatArray, b: FloatArray) -> float:
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def triangulate_polygon(
    outer: npt.ArrayLike, holes: list[FloatArray] | tuple[FloatArray, ...] = ()
) -> IntArray:
    """Triangulate a simple 2D polygon, possibly non-convex, possibly with holes.

    Parameters
    ----------
    outer : array_like, shape (N, 2)
        Outer boundary, counter-clockwise, no repeated closing point.
    holes : sequence of ndarray, shape (H_k, 2)
        Inner boundaries, clockwise, strictly inside ``outer`` and disjoint.

    Returns
    -------
    ndarray of int, shape (T, 3)
        Counter-clockwise triangles as indices into ``concatenate([outer, *holes])``; every
        vertex is used (also where the boundary runs straight on), so adjacent polygons
        triangulated separately share their edges' vertices.

    Notes
    -----
    Ear clipping; holes are first bridged to the outer boundary (Eberly, "Triangulation by
    ear clipping", 2002). O(N^2), meant for the faces of CAD models.

    Examples
    --------
    >>> square = [[0, 0], [1, 0], [1, 1], [0, 1]]
    >>> triangulate_polygon(square).tolist()
    [[0, 1, 2], [0, 2, 3]]
    """
    pts_list = [np.asarray(outer, dtype=np.float64)] + [
        np.asarray(h, dtype=np.float64) for h in holes
    ]
    pts = np.concatenate(pts_list)
    starts = np.cumsum([0] + [len(p) for p in pts_list])
    if len(pts_list) == 1:
        n = len(pts)
        if n == 3:
            return np.array([[0, 1, 2]], dtype=np.int64)
        # Convex polygon: a fan (vectorised; the common case for caps and CAD faces).
        d = np.roll(pts, -1, axis=0) - pts
        turn = d[:, 0] * np.roll(d, -1, axis=0)[:, 1] - d[:, 1] * np.roll(d, -1, axis=0)[:, 0]
        if np.all(turn > 0):
            k = np.arange(1, n - 1)
            return np.column_stack([np.zeros(n - 2, dtype=np.int64), k, k + 1])
    ring: list[int] = list(range(starts[0], starts[1]))
    hole_rings = [list(range(starts[k], starts[k + 1])) for k in range(1, len(pts_list))]
    hole_rings.sort(key=lambda r: -float(pts[r, 0].max()))
    for hr in hole_rings:
        ring = _bridge_hole(pts, ring, hr)
    return _ear_clip(pts, ring)


def _bridge_hole(pts: FloatArray, ring: list[int], hole: list[int]) -> list[int]:
    """Join ``hole`` to ``ring`` with a two-way bridge from its rightmost vertex."""
    k_m = max(range(len(hole)), key=lambda k: (pts[hole[k], 0], -pts[hole[k], 1]))
    m = pts[hole[k_m]]
    best_t, best_i = math.inf, -1
    n = len(ring)
    for i in range(n):
        a, b = pts[ring[i]], pts[ring[(i + 1) % n]]
        if (a[1] - m[1]) * (b[1] - m[1]) > 0 or a[1] == b[1]:
            continue
        t = a[0] + (m[1] - a[1]) * (b[0] - a[0]) / (b[1] - a[1]) - m[0]
        if 0 <= t < best_t:
            best_t, best_i = t, i
    if best_i < 0:
        raise GeometryError("triangulate_polygon: a hole is not inside the outer boundary")
    i_a, i_b = best_i, (best_i + 1) % n
    cand = i_a if pts[ring[i_a], 0] > pts[ring[i_b], 0] else i_b
    p_vis = pts[ring[cand]]
    hit = np.array([m[0] + best_t, m[1]])
    # Reflex ring vertices inside triangle (m, hit, p_vis) block the view: take the one with
    # the smallest angle to the ray.
    best_ang, best_d = math.inf, math.inf
    tri = (m, hit, p_vis) if _cross2(m, hit, p_vis) > 0 else (m, p_vis, hit)
    for i in range(n):
        q = pts[ring[i]]
        prev, nxt = pts[ring[i - 1]], pts[ring[(i + 1) % n]]
        if i == cand or _cross2(prev, q, nxt) > 0:
            continue
        if (
            _cross2(tri[0], tri[1], q) >= 0
            and _cross2(tri[1], tri[2], q) >= 0
            and _cross2(tri[2], tri[0], q) >= 0
        ):
            d = q - m
            ang = abs(math.atan2(float(d[1]), float(d[0])))
            dist = float(d @ d)
            if (ang, dist) < (best_ang, best_d):
                best_ang, best_d, cand = ang, dist, i
    hole_seq = hole[k_m:] + hole[:k_m] + [hole[k_m]]
    return ring[: cand + 1] + hole_seq + ring[cand:]


def _ear_clip(pts: FloatArray, ring: list[int]) -> IntArray:
    # Vertices where the boundary runs straight on are kept (a mesh built from the result
    # must not have T-junctions); they are never ear tips, only ear corners.
    idx = list(ring)
    tris: list[tuple[int, int, int]] = []
    while len(idx) > 3:
        n = len(idx)
        clipped = False
        best_k, best_area = -1, -math.inf
        for k in range(n):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % n]
            a, b, c = pts[i0], pts[i1], pts[i2]
            area = _cross2(a, b, c)
            if area > best_area:
                best_k, best_area = k, area
            if area <= tol.zero_norm * float(np.linalg.norm(b - a) * np.linalg.norm(c - b)):
                continue
            ear = True
            for j in idx:
                if j in (i0, i1, i2):
                    continue
                q = pts[j]
                if (q == a).all() or (q == b).all() or (q == c).all():
                    continue
                if _cross2(a, b, q) >= 0 and _cross2(b, c, q) >= 0 and _cross2(c, a, q) >= 0:
                    ear = False
                    break
            if ear:
                tris.append((i0, i1, i2))
                del idx[k]
                clipped = True
                break
        if not clipped:
            # Numerically stuck (near-degenerate input): clip the most convex vertex.
            k = best_k
            tris.append((idx[k - 1], idx[k], idx[(k + 1) % n]))
            del idx[k]
    tris.append((idx[0], idx[1], idx[2]))
    return np.asarray(tris, dtype=np.int64)


# --------------------------------------------------------------------------------------------
# Distances and closest points
# --------------------------------------------------------------------------------------------


def closest_point_on_segment(
    points: npt.ArrayLike, a: npt.ArrayLike, b: npt.ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Closest points on segments ``[a, b]`` to ``points`` (broadcasting).

    Parameters
    ----------
    points : array_like, shape (..., 3)
        Query points, metres.
    a, b : array_like, shape (..., 3)
        Segment end points, broadcast against ``points``.

    Returns
    -------
    closest : ndarray, shape (..., 3)
        ``a + t (b - a)``.
    t : ndarray, shape (...)
        Segment parameter in ``[0, 1]`` (0 for a zero-length segment).

    Examples
    --------
    >>> c, t = closest_point_on_segment([0.5, 1.0, 0.0], [0, 0, 0], [1, 0, 0])
    >>> c.tolist(), float(t)
    ([0.5, 0.0, 0.0], 0.5)
    """
    p = np.asarray(points, dtype=np.float64)
    a_ = np.asarray(a, dtype=np.float64)
    d = np.asarray(b, dtype=np.float64) - a_
    dd = np.einsum("...i,...i->...", d, d)
    num = np.einsum("...i,...i->...", p - a_, d)
    t = np.clip(np.divide(num, dd, out=np.zeros(np.broadcast(num, dd).shape), where=dd > 0), 0, 1)
    return a_ + t[..., None] * d, t


class SegmentClosest(NamedTuple):
    """Closest points between two families of segments (see :func:`segment_segment_closest`).

    Attributes
    ----------
    s, t : ndarray, shape (...)
        Parameters on the first and second segments, in ``[0, 1]``.
    p, q : ndarray, shape (..., 3)
        Closest points ``p0 + s (p1 - p0)`` and ``q0 + t (q1 - q0)``, metres.
    distance : ndarray, shape (...)
        ``|p - q|``, metres.
    parallel : ndarray of bool, shape (...)
        True where the segments are parallel (or one has zero length): the closest pair is
        then not unique and ``(s, t)`` is one of them.
    """

    s: FloatArray
    t: FloatArray
    p: FloatArray
    q: FloatArray
    distance: FloatArray
    parallel: BoolArray


def segment_segment_closest(
    p0: npt.ArrayLike, p1: npt.ArrayLike, q0: npt.ArrayLike, q1: npt.ArrayLike
) -> SegmentClosest:
    """Closest points between segments ``[p0, p1]`` and ``[q0, q1]`` (broadcasting).

    Parameters
    ----------
    p0, p1 : array_like, shape (..., 3)
        End points of the first segments, metres.
    q0, q1 : array_like, shape (..., 3)
        End points of the second segments; all four broadcast together, so
        ``p0[:, None], p1[:, None], q0[None], q1[None]`` gives all pairs.

    Returns
    -------
    SegmentClosest
        Parameters, closest points, distances and a parallel flag.

    Notes
    -----
    Ericson, *Real-Time Collision Detection*, 5.1.9. Segments are parallel when
    ``|d1 x d2| <= tol.normal_angle * |d1| |d2|``; for parallel segments ``s`` is the
    parameter of ``q``'s projection clamped to the overlap's start.

    Examples
    --------
    >>> r = segment_segment_closest([0, 0, 0], [2, 0, 0], [1, -1, 1], [1, 1, 1])
    >>> r.p.tolist(), r.q.tolist(), float(r.distance)
    ([1.0, 0.0, 0.0], [1.0, 0.0, 1.0], 1.0)
    """
    P0 = np.asarray(p0, dtype=np.float64)
    Q0 = np.asarray(q0, dtype=np.float64)
    d1 = np.asarray(p1, dtype=np.float64) - P0
    d2 = np.asarray(q1, dtype=np.float64) - Q0
    P0, Q0, d1, d2 = np.broadcast_arrays(P0, Q0, d1, d2)
    r = P0 - Q0

    def dot(x: FloatArray, y: FloatArray) -> FloatArray:
        out: FloatArray = np.einsum("...i,...i->...", x, y)
        return out

    a = dot(d1, d1)
    e = dot(d2, d2)
    f = dot(d2, r)
    c = dot(d1, r)
    b = dot(d1, d2)
    denom = a * e - b * b
    cross_n = np.linalg.norm(np.cross(d1, d2), axis=-1)
    parallel = (cross_n <= tol.normal_angle * np.sqrt(a * e)) | (a <= 0) | (e <= 0)

    def safe_div(x: FloatArray, y: FloatArray) -> FloatArray:
        out = np.zeros(np.broadcast(x, y).shape)
        return np.divide(x, y, out=out, where=y > 0)

    s_gen = np.clip(safe_div(b * f - c * e, np.where(parallel, 1.0, denom)), 0.0, 1.0)
    s = np.where(parallel, 0.0, s_gen)
    # For parallel segments start from q0's projection onto the first segment.
    s = np.where(parallel & (a > 0), np.clip(safe_div(-c, a), 0, 1), s)
    t = safe_div(b * s + f, e)
    # Clamp t and recompute s.
    t_cl = np.clip(t, 0, 1)
    s = np.where(t != t_cl, np.clip(safe_div(b * t_cl - c, a), 0, 1), s)
    t = np.where(e > 0, t_cl, 0.0)
    p = P0 + s[..., None] * d1
    q = Q0 + t[..., None] * d2
    return SegmentClosest(s, t, p, q, np.linalg.norm(p - q, axis=-1), parallel)


def point_face_distance(
    poly: Polyhedron, f: int, points: npt.ArrayLike
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Distance from points to the polygon of face ``f`` (holes respected).

    Parameters
    ----------
    poly : Polyhedron
        The model; ``points`` are in its frame.
    f : int
        Face id.
    points : array_like, shape (N, 3) or (3,)
        Query points, metres, model frame.

    Returns
    -------
    distance : ndarray, shape (N,)
        Euclidean distance to the closest point of the face (its closed polygon), metres.
    closest : ndarray, shape (N, 3)
        That closest point.
    inside : ndarray of bool, shape (N,)
        True where the orthogonal projection onto the face's plane lies inside the face
        polygon (on the boundary counts as inside, within ``tol.merge * scale``); then
        ``distance`` is the absolute height above the plane.

    Notes
    -----
    The signed height is ``poly.face_normals[f] @ x - poly.face_offsets[f]`` (positive
    outside the solid). Inside is decided with the even-odd rule on all boundary loops.

    Examples
    --------
    >>> from apo.shapes import box
    >>> b = box([1.0, 1.0, 1.0])
    >>> top = int(np.argmax(b.face_normals[:, 2]))
    >>> d, c, ins = point_face_distance(b, top, [[0.0, 0.0, 1.5], [1.5, 0.0, 1.0]])
    >>> d.round(6).tolist(), ins.tolist()
    ([1.0, 1.118034], [True, False])
    """
    pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
    n = poly.face_normals[f]
    h = pts @ n - poly.face_offsets[f]
    proj = pts - h[:, None] * n
    segs = poly.face_boundary_segments[f]
    a = poly.vertices[segs[:, 0]]
    b = poly.vertices[segs[:, 1]]
    u, w = _plane_basis(n)
    px, py = proj @ u, proj @ w
    ax, ay, bx, by = a @ u, a @ w, b @ u, b @ w
    # Even-odd rule: count crossings of a ray towards +u.
    straddle = (ay[None, :] > py[:, None]) != (by[None, :] > py[:, None])
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = ax[None, :] + (py[:, None] - ay[None, :]) * (bx - ax)[None, :] / (by - ay)[None, :]
    crossings = np.count_nonzero(straddle & (x_at > px[:, None]), axis=1)
    inside_strict = crossings % 2 == 1
    cl, _ = closest_point_on_segment(proj[:, None, :], a[None], b[None])
    d_edge = np.linalg.norm(cl - proj[:, None, :], axis=2)
    k = np.argmin(d_edge, axis=1)
    on_boundary = d_edge[np.arange(len(pts)), k] <= tol.merge * poly.scale
    inside = inside_strict | on_boundary
    closest = np.where(inside[:, None], proj, cl[np.arange(len(pts)), k])
    return np.linalg.norm(pts - closest, axis=1), closest, inside


# --------------------------------------------------------------------------------------------
# Local solid at a feature
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LocalSolid:
    """The solid near a point of a vertex, edge or face, as a union of convex cones.

    Near ``point`` the solid is ``point + K`` with ``K`` the union over ``pieces`` of the
    convex cones ``{x : face_normals[g] @ x <= 0 for every face g of the piece}``.

    Attributes
    ----------
    kind : str
        ``"v"``, ``"e"`` or ``"f"``.
    index : int
        Feature id.
    point : ndarray, shape (3,)
        A point of the feature, metres, model frame (the vertex, the edge midpoint, the face's
        first vertex).
    face_ids : ndarray of int, shape (K,)
        Incident faces; for a vertex in counter-clockwise order seen from outside, each face
        once.
    normals : ndarray, shape (K, 3)
        Their outward unit normals.
    edge_ids : ndarray of int, shape (L,)
        Incident edges (a vertex: all its edges; an edge: itself; a face: none).
    directions : ndarray, shape (L, 3)
        Unit directions of those edges, pointing away from the vertex (for an edge, from
        ``edges[e, 0]`` to ``edges[e, 1]``).
    pieces : tuple of ndarray of int
        Each piece is an array of face ids whose inward half-spaces intersect to one convex
        cone; their union is the local solid. A convex feature has one piece. Pieces may
        overlap.
    """

    kind: str
    index: int
    point: FloatArray
    face_ids: IntArray
    normals: FloatArray
    edge_ids: IntArray
    directions: FloatArray
    pieces: tuple[IntArray, ...]

    @property
    def convex(self) -> bool:
        """True if the local solid is one convex cone."""
        return len(self.pieces) == 1

    def piece_normals(self, k: int) -> FloatArray:
        """Outward unit normals of the faces of piece ``k``, shape (K_k, 3)."""
        pos = {int(f): i for i, f in enumerate(self.face_ids)}
        return self.normals[[pos[int(f)] for f in self.pieces[k]]]


def local_solid(poly: Polyhedron, kind: str, index: int) -> LocalSolid:
    """Local solid of ``poly`` at a vertex, edge or face, split into convex pieces.

    Parameters
    ----------
    poly : Polyhedron
        The model.
    kind : {"v", "e", "f"}
        Feature kind (as in ``apo.contact.Feature``).
    index : int
        Feature id.

    Returns
    -------
    LocalSolid
        Incident faces and normals, emanating edge directions and the convex pieces.

    Raises
    ------
    ValueError
        Unknown ``kind`` or ``index`` out of range.

    Notes
    -----
    - Face: one piece, the face's half-space.
    - Edge: convex: one piece, the intersection of its two faces' half-spaces; concave: two
      pieces, one half-space each (their union).
    - Vertex: walk the face corners counter-clockwise around the vertex. Consecutive faces
      joined by a convex edge belong to the same piece; a concave edge starts a new piece. A
      face whose corner at the vertex is reflex (interior angle > 180 deg, e.g. the top of an
      L-shaped prism at its inner corner) also ends a piece and starts the next one, and
      belongs to both. Each piece is the intersection of its faces' half-spaces. This is
      exact for the corners of prisms, pockets and slots (every case in the tests); for
      vertices with more complex cones it is a decomposition by the face planes that may
      over-approximate the solid, which the caller can detect with ``convex``.

    Examples
    --------
    >>> from apo.shapes import box
    >>> b = box([1.0, 1.0, 1.0])
    >>> ls = local_solid(b, "v", 0)
    >>> len(ls.face_ids), len(ls.pieces), ls.convex
    (3, 1, True)
    """
    if kind == "f":
        _check_index(index, len(poly.faces), "face")
        fid = np.array([index], dtype=np.int64)
        return LocalSolid(
            "f",
            index,
            poly.vertices[poly.faces[index][0]].copy(),
            fid,
            poly.face_normals[fid],
            np.zeros(0, dtype=np.int64),
            np.zeros((0, 3)),
            (fid,),
        )
    if kind == "e":
        _check_index(index, len(poly.edges), "edge")
        fids = poly.edge_faces[index].astype(np.int64)
        pieces = (fids,) if poly.edge_convex[index] else (fids[:1], fids[1:])
        a, b = poly.vertices[poly.edges[index]]
        return LocalSolid(
            "e",
            index,
            0.5 * (a + b),
            fids,
            poly.face_normals[fids],
            np.array([index], dtype=np.int64),
            poly.edge_directions[[index]],
            pieces,
        )
    if kind != "v":
        raise ValueError(f"unknown feature kind {kind!r}; expected 'v', 'e' or 'f'")
    _check_index(index, len(poly.vertices), "vertex")
    return _local_solid_vertex(poly, index)


def _check_index(index: int, n: int, what: str) -> None:
    if not 0 <= index < n:
        raise ValueError(f"{what} id {index} out of range [0, {n})")


def _local_solid_vertex(poly: Polyhedron, v: int) -> LocalSolid:
    corners = poly.vertex_corners[v]
    p = poly.vertices[v]
    eids = poly.vertex_edges[v]
    e = poly.edges[eids]
    other = np.where(e[:, 0] == v, e[:, 1], e[:, 0])
    dirs = poly.vertices[other] - p
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    edge_of = {int(o): int(k) for o, k in zip(other, eids, strict=True)}

    k_n = len(corners)
    # Reflex corners: interior angle from the outgoing edge counter-clockwise (about the face
    # normal) to the incoming edge exceeds pi.
    reflex = np.zeros(k_n, dtype=bool)
    for k, (f, u, w) in enumerate(corners):
        n = poly.face_normals[f]
        d_out = poly.vertices[w] - p
        d_back = poly.vertices[u] - p
        ang = math.atan2(float(n @ np.cross(d_out, d_back)), float(d_out @ d_back)) % (2 * math.pi)
        reflex[k] = ang > math.pi + tol.coplanar_angle
    # Edge between corner k and k+1 is the edge {v, u_k}.
    concave_after = np.array(
        [not poly.edge_convex[edge_of[int(corners[k, 1])]] for k in range(k_n)], dtype=bool
    )
    face_ids = corners[np.sort(np.unique(corners[:, 0], return_index=True)[1]), 0]

    if not concave_after.any() and not reflex.any():
        pieces: list[IntArray] = [face_ids.astype(np.int64)]
    else:
        # Start right after a break (a concave edge, or at a reflex corner).
        breaks = [k for k in range(k_n) if concave_after[k - 1] or reflex[k]]
        start = breaks[0]
        pieces = []
        current: list[int] = []
        # Walk once around (start is a break, so the walk ends by closing the last piece).
        for step in range(k_n + 1):
            k = (start + step) % k_n
            if step > 0 and (concave_after[k - 1] or reflex[k]):
                if reflex[k] and not concave_after[k - 1]:
                    current.append(int(corners[k, 0]))  # a reflex face closes this piece too
                pieces.append(unique(np.asarray(current, dtype=np.int64)))
                current = []
            if step < k_n:
                current.append(int(corners[k, 0]))
        pieces = _drop_subsumed([pc for pc in pieces if len(pc)])
    return LocalSolid(
        "v",
        v,
        p.copy(),
        face_ids.astype(np.int64),
        poly.face_normals[face_ids],
        eids.astype(np.int64),
        dirs,
        tuple(pieces),
    )


def _drop_subsumed(pieces: list[IntArray]) -> list[IntArray]:
    """Drop pieces whose face set contains another piece's (a smaller cone) and duplicates."""
    sets = [frozenset(int(x) for x in pc) for pc in pieces]
    keep = []
    for i, s in enumerate(sets):
        if any((t < s) or (t == s and j < i) for j, t in enumerate(sets) if j != i):
            continue
        keep.append(pieces[i])
    return keep
