"""Inside a closed mesh by ray parity (apo.perception.meshdistance) and its use by the
non-penetration rows and the penetration share (apo.perception.register)."""

from __future__ import annotations

import numpy as np
import pytest

from apo import synthetic
from apo.perception.example import polyhedron_triangles
from apo.perception.meshdistance import ClosedMesh, is_closed
from apo.perception.register import ModelCloud, _non_penetration, penetration
from apo.perception.variants import DEMOS
from apo.spatial import pose_from_twist


def _models(demo: str) -> tuple[ModelCloud, ModelCloud]:
    d = getattr(synthetic, demo)(20)
    G = ModelCloud(polyhedron_triangles(d.grasped), seed=1)
    E = ModelCloud(polyhedron_triangles(d.environment), spacing=0.0005, max_dense=60000, seed=1)
    return G, E


def _winding(V: np.ndarray, T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """The generalised winding number (sum of solid angles), the reference."""
    a, b, c = (V[T[:, k]][None] - P[:, None] for k in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
    det = np.einsum("ntk,ntk->nt", a, np.cross(b, c))
    dot = lambda x, y: np.einsum("ntk,ntk->nt", x, y)  # noqa: E731
    den = la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb
    return np.arctan2(det, den).sum(axis=1) / (2 * np.pi)


@pytest.mark.parametrize("demo", DEMOS)
@pytest.mark.parametrize("seed", [0, 1])
def test_inside_by_parity_is_the_winding_number(demo: str, seed: int) -> None:
    _, E = _models(demo)
    rng = np.random.default_rng(seed)
    lo, hi = E.vertices.min(0), E.vertices.max(0)
    P = rng.uniform(lo - 0.003, hi + 0.003, size=(3000, 3))
    # and points near the faces, on both sides
    near = E.dense_points[rng.choice(len(E.dense_points), 1000)]
    P = np.vstack([P, near + rng.normal(0, 0.0005, near.shape)])
    inside = ClosedMesh(E.vertices, E.triangles).inside(P)
    w = _winding(E.vertices, E.triangles, P)
    assert np.all(np.isclose(np.abs(w), 1.0, atol=1e-6) | np.isclose(w, 0.0, atol=1e-6))
    np.testing.assert_array_equal(inside, np.abs(w) > 0.5)
    assert 0.1 < inside.mean() < 0.9


def test_closed_mesh_and_an_open_one() -> None:
    _, E = _models(DEMOS[0])
    assert is_closed(E.vertices, E.triangles)
    V = E.vertices[E.triangles].reshape(-1, 3)  # one copy per triangle, as an STL file
    T = np.arange(len(V)).reshape(-1, 3)
    assert is_closed(V, T) and ModelCloud((V, T)).closed() is not None
    assert not is_closed(V, T[1:]) and ModelCloud((V, T[1:])).closed() is None


@pytest.mark.parametrize("demo", DEMOS)
def test_inside_samples_are_the_nearest_samples_of_the_points_inside(demo: str) -> None:
    _, E = _models(demo)
    rng = np.random.default_rng(4)
    base = E.dense_points[rng.choice(len(E.dense_points), 2000)]
    P = base + rng.normal(0, 0.003, base.shape)
    side, dist, idx = E.inside_samples(P, max_distance=0.01)
    ref = E.nearest_sample(P, max_distance=0.01)
    ins = E.closed().inside(P)
    np.testing.assert_array_equal(idx[ins], ref[2][ins])
    np.testing.assert_array_equal(side[ins], ref[0][ins])
    np.testing.assert_array_equal(dist[ins], ref[1][ins])
    assert np.all(idx[~ins] == -1) and np.all(np.isinf(side[~ins]))


@pytest.mark.parametrize("demo", DEMOS)
def test_non_penetration_and_penetration_against_querying_every_sample(demo: str) -> None:
    # The rows and the share are those of the nearest dense samples, less the samples the
    # exact test puts outside (near the obstacle's edges a nearest sample can say "inside"
    # for a point outside).
    G, E = _models(demo)
    plain = ModelCloud((E.vertices, E.triangles), spacing=0.0005, max_dense=60000, seed=1)
    plain._closed = False  # every point queried (the path before the inside test)
    rng = np.random.default_rng(7)
    X_CE = pose_from_twist(np.r_[0.1, -0.2, 0.05, 0.01, 0.02, 0.5])
    centre = E.vertices.mean(0)
    fewer = rows = 0
    for _ in range(30):
        X_EG = pose_from_twist(np.r_[rng.normal(0, 0.3, 3), centre + rng.normal(0, 0.01, 3)])
        X_CG = X_CE @ X_EG
        q, n, r = _non_penetration(G, (E, X_CE))(X_CG)
        q0, n0, r0 = _non_penetration(G, (plain, X_CE))(X_CG)
        keep = (q0[:, None] == q[None]).all(axis=2).any(axis=1)
        assert keep.sum() == len(q)
        np.testing.assert_array_equal(r, r0[keep])
        np.testing.assert_array_equal(n, n0[keep])
        fewer += int(len(q0) - len(q))
        rows += len(q)
        assert penetration(X_CG, G, (E, X_CE)) <= penetration(X_CG, G, (plain, X_CE))
    assert rows > 50, rows  # the poses do penetrate
