"""Stages split over forked processes (apo.workers): the same results as one.

The forking checks run in a fresh interpreter (one thread: the test runner's own threads
make ``workers_for`` refuse to fork, and a fork should not copy them), which prints its
findings as JSON; the tests below read them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from apo import workers

SRC = Path(__file__).resolve().parents[1] / "src"

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")

# Runs in a fresh interpreter; prints one JSON object.
SCRIPT = r"""
import json, os, sys
import numpy as np
from apo import synthetic, task as task_mod
from apo.contact import search
from apo import workers
from apo.recognition import recognize_frames
from apo.recognition.contacts import label_frames, observe
from apo.recognition.distances import element_distances, split_distances
from apo.recognition.correction import correct_by_label
from apo.recognition.pipeline import make_scene
from apo.recognition.types import SegmentationCosts
out = {}
parent = os.getpid()

# run_parts: order, results from children, an exception raised again, a dead child's part
out["parts"] = workers.run_parts([lambda i=i: (i, os.getpid() != parent) for i in range(3)])
try:
    workers.run_parts([lambda: 1, lambda: 1 // 0])
    out["raised"] = None
except ZeroDivisionError as exc:
    out["raised"] = type(exc).__name__
def dies():
    if os.getpid() != parent:
        os._exit(3)
    return "here"
out["dead"] = workers.run_parts([lambda: "first", dies])
a = workers.shared_zeros((5, 2), np.float64, True)
def fill():
    a[2:] = 7.0
workers.run_parts([lambda: None, fill])
out["shared"] = a.tolist()
workers._reap(block=True)  # every child reaped: none left, none a zombie
out["unreaped"] = len(workers._UNREAPED)
try:
    os.waitpid(-1, os.WNOHANG)
    out["children_left"] = True
except ChildProcessError:
    out["children_left"] = False

# the contact search and the correction: parts == one process, bit for bit
search._BATCH_PRIMITIVES = 64  # blocks of a few frames: several blocks per part
same_labels, same_corr, same_task, forked, same_dist = [], [], [], [], []
for seed in (3, 17, 29, 41):
    demo = synthetic.add_noise(synthetic.random_variant(seed), sigma_mm=2.0, sigma_deg=2.0,
                               seed=seed)
    G, E, X = demo.grasped, demo.environment, demo.X_EG
    scene = make_scene(G, E, X, None, SegmentationCosts())
    one = label_frames(scene.finder, X, jobs=1)
    for jobs in (2, 3):
        got = label_frames(scene.finder, X, jobs=jobs)
        same_labels.append(all(np.array_equal(u, v) for u, v in zip(one, got)))
    # a child that dies with blocks taken from the shared counter: the parent searches them
    codes = scene.finder.element_codes
    def dying(Xb, __codes=codes, **kw):
        if os.getpid() != parent:
            os._exit(3)
        return __codes(Xb, **kw)
    scene.finder.element_codes = dying
    got = label_frames(scene.finder, X, jobs=2)
    del scene.finder.element_codes
    same_labels.append(all(np.array_equal(u, v) for u, v in zip(one, got)))
    keys = sorted({e for st in observe(scene, jobs=1).states for e in st.key})
    alone = element_distances(G, E, X, keys)
    for jobs in (2, 3):
        got = split_distances(G, E, X, keys, jobs)
        same_dist.append([np.array_equal(got, alone), type(got.base.base).__name__])
    rec = recognize_frames(G, E, demo.times, X, jobs=1)
    some = next(c.state for c in rec.candidates if c is not None)
    states = [some if c is None else c.state for c in rec.candidates]
    serial = correct_by_label(G, E, X, states, rec.assigned, rec.task.threshold, jobs=1)
    for jobs in (2, 3):
        par = correct_by_label(G, E, X, states, rec.assigned, rec.task.threshold, jobs=jobs)
        same_corr.append(all(np.array_equal(u, v) for u, v in zip(serial, par)))
        forked.append(type(par[0].base.base).__name__)
    text = "".join(task_mod.task_json_chunks(rec.task))
    for jobs in (2, None):
        r2 = recognize_frames(G, E, demo.times, X, jobs=jobs)
        same_task.append(
            "".join(task_mod.task_json_chunks(r2.task)) == text
            and np.array_equal(r2.X_corrected, rec.X_corrected)
            and np.array_equal(r2.observed, rec.observed)
            and np.array_equal(r2.converged, rec.converged)
        )
out.update(labels=same_labels, correction=same_corr, task=same_task, forked=forked,
           distances=same_dist)
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def forked() -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    run = subprocess.run(
        [sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=600
    )
    assert run.returncode == 0, run.stderr[-3000:]
    out: dict[str, Any] = json.loads(run.stdout.strip().splitlines()[-1])
    return out


def test_parts_come_back_in_order_from_children(forked: dict[str, Any]) -> None:
    assert forked["parts"] == [[0, False], [1, True], [2, True]]


def test_an_error_in_a_child_is_raised_in_the_parent(forked: dict[str, Any]) -> None:
    assert forked["raised"] == "ZeroDivisionError"


def test_a_child_that_dies_has_its_part_computed_by_the_parent(forked: dict[str, Any]) -> None:
    assert forked["dead"] == ["first", "here"]


def test_children_are_all_reaped(forked: dict[str, Any]) -> None:
    assert forked["unreaped"] == 0 and forked["children_left"] is False


def test_children_write_shared_arrays(forked: dict[str, Any]) -> None:
    assert forked["shared"] == [[0.0, 0.0], [0.0, 0.0], [7.0, 7.0], [7.0, 7.0], [7.0, 7.0]]


def test_contact_labels_split_over_processes_are_those_of_one(forked: dict[str, Any]) -> None:
    assert forked["labels"] and all(forked["labels"])


def test_correction_split_over_processes_is_that_of_one(forked: dict[str, Any]) -> None:
    assert forked["correction"] and all(forked["correction"])
    assert set(forked["forked"]) == {"memoryview"}  # the parallel runs wrote shared arrays


def test_distances_split_over_processes_are_those_of_one(forked: dict[str, Any]) -> None:
    """Each key's column computed in either process: element_distances bit for bit."""
    assert forked["distances"] == [[True, "memoryview"]] * 8


def test_recognition_with_jobs_is_the_same_bit_for_bit(forked: dict[str, Any]) -> None:
    assert forked["task"] and all(forked["task"])


def test_workers_for_auto_short_explicit_and_threads() -> None:
    run_here = threading.active_count() == 1
    assert workers.workers_for(None, workers.PARALLEL_MIN_FRAMES - 1) == 1
    assert workers.workers_for(1, 100_000) == 1
    assert workers.workers_for(3, 2) <= 2
    if run_here:  # the test runner may have threads of its own (then: never fork)
        assert workers.workers_for(3, 100) == 3
    with pytest.raises(ValueError, match="jobs"):
        workers.workers_for(0, 100)
    stop = threading.Event()
    t = threading.Thread(target=stop.wait)
    t.start()
    try:  # another thread running: no fork
        assert workers.workers_for(3, 100_000) == 1
        assert workers.workers_for(None, 100_000) == 1
    finally:
        stop.set()
        t.join()


def test_run_parts_of_one_part_runs_here() -> None:
    pid = os.getpid()
    assert workers.run_parts([os.getpid]) == [pid]
    assert workers.run_parts([]) == []
    a = workers.shared_zeros((3,), bool, False)
    assert a.tolist() == [False] * 3


def test_jobs_option(tmp_path: Path) -> None:
    from apo.cli import build_parser

    parser = build_parser("analyze")
    assert parser.parse_args(["analyze", "x.csv"]).jobs is None
    assert parser.parse_args(["analyze", "x.csv", "--jobs", "auto"]).jobs is None
    assert parser.parse_args(["analyze", "x.csv", "--jobs", "2"]).jobs == 2
    for bad in ("0", "-1", "two"):
        with pytest.raises(SystemExit):
            parser.parse_args(["analyze", "x.csv", "--jobs", bad])


def test_correction_shares_cover_every_chunk_once() -> None:
    from apo.recognition.correction import _share

    chunks = [(0, 0, 2048), (0, 2048, 900), (3, 0, 10), (5, 0, 1500), (7, 0, 1)]
    assert _share(chunks, 1) == [[(k, a, 0, 1) for k, a, _n in chunks]]
    for parts in (2, 3, 5):
        shares = _share(chunks, parts)
        assert len(shares) == parts
        got: dict[tuple[int, int], set[tuple[int, int]]] = {}
        for share in shares:
            for k, a, i, m in share:
                got.setdefault((k, a), set()).add((i, m))
        for k, a, _n in chunks:  # each chunk's runs i of m, each once
            runs = got[(k, a)]
            (m,) = {m for _i, m in runs}
            assert sorted(i for i, _m in runs) == list(range(m))
        loads = [sum(n / m for k, a, _i, m in s for kk, aa, n in chunks if (kk, aa) == (k, a))
                 for s in shares]  # fmt: skip
        assert max(loads) <= 1.5 * sum(n for _k, _a, n in chunks) / parts + 1


@pytest.mark.parametrize("jobs", [None, 1, 2])
def test_correction_of_frames_without_elements_keeps_them(jobs: int | None) -> None:
    # no state with elements (a demonstration without contact): nothing to correct or fork
    from apo.contact import ContactState
    from apo.recognition.correction import correct_by_label
    from apo.shapes import box

    cube = box([0.1, 0.1, 0.1])
    X = np.stack([np.eye(4)] * 5)
    X[:, 2, 3] = np.arange(5.0)
    free = [ContactState((), frozenset())]
    labels = np.zeros(5, dtype=np.int64)
    Xc, b, a, c = correct_by_label(cube, cube, X, free, labels, 1e-3, jobs=jobs)
    assert np.array_equal(Xc, X) and not b.any() and not a.any() and c.all()


# apo analyze with task.json written by a child whatever the number of states
TASK_IN_CHILD = """
import sys
from apo.report import writer
from apo.cli import main
writer.TASK_IN_CHILD_STATES = 1
sys.exit(main(["analyze", *sys.argv[1:]]))
"""


def _analyze(args: list[str], *, task_in_child: bool = False) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    how = ["-c", TASK_IN_CHILD] if task_in_child else ["-m", "apo.cli", "analyze"]
    cmd = [sys.executable, *how, *args]
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)


def test_a_long_pose_file_read_in_a_child_gives_the_same_outputs(tmp_path: Path) -> None:
    # apo analyze reads a long pose file and its models in a forked child while it imports
    # the stages, and splits the search and the correction: every output byte the same
    from apo import synthetic
    from apo.cli.analyze import READ_IN_CHILD_BYTES
    from apo.cli.demo import _write_stl
    from apo.io.poses import write_pose_csv

    demo = synthetic.add_noise(
        synthetic.peg_in_hole_2d(n_frames=900), sigma_mm=1.0, sigma_deg=1.0, seed=5
    )
    g, e = tmp_path / "g.stl", tmp_path / "e.stl"
    _write_stl(demo.grasped, g, 1000.0)
    _write_stl(demo.environment, e, 1000.0)
    poses = write_pose_csv(tmp_path / "long.csv", demo.times, demo.X_EG, units="mm")
    assert poses.stat().st_size >= READ_IN_CHILD_BYTES
    models = ["--grasped", str(g), "--environment", str(e)]
    runs = {}
    for jobs, child in (("1", False), ("auto", False), ("auto", True)):
        out = tmp_path / f"out-{jobs}-{child}"
        args = [str(poses), "--out", str(out), "--json", "--jobs", jobs, *models]
        run = _analyze(args, task_in_child=child)
        assert run.returncode == 0, run.stderr[-2000:]
        files = {n: (out / n).read_bytes() for n in ("task.json", "frames.csv", "report.html")}
        runs[jobs, child] = (run.stdout.replace(str(out), "OUT"), files)
    assert runs["1", False] == runs["auto", False] == runs["auto", True]
    # a bad long file: the same error from the child as from this process
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x,y,z,qw,qx,qy,qz\n" + "0,1,2,3,1,0,0,0\n" * 8000 + "1,nan?,2\n")
    errors = set()
    for jobs in ("1", "auto"):
        run = _analyze([str(bad), "--out", str(tmp_path / "bad"), "--jobs", jobs, *models])
        assert run.returncode == 2
        errors.add(run.stderr.strip().splitlines()[-1])
    assert len(errors) == 1 and "bad.csv" in errors.pop()
