from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from apo import shapes
from apo.errors import GeometryError
from apo.geometry import (
    Polyhedron,
    closest_point_on_segment,
    local_solid,
    point_face_distance,
    polyhedron_from_triangles,
    segment_segment_closest,
    transformed,
    triangulate_polygon,
)

# A unit cube as 8 vertices and 12 outward triangles.
CUBE_V = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
    dtype=float,
)
CUBE_T = np.array(
    [
        [0, 2, 1], [0, 3, 2],  # bottom
        [4, 5, 6], [4, 6, 7],  # top
        [0, 1, 5], [0, 5, 4],  # front (y = 0)
        [1, 2, 6], [1, 6, 5],  # right (x = 1)
        [2, 3, 7], [2, 7, 6],  # back (y = 1)
        [3, 0, 4], [3, 4, 7],  # left (x = 0)
    ]
)  # fmt: skip


def grid_cube(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit cube whose faces are n x n grids: vertices inside faces and along edges."""
    verts: list[np.ndarray] = []
    tris: list[np.ndarray] = []
    s = np.linspace(0.0, 1.0, n + 1)
    uu, vv = np.meshgrid(s, s, indexing="ij")
    for axis in range(3):
        for side in (0.0, 1.0):
            pts = np.zeros(((n + 1) ** 2, 3))
            a, b = (axis + 1) % 3, (axis + 2) % 3
            pts[:, axis] = side
            pts[:, a] = uu.ravel()
            pts[:, b] = vv.ravel()
            base = sum(len(p) for p in verts)
            idx = base + np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
            q = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1)
            q = q.reshape(-1, 4)
            t = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
            # (a, b, axis) is right-handed, so the loop is CCW about +axis.
            tris.append(t if side == 1.0 else t[:, ::-1])
            verts.append(pts)
    return np.concatenate(verts), np.concatenate(tris)


def test_tetrahedron_counts() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    t = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    p = polyhedron_from_triangles(v, t, name="tetra")
    assert (len(p.vertices), len(p.edges), len(p.faces)) == (4, 6, 4)
    assert p.edge_convex.all()
    assert p.volume == pytest.approx(1 / 6)


def test_cube_counts_normals_and_offsets() -> None:
    p = polyhedron_from_triangles(CUBE_V, CUBE_T, name="cube")
    assert (len(p.faces), len(p.edges), len(p.vertices)) == (6, 12, 8)
    assert p.edge_convex.all()
    assert p.volume == pytest.approx(1.0)
    assert p.scale == pytest.approx(np.sqrt(3))
    centroids = np.array([p.vertices[f].mean(axis=0) for f in p.faces])
    # Outward: the normal points from the cube's centre towards the face centroid.
    assert np.allclose(p.face_normals, 2 * (centroids - 0.5))
    for f, loop in enumerate(p.faces):
        assert np.allclose(p.vertices[loop] @ p.face_normals[f], p.face_offsets[f])
        assert len(loop) == 4 and p.face_holes[f] == ()
    assert np.allclose(p.face_areas, 1.0)


def test_triangle_soup_is_merged() -> None:
    # STL-like: every triangle has its own three vertices, with sub-tolerance noise.
    rng = np.random.default_rng(0)
    v = CUBE_V[CUBE_T].reshape(-1, 3) + rng.normal(scale=1e-12, size=(36, 3))
    t = np.arange(36).reshape(-1, 3)
    p = polyhedron_from_triangles(v, t)
    assert (len(p.faces), len(p.edges), len(p.vertices)) == (6, 12, 8)


def test_vertices_inside_faces_and_on_straight_edges_disappear() -> None:
    v, t = grid_cube(4)
    p = polyhedron_from_triangles(v, t, name="grid")
    assert (len(p.faces), len(p.edges), len(p.vertices)) == (6, 12, 8)
    assert all(len(loop) == 4 for loop in p.faces)
    assert sum(len(tr) for tr in p.face_triangles) == 12
    assert p.volume == pytest.approx(1.0)


def test_ids_are_deterministic() -> None:
    v, t = grid_cube(3)
    a = polyhedron_from_triangles(v, t)
    b = polyhedron_from_triangles(v.copy(), t.copy())
    assert np.array_equal(a.vertices, b.vertices)
    assert np.array_equal(a.edges, b.edges)
    assert all(np.array_equal(x, y) for x, y in zip(a.faces, b.faces, strict=True))
    # Vertices keep the order of first occurrence in the input.
    order = [int(np.flatnonzero((v == x).all(axis=1))[0]) for x in a.vertices]
    assert order == sorted(order)


def test_edge_faces_convention() -> None:
    p = shapes.u_block()
    assert (p.edges[:, 0] < p.edges[:, 1]).all()
    for e, (a, b) in enumerate(p.edges):
        f0, f1 = p.edge_faces[e]
        segs0 = {tuple(s) for s in p.face_boundary_segments[f0].tolist()}
        segs1 = {tuple(s) for s in p.face_boundary_segments[f1].tolist()}
        assert (a, b) in segs0 and (b, a) in segs1


def test_u_block_concave_edges_are_the_slot_bottom() -> None:
    p = shapes.u_block(width=0.14, height=0.088, slot_width=0.035, slot_depth=0.053)
    assert (len(p.faces), len(p.edges), len(p.vertices)) == (10, 24, 16)
    concave = p.edges[~p.edge_convex]
    assert len(concave) == 2
    mids = p.vertices[concave].mean(axis=1)
    # Both run along z at the bottom of the slot, x = +-slot_width / 2.
    assert np.allclose(mids[:, 1], 0.088 - 0.053)
    assert np.allclose(np.sort(np.abs(mids[:, 0])), [0.0175, 0.0175])
    assert np.allclose(mids[:, 2], 0.0)
    # The front and back faces (normal +-z) are U-shaped: 8 corners, non-convex.
    zf = np.flatnonzero(np.abs(p.face_normals[:, 2]) > 0.99)
    assert [len(p.faces[f]) for f in zf] == [8, 8]


def test_face_with_hole() -> None:
    p = shapes.block_with_square_hole(size=(0.1, 0.1, 0.05), hole=0.04, depth=0.03)
    top = int(np.flatnonzero(np.isclose(p.face_offsets, 0.05) & (p.face_normals[:, 2] > 0.99))[0])
    assert len(p.face_holes[top]) == 1
    assert len(p.face_holes[top][0]) == 4
    assert p.face_areas[top] == pytest.approx(0.1 * 0.1 - 0.04 * 0.04)
    assert p.n_concave_edges == 8
    assert p.volume == pytest.approx(0.1 * 0.1 * 0.05 - 0.04 * 0.04 * 0.03)


def test_vertex_faces_counter_clockwise_from_outside() -> None:
    p = shapes.box([1.0, 2.0, 3.0])
    for v, fs in enumerate(p.vertex_faces):
        n = p.face_normals[fs]
        out = p.vertices[v] / np.linalg.norm(p.vertices[v])  # centred box: corner direction
        assert len(fs) == 3
        assert np.dot(np.cross(n[0], n[1]), out) > 0
        assert np.dot(np.cross(n[1], n[2]), out) > 0


def test_box_with_internal_cavity() -> None:
    # The cavity's triangles face into the cavity (out of the material): all its edges are
    # concave, and the volume is the difference.
    outer = shapes.box([2.0, 2.0, 2.0])
    tris = np.concatenate(outer.face_triangles)
    v = np.vstack([outer.vertices, 0.5 * outer.vertices])
    t = np.vstack([tris, tris[:, ::-1] + len(outer.vertices)])
    p = polyhedron_from_triangles(v, t, name="hollow")
    assert (len(p.faces), len(p.edges), len(p.vertices)) == (12, 24, 16)
    assert p.n_concave_edges == 12
    assert p.volume == pytest.approx(8.0 - 1.0)


def test_inside_out_mesh_is_flipped_with_warning() -> None:
    with pytest.warns(UserWarning, match="inside-out"):
        p = polyhedron_from_triangles(CUBE_V, CUBE_T[:, ::-1], name="flipped")
    assert p.volume == pytest.approx(1.0)
    assert p.edge_convex.all()


def test_collapsed_triangle_is_dropped_with_warning() -> None:
    v = np.vstack([CUBE_V, CUBE_V[0] + 1e-13])
    t = np.vstack([CUBE_T, [[0, 8, 1]]])
    with pytest.warns(UserWarning, match="collapsed"):
        p = polyhedron_from_triangles(v, t, name="needle")
    assert (len(p.faces), len(p.edges), len(p.vertices)) == (6, 12, 8)


def test_zero_area_triangle_is_absorbed_with_warning() -> None:
    # Split the top face's edge 4-5 at its midpoint m with a zero-area triangle (4, 5, m).
    v = np.vstack([CUBE_V, [0.5, 0.0, 1.0]])
    top = [[8, 5, 6], [8, 6, 7], [8, 7, 4]]
    t = np.vstack([np.delete(CUBE_T, [2, 3], axis=0), top, [[4, 5, 8]]])
    with pytest.warns(UserWarning, match="zero-area"):
        p = polyhedron_from_triangles(v, t, name="sliver")
    assert (len(p.faces), len(p.edges), len(p.vertices)) == (6, 12, 8)


@pytest.mark.parametrize(
    ("vertices", "triangles", "match"),
    [
        (np.zeros((0, 3)), np.zeros((0, 3), int), "empty mesh"),
        (CUBE_V, np.zeros((0, 3), int), "empty mesh"),
        (CUBE_V[:, :2], CUBE_T, r"shape \(N, 3\)"),
        (CUBE_V, CUBE_T[:, :2], r"shape \(T, 3\)"),
        (CUBE_V, CUBE_T + 1, "out of range"),
        (CUBE_V, CUBE_T + 0.5, "integers"),
        (np.where(np.arange(8)[:, None] == 3, np.nan, CUBE_V), CUBE_T, "NaN"),
        (CUBE_V, CUBE_T[1:], "not closed: 3 boundary edge"),
        (CUBE_V, np.vstack([CUBE_T, CUBE_T[:1]]), "non-manifold"),
        (CUBE_V, np.vstack([CUBE_T[:1, ::-1], CUBE_T[1:]]), "inconsistent orientation"),
        (CUBE_V, [[0, 1, 2], [0, 2, 1]], "zero volume"),
        (np.zeros((3, 3)), [[0, 1, 2], [0, 2, 1]], "all vertices coincide"),
    ],
)
def test_bad_meshes_raise(vertices: object, triangles: object, match: str) -> None:
    with pytest.raises(GeometryError, match=f"^mymodel: .*{match}"):
        polyhedron_from_triangles(vertices, triangles, name="mymodel")  # type: ignore[arg-type]


def test_non_manifold_vertex_raises() -> None:
    tet_v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    tet_t = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    # A second tetrahedron mirrored through vertex 0: the two touch at one point only.
    v = np.vstack([tet_v, -tet_v[1:]])
    t2 = np.where(tet_t == 0, 0, tet_t + 3)[:, ::-1]
    with pytest.raises(GeometryError, match="non-manifold vertex"):
        polyhedron_from_triangles(v, np.vstack([tet_t, t2]), name="bowtie")


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    scale=st.floats(1e-3, 1e3),
)
def test_invariant_under_rigid_motion_and_scaling(seed: int, scale: float) -> None:
    base = shapes.t_peg()
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=rng).as_matrix()
    shift = rng.uniform(-1, 1, size=3)
    tris = np.concatenate(base.face_triangles)
    moved = polyhedron_from_triangles(scale * base.vertices @ R.T + shift, tris)
    assert (len(moved.faces), len(moved.edges), len(moved.vertices)) == (10, 24, 16)
    assert np.array_equal(moved.edges, base.edges)
    assert np.array_equal(moved.edge_convex, base.edge_convex)
    assert np.allclose(moved.face_normals, base.face_normals @ R.T, atol=1e-9)
    assert moved.volume == pytest.approx(scale**3 * base.volume, rel=1e-9)


def test_transformed_keeps_ids_and_moves_planes() -> None:
    p = shapes.u_block()
    rng = np.random.default_rng(3)
    X = np.eye(4)
    X[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    X[:3, 3] = [0.1, -0.2, 0.3]
    q = transformed(p, X)
    assert np.allclose(q.vertices, p.vertices @ X[:3, :3].T + X[:3, 3])
    for f, loop in enumerate(q.faces):
        assert np.allclose(q.vertices[loop] @ q.face_normals[f], q.face_offsets[f])
    assert q.edges is p.edges and q.volume == pytest.approx(p.volume)
    with pytest.raises(ValueError, match="not a rigid transform"):
        transformed(p, np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match=r"shape \(4, 4\)"):
        transformed(p, np.eye(3))


# ---- local solids ---------------------------------------------------------------------------


def test_local_solid_box_vertex_edge_face() -> None:
    p = shapes.box([1.0, 1.0, 1.0])
    ls = local_solid(p, "v", 0)
    assert ls.convex and len(ls.face_ids) == 3 and len(ls.directions) == 3
    assert set(ls.pieces[0].tolist()) == set(ls.face_ids.tolist())
    # Edge directions point away from the vertex, along the box edges.
    assert np.allclose(np.abs(ls.directions).sum(axis=1), 1.0)
    assert np.all(ls.directions @ p.vertices[0] < 0)
    e = local_solid(p, "e", 0)
    assert e.convex and len(e.pieces[0]) == 2
    f = local_solid(p, "f", 2)
    assert f.convex and f.pieces[0].tolist() == [2]
    assert np.allclose(f.piece_normals(0), p.face_normals[[2]])


def test_local_solid_concave_edge_has_two_half_spaces() -> None:
    p = shapes.u_block()
    e = int(np.flatnonzero(~p.edge_convex)[0])
    ls = local_solid(p, "e", e)
    assert [pc.tolist() for pc in ls.pieces] == [[p.edge_faces[e, 0]], [p.edge_faces[e, 1]]]


def test_local_solid_reflex_corner_of_l_prism() -> None:
    # Top of the inner vertical edge of an L: solid = top ∩ (wall1 ∪ wall2).
    p = shapes.l_prism(size=0.04, notch=0.02, height=0.02)
    v = int(np.flatnonzero(np.all(np.isclose(p.vertices, [0.02, 0.02, 0.02]), axis=1))[0])
    ls = local_solid(p, "v", v)
    top = int(np.flatnonzero(p.face_normals[:, 2] > 0.99)[0])
    walls = {
        int(f) for f in ls.face_ids if f != top
    }  # the two walls of the notch, normals +x and +y
    assert {frozenset(pc.tolist()) for pc in ls.pieces} == {frozenset({top, w}) for w in walls}
    assert np.allclose(np.sort(p.face_normals[list(walls)].sum(axis=0)), [0, 1, 1])


def test_local_solid_pocket_floor_corner_is_three_half_spaces() -> None:
    p = shapes.block_with_square_hole(size=(0.1, 0.1, 0.05), hole=0.04, depth=0.03)
    v = int(np.flatnonzero(np.all(np.isclose(p.vertices, [0.02, 0.02, 0.02]), axis=1))[0])
    ls = local_solid(p, "v", v)
    assert sorted(len(pc) for pc in ls.pieces) == [1, 1, 1]
    # Rim corner of the pocket: top ∩ (wall1 ∪ wall2).
    v = int(np.flatnonzero(np.all(np.isclose(p.vertices, [0.02, 0.02, 0.05]), axis=1))[0])
    assert sorted(len(pc) for pc in local_solid(p, "v", v).pieces) == [2, 2]


def voxel_solid(occupied: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of the boundary of a union of unit voxels (outward)."""
    occ = np.pad(occupied, 1)
    index: dict[tuple[int, ...], int] = {}
    tris: list[list[int]] = []
    for cell in zip(*np.nonzero(occ), strict=True):
        for ax in range(3):
            for step in (-1, 1):
                nb = list(cell)
                nb[ax] += step
                if occ[tuple(nb)]:
                    continue
                a, b = (ax + 1) % 3, (ax + 2) % 3
                quad = []
                for da, db in [(0, 0), (1, 0), (1, 1), (0, 1)]:
                    q = [int(c) for c in cell]
                    q[ax] += step > 0
                    q[a] += da
                    q[b] += db
                    quad.append(index.setdefault(tuple(q), len(index)))
                if step < 0:
                    quad = quad[::-1]
                tris += [[quad[0], quad[1], quad[2]], [quad[0], quad[2], quad[3]]]
    verts = np.array(sorted(index, key=lambda k: index[k]), dtype=float)
    return verts, np.array(tris)


def winding_number(p: Polyhedron, points: np.ndarray) -> np.ndarray:
    """Generalised winding number of the closed surface around each point."""
    tri = p.vertices[np.concatenate(p.face_triangles)][None] - points[:, None, None]
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))

    def dot(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        out: np.ndarray = np.einsum("...i,...i->...", x, y)
        return out

    num = dot(a, np.cross(b, c))
    den = la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb
    out: np.ndarray = (2 * np.arctan2(num, den)).sum(axis=1) / (4 * np.pi)
    return out


def assert_local_solids_match_the_solid(p: Polyhedron, rng: np.random.Generator) -> None:
    # Ground truth: is v + eps * d inside the solid? Compare with the union of the pieces.
    for v in range(len(p.vertices)):
        ls = local_solid(p, "v", v)
        d = rng.normal(size=(200, 3))
        d /= np.linalg.norm(d, axis=1)[:, None]
        d = d[np.abs(d @ ls.normals.T).min(axis=1) > 0.05]  # away from the face planes
        inside = winding_number(p, p.vertices[v] + 1e-3 * p.scale * d) > 0.5
        in_cone = np.zeros(len(d), dtype=bool)
        for k in range(len(ls.pieces)):
            in_cone |= (d @ ls.piece_normals(k).T <= 0).all(axis=1)
        assert np.array_equal(inside, in_cone), f"vertex {v} at {p.vertices[v]}"


@pytest.mark.parametrize(
    "make",
    [shapes.t_peg, shapes.u_block, shapes.l_prism, shapes.block_with_square_hole],
)
def test_local_solids_of_shapes_match_the_solid(make: Callable[[], Polyhedron]) -> None:
    assert_local_solids_match_the_solid(make(), np.random.default_rng(7))


def test_local_solids_of_random_voxel_solids_match_the_solid() -> None:
    # Unions of voxels have every axis-aligned corner: saddles, concave and mixed corners.
    rng = np.random.default_rng(11)
    checked = 0
    while checked < 8:
        verts, tris = voxel_solid(rng.random((3, 3, 3)) < 0.75)
        try:
            p = polyhedron_from_triangles(verts, tris)
        except GeometryError:  # voxels touching along an edge or at a corner
            continue
        assert_local_solids_match_the_solid(p, rng)
        checked += 1


def test_face_touching_itself_at_a_vertex() -> None:
    # A diamond-shaped prism standing on a 2 x 2 x 1 block with one corner on the block's
    # front top edge: the block's top face touches itself at that corner (vertex 8).
    v = np.array(
        [
            [0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0],
            [0, 0, 1], [2, 0, 1], [2, 2, 1], [0, 2, 1],
            [1, 0, 1], [1.5, 0.5, 1], [1, 1, 1], [0.5, 0.5, 1],
            [1, 0, 2], [1.5, 0.5, 2], [1, 1, 2], [0.5, 0.5, 2],
            [1, 2, 1],  # splits the top face in two simple polygons (a flat edge)
        ],
        dtype=float,
    )  # fmt: skip
    polygons: list[tuple[list[int], list[list[int]]]] = [
        ([3, 2, 1, 0], []),
        ([0, 1, 5, 8, 4], []),
        ([1, 2, 6, 5], []),
        ([2, 3, 7, 16, 6], []),
        ([3, 0, 4, 7], []),
        ([4, 8, 11, 10, 16, 7], []),
        ([8, 5, 6, 16, 10, 9], []),
        ([12, 13, 14, 15], []),
        ([8, 9, 13, 12], []),
        ([9, 10, 14, 13], []),
        ([10, 11, 15, 14], []),
        ([11, 8, 12, 15], []),
    ]
    p = polyhedron_from_triangles(v, shapes.triangles_from_polygons(v, polygons))
    assert (len(p.faces), len(p.edges), len(p.vertices), p.n_concave_edges) == (11, 25, 16, 4)
    assert p.volume == pytest.approx(4.5)
    top = int(np.flatnonzero(np.isclose(p.face_offsets, 1.0) & (p.face_normals[:, 2] > 0.9))[0])
    assert p.face_areas[top] == pytest.approx(3.5)
    pinch = int(np.flatnonzero(np.all(p.vertices == [1, 0, 1], axis=1))[0])
    loop = p.faces[top].tolist() + [i for h in p.face_holes[top] for i in h.tolist()]
    assert loop.count(pinch) == 2
    d, _, inside = point_face_distance(p, top, [[1.0, 0.5, 1.5], [0.2, 0.2, 1.5]])
    assert inside.tolist() == [False, True]
    assert np.allclose(d, [np.sqrt(0.125 + 0.25), 0.5])
    assert_local_solids_match_the_solid(p, np.random.default_rng(5))


def test_local_solid_bad_arguments() -> None:
    p = shapes.box()
    with pytest.raises(ValueError, match="unknown feature kind"):
        local_solid(p, "x", 0)
    with pytest.raises(ValueError, match=r"vertex id 8 out of range \[0, 8\)"):
        local_solid(p, "v", 8)


# ---- distances ------------------------------------------------------------------------------


def test_point_face_distance_with_hole() -> None:
    p = shapes.block_with_square_hole(size=(0.1, 0.1, 0.05), hole=0.04, depth=0.03)
    top = int(np.flatnonzero(np.isclose(p.face_offsets, 0.05) & (p.face_normals[:, 2] > 0.99))[0])
    pts = np.array(
        [
            [0.03, 0.0, 0.06],  # above the ring
            [0.0, 0.0, 0.06],  # above the pocket: closest is the rim
            [0.08, 0.0, 0.05],  # beside the block, in the plane
            [0.02, 0.0, 0.05],  # on the rim
        ]
    )
    d, c, inside = point_face_distance(p, top, pts)
    assert inside.tolist() == [True, False, False, True]
    assert np.allclose(d, [0.01, np.hypot(0.02, 0.01), 0.03, 0.0])
    assert np.allclose(c[1], [0.02, 0.0, 0.05]) or np.allclose(c[1], [-0.02, 0.0, 0.05])
    assert np.allclose(c[0], [0.03, 0.0, 0.05])


def test_closest_point_on_segment() -> None:
    c, t = closest_point_on_segment([[2.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], [0, 0, 0], [1, 0, 0])
    assert np.allclose(c, [[1, 0, 0], [0, 0, 0]])
    assert np.allclose(t, [1.0, 0.0])
    c, t = closest_point_on_segment([1.0, 1.0, 1.0], [0, 0, 0], [0, 0, 0])
    assert np.allclose(c, 0.0) and t == 0.0


def test_segment_segment_closest_against_sampling() -> None:
    rng = np.random.default_rng(1)
    p0, p1, q0, q1 = rng.normal(size=(4, 200, 3))
    r = segment_segment_closest(p0, p1, q0, q1)
    s = np.linspace(0, 1, 401)
    for i in range(0, 200, 10):
        a = p0[i] + s[:, None] * (p1[i] - p0[i])
        b = q0[i] + s[:, None] * (q1[i] - q0[i])
        brute = np.linalg.norm(a[:, None] - b[None], axis=2).min()
        assert r.distance[i] <= brute + 1e-12
        assert r.distance[i] >= brute - 1e-2
    assert np.allclose(np.linalg.norm(r.p - r.q, axis=1), r.distance)
    assert ((r.s >= 0) & (r.s <= 1) & (r.t >= 0) & (r.t <= 1)).all()


def test_segment_segment_parallel_and_all_pairs() -> None:
    r = segment_segment_closest([0, 0, 0], [2, 0, 0], [1, 1, 0], [3, 1, 0])
    assert bool(r.parallel) and float(r.distance) == pytest.approx(1.0)
    e = shapes.box([1.0, 1.0, 1.0])
    a, b = e.vertices[e.edges[:, 0]], e.vertices[e.edges[:, 1]]
    r = segment_segment_closest(a[:, None], b[:, None], a[None], b[None])
    assert r.distance.shape == (12, 12)
    assert np.allclose(np.diag(r.distance), 0.0)


# ---- triangulation --------------------------------------------------------------------------


def cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out: np.ndarray = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def polygon_area(xy: np.ndarray) -> float:
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(4, 40))
def test_triangulate_star_polygons(seed: int, n: int) -> None:
    # Star-shaped about the origin (angular gaps < pi), CCW, strongly non-convex.
    rng = np.random.default_rng(seed)
    ang = (np.arange(n) + rng.uniform(0.05, 0.95, n)) * 2 * np.pi / n
    rad = rng.uniform(0.1, 1.0, n)
    xy = np.column_stack([rad * np.cos(ang), rad * np.sin(ang)])
    tris = triangulate_polygon(xy)
    t = xy[tris]
    areas = 0.5 * cross2(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    assert (areas >= -1e-12).all()
    assert areas.sum() == pytest.approx(polygon_area(xy), rel=1e-9, abs=1e-12)


def test_triangulate_polygon_with_two_holes() -> None:
    outer = np.array([[0, 0], [4, 0], [4, 2], [0, 2]], dtype=float)
    h1 = np.array([[0.5, 0.5], [0.5, 1.5], [1.5, 1.5], [1.5, 0.5]])  # clockwise
    h2 = h1 + np.array([2.0, 0.0])
    tris = triangulate_polygon(outer, [h1, h2])
    pts = np.concatenate([outer, h1, h2])
    t = pts[tris]
    areas = 0.5 * cross2(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    assert (areas > 0).all()
    assert areas.sum() == pytest.approx(8.0 - 2.0)
