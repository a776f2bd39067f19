"""Execution in MuJoCo (apo.sim): contact parameters, the compliant hand, replay verdicts."""

from __future__ import annotations

import dataclasses
import json
from functools import cache
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mujoco")
pytest.importorskip("shapely")

from apo.cli import main
from apo.motion import plan, program_from_dict, program_to_dict
from apo.recognition import recognize_frames
from apo.sim.hand import Hand
from apo.sim.replay import replay
from apo.sim.scene import ContactParameters, build_scene
from apo.synthetic import add_noise, all_demos, peg_in_hole_2d, random_variant


@cache
def _peg_task():  # type: ignore[no-untyped-def]
    demo = peg_in_hole_2d()
    noisy = add_noise(demo, sigma_mm=0.5, sigma_deg=0.5, seed=3)
    rec = recognize_frames(demo.grasped, demo.environment, noisy.times, noisy.X_EG, units="mm")
    return demo, rec.task


def test_contact_parameters_are_the_stated_ones() -> None:
    import mujoco

    demo = peg_in_hole_2d()
    scene = build_scene(demo.grasped, demo.environment, X_WG=demo.X_EG_true[0])
    m = scene.model
    p = ContactParameters()
    assert (p.timestep, p.solref, p.solimp, p.impratio) == (
        0.001, (0.002, 1.0), (0.99, 0.999, 0.0001), 10.0,
    )  # fmt: skip
    assert m.opt.timestep == p.timestep
    assert m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    assert m.opt.impratio == p.impratio
    assert np.allclose(m.geom_solref, p.solref)
    assert np.allclose(m.geom_solimp[:, :3], p.solimp)
    assert np.allclose(m.geom_friction[:, 0], p.friction)
    hand = m.body("hand")
    assert m.body_mass[hand.id] == pytest.approx(1.0)
    # the hand carries no collision geometry of its own: only the grasped pieces collide
    assert set(np.flatnonzero(m.geom_bodyid == hand.id)) == set(scene.grasped_geoms)


@pytest.mark.parametrize("clearance", [0.0002, 0.00005])
def test_pushing_on_the_floor_senses_the_force_and_barely_sinks(clearance: float) -> None:
    demo = peg_in_hole_2d()
    X_seated = demo.X_EG_true[-1]
    X0 = X_seated.copy()
    X0[1, 3] += 0.003
    scene = build_scene(demo.grasped, demo.environment, X_WG=X0, clearance=clearance)
    hand = Hand(scene)
    S = np.diag([0.0, 1.0, 0.0])
    for _ in range(800):
        F, _ = hand.step(X0, scene.com_G, S_t=S, force=np.array([0.0, -5.0, 0.0]))
    assert F[1] == pytest.approx(5.0, rel=0.02)  # the sensed reaction equals the push
    assert hand.max_penetration < 5e-5  # < 0.05 mm, with the impact
    # the shrunk peg rests `clearance` lower than the model would (its bottom moved up)
    assert hand.pose()[1, 3] == pytest.approx(X_seated[1, 3] - clearance, abs=2e-5)


def test_the_hand_is_driven_not_teleported() -> None:
    demo = peg_in_hole_2d()
    X0 = demo.X_EG_true[0]
    scene = build_scene(demo.grasped, demo.environment, X_WG=X0)
    hand = Hand(scene)
    X1 = X0.copy()
    X1[0, 3] += 0.01
    hand.step(X1, scene.com_G)
    hand.step(X1, scene.com_G)  # MuJoCo's body poses lag the integration by one step
    moved = hand.pose()[0, 3] - X0[0, 3]
    assert 0 < moved < 1e-4  # a step of a 1 kg body under a 30 N spring force
    for _ in range(1500):
        hand.step(X1, scene.com_G)
    assert hand.pose()[0, 3] == pytest.approx(X1[0, 3], abs=1e-5)


