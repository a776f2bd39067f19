"""Tests of apo.correction: residual rows, recovery of exact contact poses, failure flags."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from apo.contact import (
    ContactElement,
    ContactKind,
    element_residuals,
    find_contacts,
    residual_counts,
)
from apo.correction import (
    ContactConstraints,
    correct_pose,
    correct_poses,
)
from apo.geometry import Polyhedron, polyhedron_from_triangles
from apo.shapes import block_with_square_hole, box, t_peg, u_block
from apo.spatial import matrix_from_axis_angle, pose_from_twist
from apo.synthetic import add_noise, peg_in_hole_2d

TABLE = box([1.0, 1.0, 0.1], center=[0.0, 0.0, -0.05])  # top face z = 0
CUBE = box([0.1, 0.1, 0.1], center=[0.0, 0.0, 0.05])  # bottom face z = 0 in its frame
POCKET = block_with_square_hole()  # pocket x, y in [-0.02, 0.02], floor z = 0.02
PEG = box([0.04, 0.04, 0.06], center=[0.0, 0.0, 0.03])
TPEG = t_peg()
SLOT = u_block(slot_depth=0.070)


def pose(R: np.ndarray | None = None, t: object = (0.0, 0.0, 0.0)) -> np.ndarray:
    X = np.eye(4)
    if R is not None:
        X[:3, :3] = R
    X[:3, 3] = np.asarray(t, dtype=float)
    return X


def scene_crossing_edges() -> tuple[Polyhedron, Polyhedron, np.ndarray]:
    # Cube on an edge (45 deg about x), that edge turned 0.2 rad about y and laid across the
    # table's convex edge x = 0.5: one EE element.
    R = matrix_from_axis_angle([0, 1, 0], 0.2) @ matrix_from_axis_angle([1, 0, 0], np.pi / 4)
    VG = CUBE.vertices @ R.T
    mid = 0.5 * (VG[CUBE.edges[:, 0]] + VG[CUBE.edges[:, 1]])
    return CUBE, TABLE, pose(R, np.array([0.5, 0.0, 0.0]) - mid[np.argmin(mid[:, 2])])


def scene_vertex_on_edge() -> tuple[Polyhedron, Polyhedron, np.ndarray]:
    # A cube corner on the table's convex edge: one singular VE element.
    R = matrix_from_axis_angle([1, 1, 1], 0.5)
    return CUBE, TABLE, pose(R, np.array([0.5, 0.0, 0.0]) - R @ np.array([-0.05, -0.05, 0.0]))


def scene_vertex_on_vertex() -> tuple[Polyhedron, Polyhedron, np.ndarray]:
    R = matrix_from_axis_angle([1, 1, 0], 0.4)
    return CUBE, TABLE, pose(R, np.array([0.5, 0.5, 0.0]) - R @ np.array([-0.05, -0.05, 0.0]))


# (scene, expected kinds, pose determined by the contacts?) with one line of reasoning.
SCENES: dict[str, tuple[Callable[[], tuple[Polyhedron, Polyhedron, np.ndarray]], str, bool]] = {
    # 4 VF of one face on a plane: 4 rows of rank 3 (redundant); x, y, yaw stay free.
    "block_on_table": (lambda: (CUBE, TABLE, pose()), "VF", False),
    # Peg seated in the pocket: 12 VF + 8 EE, every DOF constrained: the pose is unique.
    "peg_in_hole": (lambda: (PEG, POCKET, pose(t=(0, 0, 0.02))), "VF EE", True),
    # One EE element: one row, five DOF free.
    "crossing_edges": (scene_crossing_edges, "EE", False),
    # One singular VE element: two rows (distance to the edge line).
    "vertex_on_edge": (scene_vertex_on_edge, "VE", False),
    # One VV element: three rows.
    "vertex_on_vertex": (scene_vertex_on_vertex, "VV", False),
    # T-peg seated in the U-slot: 12 VE + 8 EV; z slides, so not unique.
    "t_peg_seated": (lambda: (TPEG, SLOT, pose(t=(0, 0.018, 0))), "VE EV", False),
}


def perturbed(X: np.ndarray, rng: np.random.Generator, mm: float, deg: float) -> np.ndarray:
    """X moved by a random twist about G's neighbourhood: ~mm millimetres, ~deg degrees."""
    w = rng.normal(size=3)
    w *= np.radians(deg) / np.linalg.norm(w)
    v = rng.normal(size=3)
    v *= mm * 1e-3 / np.linalg.norm(v)
    c = X[:3, 3]
    return pose_from_twist(np.concatenate([w, v - np.cross(w, c)])) @ X


