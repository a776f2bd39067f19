"""apo.arrays: numpy's unique and median, the same arrays, without importing numpy.ma."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from apo.arrays import median, unique


@pytest.mark.parametrize("seed", [3, 29])
def test_unique_is_numpys(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(200):
        n = int(rng.integers(0, 60))
        a = rng.integers(-5, int(rng.integers(1, 40)), n)
        for x in (a, a.astype(np.int32), a.astype(np.uint16) if n and a.min() >= 0 else a):
            want = np.unique(x)
            got = unique(x)
            assert got.dtype == want.dtype and np.array_equal(got, want)
        rows = rng.integers(0, 4, (n, 2))
        assert np.array_equal(unique(rows, axis=0), np.unique(rows, axis=0))
    f = np.array([0.5, -0.0, 0.0, np.nan, 0.5])
    assert np.array_equal(unique(f), np.unique(f), equal_nan=True)  # floats: numpy's own


@pytest.mark.parametrize("seed", [4, 57])
def test_median_is_numpys(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(300):
        shape = (int(rng.integers(1, 9)), int(rng.integers(1, 5)))
        a = rng.normal(size=shape) * 10.0 ** rng.integers(-9, 4)
        if rng.random() < 0.2:
            a[tuple(rng.integers(0, s) for s in shape)] = np.nan
        for axis in (None, 0):
            with np.errstate(invalid="ignore"):
                want, got = np.median(a, axis=axis), median(a, axis=axis)
            assert type(got) is type(want)
            assert np.array_equal(got, want, equal_nan=True)
        flat = a.ravel()
        assert np.array_equal(median(flat), np.median(flat), equal_nan=True)
    assert median(np.array([2.5])) == 2.5


def test_recognition_does_not_import_numpy_ma(tmp_path, analyze_imports) -> None:
    """A short demonstration analysed in a fresh interpreter never imports numpy.ma."""
    from apo.cli.demo import _write_stl
    from apo.io.poses import write_pose_csv
    from apo.synthetic import add_noise, random_variant

    demo = add_noise(random_variant(12), sigma_mm=0.5, sigma_deg=0.5, seed=12)
    g, e = tmp_path / "g.stl", tmp_path / "e.stl"
    _write_stl(demo.grasped, g, 1000.0)
    _write_stl(demo.environment, e, 1000.0)
    csv = write_pose_csv(tmp_path / "d.csv", demo.times, demo.X_EG, units="mm")
    args = ["analyze", str(csv), "--grasped", str(g), "--environment", str(e)]
    assert not analyze_imports(args, "numpy.ma")


def test_replay_of_a_long_track_does_not_import_numpy_ma() -> None:
    """The report of a long demonstration keeps a regular subset of its frames: the same
    indices as ``np.unique`` gives, without the import of numpy.ma (about 1.5 MB of resident
    memory and 9 ms, paid by long demonstrations only)."""
    code = (
        "import sys\nimport numpy as np\n"
        "from apo.report.html import MAX_REPLAY_FRAMES, replay_indices\n"
        "rng = np.random.default_rng(3)\n"
        "s = np.repeat(np.arange(900), rng.integers(1, 40, 900))\n"
        "assert len(s) > MAX_REPLAY_FRAMES\n"
        "keep = replay_indices(s)\n"
        "print('numpy.ma' in sys.modules)\n"
        "print(keep.dtype, keep.tolist())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    imported, got = out.stdout.strip().splitlines()
    assert imported == "False"
    rng = np.random.default_rng(3)
    s = np.repeat(np.arange(900), rng.integers(1, 40, 900))
    n = len(s)
    change = np.flatnonzero(np.diff(s) != 0)
    ends = np.concatenate([[0, n - 1], change, change + 1])
    from apo.report.html import MAX_REPLAY_FRAMES

    regular = np.linspace(0, n - 1, max(MAX_REPLAY_FRAMES - ends.size, 2)).round().astype(np.int64)
    want = np.unique(np.concatenate([regular, ends]))
    assert got == f"{want.dtype} {want.tolist()}"
