"""The output set (apo.outputs): checked before the work, atomic, one writer, the umask."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from apo.errors import OutputError
from apo.outputs import MANIFEST, OutputSet, atomic_file, output_files, read_manifest

SRC = str(Path(__file__).resolve().parents[1] / "src")


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = SRC + os.pathsep + env.get("PYTHONPATH", "")
    return env


def assert_whole(folder: Path) -> dict[str, object]:
    """The folder holds one set, whole: every file of its manifest, with its size and hash."""
    doc = read_manifest(folder)
    assert doc is not None, f"{folder}: no manifest"
    files = doc["files"]
    assert isinstance(files, dict)
    for name, meta in files.items():
        data = (folder / name).read_bytes()
        assert len(data) == meta["bytes"], name
        assert hashlib.sha256(data).hexdigest() == meta["sha256"], name
    return files


def no_temporaries(parent: Path) -> None:
    """Nothing but finished outputs: no staging folder, lock or temporary file anywhere."""
    stray = [p for p in parent.rglob("*") if ".apo-" in p.name and p.name != MANIFEST]
    assert stray == []


def test_a_set_is_committed_whole_with_a_manifest(tmp_path: Path) -> None:
    dest = tmp_path / "a" / "b" / "out"
    with OutputSet(dest) as outs:
        assert not dest.exists()  # nothing visible before the commit
        p = outs.write_json("task.json", {"k": 1})
        outs.write_text("sub/frames.csv", "x\n")
        outs.add_file("copy.json", outs.path("task.json"))
        assert p == dest / "task.json"
    assert json.loads((dest / "task.json").read_text()) == {"k": 1}
    assert sorted(assert_whole(dest)) == ["copy.json", "sub/frames.csv", "task.json"]
    no_temporaries(tmp_path)


def test_an_exception_leaves_the_old_set_and_no_trace(tmp_path: Path) -> None:
    dest = tmp_path / "out"
    with OutputSet(dest) as outs:
        outs.write_text("task.json", "old\n")
    with pytest.raises(RuntimeError), OutputSet(dest) as outs:
        outs.write_text("task.json", "new\n")
        raise RuntimeError("analysis failed")
    assert (dest / "task.json").read_text() == "old\n"
    no_temporaries(tmp_path)
    # a failed first run creates nothing, not even the parents it made
    with pytest.raises(RuntimeError), OutputSet(tmp_path / "x" / "y") as outs:
        outs.write_text("a", "b")
        raise RuntimeError("boom")
    assert not (tmp_path / "x").exists()


def test_the_new_set_replaces_the_old_one_and_keeps_the_users_files(tmp_path: Path) -> None:
    dest = tmp_path / "out"
    with OutputSet(dest) as outs:
        outs.write_text("dof.png", "old plot")
        outs.write_text("task.json", "old")
        outs.write_text("frames/0.png", "old frame")
    (dest / "notes.txt").write_text("mine")
    (dest / "mine").mkdir()
    (dest / "mine" / "data.txt").write_text("mine too")
    with OutputSet(dest) as outs:
        outs.write_text("task.json", "new")
    assert sorted(p.name for p in dest.iterdir()) == [MANIFEST, "mine", "notes.txt", "task.json"]
    assert (dest / "notes.txt").read_text() == "mine"
    assert (dest / "mine" / "data.txt").read_text() == "mine too"
    assert sorted(assert_whole(dest)) == ["task.json"]


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda t: (t / "f").write_text("x") and t / "f", "is an existing file, not a folder"),
        (lambda t: (t / "f").write_text("x") and t / "f" / "sub", "f is a file, not a folder"),
    ],
    ids=["existing-file", "under-a-file"],
)
def test_unusable_destinations_are_refused_on_entry(tmp_path: Path, make, match) -> None:
    dest = make(tmp_path)
    with pytest.raises(OutputError, match=match), OutputSet(dest, label="--out"):
        pytest.fail("the work must not start")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]


def test_the_current_folder_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "here").mkdir()
    monkeypatch.chdir(tmp_path / "here")
    for dest in (".", ".."):
        with pytest.raises(OutputError, match="current folder"), OutputSet(dest):
            pass


def test_umask_is_respected(tmp_path: Path) -> None:
    old = os.umask(0o027)
    try:
        with OutputSet(tmp_path / "out") as outs:
            outs.write_text("task.json", "{}")
            outs.write_text("sub/x.csv", "1")
        with atomic_file(tmp_path / "single.html") as tmp:
            tmp.write_text("x")
    finally:
        os.umask(old)
    mode = lambda p: p.stat().st_mode & 0o777  # noqa: E731
    assert mode(tmp_path / "out") == 0o750
    assert mode(tmp_path / "out" / "sub") == 0o750
    assert mode(tmp_path / "out" / "task.json") == 0o640
    assert mode(tmp_path / "out" / MANIFEST) == 0o640
    assert mode(tmp_path / "single.html") == 0o640
    # an existing destination keeps its mode
    os.chmod(tmp_path / "out", 0o705)
    with OutputSet(tmp_path / "out") as outs:
        outs.write_text("task.json", "{}")
    assert mode(tmp_path / "out") == 0o705


def test_a_second_writer_is_refused_naming_the_first(tmp_path: Path) -> None:
    dest = tmp_path / "out"
    with OutputSet(dest) as outs:
        outs.write_text("task.json", "first")
        refused = pytest.raises(OutputError, match=rf"another apo process .*pid {os.getpid()}")
        with refused, OutputSet(dest):
            pass
        # another process, too (flock is per open file)
        code = (
            "import sys\nfrom apo.outputs import OutputSet\nfrom apo.errors import OutputError\n"
            f"try:\n    OutputSet({str(dest)!r}).__enter__()\n"
            "except OutputError as e:\n    print(e); sys.exit(2)\n"
        )
        r = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, env=_env(), check=False
        )
        assert r.returncode == 2, r.stderr
        assert f"pid {os.getpid()}" in r.stdout
    assert (dest / "task.json").read_text() == "first"
    with OutputSet(dest) as outs:  # released: the next writer goes ahead
        outs.write_text("task.json", "second")
    no_temporaries(tmp_path)


def test_loose_files_are_checked_locked_and_renamed(tmp_path: Path) -> None:
    a, b = tmp_path / "poses.csv", tmp_path / "poses.environment.json"
    with output_files([a, b]) as (ta, tb):
        ta.write_text("csv")
        tb.write_text("json")
        assert not a.exists()
        with pytest.raises(OutputError, match="another apo process"), output_files([a]):
            pass
    assert (a.read_text(), b.read_text()) == ("csv", "json")
    with pytest.raises(OutputError, match="is a folder"), output_files([tmp_path]):
        pass
    no_temporaries(tmp_path)


def test_what_a_killed_writer_left_is_cleaned_or_restored(tmp_path: Path) -> None:
    dest = tmp_path / "out"
    with OutputSet(dest) as outs:
        outs.write_text("task.json", "old")
    # killed while writing: its staging folder is left beside the destination
    (tmp_path / ".out.apo-new-dead").mkdir()
    (tmp_path / ".out.apo-new-dead" / "task.json").write_text("half")
    # killed between the two renames of the fallback swap: the old set is aside, none in place
    dest.rename(tmp_path / ".out.apo-old-dead")
    with OutputSet(dest) as outs:
        assert (dest / "task.json").read_text() == "old"  # restored on opening
        outs.write_text("task.json", "new")
    assert (dest / "task.json").read_text() == "new"
    no_temporaries(tmp_path)


def test_the_fallback_swap_without_renameat2(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    import apo.outputs

    monkeypatch.setattr(apo.outputs, "_exchange", lambda a, b: False)
    dest = tmp_path / "out"
    for text in ("old", "new"):
        with OutputSet(dest) as outs:
            outs.write_text("task.json", text)
    assert (dest / "task.json").read_text() == "new"
    no_temporaries(tmp_path)


def _nobody() -> list[str] | None:
    """A command prefix running as user nobody, or None.

    None also when nobody cannot import apo from this checkout (a clone under a folder
    only root may enter, such as ``mktemp -d``'s 0700 folders).
    """
    if os.geteuid() != 0 or shutil.which("setpriv") is None:
        return None
    prefix = ["setpriv", "--reuid=nobody", "--regid=nogroup", "--clear-groups"]
    probe = subprocess.run([*prefix, sys.executable, "-c", "import apo.cli"], capture_output=True)
    return prefix if probe.returncode == 0 else None


@pytest.mark.parametrize("where", ["read-only-folder", "under-read-only-folder"])
def test_a_read_only_folder_is_refused_before_the_work(where: str) -> None:
    if os.geteuid() != 0:
        prefix: list[str] = []
    else:
        nobody = _nobody()
        if nobody is None:
            pytest.skip(
                "running as root, and user nobody is unavailable (no setpriv, or it cannot "
                "read this checkout): root may write a read-only folder"
            )
        prefix = nobody
    base = Path(tempfile.mkdtemp(prefix="apo-ro-"))
    try:
        os.chmod(base, 0o755)
        ro = base / "ro"
        ro.mkdir()
        (ro / "task.json").write_text("old")
        os.chmod(ro, 0o555)
        dest = ro if where == "read-only-folder" else ro / "sub"
        r = subprocess.run(
            [*prefix, sys.executable, "-m", "apo.cli", "demo", "--no-plot", "--out", str(dest)],
            capture_output=True,
            text=True,
            env=_env(),
            check=False,
            cwd=base,
        )
        assert r.returncode == 2, r.stderr
        assert "not writable" in r.stderr and str(ro) in r.stderr
        assert "Traceback" not in r.stderr
        assert r.stdout == ""  # refused before the analysis
        assert sorted(p.name for p in ro.iterdir()) == ["task.json"]
    finally:
        os.chmod(base / "ro", 0o755)
        shutil.rmtree(base)


_WRITER = """
import sys, numpy as np
from apo.outputs import OutputSet
dest, tag, mb = sys.argv[1], sys.argv[2], int(sys.argv[3])
block = (tag * (1 << 20 // len(tag) + 1))[: 1 << 20].encode()
with OutputSet(dest) as outs:
    for name in ("task.json", "frames.csv", "dof.png", "report.html"):
        with open(outs.path(name), "wb") as fh:
            for _ in range(mb):
                fh.write(block)
    print("done", flush=True)
"""


def test_a_kill_during_a_large_write_leaves_the_old_or_the_new_set_whole(tmp_path: Path):
    dest = tmp_path / "out"
    rng = np.random.default_rng(12)
    # time one whole run, so that the kills land inside a run on a fast machine as on a slow one
    start = time.perf_counter()
    subprocess.run(
        [sys.executable, "-c", _WRITER, str(dest), "run0-", "12"], env=_env(), check=True
    )
    duration = time.perf_counter() - start
    tags = {"run0-"}
    kills = 0
    for k in range(1, 7):
        tag = f"run{k}-"
        p = subprocess.Popen(
            [sys.executable, "-c", _WRITER, str(dest), tag, "12"],
            env=_env(),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        time.sleep(float(rng.uniform(0.3, 0.95)) * duration)
        p.send_signal(signal.SIGKILL)
        p.wait()
        kills += p.returncode == -signal.SIGKILL
        files = assert_whole(dest)
        seen = {(dest / n).read_bytes()[:5].decode() for n in files}
        assert len(seen) == 1, f"mixed set after kill {k}: {seen}"
        (found,) = seen
        assert found in tags | {tag}
        tags.add(tag)
        assert sorted(p.name for p in dest.iterdir()) == sorted([MANIFEST, *files])
    assert kills >= 3  # most runs were interrupted (not finished before the kill)
    # the next writer cleans what the killed ones left beside the destination
    subprocess.run([sys.executable, "-c", _WRITER, str(dest), "last-", "1"], env=_env(), check=True)
    no_temporaries(tmp_path)


# ---- through the command line ----------------------------------------------------------------


def _forbid_recognition(monkeypatch: pytest.MonkeyPatch) -> None:
    import apo.recognition

    def boom(*a: object, **k: object) -> None:
        raise AssertionError("the analysis ran before the destination was checked")

    monkeypatch.setattr(apo.recognition, "recognize_frames", boom)


@pytest.mark.parametrize("command", ["demo", "analyze"])
@pytest.mark.parametrize("case", ["existing-file", "under-a-file"])
def test_bad_out_exits_2_before_the_analysis(tmp_path, capsys, monkeypatch, command, case):
    from apo.cli import main

    _forbid_recognition(monkeypatch)
    f = tmp_path / "results"
    f.write_text("not a folder")
    out = f if case == "existing-file" else f / "sub"
    args = [command, "--out", str(out)]
    if command == "analyze":
        demo = tmp_path / "d.csv"
        demo.write_text("t,x,y,z,qw,qx,qy,qz\n0,0,0,0,1,0,0,0\n")
        args = ["analyze", str(demo), "--grasped", "g.stl", "--environment", "e.stl", *args[1:]]
    code = main(args)
    err = capsys.readouterr().err
    assert code == 2
    assert f"apo {command}: error: --out" in err and "Traceback" not in err
    assert ("is an existing file" if case == "existing-file" else "is a file, not a folder") in err
    assert f.read_text() == "not a folder"


def test_a_second_apo_on_the_same_out_is_refused(tmp_path, capsys, monkeypatch) -> None:
    from apo.cli import main

    _forbid_recognition(monkeypatch)
    out = tmp_path / "out"
    with OutputSet(out) as outs:  # another run holds the folder
        outs.write_text("task.json", "first")
        code = main(["demo", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert "another apo process is writing this output folder" in err and "pid" in err
    assert err.count("--out") == 2  # "--out OUT: another ...; ... choose another --out"
    assert (out / "task.json").read_text() == "first"


@pytest.mark.slow
def test_two_concurrent_runs_never_mix_their_files(tmp_path: Path) -> None:
    """Two `apo demo` into one --out at once: one is refused (exit 2) or they run in turn."""
    out = tmp_path / "out"
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "apo.cli", "demo", "--out", str(out), "--seed", str(s)],
            env=_env(),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for s in (1, 2)
    ]
    results = [(p.wait(), p.stderr.read() if p.stderr else "") for p in procs]
    for p in procs:
        if p.stderr:
            p.stderr.close()
    codes = sorted(c for c, _ in results)
    assert codes in ([0, 0], [0, 2]), results
    for c, err in results:
        if c == 2:
            assert "another apo process is writing this output folder" in err
    assert_whole(out)
    source = json.loads((out / "task.json").read_text())["source"]
    seed = source.split("seed ")[1].rstrip(")")
    report = (out / "report.html").read_text()
    assert f"apo demo (seed {seed})" in report  # the report is of the same run as task.json
    no_temporaries(tmp_path)


def test_the_cli_respects_the_umask(tmp_path: Path) -> None:
    out = tmp_path / "out"
    r = subprocess.run(
        [
            "sh",
            "-c",
            f'umask 027 && exec "$0" -m apo.cli demo --no-report --out {out}',
            sys.executable,
        ],
        env=_env(),
        capture_output=True,
        text=True,
        check=False,
    )
    assert r.returncode == 0, r.stderr
    assert out.stat().st_mode & 0o777 == 0o750
    for p in out.rglob("*"):
        assert p.stat().st_mode & 0o777 == (0o750 if p.is_dir() else 0o640), p


@pytest.mark.slow
def test_killing_apo_analyze_at_random_leaves_a_whole_set(tmp_path: Path) -> None:
    """SIGKILL `apo analyze` (3,000 frames) at random moments: the old set or the new, whole.

    Two inputs alternate, so that a mix of two runs would show: after each kill the manifest
    (sizes and SHA-256 of every file) must be exactly that of a complete run of one input.
    """
    from apo.cli.demo import _write_stl
    from apo.io.poses import write_pose_csv
    from apo.synthetic import add_noise, peg_in_hole_2d

    demo = peg_in_hole_2d()  # the report is left out: it holds the time it was written
    _write_stl(demo.grasped, tmp_path / "g.stl", 1000.0)
    _write_stl(demo.environment, tmp_path / "e.stl", 1000.0)
    out = tmp_path / "out"
    cmds, sets = [], []
    for seed in (1, 2):
        X = np.repeat(
            np.asarray(add_noise(demo, sigma_mm=0.3, sigma_deg=0.3, seed=seed).X_EG), 50, axis=0
        )
        csv = write_pose_csv(tmp_path / f"in{seed}.csv", np.arange(len(X)) * 0.01, X, units="mm")
        models = ["--grasped", str(tmp_path / "g.stl"), "--environment", str(tmp_path / "e.stl")]
        cmds.append(
            [
                sys.executable,
                "-m",
                "apo.cli",
                "analyze",
                str(csv),
                "--out",
                str(out),
                *models,
                "--no-report",
                "--plot",
            ]
        )
        t0 = time.monotonic()
        subprocess.run(cmds[-1], env=_env(), check=True, capture_output=True)
        full = time.monotonic() - t0
        sets.append(assert_whole(out))
    assert sets[0] != sets[1] and set(sets[0]) == {"task.json", "frames.csv", "dof.png"}
    rng = np.random.default_rng(2)
    for k in range(6):
        p = subprocess.Popen(
            cmds[k % 2], env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        time.sleep(float(rng.uniform(0.4, 1.1) * full))
        p.send_signal(signal.SIGKILL)
        p.wait()
        files = assert_whole(out)
        assert files in sets, f"kill {k}: a set of no complete run"
        assert sorted(q.name for q in out.iterdir()) == sorted([MANIFEST, *files])
    subprocess.run(cmds[0], env=_env(), check=True, capture_output=True)
    assert assert_whole(out) == sets[0]
    no_temporaries(tmp_path)


@pytest.mark.parametrize("case", ["folder", "under-a-file"])
def test_apo_track_checks_its_outputs_before_tracking(tmp_path, capsys, monkeypatch, case):
    import apo.cli.track
    from apo.cli import main

    def boom(*a: object, **k: object) -> None:
        raise AssertionError("tracked before the destination was checked")

    monkeypatch.setattr(apo.cli.track, "track_from_args", boom)
    (tmp_path / "f").write_text("x")
    out = tmp_path if case == "folder" else tmp_path / "f" / "poses.csv"
    code = main(["track", str(tmp_path), "--grasped", "g", "--environment", "e", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "apo track: error: --out" in err and "Traceback" not in err
    assert ("is a folder" if case == "folder" else "is a file, not a folder") in err
