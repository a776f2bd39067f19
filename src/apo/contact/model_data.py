"""Per-model data: local solids split into convex pieces, tangent cones, k-d trees.

Computed once per :class:`~apo.geometry.Polyhedron` (cached weakly) and reused for every
pose: each feature's local solid (``apo.geometry.local_solid``) is split into convex pieces,
each with its tangent cone (lineality basis and extreme rays) and outward face normals; the
vertices and sample points covering edges and triangles go into k-d trees for large models.
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from apo.arrays import unique
from apo.constants import tol
from apo.contact._arrays import _EMPTY_3, _EMPTY_I, _csr, _dedupe, _plane_basis
from apo.contact.elements import _CODE, Feature
from apo.geometry import Polyhedron, local_solid
from apo.typing import FloatArray, IntArray

if TYPE_CHECKING:
    from scipy.spatial import cKDTree


class _Cone(NamedTuple):  # not a dataclass: no methods made at import
    """A convex piece of the local solid at a feature: its refined feature and tangent cone.

    The cone is ``span(lin) + cone(rays)`` in the model frame (unit vectors).
    """

    feature: Feature
    lin: FloatArray
    rays: FloatArray
    normals: FloatArray  # outward unit normals of the piece's faces


class _Pieces(NamedTuple):
    """Convex pieces of a model's local solids as flat arrays, for tests vectorised over pieces.

    Piece ``p`` has refined feature ``(kind[p], number[p])`` (kind codes v 0, e 1, f 2), and its
    lineality rows, rays and face normals (model frame) are the rows ``ptr[p] : ptr[p] + n[p]``
    of ``lin``, ``rays`` and ``normals``.
    """

    kind: IntArray
    number: IntArray  # the feature's index (not ``index``: a tuple method)
    nlin: IntArray
    lin_ptr: IntArray
    lin: FloatArray
    nrays: IntArray
    ray_ptr: IntArray
    rays: FloatArray
    nnorm: IntArray
    norm_ptr: IntArray
    normals: FloatArray

    @staticmethod
    def empty() -> _Pieces:
        """No pieces."""
        i, x = _EMPTY_I, _EMPTY_3
        return _Pieces(i, i, i, i, x, i, i, x, i, i, x)

    def extended(self, cones: Sequence[_Cone]) -> _Pieces:
        """Return these pieces followed by ``cones``."""
        if not cones:
            return self
        kind = np.array([_CODE[c.feature[0]] for c in cones], dtype=np.int64)
        index = np.array([c.feature[1] for c in cones], dtype=np.int64)
        parts = []
        for name, new in (
            ("lin", [c.lin for c in cones]),
            ("rays", [c.rays for c in cones]),
            ("normals", [c.normals for c in cones]),
        ):
            n, ptr, flat = _csr(new)
            old_flat: FloatArray = getattr(self, name)
            parts += [n, ptr + len(old_flat), flat]
        cat = np.concatenate
        return _Pieces(
            cat([self.kind, kind]),
            cat([self.number, index]),
            cat([self.nlin, parts[0]]),
            cat([self.lin_ptr, parts[1]]),
            cat([self.lin, parts[2]]),
            cat([self.nrays, parts[3]]),
            cat([self.ray_ptr, parts[4]]),
            cat([self.rays, parts[5]]),
            cat([self.nnorm, parts[6]]),
            cat([self.norm_ptr, parts[7]]),
            cat([self.normals, parts[8]]),
        )


def _tangent_cone(normals: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Lineality basis and extreme rays of ``{x : normals @ x <= 0}`` (exact model data)."""
    eps = tol.model_cone
    _, sv, vt = np.linalg.svd(normals)
    rank = int(np.count_nonzero(sv > eps * sv[0]))
    if rank == 1:
        n = normals[0] / np.linalg.norm(normals[0])
        return _plane_basis(n), -n[None, :]
    lin = vt[rank:].copy()
    cand = []
    if rank == 2:
        line = lin[0]
        for n in normals:
            c = np.cross(line, n)
            if np.linalg.norm(c) > eps:
                c /= np.linalg.norm(c)
                cand += [c, -c]
    else:
        for i in range(len(normals)):
            for j in range(i + 1, len(normals)):
                c = np.cross(normals[i], normals[j])
                if np.linalg.norm(c) > eps:
                    c /= np.linalg.norm(c)
                    cand += [c, -c]
    cand_arr = np.asarray(cand)
    ok = np.all(cand_arr @ normals.T <= eps, axis=1)
    return lin, _dedupe(cand_arr[ok], tol.model_cone_merge)