@pytest.mark.slow
def test_replay_of_the_peg_in_hole_reaches_the_final_state_under_perturbation() -> None:
    demo, task = _peg_task()
    res = replay(
        task, demo.grasped, demo.environment, perturb=(0.002, np.radians(2)),
        environment_offset=(0.001, np.radians(1)), seed=11,
    )  # fmt: skip
    assert res.success, res.verdict
    assert res.final_state == task.states[-1].id
    # the states visited follow the task's order (F may pass between two samples)
    order = [task.states.index(task.state(s)) for s in res.states_reached]
    assert order == sorted(order)
    assert res.states_reached[0] == "A" and res.states_reached[-1] == task.states[-1].id
    assert res.max_penetration < 5e-5
    assert all(r.ok for r in res.primitives)


PERTURBED = {"perturb": (0.002, np.radians(2)), "environment_offset": (0.001, np.radians(1))}
"""The benchmark's largest trial: start pose 2 mm / 2 deg off, environment 1 mm / 1 deg."""


SQUARE_PEG_YAW = pytest.mark.xfail(
    reason="known failure (docs/sim.md): the environment's unknown 1 deg turn exceeds the "
    "0.57 deg of yaw a 40 mm square peg may have in a hole of 0.2 mm clearance; the align "
    "stalls",
    strict=False,
)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("name", "seed"),
    [
        pytest.param("square_peg_in_hole", 1, marks=SQUARE_PEG_YAW),
        ("square_peg_in_hole", 2),
        ("block_on_table_to_corner", 1),
        ("block_on_table_to_corner", 2),
        ("block_tipping", 1),
        ("block_tipping", 2),
    ],
)
def test_every_scripted_demonstration_replays_under_perturbation(name: str, seed: int) -> None:
    # (the T-peg under perturbation: the test above and test_a_random_variant_replays)
    demo = all_demos()[name]
    noisy = add_noise(demo, sigma_mm=0.5, sigma_deg=0.5, seed=5)
    task = recognize_frames(
        demo.grasped, demo.environment, noisy.times, noisy.X_EG, units="mm"
    ).task
    res = replay(task, demo.grasped, demo.environment, seed=seed, **PERTURBED)
    assert res.success, res.verdict
    assert res.states_reached[-1] == task.states[-1].id
    assert res.max_penetration < 5e-5


@pytest.mark.slow
@pytest.mark.parametrize(
    "seed",
    [
        0,
        pytest.param(
            1,
            marks=pytest.mark.xfail(
                reason="known failure (docs/sim.md): this T-peg variant (drawn since 79c1af5) "
                "stalls in its alignment search with a 0.19 mm penetration",
                strict=False,
            ),
        ),
        4,
        11,
    ],
)  # the first seeds that drew each of the four scripted demonstrations before 79c1af5
def test_a_random_variant_replays_under_perturbation(seed: int) -> None:
    # synthetic.random_variant: a random scripted demonstration with random speed, frame
    # rate, approach angle, margin and placement of the whole scene, recognised from noisy
    # poses; replayed with the largest perturbation of the benchmark
    demo = random_variant(seed)
    noisy = add_noise(demo, sigma_mm=0.5, sigma_deg=0.5, seed=seed)
    task = recognize_frames(
        demo.grasped, demo.environment, noisy.times, noisy.X_EG, units="mm"
    ).task
    res = replay(task, demo.grasped, demo.environment, seed=seed, **PERTURBED)
    assert res.success, f"{demo.meta['variant']['name']}: {res.verdict}"
    assert res.max_penetration < 5e-5


