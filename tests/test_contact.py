"""Tests of apo.contact: canonical contact states, consistency, naive vs fast, residuals."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from apo.contact import (
    ContactFinder,
    ContactKind,
    ContactState,
    contact_points,
    default_angle_tolerance,
    default_threshold,
    element_residuals,
    find_contacts,
    find_contacts_batch,
    find_contacts_naive,
    residual_counts,
)
from apo.geometry import Polyhedron, polyhedron_from_triangles
from apo.shapes import block_with_square_hole, box, t_peg, u_block
from apo.spatial import invert_pose, matrix_from_axis_angle, pose_from_twist

# --------------------------------------------------------------------------------------------
# Scenes
# --------------------------------------------------------------------------------------------


def pose(R: np.ndarray | None = None, t: object = (0.0, 0.0, 0.0)) -> np.ndarray:
    X = np.eye(4)
    if R is not None:
        X[:3, :3] = R
    X[:3, 3] = np.asarray(t, dtype=float)
    return X


def transformed(poly: Polyhedron, X: np.ndarray) -> Polyhedron:
    """The same model with its vertices moved by the rigid transform X (same feature ids)."""
    V = poly.vertices @ X[:3, :3].T + X[:3, 3]
    return polyhedron_from_triangles(V, np.concatenate(poly.face_triangles), name=poly.name)


TABLE = box([1.0, 1.0, 0.1], center=[0.0, 0.0, -0.05])  # top face z = 0, edges at x, y = +-0.5
CUBE = box([0.1, 0.1, 0.1], center=[0.0, 0.0, 0.05])  # bottom face z = 0 in its frame
POCKET = block_with_square_hole()  # pocket x, y in [-0.02, 0.02], floor z = 0.02, rim 0.05
PEG = box([0.04, 0.04, 0.06], center=[0.0, 0.0, 0.03])
SLOT_T = u_block(slot_depth=0.070)  # slot floor y = 0.018, top y = 0.088
TPEG = t_peg()  # stem 70 long, crossbar 18 tall: seated at y = 0.018
# Fig. 18: a wedge whose top is a convex edge along y at x = z = 0, y in [-0.1, 0.1].
WEDGE = transformed(
    box([0.1, 0.2, 0.1]),
    pose(matrix_from_axis_angle([0, 1, 0], np.pi / 4), (0.0, 0.0, -0.05 * np.sqrt(2))),
)


def scene_corner_on_table() -> tuple[Polyhedron, Polyhedron, np.ndarray]:
    R = matrix_from_axis_angle([1, -1, 0], 0.3)
    c = np.array([-0.05, -0.05, 0.0])  # this corner is the lowest after the tilt
    return CUBE, TABLE, pose(R, -R @ c)


def scene_edge_on_table() -> tuple[Polyhedron, Polyhedron, np.ndarray]:
    R = matrix_from_axis_angle([1, 0, 0], 0.3)
    c = np.array([0.0, -0.05, 0.0])  # the bottom edge along x at y = -0.05 stays down
    return CUBE, TABLE, pose(R, c - R @ c)


def scene_crossing_edges() -> tuple[Polyhedron, Polyhedron, np.ndarray]:
    # Cube standing on an edge (45 deg about x), that edge tilted 0.2 rad about y, its
    # lowest point (the edge's midpoint) on the table's convex edge x = 0.5.
    R = matrix_from_axis_angle([0, 1, 0], 0.2) @ matrix_from_axis_angle([1, 0, 0], np.pi / 4)
    VG = CUBE.vertices @ R.T
    mid = 0.5 * (VG[CUBE.edges[:, 0]] + VG[CUBE.edges[:, 1]])
    m = mid[np.argmin(mid[:, 2])]
    return CUBE, TABLE, pose(R, np.array([0.5, 0.0, 0.0]) - m)


def scene_vertex_on_edge() -> tuple[Polyhedron, Polyhedron, np.ndarray]:
    R = matrix_from_axis_angle([1, 1, 1], 0.5)
    c = np.array([-0.05, -0.05, 0.0])
    return CUBE, TABLE, pose(R, np.array([0.5, 0.0, 0.0]) - R @ c)


def scene_vertex_on_vertex() -> tuple[Polyhedron, Polyhedron, np.ndarray]:
    R = matrix_from_axis_angle([1, 1, 0], 0.4)
    c = np.array([-0.05, -0.05, 0.0])
    return CUBE, TABLE, pose(R, np.array([0.5, 0.5, 0.0]) - R @ c)


def scene_parallel_edges() -> tuple[Polyhedron, Polyhedron, np.ndarray]:
    cb = box([0.1, 0.1, 0.1])
    R = matrix_from_axis_angle([0, 1, 0], np.pi / 4 + 0.3)
    VG = cb.vertices @ R.T
    lowest = VG[VG[:, 2] < VG[:, 2].min() + 1e-9]  # the lowest edge (along y)
    low = lowest[np.argmin(lowest[:, 1])]  # its end at y = -0.05
    # The cube's edge spans y in [0.05, 0.15], the wedge's [-0.1, 0.1]: overlap [0.05, 0.1].
    return cb, WEDGE, pose(R, np.array([0.0, 0.05, 0.0]) - low)


def scene_wedged_block() -> tuple[Polyhedron, Polyhedron, np.ndarray]:
    # A 36 x 30 x 20 mm block tilted about y until its diagonal spans the 40 mm pocket.
    w, h, theta = 0.036, 0.02, 0.26687936851705324  # w cos(theta) + h sin(theta) = 0.04
    blk = box([w, 0.03, h])
    R = matrix_from_axis_angle([0, 1, 0], theta)
    x = (blk.vertices @ R.T)[:, 0]
    return blk, POCKET, pose(R, (-0.02 - x.min(), 0.0, 0.035))


def scene_three_walls() -> tuple[Polyhedron, Polyhedron, np.ndarray]:
    small = box([0.01, 0.01, 0.01], center=[0.005, 0.005, 0.005])
    return small, POCKET, pose(t=(-0.02, -0.02, 0.02))  # in the pocket's corner


# A regular tetrahedron-like spike whose apex (a convex vertex) is the origin, base z = -0.1.
SPIKE = polyhedron_from_triangles(
    [[0, 0, 0], [0.1, 0, -0.1], [-0.05, 0.0866, -0.1], [-0.05, -0.0866, -0.1]],
    [[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]],
    name="spike",
)
SMALL_CUBE = box([0.04, 0.04, 0.04], center=[0.005, 0.003, 0.02])  # bottom face z = 0


def scene_face_on_vertex() -> tuple[Polyhedron, Polyhedron, np.ndarray]:
    return SMALL_CUBE, SPIKE, pose()  # the cube's bottom face rests on the spike's apex


def scene_tilted_face_on_vertex() -> tuple[Polyhedron, Polyhedron, np.ndarray]:
    return SMALL_CUBE, SPIKE, pose(matrix_from_axis_angle([1, 0, 0], 0.1))  # about the apex


def scene_face_over_corner() -> tuple[Polyhedron, Polyhedron, np.ndarray]:
    # A 40 mm cube turned 30 deg about z, centred over the corner (50, 50) of a 100 mm
    # block's top face: the face-face contact region is a quadrilateral.
    cube = box([0.04, 0.04, 0.04], center=[0.0, 0.0, 0.02])
    return (
        cube,
        box([0.1, 0.1, 0.1], center=[0, 0, -0.05]),
        pose(matrix_from_axis_angle([0, 0, 1], np.pi / 6), (0.05, 0.05, 0.0)),
    )


def kinds(state: ContactState) -> Counter[str]:
    return Counter(e.kind.value for e in state.elements)


# (name, scene, expected kind counts, n singular elements, fig25) with one line of reasoning.
CANONICAL = [
    # Nothing within the threshold; all six DOF are free (maintaining).
    ("none", lambda: (CUBE, TABLE, pose(t=(0, 0, 0.01))), {}, 0, (3, 0, 0, 3, 0, 0, 0, 0)),
    # One vertex on the table: one normal +z; any rotation is kept by a compensating slide.
    ("corner", scene_corner_on_table, {"VF": 1}, 0, (2, 1, 0, 3, 0, 0, 1, 0)),
    # Edge x edge: one normal e_G x e_E = +z-ish; same numbers as one point contact.
    ("crossing", scene_crossing_edges, {"EE": 1}, 0, (2, 1, 0, 3, 0, 0, 1, 0)),
    # Edge on face: two VF, normal +z at two points on a line along x: rotation about z and
    # about the edge keep contact, tipping about y lifts one end (either way: type I).
    ("edge_on_face", scene_edge_on_table, {"VF": 2}, 0, (2, 1, 0, 2, 1, 0, 1, 1)),
    # Block on the table: 4 VF at the corners; slide in x, y and turn about z; lift; tip 2.
    ("block", lambda: (CUBE, TABLE, pose()), {"VF": 4}, 0, (2, 1, 0, 1, 2, 0, 1, 2)),
    # Block against one wall (normal +x): the same numbers about another axis.
    (
        "wall",
        lambda: (CUBE, box([0.1, 1.0, 1.0], center=[-0.1, 0.0, 0.0]), pose()),
        {"VF": 4},
        0,
        (2, 1, 0, 1, 2, 0, 1, 2),
    ),
    # Cube in a corner of three walls: its corner gives 3 VF (floor, two walls), the other
    # corners on 2 or 1 walls: 3 + 2 + 2 + 1 (floor) + 2 + 1 + 1 (walls) = 12 VF, normals
    # +x, +y, +z: every translation and rotation is detaching (moving out frees all).
    ("three_walls", scene_three_walls, {"VF": 12}, 0, (0, 3, 0, 0, 3, 0, 3, 3)),
    # Square peg seated: each bottom corner in a concave corner (3 VF), each side face against
    # a wall up to the rim where the peg's vertical edges cross the rim edges (8 EE): only +z
    # is free (detaching), x and y constrained; all rotations constrained.
    (
        "peg_seated",
        lambda: (PEG, POCKET, pose(t=(0, 0, 0.02))),
        {"VF": 12, "EE": 8},
        0,
        (0, 1, 2, 0, 0, 3, 3, 3),
    ),
    # Same peg lifted off the floor: 8 VF on the walls + 8 EE; z slides both ways.
    (
        "peg_lifted",
        lambda: (PEG, POCKET, pose(t=(0, 0, 0.025))),
        {"VF": 8, "EE": 8},
        0,
        (1, 0, 2, 0, 0, 3, 2, 3),
    ),
    # Cube corner on the table's convex edge: VE with two normals (the cone between the
    # edge's face normals): singular; dropping it leaves no contact (singular M = 3).
    ("vertex_on_edge", scene_vertex_on_edge, {"VE": 1}, 1, (3, 0, 0, 3, 0, 0, 2, 0)),
    # Corner on corner: VV, several normals at one point: singular.
    ("vertex_on_vertex", scene_vertex_on_vertex, {"VV": 1}, 1, (3, 0, 0, 3, 0, 0, 3, 0)),
    # Paper Fig. 18: parallel convex edges overlap on [0.05, 0.1]: VE and EV at the ends,
    # each with the same two normals (one per face of the wedge's and the cube's edge
    # intersected): singular; restraining: 2 normals (rank 2) at 2 points along y (r_a = 4).
    ("parallel_edges", scene_parallel_edges, {"VE": 1, "EV": 1}, 2, (3, 0, 0, 3, 0, 0, 2, 2)),
    # T-peg seated in the U-slot: stem corners on the slot's bottom corner vertices give
    # VE x 2 each with one normal (floor +y, wall +-x; faces flush at the front/back edge),
    # crossbar corners on the top faces' front/back edges VE (normal +y), the peg's reflex
    # corners at the rim vertices EV x 2 (+y, +-x): 12 VE + 8 EV, none singular. Slide along
    # z (M), lift (D), x constrained; rotation about x lifts either way, others constrained.
    (
        "t_peg_seated",
        lambda: (TPEG, SLOT_T, pose(t=(0, 0.018, 0))),
        {"VE": 12, "EV": 8},
        0,
        (1, 1, 1, 0, 1, 2, 2, 3),
    ),
    # Face of G on a convex vertex of E (FV): one normal, minus G's face normal (+z); the
    # numbers of a single point contact.
    ("face_on_vertex", scene_face_on_vertex, {"FV": 1}, 0, (2, 1, 0, 3, 0, 0, 1, 0)),
    # Face on face over the block's corner: the contact region's corners are one cube
    # vertex on the top (VF), the block's corner under the cube's bottom (FV) and two
    # crossings of bottom edges with top edges (EE), all with normal +z; four coplanar,
    # non-collinear points: the numbers of a block on a table.
    (
        "face_over_corner",
        scene_face_over_corner,
        {"VF": 1, "FV": 1, "EE": 2},
        0,
        (2, 1, 0, 1, 2, 0, 1, 2),
    ),
    # Block wedged across the pocket (tilted, touching the left wall with its lower edge, at
    # z = 30.1 mm, and the right wall with its upper edge, at z = 39.9 mm): 4 VF (+x, -x);
    # +-x cancel: x constrained, y, z slide;
    # rotation about y only un-wedges one way (type II), about z only together with it.
    ("wedged", scene_wedged_block, {"VF": 4}, 0, (2, 0, 1, 1, 2, 0, 1, 2)),
]


@pytest.mark.parametrize(("name", "scene", "expected", "n_singular", "fig25"), CANONICAL)
def test_canonical_states(
    name: str, scene: object, expected: dict[str, int], n_singular: int, fig25: tuple[int, ...]
) -> None:
    G, E, X = scene()  # type: ignore[operator]
    state = find_contacts(G, E, X)
    assert kinds(state) == Counter(expected), name
    assert sum(e.singular for e in state.elements) == n_singular
    assert state.singular == (n_singular > 0)
    assert [e.key for e in state.elements] == sorted(e.key for e in state.elements)
    for e in state.elements:
        assert np.allclose(np.linalg.norm(e.normals, axis=1), 1.0)
    from apo.dof import analyze

    assert analyze(contact_points(state)).fig25 == fig25, name


def test_rotation_detaching_types() -> None:
    from apo.dof import analyze

    # Edge on a face: tipping about the axis perpendicular to the edge goes both ways.
    r1 = analyze(contact_points(find_contacts(*scene_edge_on_table()))).rotation
    assert (r1.detaching, r1.detaching_type1, r1.detaching_type2) == (1, 1, 0)
    # Wedged block: it can only turn the un-wedging way (type II) about y, and about z.
    r2 = analyze(contact_points(find_contacts(*scene_wedged_block()))).rotation
    assert (r2.detaching, r2.detaching_type1, r2.detaching_type2) == (2, 0, 2)


def test_normals_point_from_environment_to_grasped() -> None:
    state = find_contacts(CUBE, TABLE, pose())
    assert all(np.allclose(e.normals, [[0, 0, 1]]) for e in state.elements)
    assert np.allclose(sorted(e.point[0] for e in state.elements), [-0.05, -0.05, 0.05, 0.05])
    ee = find_contacts(*scene_crossing_edges()).elements[0]
    assert ee.normals[0, 2] > 0.9  # e_G x e_E signed upward, out of the table


def test_three_walls_corner_vertex_is_three_face_contacts() -> None:
    state = find_contacts(*scene_three_walls())
    corner = [e for e in state.elements if e.grasped == ("v", 0)]
    normals = sorted(tuple(np.round(e.normals[0], 6)) for e in corner)
    assert normals == [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (1.0, 0.0, 0.0)]
    assert all(e.kind is ContactKind.VF and e.environment[0] == "f" for e in corner)


def test_flush_faces_at_a_convex_edge_give_one_normal() -> None:
    # THEORY pitfall: a peg's bottom flat on a block top with peg vertices on the block's
    # edge: the local obstacle is a half-space, so those VE elements have the face normal.
    blk = box([0.1, 0.1, 0.1], center=[0, 0, -0.05])
    pg = box([0.04, 0.04, 0.04], center=[0.02, 0.02, 0.02])
    state = find_contacts(pg, blk, pose(t=(0.01, 0.0, 0.0)))  # peg x in [0.01, 0.05]
    assert kinds(state) == Counter({"VE": 2, "VF": 2})
    assert not state.singular
    assert all(np.allclose(e.normals, [[0, 0, 1]]) for e in state.elements)


def test_touching_holds_every_feature_pair_within_threshold() -> None:
    state = find_contacts(CUBE, TABLE, pose())
    top = next(e.environment for e in state.elements)
    bottom = next(f for f in range(6) if np.allclose(CUBE.face_normals[f], [0, 0, -1]))
    assert (("f", bottom), top) in state.touching  # face on face
    assert all((e.grasped, e.environment) in state.touching for e in state.elements)
    # Every feature whose closure meets the bottom face touches the top: 4 vertices, 4 bottom
    # and 4 vertical edges, the bottom and 4 side faces.
    assert sum(1 for g, e in state.touching if e == top) == 17
    assert find_contacts(CUBE, TABLE, pose(t=(0, 0, 0.01))).touching == frozenset()


def test_empty_state_and_validation() -> None:
    state = find_contacts(CUBE, TABLE, pose(t=(3.0, 0.0, 0.0)))
    assert state.elements == () and state.touching == frozenset()
    with pytest.raises(ValueError, match="shape"):
        find_contacts(CUBE, TABLE, np.eye(3))
    with pytest.raises(ValueError, match="not finite"):
        find_contacts(CUBE, TABLE, np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="threshold"):
        find_contacts(CUBE, TABLE, np.eye(4), threshold=-1.0)
    with pytest.raises(ValueError, match="rotation"):
        find_contacts(CUBE, TABLE, np.diag([1.0, 1.0, 2.0, 1.0]))


def test_defaults_are_scale_aware() -> None:
    d = default_threshold(CUBE, TABLE)
    assert d == pytest.approx(1e-3 * CUBE.scale)
    assert default_angle_tolerance(CUBE, TABLE, d) == pytest.approx(4e-3)
    small = transformed(CUBE, pose())
    big_state = find_contacts(CUBE, TABLE, pose(t=(0, 0, 0.5 * d)))
    assert kinds(big_state) == Counter({"VF": 4})
    assert find_contacts(small, TABLE, pose(t=(0, 0, 2 * d))).elements == ()


# --------------------------------------------------------------------------------------------
# Real data: the first author's T-peg in the U-hole, final pose
# --------------------------------------------------------------------------------------------


def _read_last_scene(path: Path) -> dict[str, np.ndarray]:
    """Poses of the last scene of a .pose.list: tag -> X_CM (metres)."""
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    rows = [ln for ln in lines if len(ln) == 8]
    out = {}
    for ln in rows[-2:]:
        x, y, z, ax, ay, az, ang = (float(v) for v in ln[1:])
        out[ln[0]] = pose(matrix_from_axis_angle([ax, ay, az], ang), np.array([x, y, z]) / 1e3)
    return out


@pytest.mark.realdata
def test_real_t_peg_final_pose_is_seated(real_data_dir: Path) -> None:
    from apo.dof import analyze
    from apo.io.meshes import load_polyhedron

    peg = load_polyhedron(real_data_dir / "peg.step")
    hole = load_polyhedron(real_data_dir / "hole.step")
    scene = _read_last_scene(real_data_dir / "peg_in_hole.pose.list")
    X_EG = invert_pose(scene["0"]) @ scene["2"]  # tag 0 is still (the hole), 2 moves (peg)
    # Observed pose: ~1 mm off and tilted 3.4 deg about y (2 mm across the 35 mm thickness).
    state = find_contacts(peg, hole, X_EG, threshold=0.004)
    # Seated as the synthetic T-peg: 12 VE (flush at front/back edges) + 8 EV, non-singular.
    assert kinds(state) == Counter({"VE": 12, "EV": 8})
    assert not state.singular
    assert analyze(contact_points(state)).fig25 == (1, 1, 1, 0, 1, 2, 2, 3)


# --------------------------------------------------------------------------------------------
# Consistency (hypothesis), invariance, naive vs fast
# --------------------------------------------------------------------------------------------

CONSISTENCY_SCENES = {
    "block": lambda: (CUBE, TABLE, pose()),
    "edge_on_face": scene_edge_on_table,
    "peg_seated": lambda: (PEG, POCKET, pose(t=(0, 0, 0.02))),
    "three_walls": scene_three_walls,
    "t_peg_seated": lambda: (TPEG, SLOT_T, pose(t=(0, 0.018, 0))),
    "vertex_on_edge": scene_vertex_on_edge,
    "parallel_edges": scene_parallel_edges,
    "crossing": scene_crossing_edges,
}
_REFERENCE = {k: find_contacts(*f()) for k, f in CONSISTENCY_SCENES.items()}


@settings(max_examples=60, deadline=None)
@given(
    name=st.sampled_from(sorted(CONSISTENCY_SCENES)),
    shift=st.lists(st.floats(-0.3, 0.3), min_size=3, max_size=3),
    rot=st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3),
)
def test_same_contact_slightly_apart_or_into_gives_same_keys(
    name: str, shift: list[float], rot: list[float]
) -> None:
    G, E, X = CONSISTENCY_SCENES[name]()
    d = default_threshold(G, E)
    # Shift by up to 0.3 threshold per axis (apart or into) and turn by up to 0.1 threshold
    # over the larger model size, about the first contact point.
    p = _REFERENCE[name].elements[0].point
    w = np.asarray(rot) * 0.1 * d / max(G.scale, E.scale)
    T = pose(t=p) @ pose_from_twist(np.r_[w, 0, 0, 0]) @ pose(t=-p)
    X2 = pose(t=np.asarray(shift) * d / np.sqrt(3)) @ T @ X
    state = find_contacts(G, E, X2)
    assert state.key == _REFERENCE[name].key
    assert [len(e.normals) for e in state.elements] == [
        len(e.normals) for e in _REFERENCE[name].elements
    ]


@settings(max_examples=15, deadline=None)
@given(
    name=st.sampled_from(sorted(CONSISTENCY_SCENES)),
    axis=st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(
        lambda a: np.linalg.norm(a) > 0.1
    ),
    angle=st.floats(-3.0, 3.0),
    t=st.lists(st.floats(-1, 1), min_size=3, max_size=3),
)
def test_rigid_motion_of_the_environment_model(
    name: str, axis: list[float], angle: float, t: list[float]
) -> None:
    G, E, X = CONSISTENCY_SCENES[name]()
    T = pose(matrix_from_axis_angle(axis, angle), t)
    E2 = transformed(E, T)  # E's model vertices moved by T: same feature ids
    ref = _REFERENCE[name]
    state = find_contacts(G, E2, T @ X, threshold=default_threshold(G, E))
    assert state.key == ref.key
    assert state.touching == ref.touching
    for a, b in zip(state.elements, ref.elements, strict=True):
        assert np.allclose(a.point, T[:3, :3] @ b.point + T[:3, 3], atol=1e-9)
        back = a.normals @ T[:3, :3]  # the same rays, possibly in another order
        assert len(back) == len(b.normals)
        assert np.all(np.max(back @ b.normals.T, axis=1) > 1 - 1e-9)


@pytest.mark.parametrize("kd", [False, True], ids=["dense", "kdtree"])
@pytest.mark.parametrize("seed", range(4))
def test_naive_and_fast_agree_near_contact(
    seed: int, kd: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    import apo.contact.model_data
    import apo.contact.search

    if kd:  # force the k-d tree broad phase even for these small models
        monkeypatch.setattr(apo.contact.search, "_DENSE_LIMIT", 0)
    rng = np.random.default_rng(seed)
    scenes = list(CONSISTENCY_SCENES.values())
    for k in range(len(scenes)):
        G, E, X = scenes[(k + seed) % len(scenes)]()
        d = 10 * default_threshold(G, E)
        xi = np.r_[rng.normal(size=3) * d / G.scale, rng.normal(size=3) * d]
        X2 = pose_from_twist(xi) @ X
        fast = find_contacts(G, E, X2, threshold=d)
        slow = find_contacts_naive(G, E, X2, threshold=d)
        assert fast.key == slow.key
        assert fast.touching == slow.touching
        for a, b in zip(fast.elements, slow.elements, strict=True):
            assert np.allclose(a.point, b.point) and np.allclose(a.normals, b.normals)


def test_naive_and_fast_agree_on_a_finer_mesh(monkeypatch: pytest.MonkeyPatch) -> None:
    import apo.contact.model_data
    import apo.contact.search
    from apo.shapes import icosphere

    monkeypatch.setattr(apo.contact.search, "_DENSE_LIMIT", 0)
    ball = icosphere(2, radius=0.05)  # 320 faces, centred on the origin
    plate = transformed(icosphere(2, radius=0.5), pose(t=(0, 0, -0.5)))  # top vertex at 0
    finder = ContactFinder(ball, plate, threshold=2e-3)
    for z in (0.0505, 0.06):
        X = pose(t=(0.0, 0.0, z))
        fast, slow = finder.find(X), finder.find_naive(X)
        assert fast.key == slow.key and fast.touching == slow.touching
    assert [e.kind for e in finder.find(pose(t=(0.0, 0.0, 0.0505))).elements] == [
        ContactKind.VV  # both spheres' poles
    ]
    assert apo.contact.model_data._model_data(plate)._trees is not None  # the k-d tree path ran


def test_batch_matches_single() -> None:
    G, E, X = CONSISTENCY_SCENES["peg_seated"]()
    poses = [X, pose(t=(0, 0, 0.025)), pose(t=(0, 0, 0.2))]
    batch = find_contacts_batch(G, E, poses)
    assert [s.key for s in batch] == [find_contacts(G, E, P).key for P in poses]
    assert batch[2].elements == ()


# --------------------------------------------------------------------------------------------
# Residuals for pose correction
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", [*sorted(CONSISTENCY_SCENES), "vertex_on_vertex"])
def test_residuals_vanish_at_exact_contact_and_jacobian_matches(name: str) -> None:
    scene = CONSISTENCY_SCENES.get(name, scene_vertex_on_vertex)
    G, E, X = scene()
    els = find_contacts(G, E, X).elements
    r, J = element_residuals(G, E, X, els)
    counts = residual_counts(els)
    assert r.shape == (counts.sum(),) and J.shape == (counts.sum(), 6)
    assert np.allclose(r, 0.0, atol=1e-12)
    # Finite differences of a left twist [omega; v] about an off-contact state.
    rng = np.random.default_rng(1)
    X0 = pose_from_twist(np.r_[rng.normal(size=3) * 1e-3, rng.normal(size=3) * 1e-4]) @ X
    r0, J0 = element_residuals(G, E, X0, els)
    h = 1e-7
    num = np.empty_like(J0)
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = h
        num[:, k] = (element_residuals(G, E, pose_from_twist(xi) @ X0, els)[0] - r0) / h
    assert np.allclose(num, J0, atol=1e-5)


def test_residual_signs() -> None:
    G, E, X = CUBE, TABLE, pose(t=(0, 0, 0.001))
    els = find_contacts(G, E, pose()).elements
    r, _ = element_residuals(G, E, X, els)
    assert np.allclose(r, 0.001)  # VF: positive when the vertex is above the face
    assert element_residuals(G, E, X, [])[0].shape == (0,)


def test_model_cache_does_not_keep_models_alive() -> None:
    import gc
    import weakref

    a = box([0.1, 0.1, 0.1], center=[0.0, 0.0, 0.05])
    find_contacts(a, TABLE, pose())
    ref = weakref.ref(a)
    del a
    gc.collect()
    assert ref() is None


# --------------------------------------------------------------------------------------------
# Added by the audit of issue 2: FV normals, threshold band, scaling, feature-id stability
# --------------------------------------------------------------------------------------------


def test_face_on_vertex_normal_is_minus_the_grasped_face_normal() -> None:
    # FV: the separating normal is minus G's outward face normal, moved with G: tilting the
    # cube by 0.1 rad about x turns its bottom normal (0, 0, -1) into (0, sin, -cos).
    (el,) = find_contacts(*scene_tilted_face_on_vertex()).elements
    assert el.kind is ContactKind.FV and el.environment == ("v", 0)
    np.testing.assert_allclose(el.normals, [[0.0, -np.sin(0.1), np.cos(0.1)]], atol=1e-12)
    np.testing.assert_allclose(el.point, [0, 0, 0], atol=1e-12)


SCENES_FOR_BAND = {name: scene for name, scene, *_ in CANONICAL if name != "none"}


@pytest.mark.parametrize("name", sorted(SCENES_FOR_BAND))
@pytest.mark.parametrize("frac", [-0.9, -0.5, 0.5, 0.9])
def test_within_the_threshold_apart_or_into_gives_the_same_state(name: str, frac: float) -> None:
    # The same physical contact moved by 0.9 threshold along the mean separating normal
    # (frac > 0 apart, < 0 into E), plus a turn about the contact centroid that moves no
    # vertex of G by more than 0.05 threshold: same elements, same ray counts, same numbers.
    from apo.dof import analyze

    G, E, X = SCENES_FOR_BAND[name]()
    d = default_threshold(G, E)
    ref = find_contacts(G, E, X)
    n = np.concatenate([e.normals for e in ref.elements]).sum(axis=0)
    n = n / np.linalg.norm(n) if np.linalg.norm(n) > 1e-9 else ref.elements[0].normals[0]
    c = np.mean([e.point for e in ref.elements], axis=0)
    reach = np.max(np.linalg.norm(G.vertices @ X[:3, :3].T + X[:3, 3] - c, axis=1))
    turn = pose(t=c) @ pose_from_twist(np.r_[0.05 * d / reach * np.array([1, 2, 2]) / 3, 0, 0, 0])
    X2 = pose(t=frac * d * n) @ turn @ pose(t=-c) @ X
    state = find_contacts(G, E, X2)
    assert state.key == ref.key
    assert [len(e.normals) for e in state.elements] == [len(e.normals) for e in ref.elements]
    fig = analyze(contact_points(state)).fig25
    assert fig == analyze(contact_points(ref)).fig25


def scaled(poly: Polyhedron, s: float) -> Polyhedron:
    """The same model scaled by ``s`` about its origin (same triangles, same feature ids)."""
    return polyhedron_from_triangles(
        poly.vertices * s, np.concatenate(poly.face_triangles), name=poly.name
    )


@settings(max_examples=20, deadline=None, derandomize=True)
@given(
    name=st.sampled_from([name for name, *_ in CANONICAL]),
    s=st.floats(1e-3, 1e3),
)
def test_uniform_scaling_of_the_whole_scene(name: str, s: float) -> None:
    # Both models and the pose's translation scaled by s (the default threshold scales too):
    # same elements, points scaled by s, the same normals and DOF numbers.
    from apo.dof import analyze

    scene, fig25 = next((sc, f) for n, sc, _, _, f in CANONICAL if n == name)
    G, E, X = scene()
    ref = find_contacts(G, E, X)
    Xs = X.copy()
    Xs[:3, 3] *= s
    state = find_contacts(scaled(G, s), scaled(E, s), Xs)
    assert state.key == ref.key
    for a, b in zip(state.elements, ref.elements, strict=True):
        np.testing.assert_allclose(a.point, s * b.point, rtol=1e-9, atol=1e-12 * s)
        np.testing.assert_allclose(a.normals, b.normals, atol=1e-9)
    assert analyze(contact_points(state)).fig25 == fig25


@pytest.mark.realdata
def test_real_feature_ids_are_stable_across_loads_and_frames(real_data_dir: Path) -> None:
    # Loading the STEP models twice gives the same ids, and the last four observed frames
    # (the peg seated, the hand still) give the very same state keys with a 4 mm threshold.
    from apo.io.meshes import load_polyhedron
    from apo.io.poses import read_pose_list

    peg = load_polyhedron(real_data_dir / "peg.step")
    hole = load_polyhedron(real_data_dir / "hole.step")
    again = load_polyhedron(real_data_dir / "peg.step")
    assert np.array_equal(peg.vertices, again.vertices)
    assert np.array_equal(peg.edges, again.edges)
    assert all(np.array_equal(a, b) for a, b in zip(peg.faces, again.faces, strict=True))
    demo = read_pose_list(real_data_dir / "peg_in_hole.pose.list")
    finder = ContactFinder(peg, hole, threshold=0.004)
    keys = [finder.find(X).key for X in demo.X_EG[-4:]]
    assert len(keys[0]) == 20 and all(k == keys[0] for k in keys)
    # X_EG is X_E^-1 X_G of the camera-frame poses (object 0 grasped, object 1 environment)
    np.testing.assert_allclose(demo.X_EG[-1], invert_pose(demo.X_CE[-1]) @ demo.X_CG[-1])


def test_face_face_contact_decomposes_at_the_corners_of_the_region() -> None:
    # The cube's bottom square (half-diagonal 20 sqrt2 mm, corners at 75, 165, 255, 345 deg
    # about (50, 50)) meets the quadrant x, y <= 50 mm in: the corner at 255 deg, the block's
    # corner (50, 50), and where the edges from 255 deg cross x = 50 and y = 50.
    state = find_contacts(*scene_face_over_corner())
    r = 0.02 * np.sqrt(2)
    corner = np.array([0.05, 0.05]) + r * np.array(
        [np.cos(np.radians(255)), np.sin(np.radians(255))]
    )
    toward_345 = np.array([np.cos(np.radians(30)), np.sin(np.radians(30))])  # edge direction
    toward_165 = np.array([-np.sin(np.radians(30)), np.cos(np.radians(30))])
    cross_x = corner + (0.05 - corner[0]) / toward_345[0] * toward_345
    cross_y = corner + (0.05 - corner[1]) / toward_165[1] * toward_165
    expected = {"VF": corner, "FV": np.array([0.05, 0.05]), "EE": [cross_x, cross_y]}
    for e in state.elements:
        np.testing.assert_allclose(e.normals, [[0, 0, 1]], atol=1e-12)
        assert abs(e.point[2]) < 1e-12
    got = {k: sorted(e.point[:2].tolist() for e in state.elements if e.kind.value == k)
           for k in ("VF", "FV", "EE")}  # fmt: skip
    np.testing.assert_allclose(got["VF"], [expected["VF"]], atol=1e-12)
    np.testing.assert_allclose(got["FV"], [expected["FV"]], atol=1e-12)
    np.testing.assert_allclose(got["EE"], sorted(p.tolist() for p in expected["EE"]), atol=1e-12)


def test_fv_normal_in_a_face_face_contact_is_the_environment_face_normal() -> None:
    # Face over the block's corner, the cube turned by 1e-4 rad about x (well inside the
    # merge angle of 3 * angle_tol = 0.012 rad): every element should keep the normal +z,
    # as the VF and EE elements do.
    G, E, X = scene_face_over_corner()
    state = find_contacts(G, E, pose_from_twist(np.r_[1e-4, 0, 0, 0, 0, 0]) @ X)
    assert kinds(state) == Counter({"VF": 1, "FV": 1, "EE": 2})
    for e in state.elements:
        np.testing.assert_allclose(e.normals, [[0, 0, 1]], atol=1e-12, err_msg=e.kind.value)


@pytest.mark.parametrize("tilt", [-1e-4, -0.011, -0.013, -0.1])
def test_fv_normal_snaps_within_the_merge_angle_only_and_alike_in_every_search(
    tilt: float,
) -> None:
    # Face over the block's corner, the cube turned by ``tilt`` about the x axis through that
    # corner (E's vertex stays on G's face): the FV normal -R n_G = (0, -sin, cos) becomes
    # E's top normal +z while within the merge angle 3 * angle_tol = 0.012 rad, and stays
    # -R n_G beyond it; the batched, single-frame and all-pairs searches agree.
    G, E, X = scene_face_over_corner()
    finder = ContactFinder(G, E)
    c = np.array([0.05, 0.05, 0.0])
    P = pose(t=c) @ pose_from_twist(np.r_[tilt, 0, 0, 0, 0, 0]) @ pose(t=-c) @ X
    state = finder.find(P)
    (fv,) = [e for e in state.elements if e.kind is ContactKind.FV]
    assert fv.environment == ("v", E.vertices.tolist().index([0.05, 0.05, 0.0]))
    inside = abs(tilt) < 3 * finder.angle_tol
    expected = [0.0, 0.0, 1.0] if inside else [0.0, -np.sin(tilt), np.cos(tilt)]
    np.testing.assert_allclose(fv.normals, [expected], atol=1e-12)
    _assert_same_states(finder.find_batch(P[None]), [state])
    _assert_same_states([finder.find_naive(P)], [state])


# --------------------------------------------------------------------------------------------
# Batched search (find_batch over (N, 4, 4) poses) against one frame at a time and naive
# --------------------------------------------------------------------------------------------


def _random_poses(G: Polyhedron, X: np.ndarray, d: float, n: int, seed: int) -> np.ndarray:
    """``n`` poses near ``X``: twists of about ``d`` (metres, and d / size in radians)."""
    rng = np.random.default_rng(seed)
    xis = np.c_[rng.normal(size=(n, 3)) * d / G.scale, rng.normal(size=(n, 3)) * d]
    return np.stack([pose_from_twist(xi) @ X for xi in xis])


def _assert_same_states(a: list[ContactState], b: list[ContactState]) -> None:
    assert len(a) == len(b)
    for k, (x, y) in enumerate(zip(a, b, strict=True)):
        assert x.key == y.key, k
        assert x.touching == y.touching, k
        for e, f in zip(x.elements, y.elements, strict=True):
            assert e.normals.shape == f.normals.shape, (k, e.key)
            np.testing.assert_allclose(e.point, f.point, atol=1e-12)
            np.testing.assert_allclose(e.normals, f.normals, atol=1e-12)


@pytest.mark.parametrize("kd", [False, True], ids=["dense", "kdtree"])
@pytest.mark.parametrize("name", sorted(CONSISTENCY_SCENES))
def test_batch_single_and_naive_agree_on_random_poses(
    name: str, kd: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The batched search (every stage one numpy pass over the frames), the same one frame at
    # a time and the all-pairs search with scalar cone tests find the same states: element
    # keys, touching pairs, ray counts, points and normals, at poses up to ~3 thresholds
    # off a contact (so contacts appear and disappear between frames).
    import apo.contact.model_data
    import apo.contact.search

    if kd:  # the k-d tree broad phase even for these small models
        monkeypatch.setattr(apo.contact.search, "_DENSE_LIMIT", 0)
    G, E, X = CONSISTENCY_SCENES[name]()
    d = 3 * default_threshold(G, E)
    poses = _random_poses(G, X, d, 12, seed=sorted(CONSISTENCY_SCENES).index(name))
    finder = ContactFinder(G, E, threshold=d)
    batch = finder.find_batch(poses)
    assert any(s.elements for s in batch)
    _assert_same_states(batch, [finder.find(P) for P in poses])
    _assert_same_states(batch, [finder.find_naive(P) for P in poses])


def test_batch_in_blocks_of_frames_and_with_far_frames(monkeypatch: pytest.MonkeyPatch) -> None:
    # Blocks of 3 frames (the block size is a memory bound only) and frames far apart (no
    # overlap of the bounding boxes) give the same states as one block.
    import apo.contact.model_data
    import apo.contact.search

    G, E, X = CONSISTENCY_SCENES["t_peg_seated"]()
    poses = _random_poses(G, X, 3 * default_threshold(G, E), 10, seed=7)
    poses[[2, 5]] = pose(t=(0.0, 0.5, 0.0)) @ X  # 50 cm away
    finder = ContactFinder(G, E)
    whole = finder.find_batch(poses)
    assert whole[2].elements == () and whole[2].touching == frozenset()
    monkeypatch.setattr(
        apo.contact.search, "_BATCH_PRIMITIVES", 3 * (2 * len(G.vertices) + len(G.edges))
    )
    _assert_same_states(finder.find_batch(poses), whole)
    _assert_same_states(finder.find_batch(list(poses)), whole)  # a list of 4x4 poses
    assert finder.find_batch(np.zeros((0, 4, 4))) == []


def test_batch_names_the_bad_pose() -> None:
    finder = ContactFinder(CUBE, TABLE)
    bad = np.stack([np.eye(4), np.full((4, 4), np.nan)])
    with pytest.raises(ValueError, match="pose 1: X_EG is not finite"):
        finder.find_batch(bad)
    with pytest.raises(ValueError, match="pose 0: X_EG rotation part is not a rotation matrix"):
        finder.find_batch([np.diag([1.0, 1.0, 2.0, 1.0])])
    with pytest.raises(ValueError, match="pose 1: X_EG must have shape"):
        finder.find_batch([np.eye(4), np.eye(3)])


@pytest.mark.realdata
def test_batch_matches_single_on_the_real_demonstration(real_data_dir: Path) -> None:
    # The first author's 41 poses at a 4 mm threshold: contacts appear from frame 12 on.
    from apo.io.meshes import load_polyhedron
    from apo.io.poses import load_demonstration

    peg = load_polyhedron(real_data_dir / "peg.step")
    hole = load_polyhedron(real_data_dir / "hole.step")
    X = load_demonstration(real_data_dir / "peg_in_hole.pose.list").X_EG
    finder = ContactFinder(peg, hole, threshold=0.004)
    batch = finder.find_batch(X)
    assert sum(1 for s in batch if s.elements) > 20
    _assert_same_states(batch, [finder.find(P) for P in X])
    _assert_same_states(batch[-3:], [finder.find_naive(P) for P in X[-3:]])
