"""Polyhedral models: polygonal faces, edges with convexity, outward normals (no I/O).

INTERFACE FIXED BY THE LEAD; the construction functions are being written.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class Polyhedron:
    """A closed polyhedron with merged coplanar faces, in its own frame (metres).

    Feature ids are indices into these arrays; they are deterministic for a given input mesh,
    so contact states computed at different frames can be compared by feature ids.

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