def test_the_executor_does_what_motion_json_says() -> None:
    # a controller reading motion.json has everything the simulator uses: the program read
    # back from its JSON form executes exactly like the planned one
    demo = all_demos()["block_tipping"]
    task = recognize_frames(demo.grasped, demo.environment, demo.times, demo.X_EG, units="mm").task
    program = plan(task)
    back = program_from_dict(json.loads(json.dumps(program_to_dict(program))))
    runs = [
        replay(task, demo.grasped, demo.environment, program=p, seed=3, perturb=(0.001, 0.01))
        for p in (program, back)
    ]
    assert runs[0].success and runs[1].success, runs[1].verdict
    assert [(r.kind, r.outcome) for r in runs[0].primitives] == [
        (r.kind, r.outcome) for r in runs[1].primitives
    ]
    np.testing.assert_allclose(runs[0].final_X_EG, runs[1].final_X_EG, atol=1e-6)


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.parametrize(
    ("perturb", "offset", "seed"),
    [
        ("2,2", "1,1", "4"),
        # benchmarks/replay.py's real trial 33: the peg's edge lies on the rim's edge (a line
        # contact, one MuJoCo contact point); it sank 0.13 mm with solref 0.004 (docs/sim.md)
        ("0.232074,1.415557", "0.560476,0.847557", "33"),
    ],
)
def test_the_real_demonstration_replays(
    real_data_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    perturb: str,
    offset: str,
    seed: str,
) -> None:
    out = tmp_path / "real"
    demo = real_data_dir / "peg_in_hole.pose.list"
    assert main(["analyze", str(demo), "--out", str(out), "--no-plot", "--no-report"]) == 0
    capsys.readouterr()
    rc = main(["replay", str(out / "task.json"), "--json", "--perturb", perturb,
               "--environment-offset", offset, "--seed", seed, "--clearance", "0.2"])  # fmt: skip
    res = json.loads(capsys.readouterr().out)
    assert rc == 0, res["verdict"]
    assert res["success"] and res["final_state"] == res["task_states"][-1]
    assert 0 < res["max_penetration"] < 0.05  # mm: the target at 0.2 mm clearance


@pytest.mark.slow
def test_a_plan_without_its_insertion_fails() -> None:
    demo, task = _peg_task()
    program = plan(task)
    cut = [p for p in program.primitives if p.transition != len(task.transitions) - 1]
    cut = [p for p in cut if str(p.kind) != "align"]
    short = dataclasses.replace(program, primitives=tuple(cut))
    res = replay(task, demo.grasped, demo.environment, program=short, seed=1)
    assert not res.success
    assert res.final_state != task.states[-1].id
    assert res.verdict.startswith("FAILURE")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["block_on_table_to_corner", "block_tipping"])
def test_a_plan_without_its_last_subskill_fails(name: str) -> None:
    # the last sub-skill (the push into the corner's second wall; the turn onto the face)
    # is what reaches the final state: without it the verdict must say no
    demo = all_demos()[name]
    task = recognize_frames(demo.grasped, demo.environment, demo.times, demo.X_EG, units="mm").task
    program = plan(task)
    assert replay(task, demo.grasped, demo.environment, program=program, seed=1).success
    short = dataclasses.replace(program, primitives=program.primitives[:-1])
    res = replay(task, demo.grasped, demo.environment, program=short, seed=1)
    assert not res.success and res.final_state != task.states[-1].id
    assert res.verdict.startswith("FAILURE")


def _demo_out(tmp_path: Path) -> Path:
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--no-plot", "--no-report", "--json"]) == 0
    return out / "task.json"


@pytest.mark.slow
def test_cli_replay_json_and_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    task = _demo_out(tmp_path)
    capsys.readouterr()
    rc = main(["replay", str(task), "--json", "--seed", "2", "--out", str(tmp_path / "r")])
    out = json.loads(capsys.readouterr().out)
    assert rc == (0 if out["success"] else 1)
    assert out["success"] is True
    for key in ("states_reached", "final_pose", "max_force", "max_penetration", "verdict"):
        assert key in out
    assert set(out["final_pose"]) == {"position", "quaternion"}
    assert out["units"] == "mm"
    seated = json.loads(task.read_text())["states"][-1]["pose"]["position"]
    # task units: the final position is within a millimetre of the seated pose
    assert np.allclose(out["final_pose"]["position"], seated, atol=1.0)
    assert (tmp_path / "r" / "replay.json").is_file()
    assert (tmp_path / "r" / "replay.csv").read_text().startswith("t")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--perturb", "2"], "--perturb: expected MM,DEG"),
        (["--environment-offset", "1,-1"], "non-negative"),
        (["--clearance", "0.01"], "at least 0.05 mm"),
    ],
)
def test_cli_replay_bad_arguments(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    task = tmp_path / "task.json"
    task.write_text("{}")
    assert main(["replay", str(task), *args]) == 2
    assert message in capsys.readouterr().err


def test_cli_replay_missing_task(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(tmp_path / "nope.json")]) == 2
    assert "file not found" in capsys.readouterr().err
