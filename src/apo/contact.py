"""Contact elements and contact states between two posed polyhedra (paper 2.1, 4.3.1).

:func:`find_contacts` finds every contact element between the grasped object G and the
environment object E at a pose ``X_EG`` (pose of G in E's frame, metres): candidate points
are vertices of either object within a distance threshold of the other's surface and
crossings of non-parallel edges; each candidate is snapped to the lowest-dimensional feature
of each object within the threshold, the local solids there are split into convex pieces,
and every pair of pieces that touch gives one element whose separating normals are the
extreme rays of ``N = T_G* ∩ (-T_E*)`` (``docs/contacts.md``). :class:`ContactFinder`
caches per-model data for use over many frames and searches a whole sequence of poses at
once (:meth:`ContactFinder.find_batch`: every stage is a numpy pass over a block of frames
and over all candidate elements); :func:`find_contacts_naive` is the plain all-pairs
reference; :func:`element_residuals` gives the residuals ``f_i(X_EG)`` of the elements and
their Jacobians for pose correction (paper 4.3.1).

Everything is in the environment frame E, in metres; twists are ``[omega; v]`` applied on
the left (``docs/conventions.md``).
"""

from __future__ import annotations

import enum
import itertools
import math
import weakref
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from apo.constants import tol
from apo.dof import ContactPoint
from apo.geometry import (
    Polyhedron,
    closest_point_on_segment,
    local_solid,
    point_face_distance,
    segment_segment_closest,
)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

__all__ = [
    "DEFAULT_THRESHOLD_FRACTION",
    "ContactElement",
    "ContactFinder",
    "ContactKind",
    "ContactState",
    "Feature",
    "contact_points",
    "default_angle_tolerance",
    "default_threshold",
    "element_residuals",
    "find_contacts",
    "find_contacts_batch",
    "find_contacts_naive",
    "residual_counts",
]


class ContactKind(enum.Enum):
    """Kind of a contact element: grasped feature first, environment feature second."""

    VF = "VF"
    FV = "FV"
    EE = "EE"
    VE = "VE"
    EV = "EV"
    VV = "VV"


# A feature id: ("v" | "e" | "f", index into the Polyhedron's arrays).
Feature = tuple[str, int]


@dataclass(frozen=True)
class ContactElement:
    """One contact element (environment frame, metres).

    Attributes
    ----------
    kind : ContactKind
    grasped : Feature
        Feature of the grasped object G, e.g. ``("v", 3)``.
    environment : Feature
        Feature of the environment object E.
    point : ndarray, shape (3,)
        Contact point in the environment frame.
    normals : ndarray, shape (M, 3)
        Extreme rays of the cone of separating normals (unit, from E towards G).
    """

    kind: ContactKind
    grasped: Feature
    environment: Feature
    point: FloatArray
    normals: FloatArray

    @property
    def singular(self) -> bool:
        """True if the element has more than one separating normal."""
        return int(self.normals.shape[0]) > 1

    @property
    def key(self) -> tuple[str, Feature, Feature]:
        """Hashable identity (kind and feature ids), stable across frames."""
        return (self.kind.value, self.grasped, self.environment)


@dataclass(frozen=True)
class ContactState:
    """The contact elements between G and E at one pose.

    Attributes
    ----------
    elements : tuple of ContactElement
        Sorted by ``key``.
    touching : frozenset of (Feature, Feature)
        Every (grasped feature, environment feature) pair within the threshold; Donald's
        inclusion test compares these sets (THEORY.md pitfalls).
    """

    elements: tuple[ContactElement, ...]
    touching: frozenset[tuple[Feature, Feature]]

    @property
    def singular(self) -> bool:
        """True if any element is singular."""
        return any(e.singular for e in self.elements)

    @property
    def key(self) -> frozenset[tuple[str, Feature, Feature]]:
        """Hashable identity of the state (the set of element keys)."""
        return frozenset(e.key for e in self.elements)


DEFAULT_THRESHOLD_FRACTION = 1e-3
"""Default threshold as a fraction of the smaller model's ``scale`` (bounding diagonal)."""

_KINDS: dict[tuple[str, str], ContactKind] = {
    ("v", "f"): ContactKind.VF,
    ("f", "v"): ContactKind.FV,
    ("e", "e"): ContactKind.EE,
    ("v", "e"): ContactKind.VE,
    ("e", "v"): ContactKind.EV,
    ("v", "v"): ContactKind.VV,
}
_CODE = {"v": 0, "e": 1, "f": 2}
_NAME = ("v", "e", "f")
# Models with more (query points x primitives) than this use the k-d trees.
_DENSE_LIMIT = 40_000
# A batch of frames may use this many times more for the dense all-pairs tests.
_BATCH_DENSE_FACTOR = 8
# Frames per batch: about this many vertices and edges of both models over the batch.
_BATCH_PRIMITIVES = 16_384
# Bounding-sphere tests use radius * this: rounding never drops a pair within the threshold.
_SPHERE_MARGIN = 1.0 + 1e-9
_EMPTY_I = np.zeros(0, dtype=np.int64)
_EMPTY_F = np.zeros(0, dtype=np.float64)
_EMPTY_3 = np.zeros((0, 3), dtype=np.float64)


# --------------------------------------------------------------------------------------------
# Validation and defaults
# --------------------------------------------------------------------------------------------


