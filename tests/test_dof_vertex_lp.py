"""The detaching-direction LP solved at its vertices (apo.dof._detaching_vertex) against HiGHS.

``min (sum_i a_i) . y`` s.t. ``a_i . y >= 1``: where the vertex solution proves its optimum
unique it must be HiGHS's solution (to rounding); where it cannot (ties, degenerate or
ill-conditioned bases, too many rows) it must refuse, and the direction is HiGHS's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from apo import dof
from apo.constants import tol


def _highs(a: np.ndarray) -> np.ndarray:
    """The LP solved by HiGHS, as ``_detaching_direction`` solved it before."""
    k, d = a.shape
    inf = float("inf")
    lp = dof._highs_lp(
        a.sum(axis=0), np.full(d, -inf), np.full(d, inf), a, np.ones(k), np.full(k, inf)
    )
    x = dof._solve_lp(lp, tol.cone)
    assert x is not None
    return x


def _random_lp(rng: np.random.Generator, kind: int) -> np.ndarray | None:
    """Rows ``a`` (k, d) of unit vectors with ``a y0 > 0`` for a random ``y0`` (feasible).

    ``kind`` 1: two equal rows; 2: a tie (below); 3: a row along ``y0``; 4: more rows than
    the enumeration takes.
    """
    d = int(rng.integers(2, 4))
    k = int(rng.integers(d + 1, 9)) if kind != 4 else dof._VERTEX_LP_ROWS + 1
    if kind == 2:
        return _tied_lp(rng, d)
    y0 = rng.normal(size=d)
    y0 /= np.linalg.norm(y0)
    a = rng.normal(size=(k, d))
    if kind == 1:
        a[1] = a[0]
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    a = np.where((a @ y0 < 0.0)[:, None], -a, a)
    if kind == 3:
        a[0] = y0
    if (np.abs(a @ y0) < 1e-3).any():
        return None
    return a


def _tied_lp(rng: np.random.Generator, d: int) -> np.ndarray:
    """A row ``n / 2`` and pairs of rows mirrored about ``n`` (``v . n > 0.6``): ``c`` is
    along ``n`` and the whole face ``n . y = 2`` near ``2 n`` is optimal, no single vertex."""
    n = rng.normal(size=d)
    n /= np.linalg.norm(n)
    rows = [0.5 * n]
    for _ in range(int(rng.integers(1, 4))):
        w = rng.normal(size=d)
        w -= (w @ n) * n
        w *= rng.uniform(0.1, 1.3) / np.linalg.norm(w)  # cos(v, n) > 0.6
        v = (n + w) / np.linalg.norm(n + w)
        rows += [v, 2.0 * (v @ n) * n - v]
    return np.array(rows)


@pytest.mark.parametrize("seed", [5, 6, 7])
def test_vertex_solution_is_highs_solution_or_refused(seed: int) -> None:
    rng = np.random.default_rng(seed)
    solved = refused = 0
    for trial in range(1200):
        a = _random_lp(rng, trial % 5)
        if a is None:
            continue
        x = _highs(a)
        y = dof._detaching_vertex(a, tol)
        if trial % 5 == 2:
            assert y is None, a  # a tie: refused
        if y is None:
            refused += 1
            continue
        solved += 1
        assert np.abs(y - x).max() <= 1e-11 * max(1.0, float(np.abs(x).max())), (a, x, y)
        assert (a @ y >= 1.0 - tol.cone).all()
    assert solved > 500
    assert refused > 400  # the ties and the rows beyond the enumeration's limit


def test_refuses_a_tied_optimum() -> None:
    # y2 >= 2 (a row of length 0.5, as a normal seen obliquely in the detaching subspace),
    # 0.6 y1 + 0.8 y2 >= 1 and -0.6 y1 + 0.8 y2 >= 1: c = (0, 2.1), and every (y1, 2) with
    # |y1| <= 1 is optimal: no vertex is the only optimum
    tied = np.array([[0.0, 0.5], [0.6, 0.8], [-0.6, 0.8]])
    assert dof._detaching_vertex(tied, tol) is None
    # the same with the first row tilted: the vertex on the side it leans to is the optimum
    unique = np.array([[0.1, 0.5], [0.6, 0.8], [-0.6, 0.8]])
    y = dof._detaching_vertex(unique, tol)
    assert y is not None and np.allclose(y, _highs(unique), rtol=0.0, atol=1e-12)


@pytest.mark.parametrize("seed", [11, 12])
def test_detaching_direction_equals_the_lp_direction(seed: int) -> None:
    """The whole ``_detaching_direction`` on random contact normals: the same as by HiGHS."""
    rng = np.random.default_rng(seed)
    checked = 0
    for _ in range(300):
        d = int(rng.integers(2, 4))
        t_det = np.linalg.qr(rng.normal(size=(3, 3)))[0][:d]  # orthonormal rows (d, 3)
        k = int(rng.integers(d + 1, 8))
        u0 = t_det.T @ rng.normal(size=d)
        f = rng.normal(size=(3, k))
        f /= np.linalg.norm(f, axis=0)
        f = np.where((u0 @ f < 0.0)[None, :], -f, f)
        a = f.T @ t_det.T
        if (np.abs(a @ (t_det @ u0)) < 1e-3).any():
            continue
        s_t = np.zeros(k, dtype=bool)
        got = dof._detaching_direction(f, s_t, t_det, tol)
        x = _highs(a)
        want = t_det.T @ x / np.linalg.norm(t_det.T @ x)
        assert np.abs(got - want).max() <= 1e-11
        checked += 1
    assert checked > 150


def test_a_unique_direction_needs_no_highs(monkeypatch: pytest.MonkeyPatch) -> None:
    """A DOF analysis whose direction LP has a unique vertex optimum does not call HiGHS."""
    calls: list[int] = []
    real = dof._solve_lp

    def counted(lp: object, feasibility: float) -> object:
        calls.append(1)
        return real(lp, feasibility)

    monkeypatch.setattr(dof, "_solve_lp", counted)
    # four vertex contacts of a block's bottom face on a plane, tilted: d_t = 2 with 4 rows
    up = np.array([[0.0, 0.0, 1.0]])
    side = np.array([[1.0, 0.0, 0.0]])
    pts = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
    contacts = [dof.ContactPoint(np.array(p, float), up) for p in pts]
    contacts.append(dof.ContactPoint(np.array([0.0, 0.5, 0.5]), side))
    res = dof.analyze(contacts)
    assert res.translation.detaching >= 1
    assert not calls


def test_the_real_demonstration_imports_no_highs(real_data_dir: Path, analyze_imports) -> None:
    """`apo analyze` of the 41 real frames: its one direction LP has a unique vertex optimum."""
    demo = real_data_dir / "peg_in_hole.pose.list"
    assert not analyze_imports(["analyze", str(demo)], "highspy")