# --------------------------------------------------------------------------------------------
# Residuals
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(SCENES))
def test_residual_rows_match_element_residuals(name: str) -> None:
    G, E, X = SCENES[name][0]()
    elements = find_contacts(G, E, X).elements
    assert {e.kind.value for e in elements} == set(SCENES[name][1].split())
    Xp = perturbed(X, np.random.default_rng(0), 1.0, 1.0)
    cc = ContactConstraints(G, E, elements)
    r, J = cc.residuals(Xp[None])
    r0, J0 = element_residuals(G, E, Xp, elements)
    start = np.concatenate([[0], np.cumsum(residual_counts(elements))])
    for i in range(len(elements)):
        rows = np.flatnonzero(cc.element_of_row == i)
        assert np.allclose(r[0, rows], r0[start[i] : start[i + 1]], atol=1e-15)
        assert np.allclose(J[0, rows], J0[start[i] : start[i + 1]], atol=1e-12)


@pytest.mark.parametrize("name", ["peg_in_hole", "crossing_edges", "t_peg_seated"])
def test_jacobian_matches_finite_differences(name: str) -> None:
    G, E, X = SCENES[name][0]()
    cc = ContactConstraints(G, E, find_contacts(G, E, X).elements)
    Xp = perturbed(X, np.random.default_rng(1), 2.0, 2.0)
    _, J = cc.residuals(Xp[None])
    h = 1e-7
    for j in range(6):
        xi = np.zeros(6)
        xi[j] = h
        rp, _ = cc.residuals((pose_from_twist(xi) @ Xp)[None])
        rm, _ = cc.residuals((pose_from_twist(-xi) @ Xp)[None])
        assert np.allclose((rp - rm)[0] / (2 * h), J[0, :, j], atol=1e-6), j


# --------------------------------------------------------------------------------------------
# Recovery
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(SCENES))
def test_perturbed_exact_pose_is_recovered(name: str) -> None:
    make, _, unique = SCENES[name]
    G, E, X = make()
    elements = find_contacts(G, E, X).elements
    rng = np.random.default_rng(2)
    for _ in range(5):
        Xp = perturbed(X, rng, 1.0, 1.0)
        res = correct_pose(G, E, Xp, elements)
        assert res.converged and not res.flagged
        assert res.residual_after < 1e-9 < 1e-6 < res.residual_before
        # Quadratic convergence: a few iterations from 1 mm / 1 deg.
        assert 1 <= res.iterations <= 5
        # The least movement: the correction is no larger than the perturbation.
        assert res.rotation_change <= np.radians(1.0) + 1e-9
        r, _ = element_residuals(G, E, res.X_EG, elements)
        assert np.abs(r).max() < 1e-9
        if unique:  # back to the exact pose: no vertex more than 1e-9 m off
            V = G.vertices
            moved = V @ res.X_EG[:3, :3].T + res.X_EG[:3, 3] - (V @ X[:3, :3].T + X[:3, 3])
            assert np.abs(moved).max() < 1e-9


