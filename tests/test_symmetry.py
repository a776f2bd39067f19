"""Rigid symmetries of meshes (apo.symmetry): known groups, random shapes and motions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from apo.perception.example import peg_and_slot
from apo.perception.render import box_triangles
from apo.symmetry import (
    describe_symmetries,
    nearest_twin,
    pose_distance,
    symmetries,
    twin_poses,
)


def _moved(V: np.ndarray, X: np.ndarray) -> np.ndarray:
    return V @ X[:3, :3].T + X[:3, 3]


def _random_pose(rng: np.random.Generator, scale: float = 0.1) -> np.ndarray:
    X = np.eye(4)
    X[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    X[:3, 3] = rng.uniform(-scale, scale, 3)
    return X


def _prism(n: int, radius: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    """Convex prism over a regular n-gon (dihedral group: 2n rotations if height != 2r)."""
    a = 2 * np.pi * np.arange(n) / n
    ring = np.column_stack([radius * np.cos(a), radius * np.sin(a)])
    V = np.vstack(
        [np.column_stack([ring, np.zeros(n)]), np.column_stack([ring, np.full(n, height)])]
    )
    return V, ConvexHull(V).simplices


def _check_group(syms: list, V: np.ndarray, F: np.ndarray) -> None:
    Ss = [s.S for s in syms]
    assert np.allclose(Ss[0], np.eye(4))
    for A in Ss:
        assert np.allclose(A[:3, :3] @ A[:3, :3].T, np.eye(3), atol=1e-9)
        assert np.linalg.det(A[:3, :3]) > 0  # proper rotations only
        for B in Ss:  # closed under composition
            assert min(np.abs(A @ B - C).max() for C in Ss) < 1e-6


@pytest.mark.parametrize(
    ("extents", "count"),
    [((0.02, 0.02, 0.02), 24), ((0.02, 0.02, 0.05), 8), ((0.03, 0.02, 0.01), 4)],
)
def test_boxes(extents: tuple[float, float, float], count: int) -> None:
    # A cube: the 24 rotations of the octahedral group; a square peg: the 8 of D4 (4 about
    # its axis, 4 half-turns across it); a brick: the identity and 3 half-turns.
    V, F = box_triangles(extents)
    syms = symmetries(V, F)
    assert len(syms) == count
    _check_group(syms, V, F)


def test_t_peg_has_a_half_turn_about_its_axis() -> None:
    # The T-peg is an extruded symmetric T: only the half-turn about its (z) axis maps it
    # onto itself (a half-turn about x or y would put the head at the bottom).
    peg, _ = peg_and_slot()
    syms = symmetries(*peg)
    assert len(syms) == 2
    assert np.isclose(syms[1].angle, np.pi)
    assert np.allclose(syms[1].axis, [0, 0, 1])
    assert describe_symmetries(syms) == "2 (identity; 180 deg about z)"


def test_asymmetric_shape_has_identity_only() -> None:
    # An L-shaped union of two boxes of different sizes, and random convex hulls.
    rng = np.random.default_rng(1)
    for _ in range(5):
        P = rng.normal(size=(12, 3)) * [0.03, 0.02, 0.01]
        hull = ConvexHull(P)
        V = P[np.unique(hull.simplices)]
        idx = {int(v): k for k, v in enumerate(np.unique(hull.simplices))}
        F = np.vectorize(idx.get)(hull.simplices)
        syms = symmetries(V, F)
        assert len(syms) == 1
        assert describe_symmetries(syms) == "1 (identity only)"


@pytest.mark.parametrize("seed", range(6))
def test_random_prisms_under_random_motions(seed: int) -> None:
    # A regular n-gon prism has 2n rotations; moving the mesh rigidly keeps the count and
    # conjugates every symmetry: S' = X S X^-1.
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 9))
    radius = float(rng.uniform(0.01, 0.05))
    height = float(rng.uniform(0.3, 0.8)) * radius * (1 if rng.random() < 0.5 else 4)
    V, F = _prism(n, radius, height)
    X = _random_pose(rng)
    base = symmetries(V, F)
    moved = symmetries(_moved(V, X), F)
    assert len(base) == len(moved) == 2 * n
    _check_group(moved, _moved(V, X), F)
    Xi = np.linalg.inv(X)
    for s in base:
        conj = X @ s.S @ Xi
        assert min(np.abs(conj - m.S).max() for m in moved) < 1e-6
    # Every symmetry maps the vertex set onto itself.
    for s in moved:
        W = _moved(_moved(V, X), s.S)
        d = np.linalg.norm(W[:, None] - _moved(V, X)[None], axis=2).min(axis=1)
        assert d.max() < 1e-6


def test_tolerance_accepts_small_perturbations_only() -> None:
    V, F = box_triangles((0.02, 0.02, 0.02))
    rng = np.random.default_rng(3)
    noisy = V + rng.normal(scale=2e-6, size=V.shape)
    assert len(symmetries(noisy, F, tolerance=5e-5)) == 24
    stretched = V * [1.0, 1.0, 1.01]  # 0.2 mm longer along z: a square peg now
    assert len(symmetries(stretched, F, tolerance=2e-5)) == 8


def test_bad_input() -> None:
    with pytest.raises(ValueError, match="vertices must have shape"):
        symmetries(np.zeros((2, 3)), [[0, 1, 1]])
    with pytest.raises(ValueError, match="triangle indices"):
        symmetries(np.eye(3), [[0, 1, 3]])
    with pytest.raises(ValueError, match="no area"):
        symmetries(np.zeros((3, 3)), [[0, 1, 2]])
    with pytest.raises(ValueError, match="tolerance must be positive"):
        symmetries(*box_triangles((1, 1, 1)), tolerance=0.0)


@pytest.mark.parametrize("seed", range(5))
def test_nearest_twin_undoes_a_symmetric_flip(seed: int) -> None:
    # A pose near the reference, replaced by a random twin of itself, maps back to the
    # twin near the reference (the same pose up to the noise).
    rng = np.random.default_rng(seed)
    V, F = box_triangles((0.02, 0.02, 0.05), center=(0.001, -0.002, 0.01))
    syms = symmetries(V, F)
    X_ref = _random_pose(rng)
    small = np.eye(4)
    small[:3, :3] = Rotation.from_rotvec(rng.normal(scale=0.02, size=3)).as_matrix()
    small[:3, 3] = rng.normal(scale=0.001, size=3)
    X_true = X_ref @ small
    k = int(rng.integers(len(syms)))
    flipped = X_true @ syms[k].S
    got, j = nearest_twin(flipped, X_ref, syms, length=0.03)
    assert np.allclose(got, X_true, atol=1e-9)
    assert np.allclose(syms[k].S @ syms[j].S, np.eye(4), atol=1e-9)
    # Twins show the same surface.
    for T in twin_poses(X_true, syms):
        d = np.linalg.norm(_moved(V, T)[:, None] - _moved(V, X_true)[None], axis=2)
        assert d.min(axis=1).max() < 1e-9


def test_pose_distance() -> None:
    X = np.eye(4)
    Y = np.eye(4)
    Y[:3, :3] = Rotation.from_rotvec([0, 0, 0.5]).as_matrix()
    Y[:3, 3] = [0.003, 0.004, 0]
    assert np.isclose(pose_distance(Y, X, 0.0), 0.005)
    assert np.isclose(pose_distance(Y, X, 0.02), np.hypot(0.005, 0.01))
