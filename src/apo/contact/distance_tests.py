"""Distance tests: the features of one model within the threshold of the other's.

The features near each vertex (exact point-vertex, point-segment and point-triangle
distances, pruned by bounding spheres, or by k-d trees over samples for large models), the
pairs of edges within the threshold, and every touching (G feature, E feature) pair.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from apo.arrays import unique
from apo.constants import tol
from apo.contact._arrays import (
    _EMPTY_F,
    _EMPTY_I,
    _dot,
    _norm,
    _pairs_from_ball,
    _sq_dist,
    _sq_dist_slack,
)
from apo.contact.elements import Feature
from apo.contact.model_data import _ModelData
from apo.geometry import closest_point_on_segment, point_face_distance, segment_segment_closest
from apo.typing import FloatArray, IntArray

# Bounding-sphere tests use radius * this: rounding never drops a pair within the threshold.
_SPHERE_MARGIN = 1.0 + tol.sphere_margin

#: Candidate pairs whose exact distance (point-segment, point-triangle, segment-segment) is
#: computed at once: each test's working arrays take 100-260 bytes a pair, and a block of
#: frames all in contact has some 20,000 of them (10 MB at once; docs/recognition.md,
#: "Session 9: memory"). The tests are row by row: the same distances in any chunks.
ROW_CHUNK = 8192


def _chunked_distances(n: int, dist_of: Callable[[slice], FloatArray]) -> FloatArray:
    """``dist_of(rows)`` of ``ROW_CHUNK`` rows at a time, joined: shape (n,)."""
    if n <= ROW_CHUNK:
        return dist_of(slice(0, n))
    out = np.empty(n)
    for a in range(0, n, ROW_CHUNK):
        rows = slice(a, min(n, a + ROW_CHUNK))
        out[rows] = dist_of(rows)
    return out


def _triangle_terms(
    p: FloatArray, a: FloatArray, b: FloatArray, c: FloatArray
) -> tuple[FloatArray, FloatArray, tuple[FloatArray, ...], tuple[FloatArray, ...]]:
    """Edges ``ab``, ``ac``, the dot products ``d1 .. d6`` and ``va, vb, vc`` of Ericson's test."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    bp = p - b
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    cp = p - c
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    return ab, ac, (d1, d2, d3, d4, d5, d6), (va, vb, vc)


def _point_triangle_distance(
    p: FloatArray, a: FloatArray, b: FloatArray, c: FloatArray
) -> FloatArray:
    """Distance from points to triangles, row-wise (Ericson, RTCD 5.1.5).

    Each row's closest point is computed only by the formula of its Voronoi region (the
    last region of Ericson's order that holds), with the same arithmetic as evaluating every
    formula at every row and selecting: the same distances bit for bit, in fewer passes
    (``tests/test_contact_fast_paths.py`` keeps that form as the reference).
    """
    ab, ac, (d1, d2, d3, d4, d5, d6), (va, vb, vc) = _triangle_terms(p, a, b, c)
    region = np.zeros(len(p), dtype=np.int8)  # 0: inside the face
    region[(va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)] = 1  # edge bc
    region[(vb <= 0) & (d2 >= 0) & (d6 <= 0)] = 2  # edge ac
    region[(d6 >= 0) & (d5 <= d6)] = 3  # vertex c
    region[(vc <= 0) & (d1 >= 0) & (d3 <= 0)] = 4  # edge ab
    region[(d3 >= 0) & (d4 <= d3)] = 5  # vertex b
    region[(d1 <= 0) & (d2 <= 0)] = 6  # vertex a
    q = np.empty_like(p)
    with np.errstate(divide="ignore", invalid="ignore"):
        i = np.flatnonzero(region == 0)
        den = va[i] + vb[i] + vc[i]
        v = np.where(den != 0, vb[i] / den, 0.0)
        w = np.where(den != 0, vc[i] / den, 0.0)
        q[i] = a[i] + v[:, None] * ab[i] + w[:, None] * ac[i]
        i = np.flatnonzero(region == 1)
        e43, e56 = d4[i] - d3[i], d5[i] - d6[i]
        q[i] = b[i] + (e43 / (e43 + e56))[:, None] * (c[i] - b[i])
        i = np.flatnonzero(region == 2)
        q[i] = a[i] + (d2[i] / (d2[i] - d6[i]))[:, None] * ac[i]
        i = np.flatnonzero(region == 4)
        q[i] = a[i] + (d1[i] / (d1[i] - d3[i]))[:, None] * ab[i]
    for k, corner in ((3, c), (5, b), (6, a)):
        i = np.flatnonzero(region == k)
        q[i] = corner[i]
    return _norm(p - q)


