"""Tracking rendered sequences (apo.perception.register, apo.perception.track).

The scene is the built-in insertion (apo.perception.example): 50 mm parts, camera at 0.33 m,
rendered at 320x240 with realistic depth noise (sigma = 1.5 mm at 1 m, 0.16 mm at the parts).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from apo.errors import TrackingLostError
from apo.perception.example import example_camera, insertion_trajectory, peg_and_slot
from apo.perception.render import DepthNoise, render_demonstration
from apo.perception.segment import ColourModel
from apo.spatial import invert_pose, pose_from_twist, rotation_angle, transform_points

pytest.importorskip("open3d")

from apo.perception.register import ModelCloud, free_space_violation, initialise, register
from apo.perception.track import TrackOptions, TrackResult, track_frames

NOISE = DepthNoise(sigma_1m=1.5e-3)


def errors(X_est: np.ndarray, X_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pos = np.linalg.norm(X_est[..., :3, 3] - X_true[..., :3, 3], axis=-1) * 1e3
    R = np.einsum("...ji,...jk->...ik", X_est[..., :3, :3], X_true[..., :3, :3])
    rot = np.degrees([rotation_angle(r) for r in R.reshape(-1, 3, 3)])
    return pos, rot


RZ180 = np.diag([-1.0, -1.0, 1.0, 1.0])  # both parts are symmetric under it


def sym_errors(X_est: np.ndarray, X_true: np.ndarray) -> tuple[float, float]:
    """Pose error (mm, deg) up to the parts' 180 deg symmetry about their z axis."""
    best = min(
        (errors(X_est @ S, X_true) for S in (np.eye(4), RZ180)),
        key=lambda e: float(np.max(e[1])),
    )
    return float(np.max(best[0])), float(np.max(best[1]))


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict:
    cam, X_CE = example_camera(320, 240)
    peg, slot = peg_and_slot()
    times, X_EG = insertion_trajectory(12, duration=1.2)
    root = tmp_path_factory.mktemp("frames")
    render_demonstration(peg, slot, X_CE, X_EG, times, cam, root, noise=NOISE, seed=0, hand=True)
    return {"root": root, "cam": cam, "X_CE": X_CE, "X_EG": X_EG, "peg": peg, "slot": slot}


def track_from_the_true_start(scene: dict) -> TrackResult:
    """Track the scene from the true initial poses."""
    X_CE = scene["X_CE"]
    return track_frames(
        scene["root"], scene["peg"], scene["slot"], units="m",
        init_grasped=X_CE @ scene["X_EG"][0], init_environment=X_CE,
    )  # fmt: skip


def test_tracking_with_initial_poses_within_bounds(scene: dict) -> None:
    X_CE = scene["X_CE"]
    res = track_from_the_true_start(scene)
    assert not res.lost.any()
    assert np.all(res.confidence > 0.9)
    pos, rot = errors(res.X_EG, scene["X_EG"])
    # Bounds: the benchmark's targets (1 mm, 0.5 deg) on every frame, a quarter of them median.
    assert np.median(pos) < 0.25 and pos.max() < 1.0
    assert np.median(rot) < 0.15 and rot.max() < 0.5
    env_pos, env_rot = errors(res.X_CE, X_CE)
    assert env_pos < 0.2 and env_rot < 0.2
    np.testing.assert_allclose(res.X_EG, np.einsum("ij,njk->nik", invert_pose(res.X_CE), res.X_CG))
    np.testing.assert_allclose(res.times, np.linspace(0, 1.2, 12), atol=1e-6)
    assert res.X_WC is not None


def test_tracking_without_initial_poses(scene: dict) -> None:
    # Global initialisation; both parts have a 180 deg symmetry about z, so compare shapes.
    res = track_frames(scene["root"], scene["peg"], scene["slot"], units="m")
    X_CG_true = scene["X_CE"] @ scene["X_EG"]
    env_pos, env_rot = sym_errors(res.X_CE, scene["X_CE"])
    assert env_pos < 0.2 and env_rot < 0.2
    assert not res.lost.any()
    for a, b in zip(res.X_CG, X_CG_true, strict=True):
        pos, rot = sym_errors(a, b)
        assert pos < 1.0 and rot < 0.5