def test_redundant_contacts_move_the_block_the_least() -> None:
    # 4 VF on a plane: rank 3 of 4 rows. From a pose lifted 2 mm and tilted 1 deg about
    # x (through the bottom centre), the least motion turns it back about its centroid and
    # lowers it: the centroid keeps its x and y, and nothing slides or yaws.
    Xp = pose(matrix_from_axis_angle([1, 0, 0], np.radians(1.0)), (0.0, 0.0, 0.002))
    elements = find_contacts(CUBE, TABLE, pose()).elements
    res = correct_pose(CUBE, TABLE, Xp, elements)
    assert res.converged and res.residual_after < 1e-12
    assert np.allclose(res.X_EG[:3, :3], np.eye(3), atol=1e-12)
    c_obs = Xp[:3, :3] @ [0, 0, 0.05] + Xp[:3, 3]
    assert np.allclose(res.X_EG[:3, 3], [c_obs[0], c_obs[1], 0.0], atol=1e-9)


def test_already_exact_pose_takes_no_iteration() -> None:
    G, E, X = SCENES["t_peg_seated"][0]()
    res = correct_pose(G, E, X, find_contacts(G, E, X).elements)
    assert res.iterations == 0 and res.converged and not res.flagged
    assert np.array_equal(res.X_EG, X) and res.displacement == 0.0


def test_no_elements_leave_the_pose_alone() -> None:
    X = pose(t=(0, 0, 0.3))
    res = correct_pose(CUBE, TABLE, X, ())
    assert res.converged and res.iterations == 0 and np.array_equal(res.X_EG, X)


def top_and_bottom_on_table() -> list[ContactElement]:
    """VF elements putting both the top and the bottom corners of CUBE on the table top."""
    top = int(np.flatnonzero(np.isclose(TABLE.face_normals[:, 2], 1.0))[0])
    n = np.array([[0.0, 0.0, 1.0]])
    return [
        ContactElement(ContactKind.VF, ("v", v), ("f", top), np.zeros(3), n)
        for v in range(len(CUBE.vertices))
    ]


def test_impossible_contact_set_is_flagged() -> None:
    # A rigid 0.1 m cube cannot have its top and bottom corners on one plane.
    res = correct_pose(CUBE, TABLE, pose(t=(0, 0, 0.001)), top_and_bottom_on_table())
    assert not res.converged and res.flagged
    # Some corner is always >= 0.05 m off the plane (the cube is 0.1 m across any way).
    assert res.residual_after >= 0.05 - 1e-12
    assert res.iterations < 20  # stalls instead of running out of iterations


def test_implausible_moves_are_flagged() -> None:
    elements = find_contacts(CUBE, TABLE, pose()).elements
    far = pose(t=(0, 0, 0.03))  # 30 mm above the table
    ok = correct_pose(CUBE, TABLE, far, elements)  # default: limit 10 x residual_before
    assert ok.converged and not ok.flagged and ok.displacement == pytest.approx(0.03)
    # With the 3 mm contact threshold the 30 mm move is implausible.
    bad = correct_pose(CUBE, TABLE, far, elements, threshold=0.003)
    assert bad.converged and bad.flagged
    tilted = pose(matrix_from_axis_angle([1, 0, 0], np.radians(8.0)))
    turned = correct_pose(CUBE, TABLE, tilted, elements)
    assert turned.converged and turned.flagged
    assert turned.rotation_change == pytest.approx(np.radians(8.0), rel=1e-6)
    assert not correct_pose(CUBE, TABLE, tilted, elements, max_rotation=0.2).flagged


def test_singular_state_with_many_redundant_rows() -> None:
    # The paper's state F of the T-peg (4 VV at both rims: 12 rows, rank 6) and its
    # neighbour C: the redundant rows do not blow the step up.
    d = peg_in_hole_2d()
    noisy = add_noise(d, sigma_mm=0.5, sigma_deg=0.5, seed=11)
    for k in (int(np.flatnonzero(d.labels == s)[0]) for s in (2, 5)):
        elements = find_contacts(d.grasped, d.environment, d.X_EG_true[k]).elements
        res = correct_pose(d.grasped, d.environment, noisy.X_EG[k], elements)
        assert res.converged and not res.flagged and res.residual_after < 1e-9


# --------------------------------------------------------------------------------------------
# Batches
# --------------------------------------------------------------------------------------------