class _Near(NamedTuple):  # not a dataclass: no methods made at import
    """Pairs (query point i, feature j, distance) within the threshold, per feature kind."""

    v: tuple[IntArray, IntArray, FloatArray]
    e: tuple[IntArray, IntArray, FloatArray]
    f: tuple[IntArray, IntArray, FloatArray]


def _near_features(
    md: _ModelData,
    pts: FloatArray,
    d: float,
    *,
    naive: bool = False,
    dense_limit: int,
) -> _Near:
    """Features of ``md`` within ``d`` of each point of ``pts`` (points in md's frame).

    Pairs of each kind are sorted by (point, feature). All pairs are tested when there are
    at most ``dense_limit`` of them, else the k-d trees prune.
    """
    if naive:
        return _near_features_naive(md, pts, d)
    inside = np.all((pts >= md.lo - d) & (pts <= md.hi + d), axis=1)
    rows = np.flatnonzero(inside).astype(np.int64)
    if len(rows) == 0:
        e3 = (_EMPTY_I, _EMPTY_I, _EMPTY_F)
        return _Near(e3, e3, e3)
    Q = pts[rows]
    dense = len(Q) * max(md.nv, len(md.TA)) <= dense_limit
    # vertices
    if dense:
        slack = _sq_dist_slack(Q, md.V)
        ii, jj = np.nonzero(_sq_dist(Q, md.V) <= (d * _SPHERE_MARGIN) ** 2 + slack)
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
        r2 = ((md.E_half + d) * _SPHERE_MARGIN) ** 2 + slack
        ii, jj = np.nonzero(_sq_dist(Q, md.E_mid) <= r2)
    else:
        tv, tt, town, tr, te, eown, er = md.trees()
        i, s = _pairs_from_ball(te.query_ball_point(Q, d + er), np.arange(len(Q)))
        key = np.unique(i * md.ne + eown[s])
        ii, jj = key // md.ne, key % md.ne

    def seg_dist(k: slice) -> FloatArray:
        q = Q[ii[k]]
        cl, _ = closest_point_on_segment(q, md.E0[jj[k]], md.E1[jj[k]])
        return _norm(q - cl)

    dist = _chunked_distances(len(ii), seg_dist)
    ok = dist <= d
    ee = (rows[ii[ok]], jj[ok].astype(np.int64), dist[ok])
    # faces via triangles, pre-filtered by the plane distance (and bounding spheres)
    if dense:
        near = np.abs(Q @ md.tri_n.T - md.tri_off[None, :]) <= d
        near &= _sq_dist(Q, md.tri_c) <= ((md.tri_r + d) * _SPHERE_MARGIN) ** 2 + slack
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
    return _Near(vv, ee, _nearest_face(md, Q, rows, ii, tt_, d))