def test_robust_kernel_rejects_outliers() -> None:
    peg, _ = peg_and_slot()
    model = ModelCloud(peg)
    rng = np.random.default_rng(0)
    X_true = np.eye(4)
    X_true[:3, 3] = [0.01, -0.02, 0.35]
    pts = transform_points(X_true, model.points[rng.choice(len(model.points), 1000)])
    pts += rng.normal(0, 1e-4, pts.shape)
    outliers = X_true[:3, 3] + rng.uniform(-0.03, 0.03, (300, 3))  # 23 % clutter
    obs = np.vstack([pts, outliers])
    start = pose_from_twist([0.05, -0.04, 0.03, 0.003, -0.002, 0.002]) @ X_true
    tukey = register(obs, model, start, loss="tukey")
    pos, rot = errors(tukey.X_CM, X_true)
    assert pos < 0.1 and rot < 0.1
    assert 0.7 < tukey.fitness < 0.85  # the clutter is not explained


def test_free_space_check_on_every_other_pixel_estimates_the_same_fraction() -> None:
    from apo.perception.render import rasterize

    cam, X_CE = example_camera(320, 240)
    peg, _ = peg_and_slot()
    model = ModelCloud(peg)
    X_true = X_CE @ insertion_trajectory(5)[1][1]
    depth, _ = rasterize(transform_points(X_true, peg[0]), peg[1], cam)
    fractions = []
    for shift in (0.0, 0.012):  # the model 12 mm towards the camera: the peg is seen behind it
        X = X_true.copy()
        X[:3, 3] -= shift * X[:3, 3] / np.linalg.norm(X[:3, 3])
        full = free_space_violation(X, model, depth, cam)
        half = free_space_violation(X, model, depth, cam, step=2)
        assert abs(half - full) < 0.05
        fractions.append(full)
    assert fractions[0] == 0.0 and fractions[1] > 0.3


def test_initialise_finds_pose_from_scratch() -> None:
    peg, _ = peg_and_slot()
    model = ModelCloud(peg)
    X_true = pose_from_twist([0.4, 1.0, -0.7, 0.0, 0.0, 0.0])
    X_true[:3, 3] = [0.02, 0.01, 0.3]
    visible = model.points[model.normals @ (invert_pose(X_true)[:3, :3] @ -X_true[:3, 3]) > 0]
    result = initialise(transform_points(X_true, visible), model, seed=0)
    assert result.fitness > 0.95
    pos, rot = sym_errors(result.X_CM, X_true)
    assert pos < 0.2 and rot < 0.2


def test_lost_frames_are_flagged_and_tracking_recovers(tmp_path: Path) -> None:
    cam, X_CE = example_camera(320, 240)
    peg, slot = peg_and_slot()
    times, X_EG = insertion_trajectory(10, duration=1.0)
    X_EG[4:6, :3, 3] += [0.0, 0.0, 2.0]  # frames 4, 5: the peg leaves the view (2 m up)
    render_demonstration(peg, slot, X_CE, X_EG, times, cam, tmp_path, noise=NOISE, seed=1)
    res = track_frames(
        tmp_path, peg, slot, units="m", init_grasped=X_CE @ X_EG[0], init_environment=X_CE
    )
    assert res.lost.tolist() == [False] * 4 + [True] * 2 + [False] * 4
    assert np.isnan(res.X_EG[4:6]).all()
    assert np.all(res.confidence[4:6] < 0.6)
    for k in (6, 7, 8, 9):  # recovered by global re-initialisation
        pos, rot = sym_errors(res.X_EG[k], X_EG[k])
        assert pos < 1.0 and rot < 0.5


def test_environment_not_found_raises(scene: dict) -> None:
    red = TrackOptions(colour=ColourModel((1.0, 0.0, 0.0), 0.05, 0.3))  # the parts are white
    with pytest.raises(TrackingLostError, match="environment object not found"):
        track_frames(scene["root"], scene["peg"], scene["slot"], units="m", options=red)


def recognise_rendered_builtin(
    root: Path, *, width: int, height: int, n_frames: int, hand: bool, seed: int
) -> tuple[object, object, np.ndarray, np.ndarray]:
    """Render apo demo's example from its true poses, track it, recognise truth and tracking.

    Returns the task from the true poses, the task from the tracked poses, and the tracking
    errors (mm, deg) of every frame.
    """
    from apo.perception.example import render_builtin
    from apo.recognition import recognize

    r = render_builtin(
        root, width=width, height=height, n_frames=n_frames, noise=NOISE, seed=seed, hand=hand
    )
    res = track_frames(
        r.frames, r.grasped, r.environment, units="m", init_grasped=r.X_CG0, init_environment=r.X_CE
    )
    assert not res.lost.any()
    d = r.demo
    truth = recognize(d.grasped, d.environment, d.times, d.X_EG_true)
    observed = recognize(d.grasped, d.environment, res.times, res.X_EG)
    pos, rot = errors(res.X_EG, d.X_EG_true)
    return truth, observed, pos, rot