def test_correct_poses_batches_by_state_and_keeps_the_order() -> None:
    d = peg_in_hole_2d(n_frames=40)
    noisy = add_noise(d, sigma_mm=0.5, sigma_deg=0.3, seed=3)
    states = {
        i: find_contacts(d.grasped, d.environment, d.X_EG_true[int(np.argmax(d.labels == i))])
        for i in range(len(d.true_states))
    }
    elements_seq = [states[int(s)].elements for s in d.labels]
    res = correct_poses(d.grasped, d.environment, noisy.X_EG, elements_seq)
    assert len(res) == len(d)
    assert res.converged.all() and not res.flagged.any()
    assert res.residual_after.max() < 1e-9
    free = d.labels == 0
    assert np.array_equal(res.X_EG[free], noisy.X_EG[free]) and (res.iterations[free] == 0).all()
    # Each frame as if corrected alone.
    for k in (3, 17, 31):
        one = correct_pose(d.grasped, d.environment, noisy.X_EG[k], elements_seq[k])
        assert np.allclose(one.X_EG, res.X_EG[k], atol=1e-12)
        assert one.iterations == res[k].iterations
    # Where the state fixes the pose (seated: only the z-slide is free), the correction
    # lands within the noise of the truth in the determined directions.
    seated = np.flatnonzero(d.labels == 7)
    dx = res.X_EG[seated, :2, 3] - d.X_EG_true[seated, :2, 3]
    assert np.abs(dx).max() < 1e-9


def transformed(poly: Polyhedron, T: np.ndarray) -> Polyhedron:
    """The same model with its vertices moved by T (same feature ids)."""
    V = poly.vertices @ T[:3, :3].T + T[:3, 3]
    return polyhedron_from_triangles(V, np.concatenate(poly.face_triangles), name=poly.name)


@pytest.mark.parametrize("name", ["block_on_table", "crossing_edges"])
def test_result_moves_with_the_whole_scene(name: str) -> None:
    # The step is the least motion of G (rotation about G's centroid, scaled by its size),
    # not of E's origin: moving the environment frame moves the corrected pose with it,
    # even where the contacts leave the pose free (redundant and under-determined sets).
    G, E, X = SCENES[name][0]()
    Xp = perturbed(X, np.random.default_rng(4), 1.0, 1.0)
    a = correct_pose(G, E, Xp, find_contacts(G, E, X).elements)
    T = pose(matrix_from_axis_angle([1, 2, 3], 0.7), (3.0, -2.0, 5.0))
    E2 = transformed(E, T)
    b = correct_pose(G, E2, T @ Xp, find_contacts(G, E2, T @ X).elements)
    assert a.iterations == b.iterations
    assert np.allclose(b.X_EG, T @ a.X_EG, atol=1e-9)
    assert b.displacement == pytest.approx(a.displacement, rel=1e-6)


def test_validation() -> None:
    elements = find_contacts(CUBE, TABLE, pose()).elements
    with pytest.raises(ValueError, match=r"shape \(4, 4\)"):
        correct_pose(CUBE, TABLE, np.eye(3), elements)
    with pytest.raises(ValueError, match="not finite"):
        correct_poses(CUBE, TABLE, np.full((2, 4, 4), np.nan), [elements, elements])
    with pytest.raises(ValueError, match="not a rotation"):
        correct_pose(CUBE, TABLE, np.diag([1.0, 1.0, 2.0, 1.0]), elements)
    with pytest.raises(ValueError, match="1 entries for 2 poses"):
        correct_poses(CUBE, TABLE, np.stack([np.eye(4)] * 2), [elements])
    with pytest.raises(ValueError, match="tol must be a positive"):
        correct_pose(CUBE, TABLE, np.eye(4), elements, tol=0.0)
    bad = ContactElement(ContactKind.VF, ("v", 99), ("f", 0), np.zeros(3), np.eye(3)[:1])
    with pytest.raises(ValueError, match=r"element 0: feature \('v', 99\)"):
        ContactConstraints(CUBE, TABLE, [bad])