def _check_pose(X: npt.ArrayLike) -> FloatArray:
    M = np.asarray(X, dtype=np.float64)
    if M.shape != (4, 4):
        raise ValueError(f"X_EG must have shape (4, 4), got shape {M.shape}")
    if not np.all(np.isfinite(M)):
        raise ValueError("X_EG has non-finite entries")
    R = M[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
        raise ValueError("X_EG's rotation part is not a rotation matrix")
    return M


def _check_poses(X_seq: Iterable[npt.ArrayLike] | npt.ArrayLike) -> FloatArray:
    """Validate poses as :func:`_check_pose` does, vectorised; returns shape (N, 4, 4)."""
    if isinstance(X_seq, np.ndarray) and X_seq.ndim == 3:
        M = np.asarray(X_seq, dtype=np.float64)
        items: Sequence[Any] | FloatArray = M
    else:
        items = list(X_seq)  # type: ignore[arg-type]
        if not items:
            return np.zeros((0, 4, 4))
        try:
            M = np.asarray(items, dtype=np.float64)
        except ValueError:
            M = np.zeros((0,))
    ok = M.ndim == 3 and M.shape[1:] == (4, 4)
    if ok:
        R = M[:, :3, :3]
        good = np.all(np.isfinite(M), axis=(1, 2))
        RRt = np.einsum("nij,nkj->nik", R, R)
        with np.errstate(invalid="ignore"):
            good &= np.all(np.isclose(RRt, np.eye(3), atol=1e-6), axis=(1, 2))
            good &= np.linalg.det(np.where(np.isfinite(R), R, 0.0)) > 0
        ok = bool(good.all())
    if not ok:  # find the culprit and say what is wrong with it
        for k, X in enumerate(items):
            try:
                _check_pose(X)
            except ValueError as exc:
                raise ValueError(f"pose {k}: {exc}") from None
        raise ValueError(f"X_EG_seq must have shape (N, 4, 4), got shape {M.shape}")
    return M


def default_threshold(grasped: Polyhedron, environment: Polyhedron) -> float:
    """Default contact threshold: ``DEFAULT_THRESHOLD_FRACTION`` of the smaller ``scale``.

    Parameters
    ----------
    grasped, environment : Polyhedron
        The two models.

    Returns
    -------
    float
        Metres; e.g. 0.12 mm for the 118 mm T-peg.
    """
    return DEFAULT_THRESHOLD_FRACTION * min(grasped.scale, environment.scale)


def default_angle_tolerance(
    grasped: Polyhedron, environment: Polyhedron, threshold: float
) -> float:
    """Default angular tolerance (rad) of the normal-cone intersection and parallel edges.

    Parameters
    ----------
    grasped, environment : Polyhedron
        The two models.
    threshold : float
        Contact threshold, metres.

    Returns
    -------
    float
        ``clip(4 * threshold / min(scale), tol.normal_angle, 0.2)``: a flush face of length
        ``L`` whose ends are both within the threshold may be tilted by up to
        ``2 * threshold / L``; the factor 4 allows faces down to half the bounding diagonal
        with margin.
    """
    s = min(grasped.scale, environment.scale)
    return float(np.clip(4.0 * threshold / s, tol.normal_angle, 0.2))


# --------------------------------------------------------------------------------------------
# Per-model data
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Cone:
    """A convex piece of the local solid at a feature: its refined feature and tangent cone.

    The cone is ``span(lin) + cone(rays)`` in the model frame (unit vectors).
    """

    feature: Feature
    lin: FloatArray
    rays: FloatArray
    normals: FloatArray  # outward unit normals of the piece's faces


def _csr(arrays: Sequence[FloatArray]) -> tuple[IntArray, IntArray, FloatArray]:
    """Row counts, row pointers and stacked rows of a list of (k, 3) arrays."""
    n = np.fromiter((len(a) for a in arrays), dtype=np.int64, count=len(arrays))
    ptr = np.concatenate([[0], np.cumsum(n)[:-1]]).astype(np.int64) if len(n) else _EMPTY_I
    flat = np.concatenate([np.reshape(a, (-1, 3)) for a in arrays]) if len(n) else _EMPTY_3
    return n, ptr, np.asarray(flat, dtype=np.float64)


@dataclass(frozen=True)
class _Pieces:
    """Convex pieces of a model's local solids as flat arrays, for tests vectorised over pieces.

    Piece ``p`` has refined feature ``(kind[p], index[p])`` (kind codes v 0, e 1, f 2), and its
    lineality rows, rays and face normals (model frame) are the rows ``ptr[p] : ptr[p] + n[p]``
    of ``lin``, ``rays`` and ``normals``.
    """

    kind: IntArray
    index: IntArray
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
            cat([self.index, index]),
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


def _cross3(a: FloatArray, b: FloatArray) -> FloatArray:
    """Cross product of two 3-vectors (much cheaper than ``np.cross`` for one pair)."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def _plane_basis(n: FloatArray) -> FloatArray:
    """Orthonormal basis (2, 3) of the plane perpendicular to unit ``n`` (deterministic)."""
    x, y, z = float(n[0]), float(n[1]), float(n[2])
    # t1 = n x (1, 0, 0), or n x (0, 1, 0) when n is close to x
    t1 = np.array([0.0, z, -y]) if abs(x) < 0.9 else np.array([-z, 0.0, x])
    t1 /= math.sqrt(float(t1 @ t1))
    return np.stack([t1, _cross3(n, t1)])


def _tangent_cone(normals: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Lineality basis and extreme rays of ``{x : normals @ x <= 0}`` (exact model data)."""
    eps = 1e-9
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
    return lin, _dedupe(cand_arr[ok], 1e-7)


def _dedupe(
    rays: FloatArray, angle: float, priority: npt.NDArray[np.int64] | None = None
) -> FloatArray:
    """Greedy clustering of unit rays closer than ``angle``.

    Each cluster is represented by its member of highest ``priority`` (the first such), or by
    the normalised mean when no priorities are given.
    """
    if len(rays) <= 1:
        return rays.reshape(-1, 3)
    cos_a = math.cos(angle)
    out: list[FloatArray] = []
    used = np.zeros(len(rays), dtype=bool)
    G = rays @ rays.T
    for i in range(len(rays)):
        if used[i]:
            continue
        members = (~used) & (G[i] >= cos_a)
        members[i] = True
        used |= members
        if priority is None:
            m = rays[members].sum(axis=0)
            out.append(m / np.linalg.norm(m))
        else:
            idx = np.flatnonzero(members)
            out.append(rays[idx[int(np.argmax(priority[idx]))]])
    return np.asarray(out)


class _ModelData:
    """Per-model arrays, k-d trees and local cones, computed once per Polyhedron."""

    def __init__(self, poly: Polyhedron) -> None:
        # A weak reference: the cache maps the Polyhedron (weakly) to this object, which must
        # not keep it alive.
        self._poly = weakref.ref(poly)
        V = np.ascontiguousarray(poly.vertices, dtype=np.float64)
        self.V = V
        self.nv, self.ne, self.nf = len(V), len(poly.edges), len(poly.faces)
        self.edges = poly.edges.astype(np.int64)
        self.E0 = V[self.edges[:, 0]]
        self.E1 = V[self.edges[:, 1]]
        self.edge_dir = np.asarray(poly.edge_directions, dtype=np.float64)
        self.E_mid = 0.5 * (self.E0 + self.E1)
        self.E_half = 0.5 * np.linalg.norm(self.E1 - self.E0, axis=1)
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
            for c in np.unique(codes[start < 0]).tolist():
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
        keep = u + w <= 1.0 + 1e-12
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


# --------------------------------------------------------------------------------------------
# Exact distances (vectorised over pairs)
# --------------------------------------------------------------------------------------------


def _dot(x: FloatArray, y: FloatArray) -> FloatArray:
    return np.asarray(np.einsum("ij,ij->i", x, y), dtype=np.float64)


def _point_triangle_distance(
    p: FloatArray, a: FloatArray, b: FloatArray, c: FloatArray
) -> FloatArray:
    """Distance from points to triangles, row-wise (Ericson, RTCD 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    bp = p - b
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    cp = p - c
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        den = va + vb + vc
        v = np.where(den != 0, vb / den, 0.0)
        w = np.where(den != 0, vc / den, 0.0)
        q = a + v[:, None] * ab + w[:, None] * ac
        wbc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        m = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        q = np.where(m[:, None], b + wbc[:, None] * (c - b), q)
        wac = d2 / (d2 - d6)
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        q = np.where(m[:, None], a + wac[:, None] * ac, q)
        m = (d6 >= 0) & (d5 <= d6)
        q = np.where(m[:, None], c, q)
        vab = d1 / (d1 - d3)
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        q = np.where(m[:, None], a + vab[:, None] * ab, q)
        m = (d3 >= 0) & (d4 <= d3)
        q = np.where(m[:, None], b, q)
        m = (d1 <= 0) & (d2 <= 0)
        q = np.where(m[:, None], a, q)
    return _norm(p - q)


def _norm(x: FloatArray) -> FloatArray:
    """Row norms of an (n, 3) array (faster than ``np.linalg.norm(x, axis=1)``)."""
    return np.asarray(np.sqrt(x[:, 0] ** 2 + x[:, 1] ** 2 + x[:, 2] ** 2), dtype=np.float64)


def _cross_rows(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise cross products of (n, 3) arrays (cheaper than ``np.cross``)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _sq_dist(P: FloatArray, C: FloatArray) -> FloatArray:
    """Squared distances (n, m) between the rows of P (n, 3) and C (m, 3)."""
    out = np.square(P[:, None, 0] - C[None, :, 0])
    out += np.square(P[:, None, 1] - C[None, :, 1])
    out += np.square(P[:, None, 2] - C[None, :, 2])
    return out


@dataclass
class _Near:
    """Pairs (query point i, feature j, distance) within the threshold, per feature kind."""

    v: tuple[IntArray, IntArray, FloatArray]
    e: tuple[IntArray, IntArray, FloatArray]
    f: tuple[IntArray, IntArray, FloatArray]


def _pairs_from_ball(lists: Any, rows: IntArray) -> tuple[IntArray, IntArray]:
    counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
    if counts.sum() == 0:
        return _EMPTY_I, _EMPTY_I
    i = np.repeat(rows, counts)
    j = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(counts.sum()))
    return i, j


def _near_features(
    md: _ModelData,
    pts: FloatArray,
    d: float,
    *,
    naive: bool = False,
    dense_limit: int | None = None,
) -> _Near:
    """Features of ``md`` within ``d`` of each point of ``pts`` (points in md's frame).

    Pairs of each kind are sorted by (point, feature). All pairs are tested when there are
    at most ``dense_limit`` (default ``_DENSE_LIMIT``) of them, else the k-d trees prune.
    """
    if naive:
        return _near_features_naive(md, pts, d)
    inside = np.all((pts >= md.lo - d) & (pts <= md.hi + d), axis=1)
    rows = np.flatnonzero(inside).astype(np.int64)
    if len(rows) == 0:
        e3 = (_EMPTY_I, _EMPTY_I, _EMPTY_F)
        return _Near(e3, e3, e3)
    Q = pts[rows]
    limit = _DENSE_LIMIT if dense_limit is None else dense_limit
    dense = len(Q) * max(md.nv, len(md.TA)) <= limit
    # vertices
    if dense:
        ii, jj = np.nonzero(_sq_dist(Q, md.V) <= (d * _SPHERE_MARGIN) ** 2)
        dist = _norm(Q[ii] - md.V[jj])
        ok = dist <= d
        vv = (rows[ii[ok]], jj[ok].astype(np.int64), dist[ok])
    else:
        tv, tt, town, tr, te, eown, er = md.trees()
        i, j = _pairs_from_ball(tv.query_ball_point(Q, d), np.arange(len(Q)))
        dist = np.linalg.norm(Q[i] - md.V[j], axis=1)
        vv = (rows[i], j, dist)
    # edges (dense: pre-filtered by the edges' bounding spheres)
    if dense:
        ii, jj = np.nonzero(_sq_dist(Q, md.E_mid) <= ((md.E_half + d) * _SPHERE_MARGIN) ** 2)
    else:
        tv, tt, town, tr, te, eown, er = md.trees()
        i, s = _pairs_from_ball(te.query_ball_point(Q, d + er), np.arange(len(Q)))
        key = np.unique(i * md.ne + eown[s])
        ii, jj = key // md.ne, key % md.ne
    cl, _ = closest_point_on_segment(Q[ii], md.E0[jj], md.E1[jj])
    dist = _norm(Q[ii] - cl)
    ok = dist <= d
    ee = (rows[ii[ok]], jj[ok].astype(np.int64), dist[ok])
    # faces via triangles, pre-filtered by the plane distance (and bounding spheres)
    if dense:
        near = np.abs(Q @ md.tri_n.T - md.tri_off[None, :]) <= d
        near &= _sq_dist(Q, md.tri_c) <= ((md.tri_r + d) * _SPHERE_MARGIN) ** 2
        ii, tt_ = np.nonzero(near)
    else:
        tv, tt, town, tr, te, eown, er = md.trees()
        i, s = _pairs_from_ball(tt.query_ball_point(Q, d + tr), np.arange(len(Q)))
        nt = len(md.TA)
        key = np.unique(i * nt + town[s])
        ii, tt_ = key // nt, key % nt
        h = np.abs(_dot(Q[ii], md.tri_n[tt_]) - md.tri_off[tt_])
        keep = h <= d
        ii, tt_ = ii[keep], tt_[keep]
    dist = _point_triangle_distance(Q[ii], md.TA[tt_], md.TB[tt_], md.TC[tt_])
    ok = dist <= d
    ii, ff, dist = ii[ok], md.tri_face[tt_[ok]], dist[ok]
    if len(ii):
        key = ii * md.nf + ff
        order = np.lexsort((dist, key))
        key, dist = key[order], dist[order]
        first = np.concatenate([[True], key[1:] != key[:-1]])
        key, dist = key[first], dist[first]
        fff = (rows[key // md.nf], key % md.nf, dist)
    else:
        fff = (_EMPTY_I, _EMPTY_I, _EMPTY_F)
    return _Near(vv, ee, fff)


def _near_features_naive(md: _ModelData, pts: FloatArray, d: float) -> _Near:
    """All-pairs reference: every point against every vertex, edge and face polygon."""
    n = len(pts)
    dv = np.linalg.norm(pts[:, None, :] - md.V[None, :, :], axis=2)
    ii, jj = np.nonzero(dv <= d)
    vv = (ii.astype(np.int64), jj.astype(np.int64), dv[ii, jj])
    cl, _ = closest_point_on_segment(pts[:, None, :], md.E0[None], md.E1[None])
    de = np.linalg.norm(cl - pts[:, None, :], axis=2)
    ii, jj = np.nonzero(de <= d)
    ee = (ii.astype(np.int64), jj.astype(np.int64), de[ii, jj])
    df = np.empty((n, md.nf))
    for f in range(md.nf):
        df[:, f] = point_face_distance(md.poly, f, pts)[0]
    ii, jj = np.nonzero(df <= d)
    ff = (ii.astype(np.int64), jj.astype(np.int64), df[ii, jj])
    return _Near(vv, ee, ff)


# --------------------------------------------------------------------------------------------
# Cones of separating normals
# --------------------------------------------------------------------------------------------


def _separating_rays(
    lin: FloatArray, ineq: FloatArray, n_g: int, sin_tol: float, merge_angle: float
) -> FloatArray:
    """Extreme rays of ``{n : lin @ n == 0, ineq @ n >= 0}`` with an angular tolerance.

    Equalities (lineality of the tangent cones) are kept exact; each inequality may be
    violated by ``sin_tol`` (unit vectors). Rays closer than ``merge_angle`` are merged into
    one, preferring a ray bounded by the environment's rows only (``ineq[n_g:]``, exact in
    E's frame: E's face normals) over mixed ones, so noisy poses give exact normals.
    """
    if len(lin) == 0:
        vt = np.eye(3)
        rank = 0
    elif len(lin) == 1:
        vt = np.concatenate([lin, _plane_basis(lin[0])])
        rank = 1
    elif len(lin) == 2 and abs(float(lin[0] @ lin[1])) < 0.999:
        u = _cross3(lin[0], lin[1])
        nu = math.sqrt(float(u @ u))
        vt = np.stack([lin[0], _cross3(u, lin[0]) / nu, u / nu])
        rank = 2 if nu > sin_tol else 1  # (near) parallel lines: one direction
        if rank == 1:
            vt = np.concatenate([lin[:1], _plane_basis(lin[0])])
    else:
        _, sv, vt = np.linalg.svd(lin)
        rank = int(np.count_nonzero(sv > sin_tol))
    if rank >= 3:
        return np.zeros((0, 3))
    Q = vt[rank:]  # basis of the complement of the lineality
    if rank == 2:
        u = Q[0]
        best = None
        for c in (u, -u):
            m = float(np.min(ineq @ c)) if len(ineq) else 0.0
            if m >= -sin_tol and (best is None or m > best[0]):
                best = (m, c)
        return np.zeros((0, 3)) if best is None else best[1][None, :].copy()
    if rank == 1:
        # 2D problem in the plane Q (few rows: plain floats are faster than numpy here).
        rows = (ineq @ Q.T).tolist()
        cand: list[tuple[float, float, int]] = []
        for k, (x, y) in enumerate(rows):
            nr = math.hypot(x, y)
            if nr <= sin_tol:
                continue
            px, py = -y / nr, x / nr
            for sx, sy in ((px, py), (-px, -py)):
                if all(sx * a + sy * b >= -sin_tol for a, b in rows):
                    cand.append((sx, sy, int(k >= n_g)))
        if not cand:
            return np.zeros((0, 3))
        mx = sum(c[0] for c in cand)
        my = sum(c[1] for c in cand)
        nm = math.hypot(mx, my)
        if nm < 1e-9:
            return np.zeros((0, 3))
        mx, my = mx / nm, my / nm
        ang = [math.atan2(-sx * my + sy * mx, sx * mx + sy * my) for sx, sy, _ in cand]
        ilo = min(range(len(ang)), key=ang.__getitem__)
        ihi = max(range(len(ang)), key=ang.__getitem__)
        lo, hi = cand[ilo], cand[ihi]
        if ang[ihi] - ang[ilo] < merge_angle:
            if any(c[2] for c in cand):
                mid = 0.5 * (ang[ihi] + ang[ilo])
                score = [c[2] - 1e-3 * abs(a - mid) for c, a in zip(cand, ang, strict=True)]
                pick = cand[max(range(len(score)), key=score.__getitem__)]
                r2 = np.array([pick[0], pick[1]])
            else:
                r2 = np.array([lo[0] + hi[0], lo[1] + hi[1]])
                r2 /= np.linalg.norm(r2)
            return np.asarray((r2 @ Q)[None, :], dtype=np.float64)
        return np.array([[lo[0], lo[1]], [hi[0], hi[1]]]) @ Q
    # rank 0: general 3D, vertices of a spherical polygon.
    m = len(ineq)
    iu, ju = np.triu_indices(m, 1)
    cr = np.cross(ineq[iu], ineq[ju])
    nc = np.linalg.norm(cr, axis=1)
    keep = nc > sin_tol
    cr = cr[keep] / nc[keep, None]
    prio = ((iu >= n_g).astype(np.int64) + (ju >= n_g))[keep]
    cr = np.concatenate([cr, -cr])
    prio = np.concatenate([prio, prio])
    ok = np.all(cr @ ineq.T >= -sin_tol, axis=1)
    return _dedupe(cr[ok], merge_angle, prio[ok])


def _snap_rays(
    rays: FloatArray, cg: _Cone, ce: _Cone, R: FloatArray, merge_angle: float
) -> FloatArray:
    """Snap rays to an exact face normal of the pieces within the merge angle.

    E's normals (exact in E) first, then minus G's, so that a noisy pose still gives the
    model's normals.
    """
    exact = np.concatenate([ce.normals, -(cg.normals @ R.T)])
    n_e = len(ce.normals)
    cos_m = math.cos(merge_angle)
    out = rays.copy()
    snapped = False
    for i, row in enumerate((rays @ exact.T).tolist()):
        e_best = max(range(n_e), key=row.__getitem__)
        if row[e_best] >= cos_m:
            out[i] = exact[e_best]
            snapped = True
            continue
        g_best = max(range(n_e, len(row)), key=row.__getitem__)
        if row[g_best] >= cos_m:
            out[i] = exact[g_best]
            snapped = True
    if snapped and len(out) > 1:
        out = _dedupe(out, 1e-9)
    return out


def _expand(ptr: IntArray, cnt: IntArray) -> tuple[IntArray, IntArray, IntArray]:
    """Entries of CSR rows ``ptr[k] : ptr[k] + cnt[k]``: (row k, flat index, slot in row)."""
    total = int(cnt.sum())
    rep = np.repeat(np.arange(len(cnt), dtype=np.int64), cnt)
    slot = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    return rep, ptr[rep] + slot, slot


def _padded(flat: FloatArray, ptr: IntArray, cnt: IntArray) -> FloatArray:
    """CSR rows as a zero-padded array (n, max(cnt), 3)."""
    out = np.zeros((len(cnt), max(int(cnt.max(initial=0)), 1), 3))
    rep, idx, slot = _expand(ptr, cnt)
    out[rep, slot] = flat[idx]
    return out


def _rotate(R: FloatArray, v: FloatArray) -> FloatArray:
    """``R[k] @ v[k]`` for each k."""
    return np.asarray(np.einsum("kij,kj->ki", R, v), dtype=np.float64)


def _ineq_rows(
    PG: _Pieces, PE: _Pieces, pg: IntArray, pe: IntArray, R: FloatArray
) -> tuple[FloatArray, BoolArray]:
    """Rows ``[R[k] @ G's rays; -E's rays]`` of each pair of pieces, zero-padded, in E.

    Returns the rows (n, mg + me, 3), G's in slots ``0 : mg`` and E's from slot ``mg`` (mg,
    me the largest counts), and which slots are E's, shape (mg + me,). Rows keep the order
    of the scalar code, G's then E's.
    """
    kg, ke = PG.nrays[pg], PE.nrays[pe]
    mg = int(kg.max(initial=0))
    m = max(mg + int(ke.max(initial=0)), 1)
    rows = np.zeros((len(pg), m, 3))
    rep, idx, slot = _expand(PG.ray_ptr[pg], kg)
    rows[rep, slot] = _rotate(R[rep], PG.rays[idx])
    rep, idx, slot = _expand(PE.ray_ptr[pe], ke)
    rows[rep, mg + slot] = -PE.rays[idx]
    return rows, np.arange(m) >= mg


def _arc_rays_batch(
    PG: _Pieces,
    PE: _Pieces,
    pg: IntArray,
    pe: IntArray,
    R: FloatArray,
    sin_tol: float,
    merge_angle: float,
) -> tuple[IntArray, FloatArray]:
    """Vectorised rank-1 case of :func:`_separating_rays` and :func:`_snap_rays`.

    Each pair (G piece ``pg[k]`` at rotation ``R[k]``, E piece ``pe[k]``) has exactly one
    lineality direction (an edge on one side, a pointed cone on the other). Same result as
    the scalar code up to rounding. Returns the number of rays (0, 1 or 2) of each pair and
    the rays, shape (n, 2, 3), in E.
    """
    n = len(pg)
    rows, from_e = _ineq_rows(PG, PE, pg, pe, R)
    m_max = rows.shape[1]
    axis = np.zeros((n, 3))
    has_e = PE.nlin[pe] == 1
    axis[has_e] = PE.lin[PE.lin_ptr[pe[has_e]]]
    axis[~has_e] = _rotate(R[~has_e], PG.lin[PG.lin_ptr[pg[~has_e]]])
    # Plane bases, as _plane_basis.
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    near_x = np.abs(x) >= 0.9
    t1 = np.where(
        near_x[:, None],
        np.stack([-z, np.zeros(n), x], axis=1),
        np.stack([np.zeros(n), z, -y], axis=1),
    )
    t1 /= _norm(t1)[:, None]
    Q = np.stack([t1, _cross_rows(axis, t1)], axis=1)  # (n, 2, 3)
    A2 = rows @ Q.transpose(0, 2, 1)  # (n, m, 2)
    nr = np.hypot(A2[:, :, 0], A2[:, :, 1])
    valid = nr > sin_tol
    with np.errstate(divide="ignore", invalid="ignore"):
        perp = np.stack([-A2[:, :, 1], A2[:, :, 0]], axis=2) / np.where(valid, nr, 1.0)[:, :, None]
    cand = np.stack([perp, -perp], axis=2).reshape(n, 2 * m_max, 2)  # row0+, row0-, ...
    c_valid = np.repeat(valid, 2, axis=1)
    c_prio = np.repeat(np.broadcast_to(from_e, valid.shape), 2, axis=1)
    ok: BoolArray = c_valid.copy()  # on the right side of every row (few rows: a loop)
    for j in range(m_max):
        ok &= cand[:, :, 0] * A2[:, None, j, 0] + cand[:, :, 1] * A2[:, None, j, 1] >= -sin_tol
    mean = (ok[:, None, :].astype(np.float64) @ cand)[:, 0]
    nm = np.hypot(mean[:, 0], mean[:, 1])
    good = ok.any(axis=1) & (nm >= 1e-9)
    mean /= np.where(good, nm, 1.0)[:, None]
    ang = np.arctan2(
        cand[:, :, 1] * mean[:, None, 0] - cand[:, :, 0] * mean[:, None, 1],
        cand[:, :, 0] * mean[:, None, 0] + cand[:, :, 1] * mean[:, None, 1],
    )
    ilo = np.argmin(np.where(ok, ang, np.inf), axis=1)
    ihi = np.argmax(np.where(ok, ang, -np.inf), axis=1)
    ar = np.arange(n)
    a_lo, a_hi = ang[ar, ilo], ang[ar, ihi]
    lo, hi = cand[ar, ilo], cand[ar, ihi]
    collapsed = (a_hi - a_lo) < merge_angle
    okp = np.asarray(ok & c_prio, dtype=bool)
    score = np.where(okp, 1.0 - 1e-3 * np.abs(ang - 0.5 * (a_hi + a_lo)[:, None]), -np.inf)
    pick = cand[ar, np.argmax(score, axis=1)]
    both = lo + hi
    both /= np.maximum(np.hypot(both[:, 0], both[:, 1]), 1e-300)[:, None]
    any_e: BoolArray = np.asarray(okp.any(axis=1), dtype=bool)
    one = np.where(any_e[:, None], pick, both)
    r2 = np.where(collapsed[:, None, None], one[:, None, :], np.stack([lo, hi], axis=1))
    rays = r2 @ Q  # (n, 2, 3)
    count = np.where(good, np.where(collapsed, 1, 2), 0).astype(np.int64)
    return _snap_batch(PG, PE, pg, pe, R, rays, count, merge_angle)


def _snap_batch(
    PG: _Pieces,
    PE: _Pieces,
    pg: IntArray,
    pe: IntArray,
    R: FloatArray,
    rays: FloatArray,
    count: IntArray,
    merge_angle: float,
) -> tuple[IntArray, FloatArray]:
    """Vectorised :func:`_snap_rays` of up to two rays (n, 2, 3) per pair of pieces.

    Each ray within ``merge_angle`` of an exact face normal of the pieces becomes that normal:
    E's normals first, then minus G's (rotated by ``R[k]``). Two rays of which one snapped
    are then merged if equal and normalised, as :func:`_dedupe` with a zero angle does.
    """
    n = len(pg)
    cos_m = math.cos(merge_angle)
    in_ray = np.arange(2)[None, :] < count[:, None]  # (n, 2)
    NE = _padded(PE.normals, PE.norm_ptr[pe], PE.nnorm[pe])
    NG = -_padded(PG.normals, PG.norm_ptr[pg], PG.nnorm[pg])
    NG = NG @ R.transpose(0, 2, 1)
    out = rays.copy()
    snapped = np.zeros((n, 2), dtype=bool)
    ar = np.arange(n)[:, None]
    for N, cnt in ((NG, PG.nnorm[pg]), (NE, PE.nnorm[pe])):  # E last: it wins
        dots = rays @ N.transpose(0, 2, 1)
        dots = np.where(np.arange(N.shape[1])[None, None, :] < cnt[:, None, None], dots, -np.inf)
        best = np.argmax(dots, axis=2)  # (n, 2)
        hit = in_ray & (np.take_along_axis(dots, best[:, :, None], axis=2)[:, :, 0] >= cos_m)
        out = np.where(hit[:, :, None], N[ar, best], out)
        snapped |= hit
    count = count.copy()
    two = np.flatnonzero((count == 2) & snapped.any(axis=1))
    if len(two):
        # _dedupe(rays, 1e-9): the second ray joins the first iff r0 . r1 >= cos(1e-9)
        r0, r1 = out[two, 0], out[two, 1]
        same = _dot(r0, r1) >= math.cos(1e-9)
        m = r0 + r1
        out[two, 0] = np.where(
            same[:, None],
            m / _norm(m)[:, None],
            r0 / _norm(r0)[:, None],
        )
        out[two, 1] = r1 / _norm(r1)[:, None]
        count[two[same]] = 1
    return count, out


def _edge_edge_rays_batch(
    PG: _Pieces,
    PE: _Pieces,
    pg: IntArray,
    pe: IntArray,
    R: FloatArray,
    sin_tol: float,
    merge_angle: float,
) -> tuple[IntArray, FloatArray, BoolArray]:
    """Vectorised rank-2 case of :func:`_separating_rays` for pairs of edge pieces.

    Each pair has one lineality direction on each side (non-parallel edges): the only
    candidate normals are ``+-u``, ``u`` the unit common normal. Pairs whose lines are within
    ``acos(0.999)`` of parallel, or nearly parallel within ``sin_tol``, are not solved here
    (third result False): the scalar code handles them.
    """
    n = len(pg)
    l0 = _rotate(R, PG.lin[PG.lin_ptr[pg]])
    l1 = PE.lin[PE.lin_ptr[pe]]
    u = _cross_rows(l0, l1)
    nu = np.sqrt(_dot(u, u))
    solved = (np.abs(_dot(l0, l1)) < 0.999) & (nu > sin_tol)
    u = u / np.where(solved, nu, 1.0)[:, None]
    # min and max of ineq . u over G's rays (rotated) and minus E's rays
    lo = np.full(n, np.inf)
    hi = np.full(n, -np.inf)
    for P, pk, sign, rot in ((PG, pg, 1.0, True), (PE, pe, -1.0, False)):
        j, idx, _ = _expand(P.ray_ptr[pk], P.nrays[pk])
        v = _rotate(R[j], P.rays[idx]) if rot else P.rays[idx]
        dots = sign * _dot(v, u[j])
        np.minimum.at(lo, j, dots)
        np.maximum.at(hi, j, dots)
    m_plus = np.where(np.isfinite(lo), lo, 0.0)  # no rows: min over nothing is 0
    m_minus = np.where(np.isfinite(hi), -hi, 0.0)
    ok_plus = m_plus >= -sin_tol
    ok_minus = (m_minus >= -sin_tol) & (~ok_plus | (m_minus > m_plus))
    count = (ok_plus | ok_minus).astype(np.int64)
    rays = np.zeros((n, 2, 3))
    rays[:, 0] = np.where(ok_minus[:, None], -u, u)
    count, rays = _snap_batch(PG, PE, pg, pe, R, rays, count, merge_angle)
    return np.where(solved, count, 0), rays, solved


def _pointed_rays_batch(
    PG: _Pieces,
    PE: _Pieces,
    pg: IntArray,
    pe: IntArray,
    R: FloatArray,
    sin_tol: float,
    merge_angle: float,
) -> list[FloatArray]:
    """Vectorised rank-0 case of :func:`_separating_rays`: both pieces pointed (no lineality).

    The candidate rays (cross products of pairs of rows, both signs, kept when on the right
    side of every row) are found for all pairs at once; the greedy merge (:func:`_dedupe`)
    and the snapping (:func:`_snap_rays`) of each pair's few candidates are the scalar ones.
    Returns the rays of each pair before snapping, in E.
    """
    n = len(pg)
    rows, from_e_b = _ineq_rows(PG, PE, pg, pe, R)
    from_e = from_e_b.astype(np.int64)
    iu, ju = np.triu_indices(rows.shape[1], 1)  # padding rows are zero: crosses dropped
    cr = np.cross(rows[:, iu], rows[:, ju])
    nc = np.linalg.norm(cr, axis=2)
    keep = nc > sin_tol
    cr = cr / np.where(keep, nc, 1.0)[:, :, None]
    prio = np.tile(from_e[iu] + from_e[ju], 2)
    cr = np.concatenate([cr, -cr], axis=1)
    ok = np.tile(keep, 2) & np.all((cr @ rows.transpose(0, 2, 1)) >= -sin_tol, axis=2)
    out = []
    for i in range(n):
        sel = ok[i]
        out.append(_dedupe(cr[i][sel], merge_angle, prio[sel]) if sel.any() else _EMPTY_3)
    return out


def _cone_pair_rays(
    cg: _Cone, ce: _Cone, R: FloatArray, sin_tol: float, merge_angle: float
) -> FloatArray:
    lin_g = cg.lin @ R.T
    rays_g = cg.rays @ R.T
    # Fast paths: a face on either side fixes the only candidate normal.
    if len(ce.lin) == 2:  # E's piece is a half-space: its outward normal (exact in E)
        n = ce.normals[0]
        ok = bool(np.all(rays_g @ n >= -sin_tol)) and bool(np.all(np.abs(lin_g @ n) <= sin_tol))
        return n[None, :].copy() if ok else np.zeros((0, 3))
    if len(lin_g) == 2:  # G's piece is a half-space: minus its outward normal, snapped
        c = -(R @ cg.normals[0])
        ok = bool(np.all(ce.rays @ c <= sin_tol)) and bool(np.all(np.abs(ce.lin @ c) <= sin_tol))
        return _snap_rays(c[None, :], cg, ce, R, merge_angle) if ok else np.zeros((0, 3))
    lin = np.concatenate([lin_g, ce.lin])
    ineq = np.concatenate([rays_g, -ce.rays])
    rays = _separating_rays(lin, ineq, len(cg.rays), sin_tol, merge_angle)
    if len(rays) == 0:
        return rays
    return _snap_rays(rays, cg, ce, R, merge_angle)


# --------------------------------------------------------------------------------------------
# The finder
# --------------------------------------------------------------------------------------------


class ContactFinder:
    """Find contact states of a pair of models at many poses, reusing per-model data.

    Parameters
    ----------
    grasped : Polyhedron
        Grasped object G (model frame G, metres).
    environment : Polyhedron
        Environment object E (model frame E, metres).
    threshold : float, optional
        Contact distance threshold, metres; default :func:`default_threshold`.
    angle_tol : float, optional
        Angular tolerance (rad) of the separating-normal cone intersection and of the
        parallel-edge test; default :func:`default_angle_tolerance`.

    Examples
    --------
    >>> import numpy as np
    >>> from apo.shapes import box
    >>> table = box([1.0, 1.0, 0.1], center=[0.0, 0.0, -0.05])
    >>> cube = box([0.1, 0.1, 0.1], center=[0.0, 0.0, 0.05])
    >>> finder = ContactFinder(cube, table)
    >>> [e.kind.value for e in finder.find(np.eye(4)).elements]
    ['VF', 'VF', 'VF', 'VF']

    A whole sequence at once (much faster per frame than one :meth:`find` per pose):

    >>> X = np.stack([np.eye(4), np.eye(4)])
    >>> X[1, 2, 3] = 0.5  # lifted by 50 cm
    >>> [len(s.elements) for s in finder.find_batch(X)]
    [4, 0]

    Notes
    -----
    :meth:`find` is :meth:`find_batch` of one pose. Small models are searched in blocks of
    frames, each stage one numpy pass over the block: broad phase (bounding boxes), the
    features near each vertex (all pairs pruned by bounding spheres, or k-d trees over
    samples for large models), the edge pairs, the touching pairs, the snapping, the cone
    tests of the common cases (a half-space on either side, edge-vertex, edge-edge,
    vertex-vertex) and the contact points. The rest (nearly parallel lineality, merged rays)
    goes through the scalar code that :meth:`find_naive` uses for every pair.
    """

    def __init__(
        self,
        grasped: Polyhedron,
        environment: Polyhedron,
        *,
        threshold: float | None = None,
        angle_tol: float | None = None,
    ) -> None:
        if threshold is None:
            threshold = default_threshold(grasped, environment)
        threshold = float(threshold)
        if not (math.isfinite(threshold) and threshold > 0):
            raise ValueError(f"threshold must be a positive finite length, got {threshold}")
        if angle_tol is None:
            angle_tol = default_angle_tolerance(grasped, environment, threshold)
        angle_tol = float(angle_tol)
        if not (math.isfinite(angle_tol) and 0 < angle_tol < 0.5):
            raise ValueError(f"angle_tol must be in (0, 0.5) rad, got {angle_tol}")
        self.grasped = grasped
        self.environment = environment
        self.threshold = threshold
        self.angle_tol = angle_tol
        self._g = _model_data(grasped)
        self._e = _model_data(environment)

    def find(self, X_EG: npt.ArrayLike) -> ContactState:
        """Contact state at pose ``X_EG`` (4x4, pose of G in E's frame, metres)."""
        return self._find_frames(_check_pose(X_EG)[None], naive=False)[0]

    def find_batch(self, X_EG_seq: Iterable[npt.ArrayLike] | npt.ArrayLike) -> list[ContactState]:
        """Contact states at each pose of ``X_EG_seq``, vectorised over the poses.

        Parameters
        ----------
        X_EG_seq : array_like, shape (N, 4, 4), or iterable of array_like, shape (4, 4)
            Poses of G in E's frame, metres.

        Returns
        -------
        list of ContactState
            One per pose, equal to :meth:`find` at that pose (up to rounding of the points
            and normals). Small models are processed in blocks of frames (each stage is one
            numpy pass over the block); large ones a few frames at a time.

        Raises
        ------
        ValueError
            A pose is not a finite 4x4 rigid transform (the message gives its index).
        """
        X = _check_poses(X_EG_seq)
        g, e = self._g, self._e
        step = max(1, _BATCH_PRIMITIVES // (g.nv + e.nv + g.ne))
        out: list[ContactState] = []
        for a in range(0, len(X), step):
            out.extend(self._find_frames(X[a : a + step], naive=False))
        return out

    def find_naive(self, X_EG: npt.ArrayLike) -> ContactState:
        """Find the state as :meth:`find` does, by an all-pairs search (reference)."""
        return self._find_frames(_check_pose(X_EG)[None], naive=True)[0]

    # ---------------------------------------------------------------------------------------
    def _find_frames(self, X: FloatArray, *, naive: bool) -> list[ContactState]:
        """Contact states at poses ``X`` (F, 4, 4); every stage is vectorised over frames."""
        g, e, d = self._g, self._e, self.threshold
        n_frames = len(X)
        empty = ContactState((), frozenset())
        R_all, t_all = X[:, :3, :3], X[:, :3, 3]
        # Broad phase: bounding boxes (G's box transformed conservatively).
        if naive:
            active = np.arange(n_frames)
        else:
            c = 0.5 * (g.lo + g.hi)
            r = 0.5 * (g.hi - g.lo)
            cE = np.einsum("fij,j->fi", R_all, c) + t_all
            rE = np.einsum("fij,j->fi", np.abs(R_all), r)
            apart = np.any(cE - rE > e.hi + d, axis=1) | np.any(cE + rE < e.lo - d, axis=1)
            active = np.flatnonzero(~apart)
        states = [empty] * n_frames
        if len(active) == 0:
            return states
        R, t = R_all[active], t_all[active]
        n_act = len(active)
        limit = _DENSE_LIMIT * (_BATCH_DENSE_FACTOR if n_act > 1 else 1)
        VG = g.V @ R.transpose(0, 2, 1) + t[:, None, :]  # G's vertices in E
        VE_G = (e.V[None, :, :] - t[:, None, :]) @ R  # E's in G
        near_g = _by_frame(
            _near_features(e, VG.reshape(-1, 3), d, naive=naive, dense_limit=limit), g.nv
        )
        near_e = _by_frame(
            _near_features(g, VE_G.reshape(-1, 3), d, naive=naive, dense_limit=limit), e.nv
        )
        ee = self._edge_pairs(VG, R, t, d, naive=naive, limit=limit)
        touching = self._touching(near_g, near_e, ee, n_act)

        fr, gkind, gcode, ekind, ecode = self._candidates(near_g, near_e, ee, R)

        # Work items: every pair of convex pieces of the two snapped features.
        gs, gc = g.piece_ranges(gcode)
        es, ec = e.piece_ranges(ecode)
        n = gc * ec
        rep = np.repeat(np.arange(len(n)), n)
        o = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        pg = gs[rep] + o // ec[rep]
        pe = es[rep] + o % ec[rep]
        wfr = fr[rep]
        count, rays, extra = self._cone_pairs(pg, pe, R[wfr], naive=naive)

        # Element kind from the refined features (a vertex candidate keeps its vertex).
        PG, PE = g.pieces, e.pieces
        fa_k, fa_i = PG.kind[pg].copy(), PG.index[pg].copy()
        fb_k, fb_i = PE.kind[pe].copy(), PE.index[pe].copy()
        kind = _KIND_TABLE[fa_k, fb_k]
        m = (kind < 0) & (gkind[rep] == 0)
        fa_k[m], fa_i[m] = 0, gcode[rep][m]
        kind[m] = _KIND_TABLE[fa_k[m], fb_k[m]]
        m = (kind < 0) & (ekind[rep] == 0)
        fb_k[m], fb_i[m] = 0, ecode[rep][m]
        kind[m] = _KIND_TABLE[fa_k[m], fb_k[m]]
        w = np.flatnonzero((kind >= 0) & (count > 0))
        # Elements sorted by frame, then key (kind value, G feature, E feature); the items of
        # one element in work order.
        w = w[
            np.lexsort(
                (
                    w,
                    fb_i[w],
                    _FEATURE_RANK[fb_k[w]],
                    fa_i[w],
                    _FEATURE_RANK[fa_k[w]],
                    _KIND_RANK[kind[w]],
                    wfr[w],
                )
            )
        ]
        if len(w) == 0:
            for k, f in enumerate(active.tolist()):
                states[f] = ContactState((), touching[k])
            return states
        cols = np.stack([wfr[w], kind[w], fa_k[w], fa_i[w], fb_k[w], fb_i[w]])
        new = np.concatenate([[True], np.any(cols[:, 1:] != cols[:, :-1], axis=0)])
        starts = np.flatnonzero(new)
        ends = np.append(starts[1:], len(w))
        el_fr, el_kind = wfr[w[starts]], kind[w[starts]]
        el_a, el_b = fa_i[w[starts]], fb_i[w[starts]]
        points = self._points(el_fr, el_kind, el_a, el_b, R, t, VG)
        merge = 3.0 * self.angle_tol
        ga_code = g.offset[fa_k[w[starts]]] + el_a
        eb_code = e.offset[fb_k[w[starts]]] + el_b
        cnt = count.tolist()
        normals = [extra[i] if i in extra else rays[i, : cnt[i]] for i in w[starts].tolist()]
        w_list = w.tolist()
        for j in np.flatnonzero(ends - starts > 1).tolist():  # several piece pairs: merge
            items = w_list[starts[j] : ends[j]]
            rays_j = [extra[i] if i in extra else rays[i, : cnt[i]] for i in items]
            normals[j] = _dedupe(np.concatenate(rays_j), merge)
        elements = list(
            map(
                ContactElement,
                map(_KIND_LIST.__getitem__, el_kind.tolist()),
                map(g.features.__getitem__, ga_code.tolist()),
                map(e.features.__getitem__, eb_code.tolist()),
                points,
                normals,
            )
        )
        bounds = np.searchsorted(el_fr, np.arange(n_act + 1)).tolist()
        for k, f in enumerate(active.tolist()):
            states[f] = ContactState(tuple(elements[bounds[k] : bounds[k + 1]]), touching[k])
        return states

    def _candidates(
        self,
        near_g: _NearF,
        near_e: _NearF,
        ee: tuple[IntArray, IntArray, IntArray],
        R: FloatArray,
    ) -> tuple[IntArray, IntArray, IntArray, IntArray, IntArray]:
        """Candidate (G feature, E feature) pairs, as (frame, kind, primitive code) of each.

        Returns (frame, G kind code, G primitive code, E kind code, E primitive code). Each
        vertex snapped to its lowest-dimensional (then nearest) feature of the other
        model within the threshold, and the edge pairs of :meth:`_ee_candidates`; in the
        order of the scalar search (G's vertices, E's vertices, edge pairs), duplicates
        dropped.
        """
        g, e = self._g, self._e
        sg, se = _snap(near_g), _snap(near_e)
        keep = self._ee_candidates(ee, near_g, near_e, R)
        ef_, ea_, eb_ = ee[0][keep], ee[1][keep], ee[2][keep]
        cat = np.concatenate
        fr = cat([sg[0], se[0], ef_])
        gkind = cat([np.zeros_like(sg[1]), se[2], np.ones_like(ea_)])
        gcode = cat([sg[1], g.offset[se[2]] + se[3], g.nv + ea_])
        ekind = cat([sg[2], np.zeros_like(se[1]), np.ones_like(eb_)])
        ecode = cat([e.offset[sg[2]] + sg[3], se[1], e.nv + eb_])
        src = cat([np.zeros_like(sg[1]), np.ones_like(se[1]), np.full_like(ea_, 2)])
        grp = cat([sg[4], se[4], np.zeros_like(ea_)])
        pos = cat([sg[1], se[1], ea_ * e.ne + eb_])
        order = np.lexsort((pos, grp, src, fr))
        code = (fr[order] * g.n_all + gcode[order]) * e.n_all + ecode[order]
        _, first = np.unique(code, return_index=True)
        order = order[np.sort(first)]
        return fr[order], gkind[order], gcode[order], ekind[order], ecode[order]

    def _cone_pairs(
        self, pg: IntArray, pe: IntArray, R: FloatArray, *, naive: bool
    ) -> tuple[IntArray, FloatArray, dict[int, FloatArray]]:
        """Separating normals of each pair of pieces (G piece ``pg[k]`` at ``R[k]``, ``pe[k]``).

        Returns the number of rays of each pair, the rays (n, 2, 3) of the pairs solved
        vectorised, and the rays of the others (by pair index). The naive search solves every
        pair with the scalar :func:`_cone_pair_rays`.
        """
        g, e = self._g, self._e
        PG, PE = g.pieces, e.pieces
        sin_tol = math.sin(self.angle_tol)
        merge = 3.0 * self.angle_tol
        n = len(pg)
        count = np.zeros(n, dtype=np.int64)
        rays = np.zeros((n, 2, 3))
        extra: dict[int, FloatArray] = {}
        lg, le = PG.nlin[pg], PE.nlin[pe]
        if naive:
            scalar = np.ones(n, dtype=bool)
        else:
            half_e = le == 2  # E's piece is a half-space: its outward normal (exact in E)
            half_g = ~half_e & (lg == 2)  # G's piece is one: minus its outward normal, snapped
            arc = (lg + le) == 1
            edges = (lg == 1) & (le == 1)
            pointed = (lg == 0) & (le == 0)
            scalar = ~(half_e | half_g | arc | edges | pointed)
            for sel, side in ((half_e, "e"), (half_g, "g")):
                k = np.flatnonzero(sel)
                if len(k) == 0:
                    continue
                if side == "e":  # G's rays on the normal's side, G's lineality in the plane
                    nrm = PE.normals[PE.norm_ptr[pe[k]]]
                    P, pk, sign, rot = PG, pg[k], 1.0, True
                else:  # E's rays on the other side, E's lineality in the plane
                    nrm = -_rotate(R[k], PG.normals[PG.norm_ptr[pg[k]]])
                    P, pk, sign, rot = PE, pe[k], -1.0, False
                bad = np.zeros(len(k), dtype=bool)
                j, idx, _ = _expand(P.ray_ptr[pk], P.nrays[pk])
                v = _rotate(R[k][j], P.rays[idx]) if rot else P.rays[idx]
                bad[j[sign * _dot(v, nrm[j]) < -sin_tol]] = True
                j, idx, _ = _expand(P.lin_ptr[pk], P.nlin[pk])
                v = _rotate(R[k][j], P.lin[idx]) if rot else P.lin[idx]
                bad[j[np.abs(_dot(v, nrm[j])) > sin_tol]] = True
                k, nrm = k[~bad], nrm[~bad]
                count[k] = 1
                rays[k, 0] = nrm
                if side == "g" and len(k):  # to E's exact normal within the merge angle
                    count[k], rays[k] = _snap_batch(
                        PG, PE, pg[k], pe[k], R[k], rays[k], count[k], merge
                    )
            k = np.flatnonzero(arc)
            if len(k):
                count[k], rays[k] = _arc_rays_batch(PG, PE, pg[k], pe[k], R[k], sin_tol, merge)
            k = np.flatnonzero(edges)
            if len(k):
                c, r, solved = _edge_edge_rays_batch(PG, PE, pg[k], pe[k], R[k], sin_tol, merge)
                count[k], rays[k] = c, r
                scalar[k[~solved]] = True
            k = np.flatnonzero(pointed)
            if len(k):
                for i, r in zip(
                    k.tolist(),
                    _pointed_rays_batch(PG, PE, pg[k], pe[k], R[k], sin_tol, merge),
                    strict=True,
                ):
                    if len(r):
                        r = _snap_rays(
                            r, g.piece_list[int(pg[i])], e.piece_list[int(pe[i])], R[i], merge
                        )
                        count[i] = len(r)
                        extra[i] = r
        for i in np.flatnonzero(scalar).tolist():
            r = _cone_pair_rays(
                g.piece_list[int(pg[i])], e.piece_list[int(pe[i])], R[i], sin_tol, merge
            )
            if len(r):
                count[i] = len(r)
                extra[i] = r
        return count, rays, extra

    def _edge_pairs(
        self, VG: FloatArray, R: FloatArray, t: FloatArray, d: float, *, naive: bool, limit: int
    ) -> tuple[IntArray, IntArray, IntArray]:
        """(frame, G edge, E edge) of the edge pairs within d, sorted."""
        g, e = self._g, self._e
        A0 = VG[:, g.edges[:, 0]].reshape(-1, 3)
        A1 = VG[:, g.edges[:, 1]].reshape(-1, 3)
        n_rows = len(A0)
        if naive:  # every pair, in chunks of about a million pairs
            step = max(1, 1_000_000 // max(e.ne, 1))
            parts = []
            for a in range(0, n_rows, step):
                ca = np.repeat(np.arange(a, min(a + step, n_rows), dtype=np.int64), e.ne)
                cb = np.tile(np.arange(e.ne, dtype=np.int64), len(ca) // max(e.ne, 1))
                rr = segment_segment_closest(A0[ca], A1[ca], e.E0[cb], e.E1[cb])
                m = rr.distance <= d
                parts.append((ca[m], cb[m]))
            if not parts:
                return _EMPTY_I, _EMPTY_I, _EMPTY_I
            ia, ib = np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
            return ia // g.ne, ia % g.ne, ib
        lo = np.minimum(A0, A1) - d
        hi = np.maximum(A0, A1) + d
        sel = np.flatnonzero(np.all((hi >= e.lo) & (lo <= e.hi), axis=1))
        if len(sel) == 0:
            return _EMPTY_I, _EMPTY_I, _EMPTY_I
        if len(sel) * e.ne <= 10 * limit:  # box overlaps are cheap
            eb_lo = np.minimum(e.E0, e.E1)
            eb_hi = np.maximum(e.E0, e.E1)
            ov = (hi[sel, None, 0] >= eb_lo[None, :, 0]) & (lo[sel, None, 0] <= eb_hi[None, :, 0])
            for k in (1, 2):
                ov &= (hi[sel, None, k] >= eb_lo[None, :, k]) & (
                    lo[sel, None, k] <= eb_hi[None, :, k]
                )
            ia, ib = np.nonzero(ov)
            ia = sel[ia]
        else:
            _, _, _, _, te, eown, er = e.trees()
            if g.edge_samples is None:
                g.trees()
            assert g.edge_samples is not None
            gpts, gown, gr = g.edge_samples
            ias, ibs = [], []
            for f in np.unique(sel // g.ne).tolist():
                sel_f = sel[sel // g.ne == f] - f * g.ne
                keep = np.isin(gown, sel_f)
                pts = gpts[keep] @ R[f].T + t[f]
                i, s = _pairs_from_ball(te.query_ball_point(pts, d + er + gr), gown[keep])
                key = np.unique(i * e.ne + eown[s])
                ias.append(key // e.ne + f * g.ne)
                ibs.append(key % e.ne)
            ia, ib = np.concatenate(ias), np.concatenate(ibs)
        if len(ia) == 0:
            return _EMPTY_I, _EMPTY_I, _EMPTY_I
        r = segment_segment_closest(A0[ia], A1[ia], e.E0[ib], e.E1[ib])
        ok = r.distance <= d
        ia, ib = ia[ok].astype(np.int64), ib[ok].astype(np.int64)
        return ia // g.ne, ia % g.ne, ib

    def _ee_candidates(
        self, ee: tuple[IntArray, IntArray, IntArray], near_g: _NearF, near_e: _NearF, R: FloatArray
    ) -> BoolArray:
        """Mask of the edge pairs that are non-parallel and whose endpoints touch no edge."""
        fr, ia, ib = ee
        if len(ia) == 0:
            return np.zeros(0, dtype=bool)
        g, e = self._g, self._e
        dg = _rotate(R[fr], g.edge_dir[ia])
        cross = _norm(_cross_rows(dg, e.edge_dir[ib]))
        keep: BoolArray = cross > math.sin(self.angle_tol)
        # Endpoint coverage: G vertex near E edge, E vertex near G edge.
        f_, i_, j_, _ = near_g.e
        gv_e = (f_ * g.nv + i_) * e.ne + j_
        f_, i_, j_, _ = near_e.e
        ev_g = (f_ * e.nv + i_) * g.ne + j_
        gv_e.sort()
        ev_g.sort()
        for end in (0, 1):
            keep &= ~_member((fr * g.nv + g.edges[ia, end]) * e.ne + ib, gv_e)
            keep &= ~_member((fr * e.nv + e.edges[ib, end]) * g.ne + ia, ev_g)
        return keep

    def _touching(
        self,
        near_g: _NearF,
        near_e: _NearF,
        ee: tuple[IntArray, IntArray, IntArray],
        n_frames: int,
    ) -> list[frozenset[tuple[Feature, Feature]]]:
        """Every (G feature, E feature) pair within the threshold, per frame."""
        g, e = self._g, self._e
        # Primitive pairs, encoded as primitive codes (v: i, e: nv + i, f: nv + ne + i).
        fs: list[IntArray] = []
        pg: list[IntArray] = []
        pe: list[IntArray] = []
        for c, kind in enumerate(("v", "e", "f")):
            f, i, j, _ = getattr(near_g, kind)
            fs.append(f)
            pg.append(i)
            pe.append(j + e.offset[c])
            f, i, j, _ = getattr(near_e, kind)
            fs.append(f)
            pg.append(j + g.offset[c])
            pe.append(i)
        fs.append(ee[0])
        pg.append(ee[1] + g.nv)
        pe.append(ee[2] + e.nv)
        F, P, Qe = np.concatenate(fs), np.concatenate(pg), np.concatenate(pe)
        if len(P) == 0:
            return [frozenset()] * n_frames
        # Frames with the same primitive pairs have the same touching set: expand one of each.
        same_as = list(range(n_frames))
        if n_frames > 1:
            pair = P * e.n_all + Qe
            order = np.lexsort((pair, F))
            F, P, Qe, pair = F[order], P[order], Qe[order], pair[order]
            bounds = np.searchsorted(F, np.arange(n_frames + 1)).tolist()
            rep_of: dict[bytes, int] = {}
            keep = np.ones(len(F), dtype=bool)
            for f in range(n_frames):
                lo, hi = bounds[f], bounds[f + 1]
                rep = rep_of.setdefault(pair[lo:hi].tobytes(), f)
                if rep != f:
                    same_as[f] = rep
                    keep[lo:hi] = False
            F, P, Qe = F[keep], P[keep], Qe[keep]
        lp, lq = g.star_len[P], e.star_len[Qe]
        n = lp * lq
        k = np.repeat(np.arange(len(P)), n)
        o = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        a = g.star_data[g.star_ptr[P[k]] + o // lq[k]]
        b = e.star_data[e.star_ptr[Qe[k]] + o % lq[k]]
        code = np.unique((F[k] * g.n_all + a) * e.n_all + b)
        fr, code = np.divmod(code, g.n_all * e.n_all)
        a, b = np.divmod(code, e.n_all)
        bounds = np.searchsorted(fr, np.arange(n_frames + 1)).tolist()
        gf, ef = g.features, e.features
        out: list[frozenset[tuple[Feature, Feature]]] = []
        for f in range(n_frames):
            if same_as[f] != f:
                out.append(out[same_as[f]])
                continue
            lo, hi = bounds[f], bounds[f + 1]
            aa, bb = a[lo:hi].tolist(), b[lo:hi].tolist()
            out.append(
                frozenset(zip(map(gf.__getitem__, aa), map(ef.__getitem__, bb), strict=True))
            )
        return out

    def _points(
        self,
        fr: IntArray,
        kind: IntArray,
        ga: IntArray,
        eb: IntArray,
        R: FloatArray,
        t: FloatArray,
        VG: FloatArray,
    ) -> FloatArray:
        """Contact points of elements (frame, kind code, G and E feature indices), in E.

        See ``docs/contacts.md``: VF and FV project the vertex on the face's plane, EE is the
        midpoint of the closest points of the edges, VE and EV project the vertex on the
        edge, VV is the midpoint of the vertices.
        """
        g, e = self._g, self._e
        out = np.empty((len(fr), 3))
        for code in np.unique(kind).tolist():
            m = kind == code
            f, a, b = fr[m], ga[m], eb[m]
            k = _KIND_LIST[code]
            if k is ContactKind.VF:
                p = VG[f, a]
                nrm = e.poly.face_normals[b]
                h = _dot(nrm, p) - e.poly.face_offsets[b]
                out[m] = p - h[:, None] * nrm
            elif k is ContactKind.FV:
                q = e.V[b]
                w = _rotate(R[f], g.poly.face_normals[a])
                off = g.poly.face_offsets[a] + _dot(w, t[f])
                out[m] = q - (_dot(w, q) - off)[:, None] * w
            elif k is ContactKind.EE:
                r = segment_segment_closest(
                    VG[f, g.edges[a, 0]], VG[f, g.edges[a, 1]], e.E0[b], e.E1[b]
                )
                out[m] = 0.5 * (r.p + r.q)
            elif k is ContactKind.VE:
                out[m] = closest_point_on_segment(VG[f, a], e.E0[b], e.E1[b])[0]
            elif k is ContactKind.EV:
                out[m] = closest_point_on_segment(
                    e.V[b], VG[f, g.edges[a, 0]], VG[f, g.edges[a, 1]]
                )[0]
            else:
                out[m] = 0.5 * (VG[f, a] + e.V[b])
        return out


def _member(x: IntArray, sorted_set: IntArray) -> BoolArray:
    """``np.isin(x, sorted_set)`` for a sorted ``sorted_set`` (a binary search per entry)."""
    if len(sorted_set) == 0:
        return np.zeros(len(x), dtype=bool)
    i = np.minimum(np.searchsorted(sorted_set, x), len(sorted_set) - 1)
    return np.asarray(sorted_set[i] == x, dtype=bool)


@dataclass
class _NearF:
    """Pairs (frame, query point i, feature j, distance) within the threshold, per kind."""

    v: tuple[IntArray, IntArray, IntArray, FloatArray]
    e: tuple[IntArray, IntArray, IntArray, FloatArray]
    f: tuple[IntArray, IntArray, IntArray, FloatArray]


def _by_frame(near: _Near, n_points: int) -> _NearF:
    """Split the query rows ``frame * n_points + i`` of ``near`` into (frame, i)."""
    parts = []
    for i, j, dist in (near.v, near.e, near.f):
        f, i = np.divmod(i, n_points)
        parts.append((f, i, j, dist))
    return _NearF(*parts)


def _snap(near: _NearF) -> tuple[IntArray, IntArray, IntArray, IntArray, IntArray]:
    """Lowest-dimensional (then nearest) feature within the threshold of each query point.

    Returns (frame, point, kind code, feature index, group) sorted by (frame, point); group is
    0 when a face is near the point, 1 when an edge is (and no face), else 2: the scalar
    search's order of first insertion.
    """
    cat = np.concatenate
    fr = cat([near.v[0], near.e[0], near.f[0]])
    if len(fr) == 0:
        return _EMPTY_I, _EMPTY_I, _EMPTY_I, _EMPTY_I, _EMPTY_I
    i = cat([near.v[1], near.e[1], near.f[1]])
    j = cat([near.v[2], near.e[2], near.f[2]])
    dist = cat([near.v[3], near.e[3], near.f[3]])
    k = np.repeat(np.arange(3, dtype=np.int64), [len(near.v[0]), len(near.e[0]), len(near.f[0])])
    order = np.lexsort((dist, k, i, fr))
    fr, i, j, k = fr[order], i[order], j[order], k[order]
    first = np.concatenate([[True], (fr[1:] != fr[:-1]) | (i[1:] != i[:-1])])
    start = np.flatnonzero(first)
    last = np.append(start[1:] - 1, len(fr) - 1)
    return fr[start], i[start], k[start], j[start], 2 - k[last]


_KIND_LIST = (
    ContactKind.VF,
    ContactKind.FV,
    ContactKind.EE,
    ContactKind.VE,
    ContactKind.EV,
    ContactKind.VV,
)
# Kind code of (G feature kind code, E feature kind code), -1 for no element.
_KIND_TABLE = np.full((3, 3), -1, dtype=np.int64)
for _code, _k in enumerate(_KIND_LIST):
    _KIND_TABLE[_CODE[_k.value[0].lower()], _CODE[_k.value[1].lower()]] = _code
# Sort ranks matching the tuple order of element keys (kind value, ("v" | "e" | "f", index)).
_KIND_RANK = np.argsort(np.argsort([k.value for k in _KIND_LIST]))
_FEATURE_RANK = np.argsort(np.argsort(_NAME))


# --------------------------------------------------------------------------------------------
# Public functions
# --------------------------------------------------------------------------------------------


def find_contacts(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG: npt.ArrayLike,
    *,
    threshold: float | None = None,
    angle_tol: float | None = None,
) -> ContactState:
    """Contact state between G at pose ``X_EG`` and E (paper 4.3.1).

    Parameters
    ----------
    grasped : Polyhedron
        Grasped object G, model frame G, metres.
    environment : Polyhedron
        Environment object E, model frame E, metres.
    X_EG : array_like, shape (4, 4)
        Pose of G in E's frame (``p_E = X_EG @ p_G``), metres.
    threshold : float, optional
        Two features closer than this (metres) touch. Default :func:`default_threshold`
        (``1e-3`` of the smaller model's bounding diagonal), meant for exact poses; observed
        poses need a few millimetres.
    angle_tol : float, optional
        Angular tolerance (rad) of the normal-cone intersection and of the parallel-edge
        test; default :func:`default_angle_tolerance`.

    Returns
    -------
    ContactState
        Elements sorted by key (points and normals in E, metres) and every touching
        feature pair.

    Raises
    ------
    ValueError
        ``X_EG`` is not a finite 4x4 rigid transform, or a bad threshold or tolerance.

    See Also
    --------
    ContactFinder : the same with per-model data reused over many poses.
    find_contacts_naive : all-pairs reference search.

    Notes
    -----
    Candidates: each vertex of G within ``threshold`` of E's surface, each vertex of E within
    ``threshold`` of G's surface, and each non-parallel pair of edges within ``threshold``
    whose endpoints do not touch the other edge. Each is snapped to the lowest-dimensional
    feature of each object within the threshold; the local solids there are split into
    convex pieces and each pair of touching pieces gives an element whose separating normals
    are the extreme rays of ``T_G* ∩ (-T_E*)`` (``docs/contacts.md``).
    """
    finder = ContactFinder(grasped, environment, threshold=threshold, angle_tol=angle_tol)
    return finder.find(X_EG)


def find_contacts_batch(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG_seq: Iterable[npt.ArrayLike] | npt.ArrayLike,
    *,
    threshold: float | None = None,
    angle_tol: float | None = None,
) -> list[ContactState]:
    """Contact states at each pose of ``X_EG_seq`` (N x 4 x 4 poses of G in E, metres).

    Same parameters and result as :func:`find_contacts`, one state per pose; the per-model
    data (k-d trees, local cones) is computed once and the search is vectorised over the
    poses (:meth:`ContactFinder.find_batch`).
    """
    finder = ContactFinder(grasped, environment, threshold=threshold, angle_tol=angle_tol)
    return finder.find_batch(X_EG_seq)


def find_contacts_naive(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG: npt.ArrayLike,
    *,
    threshold: float | None = None,
    angle_tol: float | None = None,
) -> ContactState:
    """Find contacts as :func:`find_contacts` does, by a plain all-pairs search.

    Every vertex is measured against every face polygon of the other model
    (:func:`apo.geometry.point_face_distance`), every edge and vertex, and every edge against
    every edge, with no broad phase, and every pair of convex pieces goes through the scalar
    cone intersection (the fast search solves the common cases vectorised); used to test and
    benchmark the fast search.
    """
    finder = ContactFinder(grasped, environment, threshold=threshold, angle_tol=angle_tol)
    return finder.find_naive(X_EG)


def contact_points(state: ContactState) -> list[ContactPoint]:
    """Convert the elements of ``state`` to DOF-analysis contact points (frame E, metres).

    Parameters
    ----------
    state : ContactState
        A contact state.

    Returns
    -------
    list of apo.dof.ContactPoint
        One per element, in the state's order, with its point and separating normals.
    """
    return [ContactPoint(el.point.copy(), el.normals.copy()) for el in state.elements]


# --------------------------------------------------------------------------------------------
# Residuals for pose correction
# --------------------------------------------------------------------------------------------

_N_RESIDUALS = {
    ContactKind.VF: 1,
    ContactKind.FV: 1,
    ContactKind.EE: 1,
    ContactKind.VE: 2,
    ContactKind.EV: 2,
    ContactKind.VV: 3,
}


def residual_counts(elements: Sequence[ContactElement]) -> IntArray:
    """Return the number of residual rows of each element (VF, FV, EE: 1; VE, EV: 2; VV: 3)."""
    return np.array([_N_RESIDUALS[el.kind] for el in elements], dtype=np.int64)


def _perp_basis(u: FloatArray) -> FloatArray:
    """Deterministic orthonormal basis (2, 3) of the plane perpendicular to unit ``u``."""
    return _plane_basis(u / np.linalg.norm(u))


def element_residuals(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG: npt.ArrayLike,
    elements: Sequence[ContactElement],
) -> tuple[FloatArray, FloatArray]:
    """Residuals ``f_i(X_EG)`` of contact elements and their Jacobians (paper 4.3.1).

    Parameters
    ----------
    grasped, environment : Polyhedron
        The models (frames G and E, metres).
    X_EG : array_like, shape (4, 4)
        Pose of G in E, metres.
    elements : sequence of ContactElement
        Elements whose feature ids refer to these models (e.g. from :func:`find_contacts`).

    Returns
    -------
    r : ndarray, shape (K,)
        Residuals, metres, concatenated in element order; element i contributes
        ``residual_counts(elements)[i]`` rows. All zero iff every contact holds exactly.
    J : ndarray, shape (K, 6)
        ``dr / dxi`` for a twist ``xi = [omega; v]`` (rotation first, environment frame)
        applied on the left: ``X_EG_new = exp(xi) @ X_EG`` (``apo.spatial.pose_from_twist``).

    Notes
    -----
    With ``p`` a vertex of G in E, ``q`` a vertex of E (all in E):

    - VF: ``n_f . p - d_f`` (E's face plane, positive outside E); row ``[p x n, n]``.
    - FV: ``w . (q - p_0)`` with ``w`` G's face normal and ``p_0`` a point of G's face
      plane, in E (positive outside G); row ``[w x q, -w]``.
    - EE: ``m . (a - b)``, ``a``, ``b`` points of G's and E's edge lines, ``m`` the unit
      common normal of the lines, signed from E to G (the element's normal); row
      ``[a x m + e (u . c) - c (u . e), m]`` with ``u``, ``e`` the edge directions and
      ``c = (I - m m^T)(a - b) / |u x e|``.
    - VE: the two components ``k_j . (p - b)`` of p's offset from E's edge line, ``k_1, k_2``
      a fixed orthonormal basis perpendicular to the edge; rows ``[p x k_j, k_j]``.
    - EV: ``k_j . (q - a)``, ``k_j`` perpendicular to G's edge (moving with G); rows
      ``[k_j x q, -k_j]``.
    - VV: ``p - q`` (3 rows); rows ``[-[p]_x, I]``.
    """
    X = _check_pose(X_EG)
    R, t = X[:3, :3], X[:3, 3]
    g, e = _model_data(grasped), _model_data(environment)
    rows_r: list[float] = []
    rows_J: list[FloatArray] = []
    for el in elements:
        ga, eb = el.grasped[1], el.environment[1]
        k = el.kind
        if k is ContactKind.VF:
            p = R @ g.V[ga] + t
            n = e.poly.face_normals[eb]
            rows_r.append(float(n @ p - e.poly.face_offsets[eb]))
            rows_J.append(np.concatenate([np.cross(p, n), n]))
        elif k is ContactKind.FV:
            q = e.V[eb]
            w = R @ g.poly.face_normals[ga]
            p0 = R @ (g.poly.face_offsets[ga] * g.poly.face_normals[ga]) + t
            rows_r.append(float(w @ (q - p0)))
            rows_J.append(np.concatenate([np.cross(w, q), -w]))
        elif k is ContactKind.EE:
            a = R @ g.E0[ga] + t
            u = R @ g.edge_dir[ga]
            b = e.E0[eb]
            ed = e.edge_dir[eb]
            cr = np.cross(u, ed)
            nc = float(np.linalg.norm(cr))
            m = cr / nc
            ref = el.normals[0] if len(el.normals) else a - b
            if float(m @ ref) < 0:
                m = -m
            diff = a - b
            c = (diff - (m @ diff) * m) / nc
            sign = 1.0 if float(np.cross(u, ed) @ m) > 0 else -1.0
            jw = np.cross(a, m) + sign * (ed * float(u @ c) - c * float(u @ ed))
            rows_r.append(float(m @ diff))
            rows_J.append(np.concatenate([jw, m]))
        elif k is ContactKind.VE:
            p = R @ g.V[ga] + t
            b = e.E0[eb]
            for kj in _perp_basis(e.edge_dir[eb]):
                rows_r.append(float(kj @ (p - b)))
                rows_J.append(np.concatenate([np.cross(p, kj), kj]))
        elif k is ContactKind.EV:
            q = e.V[eb]
            a = R @ g.E0[ga] + t
            for kj0 in _perp_basis(g.edge_dir[ga]):
                kj = R @ kj0
                rows_r.append(float(kj @ (q - a)))
                rows_J.append(np.concatenate([np.cross(kj, q), -kj]))
        else:
            p = R @ g.V[ga] + t
            q = e.V[eb]
            for j in range(3):
                unit = np.zeros(3)
                unit[j] = 1.0
                rows_r.append(float(p[j] - q[j]))
                rows_J.append(np.concatenate([np.cross(p, unit), unit]))
    if not rows_r:
        return np.zeros(0), np.zeros((0, 6))
    return np.asarray(rows_r, dtype=np.float64), np.asarray(rows_J, dtype=np.float64)