# With the hand, seed 3: the second frame moves 12 mm with no velocity to predict it; an ICP
# stopped on its iteration limit left it 1.7 mm off before the tracker let it settle.
@pytest.mark.parametrize(("hand", "seed"), [(False, 0), (True, 3)])
def test_recognition_from_rendered_frames_matches_true_poses(
    tmp_path: Path, hand: bool, seed: int
) -> None:
    """apo demo's example (peg_in_hole_2d, states A-H), rendered at 320x240 and tracked."""
    truth, observed, pos, rot = recognise_rendered_builtin(
        tmp_path, width=320, height=240, n_frames=30, hand=hand, seed=seed
    )
    assert len(truth.subskill_sequence()) == 9  # Fig. 25: 3 push-to pairs, 3 slides
    assert observed.subskill_sequence() == truth.subskill_sequence()
    assert [s.id for s in observed.states] == [s.id for s in truth.states]
    assert np.median(pos) < 0.25 and pos.max() < 1.0
    assert np.median(rot) < 0.15 and rot.max() < 0.5


# Seed 7: the peg turns 27 deg upright within one frame (E -> F); a pose 1.5 deg off scored
# confidence 0.993 there until the tracker also required an RMS residual like the last frames'.
@pytest.mark.slow
@pytest.mark.parametrize("seed", [3, 7])
def test_recognition_from_rendered_frames_full_demo_with_hand(tmp_path: Path, seed: int) -> None:
    """The whole built-in example (60 frames) at 640x480, with a hand occluding the peg."""
    truth, observed, pos, rot = recognise_rendered_builtin(
        tmp_path, width=640, height=480, n_frames=60, hand=True, seed=seed
    )
    assert observed.subskill_sequence() == truth.subskill_sequence()
    assert [t.critical for t in observed.transitions] == [t.critical for t in truth.transitions]
    # While the peg pivots over the rim (state D) the wrist hides the crossbar's top face,
    # the only face in view that fixes the position along the stem: it rests on edges and
    # silhouettes there, 0.7 to 1.0 mm off over seeds 0-8 (0.98 mm at seed 3), 0.06 elsewhere.
    assert np.median(pos) < 0.25 and pos.max() < 1.5
    assert np.median(rot) < 0.15 and rot.max() < 0.5


@pytest.mark.parametrize(
    "name", ["peg_in_hole_2d", "square_peg_in_hole", "block_on_table_to_corner", "block_tipping"]
)
def test_synthetic_camera_keeps_the_demonstration_in_view(name: str) -> None:
    from apo.perception.example import polyhedron_triangles, synthetic_camera
    from apo.synthetic import all_demos

    d = all_demos()[name]
    cam, X_CE = synthetic_camera(d, 320, 240)
    G = polyhedron_triangles(d.grasped)[0]
    P = [transform_points(X_CE, d.environment.vertices)]
    P += [transform_points(X_CE @ X, G) for X in d.X_EG_true]
    uv = cam.project(np.vstack(P))
    assert np.all(np.vstack(P)[:, 2] > 0.1)  # in front of the camera, and inside the image:
    assert np.all((uv >= 0) & (uv <= [cam.width - 1, cam.height - 1]))


@pytest.mark.slow
@pytest.mark.parametrize(
    "name", ["square_peg_in_hole", "block_on_table_to_corner", "block_tipping"]
)
def test_recognition_from_rendered_synthetic_demonstrations(tmp_path: Path, name: str) -> None:
    """The other apo.synthetic demonstrations, rendered at 320x240 from their true poses."""
    from apo.perception.example import render_synthetic
    from apo.recognition import recognize
    from apo.synthetic import all_demos

    d = all_demos()[name]
    r = render_synthetic(d, tmp_path, width=320, height=240, noise=NOISE, seed=1)
    res = track_frames(
        r.frames, r.grasped, r.environment, units="m", init_grasped=r.X_CG0, init_environment=r.X_CE
    )
    assert not res.lost.any()
    pos, rot = errors(res.X_EG, d.X_EG_true)
    assert np.median(pos) < 0.25 and pos.max() < 1.0
    assert np.median(rot) < 0.5 and rot.max() < 1.0
    truth = recognize(d.grasped, d.environment, d.times, d.X_EG_true)
    observed = recognize(d.grasped, d.environment, res.times, res.X_EG)
    assert observed.subskill_sequence() == truth.subskill_sequence()
    assert [s.id for s in observed.states] == [s.id for s in truth.states]