class _ModelData:
    """Per-model arrays, k-d trees and local cones, computed once per Polyhedron."""

    def __init__(self, poly: Polyhedron) -> None:
        # A weak reference: the cache maps the Polyhedron (weakly) to this object, which must
        # not keep it alive.
        self._poly = weakref.ref(poly)
        # (G feature, E feature) pairs met with each other model, one tuple per pair code
        # (:func:`apo.contact.distance_tests._touching`): the observed states share them.
        self.pairs: weakref.WeakKeyDictionary[_ModelData, dict[int, tuple[Feature, Feature]]] = (
            weakref.WeakKeyDictionary()
        )
        V = np.ascontiguousarray(poly.vertices, dtype=np.float64)
        self.V = V
        self.nv, self.ne, self.nf = len(V), len(poly.edges), len(poly.faces)
        self.edges = poly.edges.astype(np.int64)
        self.E0 = V[self.edges[:, 0]]
        self.E1 = V[self.edges[:, 1]]
        self.edge_dir = np.asarray(poly.edge_directions, dtype=np.float64)
        self.E_mid = 0.5 * (self.E0 + self.E1)
        self.E_half = 0.5 * np.linalg.norm(self.E1 - self.E0, axis=1)
        self.E_lo = np.minimum(self.E0, self.E1)  # the edges' bounding boxes
        self.E_hi = np.maximum(self.E0, self.E1)
        tri = np.concatenate(poly.face_triangles).astype(np.int64)
        self.tri_face = np.repeat(
            np.arange(self.nf, dtype=np.int64), [len(t) for t in poly.face_triangles]
        )
        self.TA, self.TB, self.TC = V[tri[:, 0]], V[tri[:, 1]], V[tri[:, 2]]
        self.tri_n = poly.face_normals[self.tri_face]
        self.tri_off = poly.face_offsets[self.tri_face]
        # bounding spheres of the triangles
        self.tri_c = (self.TA + self.TB + self.TC) / 3.0
        self.tri_r = np.max(
            [np.linalg.norm(T - self.tri_c, axis=1) for T in (self.TA, self.TB, self.TC)], axis=0
        )
        self.lo = V.min(axis=0)
        self.hi = V.max(axis=0)
        self.scale = float(poly.scale)
        # Star of each primitive (features whose closure contains it), as encoded features
        # code * n_all + index, in CSR form over primitives v (0..nv), e (nv..), f (nv+ne..).
        stars: list[list[int]] = []
        for v in range(self.nv):
            s = [v]
            s += [self.nv + int(e) for e in poly.vertex_edges[v]]
            s += [self.nv + self.ne + int(f) for f in poly.vertex_faces[v]]
            stars.append(s)
        for e in range(self.ne):
            stars.append([self.nv + e] + [self.nv + self.ne + int(f) for f in poly.edge_faces[e]])
        for f in range(self.nf):
            stars.append([self.nv + self.ne + f])
        self.star_len = np.array([len(s) for s in stars], dtype=np.int64)
        self.star_ptr = np.concatenate([[0], np.cumsum(self.star_len)]).astype(np.int64)
        self.star_data = np.concatenate([np.asarray(s, dtype=np.int64) for s in stars])
        self._trees: tuple[cKDTree, cKDTree, IntArray, float, cKDTree, IntArray, float] | None
        self._trees = None
        self._cones: dict[Feature, list[_Cone]] = {}
        self.edge_samples: tuple[FloatArray, IntArray, float] | None = None
        # Primitive codes (v: i, e: nv + i, f: nv + ne + i) -> Feature, and the convex pieces
        # of each primitive's local solid as flat arrays (filled on demand).
        self.n_all = self.nv + self.ne + self.nf
        self.offset = np.array([0, self.nv, self.nv + self.ne], dtype=np.int64)
        self.features: list[Feature] = [
            *(("v", i) for i in range(self.nv)),
            *(("e", i) for i in range(self.ne)),
            *(("f", i) for i in range(self.nf)),
        ]
        self._piece_start = np.full(self.n_all, -1, dtype=np.int64)
        self._piece_count = np.zeros(self.n_all, dtype=np.int64)
        self.piece_list: list[_Cone] = []
        self.pieces = _Pieces.empty()

    @property
    def poly(self) -> Polyhedron:
        poly = self._poly()
        if poly is None:  # pragma: no cover - the callers hold the model
            raise RuntimeError("the Polyhedron of this model data was garbage-collected")
        return poly

    # -- k-d trees over vertices and sample points covering triangles and edges -------------
    @property
    def spacing(self) -> float:
        return self.scale / 64.0

    def trees(self) -> tuple[cKDTree, cKDTree, IntArray, float, cKDTree, IntArray, float]:
        if self._trees is None:
            from scipy.spatial import cKDTree  # imported on use: large models only

            h = self.spacing
            tri_pts, tri_own, tri_r = _sample_triangles(self.TA, self.TB, self.TC, h)
            e_pts, e_own, e_r = _sample_segments(self.E0, self.E1, h)
            self.edge_samples = (e_pts, e_own, e_r)
            self._trees = (
                cKDTree(self.V),
                cKDTree(tri_pts),
                tri_own,
                tri_r,
                cKDTree(e_pts),
                e_own,
                e_r,
            )
        return self._trees

    # -- convex pieces of the local solid ----------------------------------------------------
    def piece_ranges(self, codes: IntArray) -> tuple[IntArray, IntArray]:
        """First piece id and number of pieces of each primitive code (computed on demand)."""
        start = self._piece_start[codes]
        if np.any(start < 0):
            new: list[_Cone] = []
            for c in unique(codes[start < 0]).tolist():
                cones = self.cones(self.features[c])
                self._piece_start[c] = len(self.piece_list) + len(new)
                self._piece_count[c] = len(cones)
                new.extend(cones)
            self.piece_list.extend(new)
            self.pieces = self.pieces.extended(new)
            start = self._piece_start[codes]
        return start, self._piece_count[codes]

    def cones(self, feat: Feature) -> list[_Cone]:
        got = self._cones.get(feat)
        if got is not None:
            return got
        kind, idx = feat
        poly = self.poly
        ls = local_solid(poly, kind, idx)
        out = []
        for k, piece in enumerate(ls.pieces):
            normals = ls.piece_normals(k)
            lin, rays = _tangent_cone(normals)
            if ls.convex:
                refined: Feature = feat
            elif len(piece) == 1:
                refined = ("f", int(piece[0]))
            elif kind == "v" and len(piece) == 2:
                refined = ("v", idx)
                pset = {int(piece[0]), int(piece[1])}
                for e in poly.vertex_edges[idx]:
                    if {int(x) for x in poly.edge_faces[e]} == pset:
                        refined = ("e", int(e))
                        break
            else:
                refined = (kind, idx)
            out.append(_Cone(refined, lin, rays, normals))
        self._cones[feat] = out
        return out


