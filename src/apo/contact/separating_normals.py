"""Separating normals: extreme rays of ``N = T_G* ∩ (-T_E*)`` for pairs of convex pieces.

The scalar reference (:func:`_cone_pair_rays`, used by the naive search and for the rare
cases) and the vectorised common cases (a half-space on either side, edge-vertex, edge-edge,
vertex-vertex); rays within the merge angle of an exact face normal are snapped to it, so
noisy poses give the models' normals (``docs/contacts.md``).
"""

from __future__ import annotations

import math

import numpy as np

from apo.constants import tol
from apo.contact._arrays import (
    _EMPTY_3,
    _cross3,
    _cross_rows,
    _dedupe,
    _dot,
    _expand,
    _norm,
    _padded,
    _plane_basis,
    _rotate,
)
from apo.contact.model_data import _Cone, _ModelData, _Pieces
from apo.typing import BoolArray, FloatArray, IntArray

_CENTRE_WEIGHT = 1e-3
"""Tie-break weight (1/rad), not a tolerance: among the rays of a collapsed fan, prefer those
of E's model, then the one nearest the middle (angles < pi, so the weight never overrides)."""


def _arc_rays(
    ineq: FloatArray, Q: FloatArray, n_g: int, sin_tol: float, merge_angle: float
) -> FloatArray:
    """Rank-1 case of :func:`_separating_rays`: a 2D problem in the plane spanned by ``Q``.

    The rays are the one or two ends of the arc of unit vectors in the plane on the right
    side of every row of ``ineq``; ends closer than ``merge_angle`` are merged into one,
    preferring a ray bounded by the environment's rows (``ineq[n_g:]``).
    """
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
    if nm < tol.ray_sum_norm:
        return np.zeros((0, 3))
    mx, my = mx / nm, my / nm
    ang = [math.atan2(-sx * my + sy * mx, sx * mx + sy * my) for sx, sy, _ in cand]
    ilo = min(range(len(ang)), key=ang.__getitem__)
    ihi = max(range(len(ang)), key=ang.__getitem__)
    lo, hi = cand[ilo], cand[ihi]
    if ang[ihi] - ang[ilo] < merge_angle:
        if any(c[2] for c in cand):
            mid = 0.5 * (ang[ihi] + ang[ilo])
            score = [c[2] - _CENTRE_WEIGHT * abs(a - mid) for c, a in zip(cand, ang, strict=True)]
            pick = cand[max(range(len(score)), key=score.__getitem__)]
            r2 = np.array([pick[0], pick[1]])
        else:
            r2 = np.array([lo[0] + hi[0], lo[1] + hi[1]])
            r2 /= np.linalg.norm(r2)
        return np.asarray((r2 @ Q)[None, :], dtype=np.float64)
    return np.array([[lo[0], lo[1]], [hi[0], hi[1]]]) @ Q


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
    elif len(lin) == 2 and abs(float(lin[0] @ lin[1])) < tol.parallel_cos:
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
        return _arc_rays(ineq, Q, n_g, sin_tol, merge_angle)
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
        out = _dedupe(out, tol.ray_merge)
    return out


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
    *,
    counts_only: bool = False,
) -> tuple[IntArray, FloatArray]:
    """Vectorised rank-1 case of :func:`_separating_rays` and :func:`_snap_rays`.

    Each pair (G piece ``pg[k]`` at rotation ``R[k]``, E piece ``pe[k]``) has exactly one
    lineality direction (an edge on one side, a pointed cone on the other). Same result as
    the scalar code up to rounding. Returns the number of rays (0, 1 or 2) of each pair and
    the rays, shape (n, 2, 3), in E; with ``counts_only``, 1 for each pair with a ray and no
    rays.
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
    good = ok.any(axis=1) & (nm >= tol.ray_sum_norm)
    if counts_only:
        return good.astype(np.int64), np.zeros((n, 2, 3))
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
    off_centre = np.abs(ang - 0.5 * (a_hi + a_lo)[:, None])
    score = np.where(okp, 1.0 - _CENTRE_WEIGHT * off_centre, -np.inf)
    pick = cand[ar, np.argmax(score, axis=1)]
    both = lo + hi
    both /= np.maximum(np.hypot(both[:, 0], both[:, 1]), tol.division_floor)[:, None]
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
        # _dedupe(rays, tol.ray_merge): the second ray joins the first iff r0 . r1 >= cos(ray_merge)
        r0, r1 = out[two, 0], out[two, 1]
        same = _dot(r0, r1) >= math.cos(tol.ray_merge)
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
    *,
    counts_only: bool = False,
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
    solved = (np.abs(_dot(l0, l1)) < tol.parallel_cos) & (nu > sin_tol)
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
    if not counts_only:
        count, rays = _snap_batch(PG, PE, pg, pe, R, rays, count, merge_angle)
    return np.where(solved, count, 0), rays, solved


def _pointed_candidates(
    PG: _Pieces, PE: _Pieces, pg: IntArray, pe: IntArray, R: FloatArray, sin_tol: float
) -> tuple[FloatArray, BoolArray, IntArray]:
    """Candidate rays of the rank-0 case for all pairs at once (both pieces pointed).

    The cross products of pairs of rows, both signs, shape (n, c, 3); which are on the right
    side of every row (n, c); and their priorities (c,) for :func:`_dedupe` (rows of E's).
    """
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
    return cr, ok, prio


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

    The candidate rays (:func:`_pointed_candidates`) are found for all pairs at once; the
    greedy merge (:func:`_dedupe`) and the snapping (:func:`_snap_rays`) of each pair's few
    candidates are the scalar ones. Returns the rays of each pair before snapping, in E.
    """
    cr, ok, prio = _pointed_candidates(PG, PE, pg, pe, R, sin_tol)
    out = []
    for i in range(len(pg)):
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


def _half_space_rays(
    PG: _Pieces,
    PE: _Pieces,
    pg: IntArray,
    pe: IntArray,
    R: FloatArray,
    side: str,
    sin_tol: float,
    merge_angle: float,
    *,
    counts_only: bool = False,
) -> tuple[IntArray, FloatArray]:
    """Vectorised pairs where one piece is a half-space: its normal is the only candidate.

    ``side`` "e": E's piece is the half-space, its outward normal (exact in E) separates if
    G's rays are on its side and G's lineality in its plane. ``side`` "g": G's piece is the
    half-space, minus its outward normal (rotated by ``R[k]``) separates if E's rays are on
    the other side and E's lineality in the plane; it is then snapped to E's exact normal
    within the merge angle. Returns the count (0 or 1) and the rays (n, 2, 3) of each pair.
    """
    n = len(pg)
    count = np.zeros(n, dtype=np.int64)
    rays = np.zeros((n, 2, 3))
    if side == "e":
        nrm = PE.normals[PE.norm_ptr[pe]]
        P, pk, sign, rot = PG, pg, 1.0, True
    else:
        nrm = -_rotate(R, PG.normals[PG.norm_ptr[pg]])
        P, pk, sign, rot = PE, pe, -1.0, False
    bad = np.zeros(n, dtype=bool)
    j, idx, _ = _expand(P.ray_ptr[pk], P.nrays[pk])
    v = _rotate(R[j], P.rays[idx]) if rot else P.rays[idx]
    bad[j[sign * _dot(v, nrm[j]) < -sin_tol]] = True
    j, idx, _ = _expand(P.lin_ptr[pk], P.nlin[pk])
    v = _rotate(R[j], P.lin[idx]) if rot else P.lin[idx]
    bad[j[np.abs(_dot(v, nrm[j])) > sin_tol]] = True
    k = np.flatnonzero(~bad)
    count[k] = 1
    rays[k, 0] = nrm[k]
    if side == "g" and len(k) and not counts_only:
        count[k], rays[k] = _snap_batch(PG, PE, pg[k], pe[k], R[k], rays[k], count[k], merge_angle)
    return count, rays


def _cone_pairs(
    g: _ModelData,
    e: _ModelData,
    angle_tol: float,
    pg: IntArray,
    pe: IntArray,
    R: FloatArray,
    *,
    naive: bool,
    counts_only: bool = False,
) -> tuple[IntArray, FloatArray, dict[int, FloatArray]]:
    """Separating normals of each pair of pieces (G piece ``pg[k]`` at ``R[k]``, ``pe[k]``).

    Returns the number of rays of each pair, the rays (n, 2, 3) of the pairs solved
    vectorised, and the rays of the others (by pair index). The naive search solves every
    pair with the scalar :func:`_cone_pair_rays`. With ``counts_only`` the count is only
    right as to whether it is zero (the rays of the vectorised cases are not snapped nor
    merged, which never empties a cone), and the rays are left out.
    """
    sin_tol = math.sin(angle_tol)
    merge = tol.ray_merge_factor * angle_tol
    n = len(pg)
    count = np.zeros(n, dtype=np.int64)
    rays = np.zeros((n, 2, 3))
    extra: dict[int, FloatArray] = {}
    if naive:
        scalar = np.ones(n, dtype=bool)
    else:
        scalar = _vectorised_cases(
            g, e, pg, pe, R, (sin_tol, merge), (count, rays, extra), counts_only
        )
    for i in np.flatnonzero(scalar).tolist():
        r = _cone_pair_rays(
            g.piece_list[int(pg[i])], e.piece_list[int(pe[i])], R[i], sin_tol, merge
        )
        if len(r):
            count[i] = len(r)
            extra[i] = r
    return count, rays, extra


def _vectorised_cases(
    g: _ModelData,
    e: _ModelData,
    pg: IntArray,
    pe: IntArray,
    R: FloatArray,
    tols: tuple[float, float],
    out: tuple[IntArray, FloatArray, dict[int, FloatArray]],
    counts_only: bool,
) -> BoolArray:
    """Solve the common cases of :func:`_cone_pairs` into ``out`` (count, rays, extra).

    Returns the mask of the pairs left to the scalar code.
    """
    PG, PE = g.pieces, e.pieces
    sin_tol, merge = tols
    count, rays, extra = out
    lg, le = PG.nlin[pg], PE.nlin[pe]
    half_e = le == 2  # E's piece is a half-space: its outward normal (exact in E)
    half_g = ~half_e & (lg == 2)  # G's piece is one: minus its outward normal, snapped
    arc = (lg + le) == 1
    edges = (lg == 1) & (le == 1)
    pointed = (lg == 0) & (le == 0)
    scalar: BoolArray = ~(half_e | half_g | arc | edges | pointed)
    opt = {"counts_only": counts_only}
    for sel, side in ((half_e, "e"), (half_g, "g")):
        k = np.flatnonzero(sel)
        if len(k):
            count[k], rays[k] = _half_space_rays(
                PG, PE, pg[k], pe[k], R[k], side, sin_tol, merge, **opt
            )
    k = np.flatnonzero(arc)
    if len(k):
        count[k], rays[k] = _arc_rays_batch(PG, PE, pg[k], pe[k], R[k], sin_tol, merge, **opt)
    k = np.flatnonzero(edges)
    if len(k):
        c, r, solved = _edge_edge_rays_batch(PG, PE, pg[k], pe[k], R[k], sin_tol, merge, **opt)
        count[k], rays[k] = c, r
        scalar[k[~solved]] = True
    k = np.flatnonzero(pointed)
    if len(k) and counts_only:
        count[k] = _pointed_candidates(PG, PE, pg[k], pe[k], R[k], sin_tol)[1].any(axis=1)
    elif len(k):
        for i, r in zip(
            k.tolist(),
            _pointed_rays_batch(PG, PE, pg[k], pe[k], R[k], sin_tol, merge),
            strict=True,
        ):
            if len(r):
                r = _snap_rays(r, g.piece_list[int(pg[i])], e.piece_list[int(pe[i])], R[i], merge)
                count[i] = len(r)
                extra[i] = r
    return scalar