def test_tracking_without_background_frames_uses_the_table_plane(tmp_path: Path) -> None:
    cam, X_CE = example_camera(320, 240)
    peg, slot = peg_and_slot()
    times, X_EG = insertion_trajectory(6, duration=0.6)
    render_demonstration(
        peg, slot, X_CE, X_EG, times, cam, tmp_path, noise=NOISE, seed=4, background=False
    )
    assert not (tmp_path / "background").exists()
    res = track_frames(
        tmp_path, peg, slot, units="m", init_grasped=X_CE @ X_EG[0], init_environment=X_CE
    )
    assert not res.lost.any()
    for a, b in zip(res.X_EG, X_EG, strict=True):  # fast motion: re-initialised frames may
        pos, rot = sym_errors(a, b)  # come back in the symmetric pose
        assert pos < 1.0 and rot < 0.5


def test_first_tukey_scale_follows_the_prediction_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Once three frames are tracked in a row, the projective ICP from the prediction starts
    # at start_factor times the last prediction errors (under a millimetre at 40 frames),
    # not at the reach: fewer steps (113 against 140 when written), the same poses within
    # 0.05 mm.
    import apo.perception.register as register

    cam, X_CE = example_camera(320, 240)
    peg, slot = peg_and_slot()
    times, X_EG = insertion_trajectory(40)
    render_demonstration(peg, slot, X_CE, X_EG, times, cam, tmp_path, noise=NOISE, seed=1)
    runs: list[tuple[float, int]] = []
    real = register.projective_icp

    def counted(*args: object, **kw: object) -> object:
        res = real(*args, **kw)  # type: ignore[arg-type]
        runs.append((float(kw["start_scale"]), res.iterations))  # type: ignore[arg-type]
        return res

    monkeypatch.setattr(register, "projective_icp", counted)

    def run(factor: float | None) -> tuple[np.ndarray, list[tuple[float, int]]]:
        runs.clear()
        res = track_frames(
            tmp_path, peg, slot, units="m", init_grasped=X_CE @ X_EG[0], init_environment=X_CE,
            options=TrackOptions(start_factor=factor),
        )  # fmt: skip
        assert not res.lost.any()
        return res.X_EG, list(runs)

    X_fast, fast = run(3.0)
    X_full, full = run(None)
    reach = min(s for s, _ in full)
    assert reach >= 0.006
    assert sum(s < 0.5 * reach for s, _ in fast) >= 20
    assert sum(i for _, i in fast) < sum(i for _, i in full)
    pos, rot = errors(X_fast, X_full)
    assert pos.max() < 0.05 and rot.max() < 0.02, (pos.max(), rot.max())  # 0.037 / 0.006


_POOLED_FIELDS = {
    # register.evaluate: the fitness and the penetration scored on a thread of the pool
    # while the surface check renders
    "evaluate": ("X_CM", "fitness", "rmse", "n_points", "violation", "penetration", "surface"),
    # projective.projective_icp: each step's non-penetration rows computed on a thread of
    # the pool while the model renders
    "projective_icp": ("X_CM", "pairs", "rms", "iterations", "converged"),
}


@pytest.mark.parametrize("name", sorted(_POOLED_FIELDS))
def test_work_on_the_pools_second_thread_gives_the_same_numbers(
    scene: dict, monkeypatch: pytest.MonkeyPatch, name: str
) -> None:
    # The frame loop's pooled calls return what the same call on one thread returns.
    import apo.perception.register as register

    real = getattr(register, name)
    pooled = 0

    def both(*args: object, **kw: object) -> object:
        nonlocal pooled
        got = real(*args, **kw)
        if kw.get("pool") is not None and (name == "evaluate" or kw.get("constraint")):
            pooled += 1
            alone = real(*args, **{**kw, "pool": None})
            for field in _POOLED_FIELDS[name]:
                np.testing.assert_array_equal(getattr(got, field), getattr(alone, field), field)
        return got

    monkeypatch.setattr(register, name, both)
    res = track_from_the_true_start(scene)
    assert not res.lost.any()
    assert pooled >= len(res.times)  # every frame's projective run and its scoring
