"""Element classification: element kinds, grouping of piece pairs into elements, points.

Each pair of touching convex pieces with a non-empty cone of separating normals gives an
element whose kind (VF, FV, EE, VE, EV, VV) follows from the pieces' refined features; the
pairs of one element are merged and its contact point computed (``docs/contacts.md``).
"""

from __future__ import annotations

import numpy as np

from apo.arrays import unique
from apo.contact._arrays import _dedupe, _dot, _rotate
from apo.contact.elements import (
    _FEATURE_RANK,
    _KIND_LIST,
    _KIND_RANK,
    _KIND_TABLE,
    ContactElement,
    ContactKind,
)
from apo.contact.model_data import _ModelData
from apo.geometry import closest_point_on_segment, segment_segment_closest
from apo.typing import BoolArray, FloatArray, IntArray


def _classify(
    g: _ModelData,
    e: _ModelData,
    pg: IntArray,
    pe: IntArray,
    gkind: IntArray,
    gcode: IntArray,
    ekind: IntArray,
    ecode: IntArray,
) -> tuple[IntArray, IntArray, IntArray, IntArray, IntArray]:
    """Element kind of each pair of pieces from their refined features.

    ``pg``, ``pe`` are the pieces of each pair; ``gkind``, ``gcode``, ``ekind``, ``ecode`` the
    kind code and primitive code of the candidate features the pieces came from. A vertex
    candidate keeps its vertex when the refined feature pair has no kind. Returns the kind
    code (index into ``_KIND_LIST``, -1 for no element) and the refined features (kind code,
    index) of G and of E.
    """
    PG, PE = g.pieces, e.pieces
    fa_k, fa_i = PG.kind[pg].copy(), PG.number[pg].copy()
    fb_k, fb_i = PE.kind[pe].copy(), PE.number[pe].copy()
    kind = _KIND_TABLE[fa_k, fb_k]
    m = (kind < 0) & (gkind == 0)
    fa_k[m], fa_i[m] = 0, gcode[m]
    kind[m] = _KIND_TABLE[fa_k[m], fb_k[m]]
    m = (kind < 0) & (ekind == 0)
    fb_k[m], fb_i[m] = 0, ecode[m]
    kind[m] = _KIND_TABLE[fa_k[m], fb_k[m]]
    return kind, fa_k, fa_i, fb_k, fb_i


def _elements(
    g: _ModelData,
    e: _ModelData,
    merge_angle: float,
    frames: tuple[IntArray, FloatArray, FloatArray, FloatArray, int],
    items: tuple[IntArray, IntArray, IntArray, IntArray, IntArray, BoolArray],
    normals: tuple[IntArray, FloatArray, dict[int, FloatArray]],
) -> list[tuple[ContactElement, ...]]:
    """Return the elements of each frame, sorted by key, from the classified piece pairs.

    Parameters
    ----------
    g, e : _ModelData
        The models' data.
    merge_angle : float
        Rays of one element's pairs of pieces closer than this (rad) are merged.
    frames : tuple
        ``(fr, R, t, VG, n_frames)``: frame of each pair, rotations and translations of the
        frames, G's vertices in E per frame, number of frames.
    items : tuple
        ``(kind, fa_k, fa_i, fb_k, fb_i)`` of :func:`_classify`, one entry per pair, and
        ``valid``, the mask of the pairs with a kind and at least one separating normal.
    normals : tuple
        ``(count, rays, extra)`` of :func:`~apo.contact.separating_normals._cone_pairs`.
    """
    fr, R, t, VG, n_frames = frames
    kind, fa_k, fa_i, fb_k, fb_i, valid = items
    count, rays, extra = normals
    w = np.flatnonzero(valid)
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
                fr[w],
            )
        )
    ]
    if len(w) == 0:
        return [()] * n_frames
    cols = np.stack([fr[w], kind[w], fa_k[w], fa_i[w], fb_k[w], fb_i[w]])
    new = np.concatenate([[True], np.any(cols[:, 1:] != cols[:, :-1], axis=0)])
    starts = np.flatnonzero(new)
    ends = np.append(starts[1:], len(w))
    el_fr, el_kind = fr[w[starts]], kind[w[starts]]
    el_a, el_b = fa_i[w[starts]], fb_i[w[starts]]
    points = _points(g, e, el_fr, el_kind, el_a, el_b, R, t, VG)
    ga_code = g.offset[fa_k[w[starts]]] + el_a
    eb_code = e.offset[fb_k[w[starts]]] + el_b
    cnt = count.tolist()
    el_normals = [extra[i] if i in extra else rays[i, : cnt[i]] for i in w[starts].tolist()]
    w_list = w.tolist()
    for j in np.flatnonzero(ends - starts > 1).tolist():  # several piece pairs: merge
        rays_j = [
            extra[i] if i in extra else rays[i, : cnt[i]] for i in w_list[starts[j] : ends[j]]
        ]
        el_normals[j] = _dedupe(np.concatenate(rays_j), merge_angle)
    elements = list(
        map(
            ContactElement,
            map(_KIND_LIST.__getitem__, el_kind.tolist()),
            map(g.features.__getitem__, ga_code.tolist()),
            map(e.features.__getitem__, eb_code.tolist()),
            points,
            el_normals,
        )
    )
    bounds = np.searchsorted(el_fr, np.arange(n_frames + 1)).tolist()
    return [tuple(elements[bounds[k] : bounds[k + 1]]) for k in range(n_frames)]


def _points(
    g: _ModelData,
    e: _ModelData,
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
    out = np.empty((len(fr), 3))
    for code in unique(kind).tolist():
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
            out[m] = closest_point_on_segment(e.V[b], VG[f, g.edges[a, 0]], VG[f, g.edges[a, 1]])[0]
        else:
            out[m] = 0.5 * (VG[f, a] + e.V[b])
    return out
