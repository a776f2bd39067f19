"""The fast paths of ``ContactConstraints.correct`` give the slow paths' numbers bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

import apo.correction as corr
from apo import synthetic
from apo.contact import ContactFinder
from apo.correction import ContactConstraints


def _noisy_states(seed: int, sigma: float) -> list[tuple[object, object, np.ndarray, tuple]]:
    """(G, E, poses, elements) of each distinct state of a noisy random variant."""
    demo = synthetic.random_variant(seed)
    d = synthetic.add_noise(demo, sigma_mm=sigma, sigma_deg=sigma, seed=seed)
    finder = ContactFinder(d.grasped, d.environment, threshold=3.0 * max(sigma, 1.0) * 1e-3)
    states = {s.key: s for s in finder.find_batch(d.X_EG) if s.elements}
    return [(d.grasped, d.environment, d.X_EG, s.elements) for s in states.values()]


def _fields(res: corr.BatchCorrection) -> list[np.ndarray]:
    return [res.X_EG, res.residual_before, res.residual_after, res.iterations, res.flagged,
            res.displacement, res.rotation_change]  # fmt: skip


@pytest.mark.parametrize(("seed", "sigma"), [(4101, 1.0), (4102, 2.0), (4103, 3.0)])
def test_whole_steps_at_once_give_the_row_by_row_numbers(
    seed: int, sigma: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    rng = np.random.default_rng(seed)
    checked = 0
    for G, E, X, elements in _noisy_states(seed, sigma):
        cc = ContactConstraints(G, E, elements)
        # far poses too (turned by up to 25 deg): some steps are halved there
        far = X[rng.integers(0, len(X), 4)].copy()
        for k in range(len(far)):
            ax = rng.normal(size=3)
            ax /= np.linalg.norm(ax)
            far[k, :3, :3] = synthetic_rotation(ax, np.radians(rng.uniform(5, 25))) @ far[k, :3, :3]
        for poses in (X, far, X[:1]):
            fast = cc.correct(poses, max_iter=12, tol=1e-7, threshold=0.005)
            monkeypatch.setattr(corr, "_WHOLE_STEPS_AT_ONCE", False)
            slow = cc.correct(poses, max_iter=12, tol=1e-7, threshold=0.005)
            monkeypatch.setattr(corr, "_WHOLE_STEPS_AT_ONCE", True)
            for a, b in zip(_fields(fast), _fields(slow), strict=True):
                assert a.tobytes() == b.tobytes()
            checked += 1
    assert checked >= 3


def test_halved_steps_mixed_with_whole_ones(monkeypatch: pytest.MonkeyPatch) -> None:
    # A cube's top and bottom corners on one plane (no pose holds them): steps stall and are
    # halved, at some poses from the first iteration, at others later.
    from apo.contact import find_contacts
    from apo.shapes import box

    table = box([1.0, 1.0, 0.1], center=[0.0, 0.0, -0.05])
    cube = box([0.1, 0.1, 0.1], center=[0.0, 0.0, 0.05])
    lower = find_contacts(cube, table, np.eye(4)).elements
    upper = find_contacts(cube, table, _flipped()).elements
    cc = ContactConstraints(cube, table, tuple(lower) + tuple(upper))
    rng = np.random.default_rng(11)
    X = np.repeat(np.eye(4)[None], 12, axis=0)
    for k in range(12):
        ax = rng.normal(size=3)
        X[k, :3, :3] = synthetic_rotation(ax / np.linalg.norm(ax), rng.uniform(0.0, 0.5))
        X[k, :3, 3] = rng.normal(size=3) * 0.01
    calls: list[int] = []
    step = corr._step_poses

    def counted(omega: np.ndarray, v: np.ndarray, c: np.ndarray) -> np.ndarray:
        calls.append(len(omega))
        return step(omega, v, c)

    monkeypatch.setattr(corr, "_step_poses", counted)
    fast = cc.correct(X, max_iter=12, tol=1e-7)
    assert len(calls) > int(fast.iterations.max()) + 1  # some steps were halved
    monkeypatch.setattr(corr, "_WHOLE_STEPS_AT_ONCE", False)
    slow = cc.correct(X, max_iter=12, tol=1e-7)
    for a, b in zip(_fields(fast), _fields(slow), strict=True):
        assert a.tobytes() == b.tobytes()


def _flipped() -> np.ndarray:
    """The cube turned upside down about x through its centre (its top face on z = 0)."""
    X = np.eye(4)
    X[:3, :3] = np.diag([1.0, -1.0, -1.0])
    X[2, 3] = 0.1
    return X


def synthetic_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    from apo.spatial import matrix_from_axis_angle

    return np.asarray(matrix_from_axis_angle(axis, angle))


def test_step_rotation_is_the_twist_rotation_bit_for_bit() -> None:
    rng = np.random.default_rng(7)
    omega = rng.normal(size=(200, 3)) * rng.choice([1e-9, 1e-4, 0.1, 1.0], size=(200, 1))
    omega[:3] = 0.0
    c = rng.normal(size=(200, 3))
    v = rng.normal(size=(200, 3)) * 1e-3
    step = corr._step_poses(omega, v, c)
    twist = corr._poses_from_twists(np.concatenate([omega, np.zeros_like(omega)], axis=1))
    assert step[:, :3, :3].tobytes() == np.ascontiguousarray(twist[:, :3, :3]).tobytes()
    assert np.array_equal(step[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (200, 1)))


def test_cross_is_numpys_cross_on_broadcast_shapes() -> None:
    rng = np.random.default_rng(8)
    a = rng.normal(size=(5, 4, 3))
    for b in (rng.normal(size=(5, 4, 3)), rng.normal(size=(5, 1, 3)), rng.normal(size=(1, 4, 3))):
        assert np.array_equal(corr._cross(a, b), np.cross(a, b))
