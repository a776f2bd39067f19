"""Offline smoothing of tracked poses (apo.perception.smoothing) and its switch.

On noisy known trajectories (random piecewise constant-velocity motions with jumps, kinks
and stops, and the scripted demonstrations of apo.synthetic): the noise shrinks, a jump
or a kink stays sharp, a clean piecewise-linear trajectory comes back unchanged, the
recognised task model is the truth's; ``smooth=False`` / ``--no-smooth`` leave the poses
as registered.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from apo.perception.smoothing import pose_noise, smooth_poses
from apo.spatial import invert_pose, rotation_angle


def _errors(X: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pos = np.linalg.norm(X[:, :3, 3] - Y[:, :3, 3], axis=1)
    rot = np.array([rotation_angle(a[:3, :3].T @ b[:3, :3]) for a, b in zip(X, Y, strict=True)])
    return pos, rot


def _piecewise(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """A random motion of constant-velocity segments (some at rest); jumps and kinks between.

    Returns times, poses and the first frame of each segment after the first.
    """
    t = np.arange(n) * 0.1
    cuts = sorted(rng.choice(np.arange(8, n - 8), size=4, replace=False).tolist())
    X = np.zeros((n, 4, 4))
    R = Rotation.random(random_state=rng).as_matrix()
    p = rng.uniform(-0.1, 0.1, 3) + np.array([0.0, 0.0, 0.8])
    v, w = np.zeros(3), np.zeros(3)
    for i in range(n):
        if i == 0 or i in cuts:
            moving = rng.random() < 0.7
            v = rng.normal(0, 0.002, 3) * moving  # up to a few mm a frame
            w = rng.normal(0, np.radians(1.0), 3) * moving
            if i in cuts and rng.random() < 0.5:  # a jump as well as a kink
                p = p + rng.normal(0, 0.002, 3)
                R = Rotation.from_rotvec(rng.normal(0, np.radians(3), 3)).as_matrix() @ R
        X[i] = np.eye(4)
        X[i, :3, :3], X[i, :3, 3] = R, p
        p = p + v
        R = Rotation.from_rotvec(w).as_matrix() @ R
    return t, X, cuts


def _noisy(rng: np.random.Generator, X: np.ndarray, mm: float, deg: float) -> np.ndarray:
    Y = X.copy()
    dR = Rotation.from_rotvec(rng.normal(0, np.radians(deg), (len(X), 3))).as_matrix()
    Y[:, :3, :3] = dR @ X[:, :3, :3]
    Y[:, :3, 3] += rng.normal(0, mm * 1e-3, (len(X), 3))
    return Y


@pytest.mark.parametrize("seed", range(6))
def test_noise_shrinks_and_events_stay_sharp(seed: int) -> None:
    rng = np.random.default_rng(seed)
    t, X, cuts = _piecewise(rng, 120)
    Y = _noisy(rng, X, 0.3, 0.7)
    S = smooth_poses(t, Y)
    raw_pos, raw_rot = _errors(Y, X)
    pos, rot = _errors(S, X)
    # Over the whole sequence the noise shrinks (7-frame windows: about 0.5 of it)...
    assert np.median(rot) < 0.7 * np.median(raw_rot)
    assert np.median(pos) < 0.7 * np.median(raw_pos)
    # ...and next to each event (kink, jump) nothing is smeared: a window across a jump of
    # millimetres or degrees would put the frames beside it half-way.
    near = sorted({c + d for c in cuts for d in (-2, -1, 0, 1)})
    assert np.max(rot[near]) < np.radians(0.7 * 3.5), np.degrees(rot[near])
    assert np.max(pos[near]) < 0.3e-3 * 3.5 * np.sqrt(3), pos[near]


def test_noise_estimate_from_the_sequence() -> None:
    rng = np.random.default_rng(11)
    t, X, _ = _piecewise(rng, 200)
    s = pose_noise(t, _noisy(rng, X, 0.3, 0.7))
    assert np.allclose(s[:3], np.radians(0.7), rtol=0.25), np.degrees(s[:3])
    assert np.allclose(s[3:], 0.3e-3, rtol=0.25), s[3:]


def test_clean_piecewise_motion_is_returned_unchanged_and_gaps_stay() -> None:
    rng = np.random.default_rng(3)
    t, X, _ = _piecewise(rng, 80)
    S = smooth_poses(t, X)
    np.testing.assert_allclose(S, X, atol=1e-9)
    Y = _noisy(rng, X, 0.3, 0.7)
    Y[[10, 40, 41]] = np.nan  # lost frames
    valid = np.isfinite(Y[:, 0, 0])
    S = smooth_poses(t, Y, valid)
    assert np.isnan(S[~valid]).all() and np.isfinite(S[valid]).all()
    np.testing.assert_array_equal(smooth_poses(t, Y, valid, half_window=0)[valid], Y[valid])
    # No window spans a gap or a re-initialisation: a jump of 20 mm across either stays
    # sharp (the frames beside it stay within the noise).
    Z = Y.copy()
    Z[42:, :3, 3] += 0.02
    Z[60:, :3, 3] += 0.02
    restart = np.zeros(len(Z), dtype=bool)
    restart[60] = True
    S = smooth_poses(t, Z, valid, restart=restart)
    X2 = X.copy()
    X2[42:, :3, 3] += 0.02
    X2[60:, :3, 3] += 0.02
    near = [38, 39, 42, 43, 58, 59, 60, 61]
    assert np.max(_errors(S[near], X2[near])[0]) < 0.3e-3 * 4 * np.sqrt(3)
    # Too few frames to tell the noise from the motion: returned as registered.
    short = _noisy(rng, X[:15], 0.3, 0.7)
    assert np.isnan(pose_noise(t[:15], short)).all()
    np.testing.assert_array_equal(smooth_poses(t[:15], short), short)


@pytest.mark.parametrize("name", ["peg_in_hole_2d", "square_peg_in_hole"])
def test_smoothed_noisy_demonstration_gives_the_true_task(name: str) -> None:
    # The scripted demonstrations' contacts: states held for one or two frames, jumps of
    # 30 deg in one frame. Noise of a tracked part at about 1 m (0.3 mm, 0.7 deg per axis).
    from apo import synthetic
    from apo.recognition import recognize
    from apo.recognition.pipeline import TRACKED_FLOOR_SHARE

    d = getattr(synthetic, name)(120)
    truth = recognize(d.grasped, d.environment, d.times, d.X_EG_true)
    rng = np.random.default_rng(5)
    Y = _noisy(rng, np.asarray(d.X_EG_true), 0.3, 0.7)
    S = smooth_poses(d.times, Y)
    assert np.median(_errors(S, d.X_EG_true)[1]) < 0.7 * np.median(_errors(Y, d.X_EG_true)[1])
    got = recognize(d.grasped, d.environment, d.times, S, floor_share=TRACKED_FLOOR_SHARE)
    assert [s.id for s in got.states] == [s.id for s in truth.states]
    assert got.subskill_sequence() == truth.subskill_sequence()


def test_tracker_smooths_only_when_asked(tmp_path: Path) -> None:
    # smooth=False is the registration of each frame; smooth=True is exactly those poses
    # smoothed; X_EG follows X_CG either way.
    from apo.perception.example import (
        example_camera,
        insertion_trajectory,
        peg_and_slot,
    )
    from apo.perception.render import DepthNoise, render_demonstration
    from apo.perception.track import TrackOptions, track_frames

    cam, X_CE = example_camera(320, 240)
    peg, slot = peg_and_slot()
    times, X_EG = insertion_trajectory(30)
    render_demonstration(peg, slot, X_CE, X_EG, times, cam, tmp_path,
                         noise=DepthNoise(sigma_1m=6e-3), seed=2)  # fmt: skip
    init = {"init_grasped": X_CE @ X_EG[0], "init_environment": X_CE}
    off = track_frames(tmp_path, peg, slot, units="m", options=replace(TrackOptions(),
                       smooth=False), **init)  # fmt: skip
    on = track_frames(tmp_path, peg, slot, units="m", **init)
    centre = (peg[0].min(0) + peg[0].max(0)) / 2
    expect = smooth_poses(off.times, off.X_CG, ~off.lost, centre=centre, restart=off.reinitialised)
    np.testing.assert_allclose(on.X_CG, expect, atol=1e-12)
    moved = np.linalg.norm(on.X_CG[:, :3, 3] - off.X_CG[:, :3, 3], axis=1)
    assert np.count_nonzero(moved > 1e-6) >= 10, moved  # most frames are smoothed
    for r in (on, off):
        np.testing.assert_allclose(r.X_EG, np.einsum("ij,njk->nik", invert_pose(r.X_CE), r.X_CG))


def test_smooth_flags_of_track_and_analyze() -> None:
    from apo.cli import build_parser

    p = build_parser()
    common = ["--grasped", "g.stl", "--environment", "e.stl"]
    assert p.parse_args(["track", "F", *common, "--out", "o.csv"]).smooth is True
    assert p.parse_args(["track", "F", *common, "--out", "o.csv", "--no-smooth"]).smooth is False
    assert p.parse_args(["analyze", "F", *common, "--no-smooth"]).smooth is False
    assert p.parse_args(["analyze", "F", *common, "--smooth"]).smooth is True
