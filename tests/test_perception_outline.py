"""Two-sided outline rows of the projective ICP, and the static region's outline pixels.

A box seen face on has its sideways position set by its outline alone. The contour rows are
one-sided (a pixel gives a row only where the rendering and the observation put it on
opposite sides of the outline), so every pose whose outline passes between the same pixel
centres has no contour residual: the ICP stops anywhere in a band up to a pixel wide. The
outline rows take the observed edge half-way between an object pixel and its neighbour seen
past it, on both sides of the model's outline.
"""

from __future__ import annotations

import numpy as np
import pytest

from apo.perception.camera import Camera
from apo.perception.projective import FacePlanes, face_planes, projective_icp
from apo.perception.render import box_triangles, rasterize
from apo.spatial import pose_from_twist, transform_points

CAMERA = Camera(383.0, 383.0, 80.5, 60.3, 160, 120, 1e-4)  # D435-like: 1 px = 2.1 mm at 0.8 m


def _box_scene(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, object]:
    """A 50 x 40 x 20 mm box face on at 0.8 m, its edges within 3 deg of the pixel grid's
    (every row of pixels meets an edge at about the same place: the band is a whole pixel),
    before a wall 0.1 m behind; depth noise 0.3 mm. Returns the depth, the mask, X_CM and
    the faces."""
    rng = np.random.default_rng(seed)
    V, T = box_triangles((0.05, 0.04, 0.02))
    X = pose_from_twist(np.r_[0.0, 0.0, rng.uniform(-0.05, 0.05), rng.uniform(-0.01, 0.01, 2), 0.8])
    depth, _ = rasterize(transform_points(X, V), T, CAMERA)
    mask = depth > 0
    depth = np.where(mask, depth, 0.9) + rng.normal(0.0, 3e-4, depth.shape)
    return depth.astype(np.float32), mask, X, face_planes(V, T)


@pytest.mark.parametrize("seed", range(6))
def test_outline_rows_end_at_one_sideways_position(seed: int) -> None:
    # Started a pixel or less sideways of the true pose, the ICP with the outline rows ends
    # at one place (within 0.05 mm) whatever the start, within 0.4 px (0.84 mm) of the truth:
    # measured 0.01-0.73 mm, the edges' phase against the pixel grid (the same in every row)
    # unknown within a pixel. Contour rows alone, measured: the ends spread over up to 1.6 mm
    # (0.1 to 1.6 mm on these seeds), up to 1.2 mm off.
    depth, mask, X_true, faces = _box_scene(seed)
    rng = np.random.default_rng(100 + seed)
    sigma = np.full(depth.shape, 3e-4)
    ends = []
    for _ in range(5):
        start = X_true.copy()
        start[:2, 3] += rng.uniform(-2e-3, 2e-3, 2)
        res = projective_icp(depth, CAMERA, faces, start, mask=mask, sigma=sigma, outline=True)
        ends.append(res.X_CM[:2, 3] - X_true[:2, 3])
    e = np.array(ends) * 1e3
    assert np.ptp(e, axis=0).max() < 0.05 and np.abs(e).max() < 0.84, e.round(3)


def _soup(V: np.ndarray, T: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The mesh as an STL file stores it: each triangle its own three vertices, shuffled."""
    order = rng.permutation(len(T))
    return V[T[order]].reshape(-1, 3), np.arange(3 * len(T)).reshape(-1, 3)


def _models() -> list[tuple[np.ndarray, np.ndarray]]:
    from apo import synthetic
    from apo.perception.example import polyhedron_triangles

    out = [box_triangles((0.05, 0.04, 0.02))]
    for name in ("peg_in_hole_2d", "square_peg_in_hole"):
        demo = getattr(synthetic, name)(30)
        out += [polyhedron_triangles(demo.grasped), polyhedron_triangles(demo.environment)]
    return out


def _segments(faces: FacePlanes, edges: np.ndarray) -> set[tuple[tuple[float, ...], ...]]:
    """The edges as pairs of their ends' coordinates (in either order)."""
    V, E = faces.vertices.round(9), faces.edges[edges]
    return {tuple(sorted([tuple(V[a]), tuple(V[b])])) for a, b in E}


@pytest.mark.parametrize("seed", range(4))
def test_silhouette_edges_do_not_depend_on_shared_vertices(seed: int) -> None:
    # An STL file repeats each vertex per triangle. With the edges joined by vertex index,
    # every edge then had one triangle and every edge of a face turned to the camera (a
    # face's diagonal, the rim between a block's top and a side in view) was a silhouette
    # edge: on dev variant 205 (apo track reads STL files), the outline rows matched a
    # side face seen at 84 deg with the rim and moved the environment 0.26 mm.
    rng = np.random.default_rng(seed)
    for V, T in _models():
        mesh, soup = face_planes(V, T), face_planes(*_soup(np.asarray(V), np.asarray(T), rng))
        assert len(soup.edges) == len(mesh.edges) and (soup.edge_faces[:, 1] >= 0).all()
        for _ in range(5):
            twist = np.r_[rng.uniform(-np.pi, np.pi, 3), rng.uniform(-0.1, 0.1, 2), 0.6]
            X = pose_from_twist(twist)
            got = _segments(soup, soup.silhouette_edges(X))
            assert got == _segments(mesh, mesh.silhouette_edges(X))


@pytest.mark.parametrize("seed", range(3))
def test_projective_icp_is_the_same_on_a_triangle_soup(seed: int) -> None:
    # A box on a table seen from 55 deg above, one side face at 78-85 deg from its normal
    # (its depth steps from pixel to pixel like an outline): with the outline and contour
    # rows, the ICP ends at the same pose on the mesh and on the same triangles as an STL
    # file stores them. Before the edges were joined by the corners' coordinates, the
    # soup's rim between the top and that side was a silhouette edge, and the side's pixel
    # pairs pulled the box sideways: measured, the soup's ends 0.10, 0.11, 0.29 mm from the
    # truth against the mesh's 0.01, 0.01, 0.04 mm.
    from apo.perception.render import pose_looking_at

    rng = np.random.default_rng(seed)
    V, T = box_triangles((0.06, 0.05, 0.03))
    el, side = np.radians(55.0), np.radians(rng.uniform(78.0, 85.0))
    phi = np.arccos(np.cos(side) / np.cos(el))  # the side's normal is -x
    eye = 0.5 * np.r_[-np.cos(el) * np.cos(phi), -np.cos(el) * np.sin(phi), np.sin(el)]
    X_MC = pose_looking_at(eye, np.zeros(3))
    X = np.linalg.inv(X_MC)
    table_V, table_T = box_triangles((1.0, 1.0, 0.01))
    depth, _ = rasterize(transform_points(X, V), T, CAMERA)
    table, _ = rasterize(transform_points(X, table_V - [0.0, 0.0, 0.02]), table_T, CAMERA)
    mask = depth > 0
    seen = (np.where(mask, depth, table) + rng.normal(0.0, 2e-4, depth.shape)).astype(np.float32)
    start = X.copy()
    start[:3, 3] += rng.uniform(-1e-3, 1e-3, 3)
    sigma = np.full(depth.shape, 2e-4)
    ends = []
    for faces in (face_planes(V, T), face_planes(*_soup(V, T, rng))):
        res = projective_icp(seen, CAMERA, faces, start, mask=mask, sigma=sigma, outline=True)
        ends.append(res.X_CM)
    err = [np.linalg.norm(e[:3, 3] - X[:3, 3]) for e in ends]
    assert np.abs(ends[0] - ends[1]).max() < 1e-9, err