def _sample_segments(a: FloatArray, b: FloatArray, h: float) -> tuple[FloatArray, IntArray, float]:
    """Points along segments every <= h; any segment point is within h/2 of a sample."""
    length = np.linalg.norm(b - a, axis=1)
    n = np.maximum(1, np.ceil(length / h).astype(np.int64))
    own = np.repeat(np.arange(len(a), dtype=np.int64), n + 1)
    start = np.repeat(np.concatenate([[0], np.cumsum(n + 1)[:-1]]), n + 1)
    k = np.arange(len(own)) - start
    t = k / n[own]
    pts = a[own] + t[:, None] * (b - a)[own]
    return pts, own, 0.5 * h


def _sample_triangles(
    A: FloatArray, B: FloatArray, C: FloatArray, h: float
) -> tuple[FloatArray, IntArray, float]:
    """Grid points on triangles; any triangle point is within ``2 h`` of a sample.

    A point lies in a grid cell (sides <= h along the two edges from the first corner) whose
    first corner is a sample inside the triangle, at most a cell diagonal (<= 2 h) away.
    """
    n1 = np.maximum(1, np.ceil(np.linalg.norm(B - A, axis=1) / h)).astype(np.int64)
    n2 = np.maximum(1, np.ceil(np.linalg.norm(C - A, axis=1) / h)).astype(np.int64)
    pts: list[FloatArray] = []
    own: list[IntArray] = []
    # Group triangles by (n1, n2) so each group is one vectorised grid.
    keys = n1 * 100_003 + n2
    for key in np.unique(keys):
        sel = np.flatnonzero(keys == key)
        a1, a2 = int(n1[sel[0]]), int(n2[sel[0]])
        i, j = np.meshgrid(np.arange(a1 + 1), np.arange(a2 + 1), indexing="ij")
        u, w = (i / a1).ravel(), (j / a2).ravel()
        keep = u + w <= 1.0 + tol.zero_norm
        u, w = u[keep], w[keep]
        p = (
            A[sel, None, :]
            + u[None, :, None] * (B - A)[sel, None, :]
            + w[None, :, None] * (C - A)[sel, None, :]
        )
        pts.append(p.reshape(-1, 3))
        own.append(np.repeat(sel, len(u)))
    return np.concatenate(pts), np.concatenate(own).astype(np.int64), 2.0 * h


_MODEL_CACHE: weakref.WeakKeyDictionary[Polyhedron, _ModelData] = weakref.WeakKeyDictionary()


def _model_data(poly: Polyhedron) -> _ModelData:
    md = _MODEL_CACHE.get(poly)
    if md is None:
        md = _ModelData(poly)
        _MODEL_CACHE[poly] = md
    return md
