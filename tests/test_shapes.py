from __future__ import annotations

import numpy as np
import pytest

from apo import shapes
from apo.geometry import Polyhedron


def counts(p: Polyhedron) -> tuple[int, int, int, int]:
    return len(p.faces), len(p.edges), len(p.vertices), p.n_concave_edges


def euler(p: Polyhedron) -> int:
    """V - E + F minus the number of face holes (2 for a genus-0 solid)."""
    holes = sum(len(h) for h in p.face_holes)
    return len(p.vertices) - len(p.edges) + len(p.faces) - holes


def test_box() -> None:
    b = shapes.box([0.1, 0.2, 0.3], center=[1.0, 2.0, 3.0])
    assert counts(b) == (6, 12, 8, 0)
    assert b.volume == pytest.approx(0.006)
    assert np.allclose(b.vertices.min(axis=0), [0.95, 1.9, 2.85])
    assert np.allclose(b.vertices.max(axis=0), [1.05, 2.1, 3.15])


def test_prism_non_convex_star() -> None:
    ang = np.arange(10) * np.pi / 5
    rad = np.where(np.arange(10) % 2 == 0, 1.0, 0.4)
    star = np.column_stack([rad * np.cos(ang), rad * np.sin(ang)])
    p = shapes.prism(star[::-1], 0.5)  # clockwise input is accepted
    assert counts(p) == (12, 30, 20, 5)
    x, y = star[:, 0], star[:, 1]
    area = 0.5 * (np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))
    assert p.volume == pytest.approx(0.5 * area)
    assert euler(p) == 2


def test_t_peg_matches_the_authors_peg_proportions() -> None:
    p = shapes.t_peg()
    assert counts(p) == (10, 24, 16, 2)
    lo, hi = p.vertices.min(axis=0), p.vertices.max(axis=0)
    assert np.allclose(hi - lo, [0.070, 0.088, 0.035])
    assert np.allclose([lo[1], lo[2] + hi[2]], [0.0, 0.0])
    assert p.volume == pytest.approx((0.035 * 0.070 + 0.070 * 0.018) * 0.035)


def test_l_prism_and_u_block() -> None:
    assert counts(shapes.l_prism()) == (8, 18, 12, 1)
    u = shapes.u_block()
    assert counts(u) == (10, 24, 16, 2)
    assert euler(u) == 2


def test_block_with_square_hole() -> None:
    p = shapes.block_with_square_hole()
    assert counts(p) == (11, 24, 16, 8)
    assert euler(p) == 2
    assert np.allclose(p.vertices.min(axis=0), [-0.05, -0.05, 0.0])


def test_cylinder_is_large_and_merges_caps() -> None:
    c = shapes.cylinder(0.01, 0.02, sections=2500)
    assert sum(len(t) for t in c.face_triangles) >= 2 * 2500 + 2 * 2498
    assert counts(c) == (2502, 7500, 5000, 0)
    # The centre vertices of the cap fans are not corners.
    assert not np.any(np.all(np.isclose(c.vertices[:, :2], 0.0), axis=1))
    assert c.volume == pytest.approx(np.pi * 0.01**2 * 0.02, rel=1e-5)


def test_icosphere_has_over_ten_thousand_faces() -> None:
    s = shapes.icosphere(subdivisions=5, radius=0.02)
    assert counts(s) == (20480, 30720, 10242, 0)
    assert np.allclose(np.linalg.norm(s.vertices, axis=1), 0.02)
    assert s.volume == pytest.approx(4 / 3 * np.pi * 0.02**3, rel=2e-3)


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: shapes.prism([[0, 0], [1, 0]], 1.0), "shape"),
        (lambda: shapes.prism([[0, 0], [1, 0], [0, 1]], 0.0), "height"),
        (lambda: shapes.t_peg(stem_width=0.1, bar_width=0.05), "bar_width"),
        (lambda: shapes.u_block(slot_width=0.2), "slot"),
        (lambda: shapes.block_with_square_hole(hole=0.2), "pocket"),
        (lambda: shapes.cylinder(sections=2), "sections"),
        (lambda: shapes.icosphere(-1), "subdivisions"),
    ],
)
def test_bad_parameters(call: object, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        call()  # type: ignore[operator]
