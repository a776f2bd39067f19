"""Convex pieces of the simulator's scene (apo.sim.pieces): exact, inside, covering, shrunk."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mujoco")
pytest.importorskip("shapely")

from apo.errors import GeometryError
from apo.geometry import Polyhedron
from apo.shapes import block_with_square_hole, box, t_peg, u_block
from apo.sim.pieces import convex_pieces, shrink_piece
from apo.spatial import matrix_from_axis_angle

TOL = 1e-9  # metres: exact pieces may cross the surface by rounding only


def _inside_model(poly: Polyhedron, points: np.ndarray) -> np.ndarray:
    import trimesh

    mesh = trimesh.Trimesh(poly.vertices, np.concatenate(poly.face_triangles))
    return np.asarray(mesh.contains(points))


def _signed_distance(poly: Polyhedron, points: np.ndarray) -> np.ndarray:
    import trimesh

    mesh = trimesh.Trimesh(poly.vertices, np.concatenate(poly.face_triangles))
    return np.asarray(trimesh.proximity.signed_distance(mesh, points))  # > 0 inside


def _volume(poly: Polyhedron) -> float:
    import trimesh

    return float(trimesh.Trimesh(poly.vertices, np.concatenate(poly.face_triangles)).volume)


def _rotated(poly: Polyhedron, seed: int) -> Polyhedron:
    """The same solid turned and moved at random (the decomposition must not rely on axes)."""
    from apo.geometry import polyhedron_from_triangles

    rng = np.random.default_rng(seed)
    a = rng.normal(size=3)
    R = matrix_from_axis_angle(a / np.linalg.norm(a), rng.uniform(0, np.pi))
    V = poly.vertices @ R.T + rng.normal(scale=0.05, size=3)
    return polyhedron_from_triangles(V, np.concatenate(poly.face_triangles), name=poly.name)


@pytest.mark.parametrize(
    ("poly", "n"),
    [(t_peg(), 2), (u_block(slot_depth=0.07), 3), (box([0.1, 0.2, 0.3]), 1)],
    ids=["t_peg", "u_block", "box"],
)
def test_polyhedra_cut_into_the_expected_boxes(poly: Polyhedron, n: int) -> None:
    dec = convex_pieces(poly)
    assert len(dec.pieces) == n
    assert dec.method in ("exact", "convex")
    assert dec.tolerance == 0.0


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(
    "make", [t_peg, lambda: u_block(slot_depth=0.05), block_with_square_hole], ids=["t", "u", "sq"]
)
def test_exact_pieces_stay_inside_and_tile_the_volume(make, seed: int) -> None:
    poly = _rotated(make(), seed)
    dec = convex_pieces(poly)
    assert dec.method == "exact"
    V = np.concatenate([p.vertices for p in dec.pieces])
    # no piece crosses the original surface by more than TOL
    assert _signed_distance(poly, V).min() >= -TOL
    # the pieces do not overlap and fill the volume: volumes add up, sampled points covered
    assert sum(p.volume for p in dec.pieces) == pytest.approx(_volume(poly), rel=1e-9)
    rng = np.random.default_rng(seed)
    lo, hi = poly.vertices.min(0), poly.vertices.max(0)
    pts = rng.uniform(lo, hi, size=(4000, 3))
    inside = _inside_model(poly, pts)
    covered = np.zeros(len(pts), dtype=bool)
    for p in dec.pieces:
        covered |= p.contains(pts, tol=TOL)
    assert np.array_equal(covered, inside)


def test_coacd_fallback_states_its_tolerance() -> None:
    pytest.importorskip("coacd")
    poly = u_block(slot_depth=0.05)
    dec = convex_pieces(poly, method="coacd")
    assert dec.method == "coacd"
    assert len(dec.pieces) >= 3
    V = np.concatenate([p.vertices for p in dec.pieces])
    measured = max(0.0, -float(_signed_distance(poly, V).min()))
    assert dec.tolerance == pytest.approx(measured, abs=1e-9)
    assert dec.tolerance < 0.02 * poly.scale  # approximate, but close to the surface


def test_method_must_be_known() -> None:
    with pytest.raises(ValueError, match="method"):
        convex_pieces(t_peg(), method="magic")


@pytest.mark.parametrize("clearance", [0.0002, 0.00005])
def test_shrinking_moves_surface_faces_only(clearance: float) -> None:
    poly = t_peg()
    dec = convex_pieces(poly)
    for piece in dec.pieces:
        small = shrink_piece(piece, clearance)
        assert np.all(small.offsets == pytest.approx(piece.offsets - clearance * piece.surface))
        # every vertex of the shrunk piece is at least `clearance` inside each surface facet
        s = small.vertices @ piece.normals.T - piece.offsets
        assert np.all(s[:, piece.surface] <= -clearance + 1e-12)
        # ... and on the cut facets nothing moved (the stem still reaches the crossbar)
        cut = ~piece.surface
        if cut.any():
            assert np.max(s[:, cut], axis=0) == pytest.approx(np.zeros(cut.sum()), abs=1e-12)
    # the whole stem cross-section shrinks by 2 * clearance
    stem = min(dec.pieces, key=lambda p: p.vertices[:, 1].min())
    w = np.ptp(shrink_piece(stem, clearance).vertices[:, 0])
    assert w == pytest.approx(np.ptp(stem.vertices[:, 0]) - 2 * clearance, abs=1e-12)


def test_too_thin_piece_is_a_clear_error() -> None:
    piece = convex_pieces(box([0.001, 0.1, 0.1])).pieces[0]
    with pytest.raises(GeometryError, match="thinner than twice the clearance"):
        shrink_piece(piece, 0.0006)
