"""The vectorised pose-list reader gives what the line-by-line reader gives."""

import numpy as np
import pytest

from apo.io import poses


def _write(tmp_path, lines):
    p = tmp_path / "demo.pose.list"
    head = ["No of Models: 2", "g.stl", "e.stl", "", f"No of Scenes: {len(lines) // 2}"]
    body = []
    for i in range(0, len(lines), 2):
        body += [lines[i], lines[i + 1], ""]
    p.write_text("\n".join(head + body) + "\n")
    return p


def test_fast_reader_matches_the_line_by_line_reader(tmp_path, monkeypatch):
    rng = np.random.default_rng(0)
    lines = []
    for _ in range(40):
        x = rng.normal(scale=100, size=3)
        ax = rng.normal(size=3)
        lines.append(f"2 {x[0]} {x[1]} {x[2]} {ax[0]} {ax[1]} {ax[2]} {rng.uniform(-3.1, 3.1)}")
    lines[5] = "0 1 2 3 0 0 0 0"  # zero axis with a zero angle: identity
    p = _write(tmp_path, lines)
    fast = poses.read_pose_list(p)
    monkeypatch.setattr(poses, "_scene_poses_fast", lambda *a: None)
    slow = poses.read_pose_list(p)
    np.testing.assert_allclose(fast.X_EG, slow.X_EG, atol=1e-12)
    np.testing.assert_allclose(fast.X_C, slow.X_C, atol=1e-12)
    assert fast.tags.tolist() == slow.tags.tolist()


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        ("2 1 2 3 0 0 1 nan", "line 9: angle is not finite"),
        ("2 1 2 3 0 0 1", "line 9: expected 8 fields"),
        ("2.5 1 2 3 0 0 1 0", "line 9: tag is not an integer"),
        ("2 1 2 3 0 0 0 1", "line 9: rotation axis is zero"),
        ("2 1 2 x 0 0 1 0", "line 9: z is not a number"),
    ],
)
def test_a_bad_line_is_still_named_by_the_line_by_line_reader(tmp_path, bad, match):
    good = "2 1 2 3 0 0 1 0.5"
    p = _write(tmp_path, [good, good, bad, good])
    with pytest.raises(poses.InputFormatError, match=match):
        poses.read_pose_list(p)


@pytest.mark.parametrize("seed", range(4))
def test_plain_csv_read_by_numpy_equals_the_csv_module_reader(tmp_path, monkeypatch, seed):
    """Header or not, extra columns, CR LF, blank lines, spaces around fields: same arrays."""
    rng = np.random.default_rng(seed)
    n, extra = int(rng.integers(2, 30)), int(rng.integers(0, 3))
    names = ["t", "x", "y", "z", "qw", "qx", "qy", "qz"] + [f"c{j}" for j in range(extra)]
    rows = []
    for i in range(n):
        vals = [i * 0.1 + rng.uniform(0, 0.05), *rng.normal(scale=50, size=3)]
        q = rng.normal(size=4)
        vals += [*(q / np.linalg.norm(q)), *rng.normal(size=extra)]
        pad = " " if rng.random() < 0.3 else ""
        rows.append(",".join(f"{pad}{float(v)!r}{pad}" for v in vals))
        if rng.random() < 0.2:
            rows.append(" , ,")  # a row of blank fields: skipped
    if extra:
        rows[-1] = rows[-1].rsplit(",", 1)[0] + ",nan"  # extra columns may hold nan
    text = ([",".join(names)] if seed % 2 == 0 else []) + rows
    p = tmp_path / "demo.csv"
    p.write_bytes(("\r\n" if seed == 2 else "\n").join(text).encode() + b"\n")
    assert poses._csv_fast(p) is not None
    fast = poses.read_pose_csv(p, units="mm")
    monkeypatch.setattr(poses, "_csv_fast", lambda path: None)
    slow = poses.read_pose_csv(p, units="mm")
    assert np.array_equal(fast.X_EG, slow.X_EG) and np.array_equal(fast.times, slow.times)
    assert fast.lines.tolist() == slow.lines.tolist()
    assert fast.extra.keys() == slow.extra.keys()
    for k in fast.extra:
        assert np.array_equal(fast.extra[k], slow.extra[k], equal_nan=True)
