"""Fast paths of the contact search's distance tests give the reference numbers bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from apo import synthetic
from apo.contact import ContactFinder
from apo.contact._arrays import _norm
from apo.contact.distance_tests import (
    _nearest_face,
    _point_triangle_distance,
    _triangle_terms,
)
from apo.contact.model_data import _model_data
from apo.contact.search import _group_sets, block_sets, merge_sets
from apo.typing import FloatArray


def point_triangle_distance_all(
    p: FloatArray, a: FloatArray, b: FloatArray, c: FloatArray
) -> FloatArray:
    """Every formula at every row, then the region selected (the form before the fast path)."""
    ab, ac, (d1, d2, d3, d4, d5, d6), (va, vb, vc) = _triangle_terms(p, a, b, c)
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


def nearest_face_lexsort(md, Q, rows, ii, tt_, d):  # type: ignore[no-untyped-def]
    """The (point, face) pairs by sorting every candidate (the form before the fast path)."""
    dist = point_triangle_distance_all(Q[ii], md.TA[tt_], md.TB[tt_], md.TC[tt_])
    ok = dist <= d
    ii, ff, dist = ii[ok], md.tri_face[tt_[ok]], dist[ok]
    key = ii * md.nf + ff
    order = np.lexsort((dist, key))
    key, dist = key[order], dist[order]
    first = np.concatenate([[True], key[1:] != key[:-1]])
    key, dist = key[first], dist[first]
    return rows[key // md.nf], key % md.nf, dist


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_point_triangle_distance_by_region_is_the_all_formulas_form(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 4000
    a, b, c = (rng.normal(size=(n, 3)) for _ in range(3))
    c[: n // 4] = a[: n // 4] + (b - a)[: n // 4] * rng.uniform(size=(n // 4, 1))  # collinear
    b[n // 4 : n // 2] = a[n // 4 : n // 2]  # two corners equal
    p = rng.normal(size=(n, 3)) * rng.choice([0.01, 1.0, 10.0], size=(n, 1))
    p[-50:] = a[-50:]  # on a corner
    fast = _point_triangle_distance(p, a, b, c)
    assert fast.tobytes() == point_triangle_distance_all(p, a, b, c).tobytes()
    # every region is met
    tri = np.stack([a, b, c], axis=1)
    inside = np.abs(fast - np.min(np.linalg.norm(tri - p[:, None], axis=2), axis=1)) > 1e-9
    assert inside.any() and (~inside).any()


@pytest.mark.parametrize(("seed", "sigma"), [(5101, 1.0), (5102, 2.5), (5103, 0.5)])
def test_nearest_face_runs_are_the_sorted_minima(seed: int, sigma: float) -> None:
    d = synthetic.add_noise(synthetic.random_variant(seed), sigma_mm=sigma, sigma_deg=sigma,
                            seed=seed)  # fmt: skip
    finder = ContactFinder(d.grasped, d.environment, threshold=4.0 * sigma * 1e-3)
    g, e = _model_data(d.grasped), _model_data(d.environment)
    R, t = d.X_EG[:, :3, :3], d.X_EG[:, :3, 3]
    Q = (g.V @ R.transpose(0, 2, 1) + t[:, None, :]).reshape(-1, 3)  # G's vertices in E
    rows = np.arange(len(Q), dtype=np.int64)
    near = np.abs(Q @ e.tri_n.T - e.tri_off[None, :]) <= 2 * finder.threshold
    ii, tt_ = np.nonzero(near)
    got = _nearest_face(e, Q, rows, ii, tt_, finder.threshold)
    want = nearest_face_lexsort(e, Q, rows, ii, tt_, finder.threshold)
    assert len(want[0]) > 20
    for x, y in zip(got, want, strict=True):
        assert x.tobytes() == y.tobytes()
    # pairs not by (point, triangle) are sorted first
    perm = np.random.default_rng(seed).permutation(len(ii))
    got = _nearest_face(e, Q, rows, ii[perm], tt_[perm], finder.threshold)
    for x, y in zip(got, want, strict=True):
        assert np.array_equal(x, y)


def group_sets_sorted(frame: np.ndarray, code: np.ndarray, n: int) -> tuple[np.ndarray, ...]:
    """Labels by sorting the rows (``np.unique(axis=0)``; the form before the dict)."""
    cnt = np.bincount(frame, minlength=n)
    M = np.full((n, int(cnt.max(initial=0)) + 1), -1, dtype=np.int64)
    M[:, 0] = cnt
    M[frame, np.arange(len(frame)) - (np.cumsum(cnt) - cnt)[frame] + 1] = code
    _, first, inverse = np.unique(M, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[inverse.ravel()], first[order]


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_group_sets_labels_by_first_appearance_like_sorting(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 400))
    sets = [np.unique(rng.integers(0, 9, size=rng.integers(0, 4))) for _ in range(12)]
    pick = rng.integers(0, len(sets), size=n)
    frame = np.concatenate([np.full(len(sets[p]), f) for f, p in enumerate(pick)]).astype(np.int64)
    code = np.concatenate([sets[p] for p in pick]).astype(np.int64)
    got = _group_sets(frame, code, n)
    want = group_sets_sorted(frame, code, n)
    for x, y in zip(got, want, strict=True):
        assert np.array_equal(x, y)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_sets_merged_block_by_block_label_like_all_rows_at_once(seed: int) -> None:
    """Frames keyed a block at a time (``block_sets``, the rows dropped) and the blocks'
    keys merged in order (``merge_sets``): the labels and first frames of sorting all the
    rows at once, whatever the blocks, also with codes beyond int32 (keys always int64)."""
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(1, 400))
    big = int(rng.integers(0, 2)) * (1 << 40)  # codes past int32 in half the runs
    sets = [np.unique(rng.integers(0, 9, size=rng.integers(0, 4))) + big for _ in range(12)]
    pick = rng.integers(0, len(sets), size=n)
    frame = np.concatenate([np.full(len(sets[p]), f) for f, p in enumerate(pick)]).astype(np.int64)
    code = np.concatenate([sets[p] for p in pick]).astype(np.int64)
    want = group_sets_sorted(frame, code, n)
    cuts = np.unique(np.concatenate([[0, n], rng.integers(0, n + 1, size=int(rng.integers(0, 9)))]))
    blocks = []
    for a, b in zip(cuts[:-1].tolist(), cuts[1:].tolist(), strict=True):
        rows = (frame >= a) & (frame < b)
        blocks.append(block_sets(frame[rows] - a, code[rows], b - a))
        assert blocks[-1].local.dtype == np.int32 and len(blocks[-1].local) == b - a
    for x, y in zip(merge_sets(blocks, n), want, strict=True):
        assert np.array_equal(x, y)
    with pytest.raises(ValueError, match="cover"):
        merge_sets(blocks, n + 1)
