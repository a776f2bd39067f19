"""Candidate features: the (G feature, E feature) pairs that may form contact elements.

Each vertex within the threshold of the other model is snapped to the lowest-dimensional
(then nearest) feature there; each pair of non-parallel edges within the threshold whose
endpoints touch no edge of the other is a candidate too (paper 4.3.1, ``docs/contacts.md``).
"""

from __future__ import annotations

import math

import numpy as np

from apo.contact._arrays import _EMPTY_I, _cross_rows, _member, _norm, _rotate
from apo.contact.distance_tests import _NearF
from apo.contact.model_data import _ModelData
from apo.typing import BoolArray, FloatArray, IntArray


def _candidates(
    g: _ModelData,
    e: _ModelData,
    angle_tol: float,
    near_g: _NearF,
    near_e: _NearF,
    ee: tuple[IntArray, IntArray, IntArray],
    R: FloatArray,
) -> tuple[IntArray, IntArray, IntArray, IntArray, IntArray]:
    """Candidate (G feature, E feature) pairs, as (frame, kind, primitive code) of each.

    Returns (frame, G kind code, G primitive code, E kind code, E primitive code). Each
    vertex snapped to its lowest-dimensional (then nearest) feature of the other
    model within the threshold, and the edge pairs of :func:`_ee_candidates`; in the
    order of the scalar search (G's vertices, E's vertices, edge pairs), duplicates
    dropped.
    """
    sg, se = _snap(near_g), _snap(near_e)
    keep = _ee_candidates(g, e, angle_tol, ee, near_g, near_e, R)
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


def _ee_candidates(
    g: _ModelData,
    e: _ModelData,
    angle_tol: float,
    ee: tuple[IntArray, IntArray, IntArray],
    near_g: _NearF,
    near_e: _NearF,
    R: FloatArray,
) -> BoolArray:
    """Mask of the edge pairs that are non-parallel and whose endpoints touch no edge."""
    fr, ia, ib = ee
    if len(ia) == 0:
        return np.zeros(0, dtype=bool)
    dg = _rotate(R[fr], g.edge_dir[ia])
    cross = _norm(_cross_rows(dg, e.edge_dir[ib]))
    keep: BoolArray = cross > math.sin(angle_tol)
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
