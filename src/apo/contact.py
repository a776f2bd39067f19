"""Contact elements and contact states between two posed polyhedra (paper 2.1, 4.3.1).

:func:`find_contacts` finds every contact element between the grasped object G and the
environment object E at a pose ``X_EG`` (pose of G in E's frame, metres): candidate points
are vertices of either object within a distance threshold of the other's surface and
crossings of non-parallel edges; each candidate is snapped to the lowest-dimensional feature
of each object within the threshold, the local solids there are split into convex pieces,
and every pair of pieces that touch gives one element whose separating normals are the
extreme rays of ``N = T_G* ∩ (-T_E*)`` (``docs/contacts.md``). :class:`ContactFinder`
caches per-model data for use over many frames; :func:`find_contacts_naive` is the plain
all-pairs reference; :func:`element_residuals` gives the residuals ``f_i(X_EG)`` of the
elements and their Jacobians for pose correction (paper 4.3.1).

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
        tri = np.concatenate(poly.face_triangles).astype(np.int64)
        self.tri_face = np.repeat(
            np.arange(self.nf, dtype=np.int64), [len(t) for t in poly.face_triangles]
        )
        self.TA, self.TB, self.TC = V[tri[:, 0]], V[tri[:, 1]], V[tri[:, 2]]
        self.tri_n = poly.face_normals[self.tri_face]
        self.tri_off = poly.face_offsets[self.tri_face]
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
    return np.asarray(np.linalg.norm(p - q, axis=1), dtype=np.float64)


@dataclass
class _Near:
    """Pairs (query point i, feature j, distance) within the threshold, per feature kind."""

    v: tuple[IntArray, IntArray, FloatArray]
    e: tuple[IntArray, IntArray, FloatArray]
    f: tuple[IntArray, IntArray, FloatArray]


_EMPTY_I = np.zeros(0, dtype=np.int64)
_EMPTY_F = np.zeros(0, dtype=np.float64)


def _pairs_from_ball(lists: Any, rows: IntArray) -> tuple[IntArray, IntArray]:
    counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
    if counts.sum() == 0:
        return _EMPTY_I, _EMPTY_I
    i = np.repeat(rows, counts)
    j = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(counts.sum()))
    return i, j


def _near_features(md: _ModelData, pts: FloatArray, d: float, *, naive: bool = False) -> _Near:
    """Features of ``md`` within ``d`` of each point of ``pts`` (points in md's frame)."""
    if naive:
        return _near_features_naive(md, pts, d)
    inside = np.all((pts >= md.lo - d) & (pts <= md.hi + d), axis=1)
    rows = np.flatnonzero(inside).astype(np.int64)
    if len(rows) == 0:
        e3 = (_EMPTY_I, _EMPTY_I, _EMPTY_F)
        return _Near(e3, e3, e3)
    Q = pts[rows]
    dense = len(Q) * max(md.nv, len(md.TA)) <= _DENSE_LIMIT
    # vertices
    if dense:
        dvv = np.linalg.norm(Q[:, None, :] - md.V[None, :, :], axis=2)
        ii, jj = np.nonzero(dvv <= d)
        vv = (rows[ii], jj.astype(np.int64), dvv[ii, jj])
    else:
        tv, tt, town, tr, te, eown, er = md.trees()
        i, j = _pairs_from_ball(tv.query_ball_point(Q, d), np.arange(len(Q)))
        dist = np.linalg.norm(Q[i] - md.V[j], axis=1)
        vv = (rows[i], j, dist)
    # edges
    if dense:
        ii, jj = np.nonzero(np.ones((len(Q), md.ne), dtype=bool))
    else:
        tv, tt, town, tr, te, eown, er = md.trees()
        i, s = _pairs_from_ball(te.query_ball_point(Q, d + er), np.arange(len(Q)))
        key = np.unique(i * md.ne + eown[s])
        ii, jj = key // md.ne, key % md.ne
    cl, _ = closest_point_on_segment(Q[ii], md.E0[jj], md.E1[jj])
    dist = np.linalg.norm(Q[ii] - cl, axis=1)
    ok = dist <= d
    ee = (rows[ii[ok]], jj[ok].astype(np.int64), dist[ok])
    # faces via triangles, pre-filtered by the plane distance
    if dense:
        height = np.abs(Q @ md.tri_n.T - md.tri_off[None, :])
        ii, tt_ = np.nonzero(height <= d)
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


def _snap(near: _Near, n_points: int) -> dict[int, Feature]:
    """Lowest-dimensional (then nearest) feature within the threshold for each point."""
    out: dict[int, Feature] = {}
    for kind in ("f", "e", "v"):  # later kinds overwrite: vertex wins over edge over face
        i, j, dist = getattr(near, kind)
        if len(i) == 0:
            continue
        order = np.lexsort((dist, i))
        i, j = i[order], j[order]
        first = np.concatenate([[True], i[1:] != i[:-1]])
        for a, b in zip(i[first].tolist(), j[first].tolist(), strict=True):
            out[a] = (kind, b)
    return out


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


def _arc_rays_batch(
    pairs: list[tuple[_Cone, _Cone]], R: FloatArray, sin_tol: float, merge_angle: float
) -> list[FloatArray]:
    """Vectorised rank-1 case of :func:`_separating_rays` for (edge, vertex) piece pairs.

    Each pair has exactly one lineality direction (an edge on one side, a pointed cone on
    the other). Same result as the scalar code up to rounding; rays are then snapped.
    """
    n = len(pairs)
    m_max = max(len(cg.rays) + len(ce.rays) for cg, ce in pairs)
    rows = np.zeros((n, m_max, 3))
    from_e = np.zeros((n, m_max), dtype=bool)
    axis = np.empty((n, 3))
    for p, (cg, ce) in enumerate(pairs):
        kg, ke = len(cg.rays), len(ce.rays)
        rows[p, :kg] = cg.rays @ R.T
        rows[p, kg : kg + ke] = -ce.rays
        from_e[p, kg : kg + ke] = True
        axis[p] = ce.lin[0] if len(ce.lin) else R @ cg.lin[0]
    # Plane bases, as _plane_basis.
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    near_x = np.abs(x) >= 0.9
    t1 = np.where(
        near_x[:, None],
        np.stack([-z, np.zeros(n), x], axis=1),
        np.stack([np.zeros(n), z, -y], axis=1),
    )
    t1 /= np.linalg.norm(t1, axis=1)[:, None]
    Q = np.stack([t1, np.cross(axis, t1)], axis=1)  # (n, 2, 3)
    A2 = np.einsum("pmk,pjk->pmj", rows, Q)  # (n, m, 2)
    nr = np.linalg.norm(A2, axis=2)
    valid = nr > sin_tol
    with np.errstate(divide="ignore", invalid="ignore"):
        perp = np.stack([-A2[:, :, 1], A2[:, :, 0]], axis=2) / np.where(valid, nr, 1.0)[:, :, None]
    cand = np.stack([perp, -perp], axis=2).reshape(n, 2 * m_max, 2)  # row0+, row0-, ...
    c_valid = np.repeat(valid, 2, axis=1)
    c_prio = np.repeat(from_e, 2, axis=1)
    ok = c_valid & np.all(np.einsum("pck,pmk->pcm", cand, A2) >= -sin_tol, axis=2)
    mean = np.einsum("pck,pc->pk", cand, ok.astype(np.float64))
    nm = np.linalg.norm(mean, axis=1)
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
    okp = ok & c_prio
    score = np.where(okp, 1.0 - 1e-3 * np.abs(ang - 0.5 * (a_hi + a_lo)[:, None]), -np.inf)
    pick = cand[ar, np.argmax(score, axis=1)]
    both = lo + hi
    both /= np.maximum(np.linalg.norm(both, axis=1), 1e-300)[:, None]
    one = np.where(okp.any(axis=1)[:, None], pick, both)
    out: list[FloatArray] = []
    for p, (cg, ce) in enumerate(pairs):
        if not good[p]:
            out.append(np.zeros((0, 3)))
            continue
        r2 = one[p][None, :] if collapsed[p] else np.stack([lo[p], hi[p]])
        out.append(_snap_rays(r2 @ Q[p], cg, ce, R, merge_angle))
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
    if len(lin_g) == 2:  # G's piece is a half-space: minus its outward normal
        c = -(R @ cg.normals[0])
        ok = bool(np.all(ce.rays @ c <= sin_tol)) and bool(np.all(np.abs(ce.lin @ c) <= sin_tol))
        return c[None, :] if ok else np.zeros((0, 3))
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
        return self._find(_check_pose(X_EG), naive=False)

    def find_batch(self, X_EG_seq: Iterable[npt.ArrayLike]) -> list[ContactState]:
        """Contact states at each pose of ``X_EG_seq`` (each 4x4, metres)."""
        return [self._find(_check_pose(X), naive=False) for X in X_EG_seq]

    def find_naive(self, X_EG: npt.ArrayLike) -> ContactState:
        """Find the state as :meth:`find` does, by an all-pairs search (reference)."""
        return self._find(_check_pose(X_EG), naive=True)

    # ---------------------------------------------------------------------------------------
    def _find(self, X: FloatArray, *, naive: bool) -> ContactState:
        g, e, d = self._g, self._e, self.threshold
        R, t = X[:3, :3], X[:3, 3]
        # Broad phase: bounding boxes (G's box transformed conservatively).
        if not naive:
            c = 0.5 * (g.lo + g.hi)
            r = 0.5 * (g.hi - g.lo)
            cE = R @ c + t
            rE = np.abs(R) @ r
            if np.any(cE - rE > e.hi + d) or np.any(cE + rE < e.lo - d):
                return ContactState((), frozenset())
        VG = g.V @ R.T + t  # G's vertices in E
        VE_G = (e.V - t) @ R  # E's vertices in G
        near_g = _near_features(e, VG, d, naive=naive)  # G vertex i vs E features
        near_e = _near_features(g, VE_G, d, naive=naive)  # E vertex i vs G features
        ee = self._edge_pairs(VG, R, t, d, naive=naive)
        touching = self._touching(near_g, near_e, ee[0], ee[1])

        # Candidates: (G snapped feature, E snapped feature).
        cands: dict[tuple[Feature, Feature], None] = {}
        for i, feat in _snap(near_g, g.nv).items():
            cands[(("v", i), feat)] = None
        for i, feat in _snap(near_e, e.nv).items():
            cands[(feat, ("v", i))] = None
        for ea, eb in self._ee_candidates(ee, near_g, near_e, R):
            cands[(("e", ea), ("e", eb))] = None

        sin_tol = math.sin(self.angle_tol)
        merge = 3.0 * self.angle_tol
        found: dict[tuple[str, Feature, Feature], tuple[ContactKind, list[FloatArray]]] = {}
        self._batch_vertex_face(cands, found, R, sin_tol)
        work = [(gf, ef, cg, ce) for gf, ef in cands for cg in g.cones(gf) for ce in e.cones(ef)]
        arc = [
            i
            for i, (_, _, cg, ce) in enumerate(work)
            if not naive and len(cg.lin) + len(ce.lin) == 1
        ]
        batch = _arc_rays_batch([work[i][2:] for i in arc], R, sin_tol, merge) if arc else []
        arc_rays = dict(zip(arc, batch, strict=True))
        for i, (gf, ef, cg, ce) in enumerate(work):
            rays = arc_rays.get(i)
            if rays is None:
                rays = _cone_pair_rays(cg, ce, R, sin_tol, merge)
            if len(rays) == 0:
                continue
            fa, fb = cg.feature, ce.feature
            kind = _KINDS.get((fa[0], fb[0]))
            if kind is None and gf[0] == "v":
                fa = gf
                kind = _KINDS.get((fa[0], fb[0]))
            if kind is None and ef[0] == "v":
                fb = ef
                kind = _KINDS.get((fa[0], fb[0]))
            if kind is None:
                continue
            k = (kind.value, fa, fb)
            if k in found:
                found[k][1].append(rays)
            else:
                found[k] = (kind, [rays])
        elements = []
        for k in sorted(found):
            kind, ray_list = found[k]
            rays = ray_list[0] if len(ray_list) == 1 else _dedupe(np.concatenate(ray_list), merge)
            point = self._point(kind, k[1], k[2], R, t, VG)
            elements.append(ContactElement(kind, k[1], k[2], point, rays))
        return ContactState(tuple(elements), touching)

    def _batch_vertex_face(
        self,
        cands: dict[tuple[Feature, Feature], None],
        found: dict[tuple[str, Feature, Feature], tuple[ContactKind, list[FloatArray]]],
        R: FloatArray,
        sin_tol: float,
    ) -> None:
        """Vectorised VF test for convex G vertices on E faces (removed from ``cands``).

        Same result as the general path's fast path: the face normal n is the separating
        normal iff every edge direction of the vertex's tangent cone has ``d . n >= -sin``.
        """
        g, e = self._g, self._e
        simple = [
            (gf, ef) for gf, ef in cands if gf[0] == "v" and ef[0] == "f" and len(g.cones(gf)) == 1
        ]
        if len(simple) < 8:
            return
        rays = [g.cones(gf)[0].rays for gf, _ in simple]
        counts = np.array([len(r) for r in rays], dtype=np.int64)
        flat = np.concatenate(rays) @ R.T
        fids = np.array([ef[1] for _, ef in simple], dtype=np.int64)
        normals = e.poly.face_normals[fids]
        dots = np.einsum("ij,ij->i", flat, np.repeat(normals, counts, axis=0))
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        ok = np.minimum.reduceat(dots, starts) >= -sin_tol
        for (gf, ef), good, n in zip(simple, ok.tolist(), normals, strict=True):
            del cands[(gf, ef)]
            if good:
                found[("VF", gf, ef)] = (ContactKind.VF, [n[None, :].copy()])

    def _edge_pairs(
        self, VG: FloatArray, R: FloatArray, t: FloatArray, d: float, *, naive: bool
    ) -> tuple[IntArray, IntArray, FloatArray, FloatArray, FloatArray]:
        """(G edge, E edge) pairs within d: ids, distance, and closest points' parameters."""
        g, e = self._g, self._e
        A0, A1 = VG[g.edges[:, 0]], VG[g.edges[:, 1]]
        if naive:  # every pair, in chunks of about a million pairs
            step = max(1, 1_000_000 // max(e.ne, 1))
            parts = []
            for a in range(0, g.ne, step):
                ca = np.repeat(np.arange(a, min(a + step, g.ne), dtype=np.int64), e.ne)
                cb = np.tile(np.arange(e.ne, dtype=np.int64), len(ca) // max(e.ne, 1))
                rr = segment_segment_closest(A0[ca], A1[ca], e.E0[cb], e.E1[cb])
                m = rr.distance <= d
                parts.append((ca[m], cb[m], rr.distance[m], rr.s[m], rr.t[m]))
            if not parts:
                return _EMPTY_I, _EMPTY_I, _EMPTY_F, _EMPTY_F, _EMPTY_F
            cat = [np.concatenate(x) for x in zip(*parts, strict=True)]
            return cat[0], cat[1], cat[2], cat[3], cat[4]
        else:
            lo = np.minimum(A0, A1) - d
            hi = np.maximum(A0, A1) + d
            sel = np.flatnonzero(np.all((hi >= e.lo) & (lo <= e.hi), axis=1))
            if len(sel) == 0:
                return _EMPTY_I, _EMPTY_I, _EMPTY_F, _EMPTY_F, _EMPTY_F
            if len(sel) * e.ne <= 10 * _DENSE_LIMIT:  # box overlaps are cheap
                eb_lo = np.minimum(e.E0, e.E1)
                eb_hi = np.maximum(e.E0, e.E1)
                ov = np.all(
                    (hi[sel, None, :] >= eb_lo[None]) & (lo[sel, None, :] <= eb_hi[None]), axis=2
                )
                ia, ib = np.nonzero(ov)
                ia = sel[ia]
            else:
                _, _, _, _, te, eown, er = e.trees()
                if g.edge_samples is None:
                    g.trees()
                assert g.edge_samples is not None
                gpts, gown, gr = g.edge_samples
                pts = gpts @ R.T + t
                keep = np.isin(gown, sel)
                pts, gown = pts[keep], gown[keep]
                i, s = _pairs_from_ball(te.query_ball_point(pts, d + er + gr), gown)
                key = np.unique(i * e.ne + eown[s])
                ia, ib = key // e.ne, key % e.ne
        if len(ia) == 0:
            return _EMPTY_I, _EMPTY_I, _EMPTY_F, _EMPTY_F, _EMPTY_F
        r = segment_segment_closest(A0[ia], A1[ia], e.E0[ib], e.E1[ib])
        ok = r.distance <= d
        return (
            ia[ok].astype(np.int64),
            ib[ok].astype(np.int64),
            r.distance[ok],
            r.s[ok],
            r.t[ok],
        )

    def _ee_candidates(
        self,
        ee: tuple[IntArray, IntArray, FloatArray, FloatArray, FloatArray],
        near_g: _Near,
        near_e: _Near,
        R: FloatArray,
    ) -> list[tuple[int, int]]:
        """Non-parallel edge pairs within d whose endpoints do not touch the other edge."""
        ia, ib = ee[0], ee[1]
        if len(ia) == 0:
            return []
        g, e = self._g, self._e
        dg = R @ g.edge_dir[ia].T
        cross = np.linalg.norm(np.cross(dg.T, e.edge_dir[ib]), axis=1)
        nonpar = cross > math.sin(self.angle_tol)
        # Endpoint coverage: G vertex near E edge, E vertex near G edge.
        gv_e = set(zip(near_g.e[0].tolist(), near_g.e[1].tolist(), strict=True))
        ev_g = set(zip(near_e.e[0].tolist(), near_e.e[1].tolist(), strict=True))
        out = []
        for a, b, ok in zip(ia.tolist(), ib.tolist(), nonpar.tolist(), strict=True):
            if not ok:
                continue
            ga, gb = g.edges[a]
            ea, eb = e.edges[b]
            if (int(ga), b) in gv_e or (int(gb), b) in gv_e:
                continue
            if (int(ea), a) in ev_g or (int(eb), a) in ev_g:
                continue
            out.append((a, b))
        return out

    def _touching(
        self, near_g: _Near, near_e: _Near, eg: IntArray, ee_: IntArray
    ) -> frozenset[tuple[Feature, Feature]]:
        g, e = self._g, self._e
        # Primitive pairs, encoded as primitive ids (v: i, e: nv + i, f: nv + ne + i).
        pg: list[IntArray] = []
        pe: list[IntArray] = []
        for kind, off in (("v", 0), ("e", e.nv), ("f", e.nv + e.ne)):
            i, j, _ = getattr(near_g, kind)
            pg.append(i)
            pe.append(j + off)
        for kind, off in (("v", 0), ("e", g.nv), ("f", g.nv + g.ne)):
            i, j, _ = getattr(near_e, kind)
            pg.append(j + off)
            pe.append(i)
        pg.append(eg + g.nv)
        pe.append(ee_ + e.nv)
        P = np.concatenate(pg)
        Qe = np.concatenate(pe)
        if len(P) == 0:
            return frozenset()
        lp, lq = g.star_len[P], e.star_len[Qe]
        n = lp * lq
        k = np.repeat(np.arange(len(P)), n)
        o = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        a = g.star_data[g.star_ptr[P[k]] + o // lq[k]]
        b = e.star_data[e.star_ptr[Qe[k]] + o % lq[k]]
        n_e = e.nv + e.ne + e.nf
        code = np.unique(a * n_e + b)
        a, b = code // n_e, code % n_e
        return frozenset(zip(_decode(a, g.nv, g.ne), _decode(b, e.nv, e.ne), strict=True))

    def _point(
        self,
        kind: ContactKind,
        a: Feature,
        b: Feature,
        R: FloatArray,
        t: FloatArray,
        VG: FloatArray,
    ) -> FloatArray:
        return _element_point(self._g, self._e, kind, a[1], b[1], R, t, VG)


def _decode(codes: IntArray, nv: int, ne: int) -> list[Feature]:
    """Features of encoded primitive ids (v: i, e: nv + i, f: nv + ne + i)."""
    kind = (codes >= nv).astype(np.int64) + (codes >= nv + ne)
    idx = codes - np.array([0, nv, nv + ne], dtype=np.int64)[kind]
    return list(zip(np.array(_NAME)[kind].tolist(), idx.tolist(), strict=True))


def _project_on_segment(p: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Closest point of segment [a, b] to p (one point; cheaper than the broadcasting one)."""
    d = b - a
    dd = float(d @ d)
    t = min(1.0, max(0.0, float((p - a) @ d) / dd)) if dd > 0 else 0.0
    return np.asarray(a + t * d, dtype=np.float64)


def _element_point(
    g: _ModelData,
    e: _ModelData,
    kind: ContactKind,
    ga: int,
    eb: int,
    R: FloatArray,
    t: FloatArray,
    VG: FloatArray,
) -> FloatArray:
    """Contact point of an element in E (see ``docs/contacts.md``)."""
    if kind is ContactKind.VF:
        p = VG[ga]
        n = e.poly.face_normals[eb]
        return np.asarray(p - (n @ p - e.poly.face_offsets[eb]) * n)
    if kind is ContactKind.FV:
        q = e.V[eb]
        w = R @ g.poly.face_normals[ga]
        off = g.poly.face_offsets[ga] + w @ t
        return np.asarray(q - (w @ q - off) * w)
    if kind is ContactKind.EE:
        a0, a1 = VG[g.edges[ga, 0]], VG[g.edges[ga, 1]]
        r = segment_segment_closest(a0, a1, e.E0[eb], e.E1[eb])
        return np.asarray(0.5 * (r.p + r.q))
    if kind is ContactKind.VE:
        return _project_on_segment(VG[ga], e.E0[eb], e.E1[eb])
    if kind is ContactKind.EV:
        return _project_on_segment(e.V[eb], VG[g.edges[ga, 0]], VG[g.edges[ga, 1]])
    return np.asarray(0.5 * (VG[ga] + e.V[eb]))


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
    X_EG_seq: Iterable[npt.ArrayLike],
    *,
    threshold: float | None = None,
    angle_tol: float | None = None,
) -> list[ContactState]:
    """Contact states at each pose of ``X_EG_seq`` (4x4 poses of G in E, metres).

    Same parameters and result as :func:`find_contacts`, one state per pose; the per-model
    data (k-d trees, local cones) is computed once.
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
    cone intersection (the fast search batches the (edge, vertex) ones); used to test and
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