def _nearest_face(
    md: _ModelData, Q: FloatArray, rows: IntArray, ii: IntArray, tt_: IntArray, d: float
) -> tuple[IntArray, IntArray, FloatArray]:
    """(point, face, distance) within ``d`` from candidate (point, triangle) pairs."""

    def tri_dist(k: slice) -> FloatArray:
        t = tt_[k]
        return _point_triangle_distance(Q[ii[k]], md.TA[t], md.TB[t], md.TC[t])

    dist = _chunked_distances(len(ii), tri_dist)
    ok = dist <= d
    ii, ff, dist = ii[ok], md.tri_face[tt_[ok]], dist[ok]
    if len(ii) == 0:
        return _EMPTY_I, _EMPTY_I, _EMPTY_F
    key = ii * md.nf + ff
    if np.any(key[1:] < key[:-1]):  # pairs not by (point, triangle): sort them
        order = np.argsort(key, kind="stable")
        key, dist = key[order], dist[order]
    # pairs come by (point, triangle) and a face's triangles are consecutive: each
    # (point, face) is a run of keys; its distance is the run's least
    first = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
    dist = np.minimum.reduceat(dist, first)
    key = key[first]
    return rows[key // md.nf], key % md.nf, dist


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


class _NearF(NamedTuple):
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


def _edge_pairs(
    g: _ModelData,
    e: _ModelData,
    VG: FloatArray,
    R: FloatArray,
    t: FloatArray,
    d: float,
    *,
    naive: bool,
    limit: int,
) -> tuple[IntArray, IntArray, IntArray]:
    """(frame, G edge, E edge) of the edge pairs within d, sorted."""
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
        lo_s, hi_s = lo[sel].T, hi[sel].T
        eb_lo, eb_hi = e.E_lo.T, e.E_hi.T
        ov = (hi_s[0][:, None] >= eb_lo[0]) & (lo_s[0][:, None] <= eb_hi[0])
        for k in (1, 2):
            ov &= hi_s[k][:, None] >= eb_lo[k]
            ov &= lo_s[k][:, None] <= eb_hi[k]
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

    def pair_dist(k: slice) -> FloatArray:
        i, j = ia[k], ib[k]
        dist: FloatArray = segment_segment_closest(A0[i], A1[i], e.E0[j], e.E1[j]).distance
        return dist

    ok = _chunked_distances(len(ia), pair_dist) <= d
    ia, ib = ia[ok].astype(np.int64), ib[ok].astype(np.int64)
    return ia // g.ne, ia % g.ne, ib


def _touching(
    g: _ModelData,
    e: _ModelData,
    near_g: _NearF,
    near_e: _NearF,
    ee: tuple[IntArray, IntArray, IntArray],
    n_frames: int,
) -> list[frozenset[tuple[Feature, Feature]]]:
    """Every (G feature, E feature) pair within the threshold, per frame."""
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
    code = _touching_codes(g, e, F, P, Qe)
    fr, code = np.divmod(code, g.n_all * e.n_all)
    bounds = np.searchsorted(fr, np.arange(n_frames + 1)).tolist()
    pairs = _pair_table(g, e, code)
    out: list[frozenset[tuple[Feature, Feature]]] = []
    for f in range(n_frames):
        if same_as[f] != f:
            out.append(out[same_as[f]])
            continue
        lo, hi = bounds[f], bounds[f + 1]
        out.append(frozenset(map(pairs.__getitem__, code[lo:hi].tolist())))
    return out


#: Feature pairs (a primitive pair's stars crossed) expanded at once by
#: :func:`_touching_codes`: some 60 bytes each, and the frames of many states in contact
#: expand to hundreds of thousands (docs/recognition.md, "Session 9: memory").
TOUCH_ROWS = 32768


def _touching_codes(
    g: _ModelData, e: _ModelData, F: IntArray, P: IntArray, Qe: IntArray
) -> IntArray:
    """Sorted distinct codes ``(frame * g.n_all + a) * e.n_all + b`` of the touching pairs.

    Each primitive pair ``(P, Qe)`` at frame ``F`` gives every pair of a feature of P's star
    (``a``) and of Qe's (``b``); the pairs are expanded about ``TOUCH_ROWS`` at a time (the
    distinct codes of all chunks' distinct codes are those of all the pairs).
    """
    lp, lq = g.star_len[P], e.star_len[Qe]
    n = lp * lq
    ends = np.cumsum(n)
    cuts = [0, *np.searchsorted(ends, np.arange(TOUCH_ROWS, int(ends[-1]), TOUCH_ROWS)).tolist()]
    parts = []
    for r0, r1 in zip(cuts, [*cuts[1:], len(P)], strict=True):
        if r1 <= r0:
            continue
        m = n[r0:r1]
        k = np.repeat(np.arange(r0, r1), m)
        o = np.arange(int(m.sum())) - np.repeat(np.cumsum(m) - m, m)
        a = g.star_data[g.star_ptr[P[k]] + o // lq[k]]
        b = e.star_data[e.star_ptr[Qe[k]] + o % lq[k]]
        parts.append(unique((F[k] * g.n_all + a) * e.n_all + b))
    return parts[0] if len(parts) == 1 else unique(np.concatenate(parts))


def _pair_table(
    g: _ModelData, e: _ModelData, codes: IntArray
) -> dict[int, tuple[Feature, Feature]]:
    """Return the feature pair of each code ``a * e.n_all + b``, one tuple per pair of models.

    Every touching set of the pair of models holds the same tuple for the same pair (a
    long noisy demonstration has hundreds of observed states of ~100 pairs each).
    """
    pairs = g.pairs.setdefault(e, {})
    gf, ef = g.features, e.features
    for c in unique(codes).tolist():
        if c not in pairs:
            a, b = divmod(c, e.n_all)
            pairs[c] = (gf[a], ef[b])
    return pairs
