"""The nominal pose trajectory, its files (motion.csv, motion.pose.list) and ``apo plan``."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from apo import synthetic
from apo.cli import main
from apo.errors import InputFormatError
from apo.io.poses import read_pose_csv, read_pose_list, write_pose_list
from apo.motion import PlanParameters, plan, program_from_dict, trajectory
from apo.motion.trajectory import min_jerk
from apo.recognition import recognize
from apo.spatial import invert_pose, pose_from_twist, rotation_angle
from apo.task import TaskModel

DEMOS = sorted(synthetic.all_demos())


@cache
def _task(name: str) -> TaskModel:
    demo = synthetic.all_demos()[name]
    return recognize(demo.grasped, demo.environment, demo.times, demo.X_EG, units="mm")


def _pose_distance(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    D = B @ invert_pose(A)
    return float(np.linalg.norm(D[:3, 3])), rotation_angle(D[:3, :3])


@pytest.mark.parametrize("name", DEMOS)
def test_trajectory_passes_every_target_smoothly(name: str) -> None:
    pp = PlanParameters(sample_period=0.01)
    program = plan(_task(name), parameters=pp)
    tr = trajectory(program)
    assert tr.times[0] == 0.0 and np.all(np.diff(tr.times) > 0)
    assert np.all(np.diff(tr.primitive) >= 0)
    assert set(tr.primitive.tolist()) == {p.index for p in program.primitives}
    np.testing.assert_allclose(tr.X_EG[0], program.start_X_EG, atol=1e-12)
    np.testing.assert_allclose(tr.X_EG[-1], program.primitives[-1].target.X_EG, atol=1e-9)
    # each target is reached: the last sample of its primitive is at (or next to) it
    for p in program.primitives:
        k = int(np.flatnonzero(tr.primitive == p.index)[-1])
        d, a = _pose_distance(tr.X_EG[k], p.target.X_EG)
        assert d < pp.speed * pp.sample_period * 1.01 + 1e-9
        assert a < pp.angular_speed * pp.sample_period * 1.01 + 1e-9
    # smooth: steps bounded by the peak speed of a minimum-jerk segment (15/8 of the mean)
    for k in range(1, len(tr.times)):
        R = tr.X_EG[k][:3, :3] @ tr.X_EG[k - 1][:3, :3].T
        assert rotation_angle(R) <= 1.9 * pp.angular_speed * (tr.times[k] - tr.times[k - 1]) + 1e-9


def test_rotational_segments_turn_about_the_pivot() -> None:
    program = plan(_task("block_tipping"))
    tr = trajectory(program)
    for p in program.primitives:
        if p.space != "rotation" or p.stop.expected < 1e-3:
            continue
        assert p.point is not None
        ks = np.flatnonzero(tr.primitive == p.index)
        X_end = p.target.X_EG
        c_G = np.linalg.inv(X_end) @ np.append(p.compliance.center, 1.0)
        for k in ks:
            # the body point on the axis does not move while the object turns about it
            np.testing.assert_allclose((tr.X_EG[k] @ c_G)[:3], p.compliance.center, atol=1e-9)


def test_min_jerk_profile() -> None:
    u = np.linspace(0, 1, 101)
    s = min_jerk(u)
    assert s[0] == 0 and s[-1] == 1 and np.all(np.diff(s) >= 0)
    assert min_jerk(0.5) == pytest.approx(0.5)


@settings(max_examples=20, deadline=None)
@given(
    n=st.integers(1, 12),
    seed=st.integers(0, 2**32 - 1),
    units=st.sampled_from(["mm", "m", "cm", "in"]),
)
def test_pose_list_writer_is_the_inverse_of_the_reader(n: int, seed: int, units: str) -> None:
    import tempfile

    rng = np.random.default_rng(seed)
    X = np.stack([pose_from_twist(rng.normal(size=6) * [2, 2, 2, 0.3, 0.3, 0.3]) for _ in range(n)])
    X[0] = np.eye(4)  # the identity: axis 1 0 0, angle 0
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "motion.pose.list"
        write_pose_list(path, X, units=units, models=("peg.step", "../models/hole.step"))
        dem = read_pose_list(path, units=units, fps=50.0)
    np.testing.assert_allclose(dem.X_EG, X, atol=1e-12)
    np.testing.assert_allclose(dem.times, np.arange(n) / 50.0)
    assert dem.grasped_path == Path(tmp) / "peg.step"
    assert dem.environment_path == Path(tmp) / "../models/hole.step"


def test_pose_list_writer_rejects_bad_input(tmp_path: Path) -> None:
    p = tmp_path / "x.pose.list"
    with pytest.raises(InputFormatError, match=r"x\.pose\.list: X_EG must have shape"):
        write_pose_list(p, np.zeros((0, 4, 4)), units="mm", models=("a", "b"))
    bad = np.eye(4)[None].copy()
    bad[0, 0, 0] = 2.0
    with pytest.raises(InputFormatError, match=r"X_EG\[0\] has no rotation"):
        write_pose_list(p, bad, units="mm", models=("a", "b"))
    with pytest.raises(InputFormatError, match="model paths"):
        write_pose_list(p, np.eye(4)[None], units="mm", models=("a", "b\nc"))
    with pytest.raises(InputFormatError, match="unknown units"):
        write_pose_list(p, np.eye(4)[None], units="furlong", models=("a", "b"))


# --------------------------------------------------------------------------------------------
# apo plan
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "--out", str(out), "--no-plot", "--no-report"]) == 0
    return out


def _run(argv: list[str]) -> int:
    return main(argv)


def test_apo_plan_writes_the_three_outputs(
    demo_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "nested" / "plan"
    assert _run(["plan", str(demo_dir / "task.json"), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "push_to rotation I" in printed and "align" in printed
    prog = program_from_dict(json.loads((out / "motion.json").read_text()), source="motion.json")
    assert prog.units == "mm"
    assert prog.task.sha256 is not None and len(prog.task.sha256) == 64
    assert (out / prog.task.path).resolve() == (demo_dir / "task.json").resolve()
    # models as recorded in task.json (relative to its folder): still found from there
    for ref in (prog.grasped, prog.environment):
        assert (demo_dir / ref.path).is_file()
    csv = read_pose_csv(out / "motion.csv", units="mm")
    tr = trajectory(prog)
    np.testing.assert_allclose(csv.times, tr.times)
    np.testing.assert_allclose(csv.X_EG, tr.X_EG, atol=1e-9)
    np.testing.assert_array_equal(csv.extra["primitive"], tr.primitive)
    pl = read_pose_list(out / "motion.pose.list", units="mm")
    np.testing.assert_allclose(pl.X_EG, tr.X_EG, atol=1e-9)
    assert pl.grasped_path is not None and pl.grasped_path.resolve().is_file()
    assert pl.environment_path is not None and pl.environment_path.resolve().is_file()


def test_apo_plan_defaults_to_the_task_folder_and_takes_options(
    demo_dir: Path, tmp_path: Path
) -> None:
    work = tmp_path / "copy"
    shutil.copytree(demo_dir, work)
    argv = ["plan", str(work / "task.json"), "--standoff", "3", "--clearance", "0.1"]
    assert _run([*argv, "--sample-period", "0.05"]) == 0
    prog = program_from_dict(json.loads((work / "motion.json").read_text()))
    assert prog.parameters.standoff == pytest.approx(0.003)
    assert prog.parameters.clearance == pytest.approx(0.0001)
    assert prog.parameters.sample_period == pytest.approx(0.05)
    assert (work / "motion.csv").is_file() and (work / "motion.pose.list").is_file()


@pytest.mark.parametrize(
    ("setup", "match"),
    [
        ("missing", r"task\.json: file not found"),
        ("garbled", r"task\.json: not valid JSON: .* line 1"),
        ("schema", r"task\.json: schema: expected 'apo\.task/1'"),
        ("no_model", r"task\.json: models\.grasped\.path: model file not found"),
        ("out_is_file", r"--out .*out.* is a file, not a folder"),
        ("bad_option", r"--standoff must be positive"),
    ],
)
def test_apo_plan_bad_input_exits_2(
    demo_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    setup: str,
    match: str,
) -> None:
    task = tmp_path / "task.json"
    out = tmp_path / "out"
    extra: list[str] = []
    if setup != "missing":
        shutil.copy(demo_dir / "task.json", task)
        for f in ("grasped.stl", "environment.stl"):
            shutil.copy(demo_dir / f, tmp_path / f)
    if setup == "garbled":
        task.write_text("{not json")
    elif setup == "schema":
        d = json.loads(task.read_text())
        d["schema"] = "apo.task/9"
        task.write_text(json.dumps(d))
    elif setup == "no_model":
        (tmp_path / "grasped.stl").unlink()
    elif setup == "out_is_file":
        out.write_text("x")
    elif setup == "bad_option":
        extra = ["--standoff", "0"]
    code = _run(["plan", str(task), "--out", str(out), *extra])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("apo plan: error: ")
    assert re.search(match, err), err
    if setup != "out_is_file":
        assert not (out / "motion.json").exists()


@pytest.mark.slow
def test_apo_plan_as_a_process_on_the_real_data(real_data_dir: Path, tmp_path: Path) -> None:
    exe = [sys.executable, "-m", "apo.cli"]
    src = str(real_data_dir / "peg_in_hole.pose.list")
    analyze = subprocess.run(
        [*exe, "analyze", src, "--out", str(tmp_path), "--no-plot"],
        capture_output=True,
        text=True,
    )
    assert analyze.returncode == 0, analyze.stderr
    res = subprocess.run(
        [*exe, "plan", str(tmp_path / "task.json"), "--json"], capture_output=True, text=True
    )
    assert res.returncode == 0, res.stderr
    d = json.loads(res.stdout)
    kinds = [p["kind"] for p in d["primitives"]]
    assert kinds[0] == "approach" and kinds.count("align") == 1


@pytest.mark.parametrize("seed", range(2))
@pytest.mark.parametrize("name", DEMOS)
def test_approach_path_stays_clear_of_the_environment(name: str, seed: int) -> None:
    from apo.contact import ContactFinder

    demo = synthetic.random_variant(seed, name=name)
    task = recognize(demo.grasped, demo.environment, demo.times, demo.X_EG, units="mm")
    pp = PlanParameters(standoff=0.005, sample_period=0.05)
    program = plan(task, parameters=pp)
    tr = trajectory(program)
    finder = ContactFinder(demo.grasped, demo.environment, threshold=0.5 * pp.standoff)
    states = finder.find_batch(tr.X_EG[tr.primitive == 0])
    touching = [k for k, s in enumerate(states) if s.elements]
    assert not touching, f"approach samples within {0.5 * pp.standoff} m of E: {touching}"
    # the finder does see the first contact, where the first push-to ends
    assert finder.find(program.primitives[1].target.X_EG).elements


def test_real_approach_stays_clear_of_the_environment(real_data_dir: Path) -> None:
    from apo.contact import ContactFinder
    from apo.io.meshes import load_polyhedron
    from apo.io.poses import load_demonstration

    dem = load_demonstration(real_data_dir / "peg_in_hole.pose.list")
    G = load_polyhedron(real_data_dir / "peg.step", units="mm")
    E = load_polyhedron(real_data_dir / "hole.step", units="mm")
    task = recognize(G, E, dem.times, dem.X_EG, units="mm")
    pp = PlanParameters(sample_period=0.05)
    program = plan(task, parameters=pp)
    tr = trajectory(program)
    finder = ContactFinder(G, E, threshold=0.5 * pp.standoff)
    states = finder.find_batch(tr.X_EG[tr.primitive == 0])
    assert not [k for k, s in enumerate(states) if s.elements]
    assert finder.find(program.primitives[1].target.X_EG).elements
