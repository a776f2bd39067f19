"""Tests of apo.io.poses: the first author's .pose.list, the pose CSV and its writer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from apo.errors import InputFormatError
from apo.io.poses import (
    Demonstration,
    load_demonstration,
    read_pose_csv,
    read_pose_list,
    write_pose_csv,
)
from apo.spatial import matrix_from_axis_angle, pose_from_position_quaternion


def real_data_dir() -> Path:
    """The first author's data beside the repository; skip the test when it is absent."""
    path = Path(__file__).resolve().parents[2] / "shared" / "data" / "apo-peg-in-hole"
    if not (path / "peg_in_hole.pose.list").is_file():
        pytest.skip(f"first author's data not found at {path}")
    return path


def pose(axis, angle, p) -> np.ndarray:
    x = np.eye(4)
    x[:3, :3] = matrix_from_axis_angle(axis, angle)
    x[:3, 3] = p
    return x


SMALL = """No of Models: 2
.\\models\\peg.step
.\\hole.step

No of Scenes: 2
2 10 20 30  0 0 2 1.5707963267948966
0 0 0 100  0 0 1 0

2 11 20 30  0 0 1 1.5707963267948966
0 0 0 100  1 0 0 0
"""


def write(tmp_path: Path, text: str, name: str = "demo.pose.list") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# ---------------------------------------------------------------------------------------------
# .pose.list
# ---------------------------------------------------------------------------------------------


def test_small_pose_list(tmp_path):
    dem = read_pose_list(write(tmp_path, SMALL))
    assert isinstance(dem, Demonstration) and dem.n_frames == 2 and dem.units == "mm"
    # Windows separators normalised, resolved against the list's directory
    assert dem.grasped_path == tmp_path / "models" / "peg.step"
    assert dem.environment_path == tmp_path / "hole.step"
    np.testing.assert_array_equal(dem.tags, [[2, 0], [2, 0]])
    np.testing.assert_array_equal(dem.lines, [6, 9])
    np.testing.assert_array_equal(dem.times, [0.0, 1.0])
    # X_CG: 90 deg about z (axis not unit: normalised), at (10, 20, 30) mm; X_CE at z = 100 mm
    x_cg = pose([0, 0, 1], np.pi / 2, [0.010, 0.020, 0.030])
    x_ce = pose([0, 0, 1], 0.0, [0, 0, 0.1])
    np.testing.assert_allclose(dem.X_CG[0], x_cg, atol=1e-15)
    np.testing.assert_allclose(dem.X_EG[0], np.linalg.inv(x_ce) @ x_cg, atol=1e-15)
    # X_EG = inv(X_CE) @ X_CG: the letters match, E's origin is 100 mm along the camera z
    np.testing.assert_allclose(dem.X_EG[1][:3, 3], [0.011, 0.020, -0.070], atol=1e-15)


def test_pose_list_fps_and_units(tmp_path):
    dem = read_pose_list(write(tmp_path, SMALL), units="cm", fps=30.0)
    np.testing.assert_allclose(dem.times, [0.0, 1 / 30])
    np.testing.assert_allclose(dem.X_EG[1][:3, 3], [0.11, 0.20, -0.70], atol=1e-14)
    assert dem.fps == 30.0 and dem.units == "cm"


def test_pose_list_trailing_blank_lines_and_crlf(tmp_path):
    path = tmp_path / "crlf.pose.list"
    path.write_bytes((SMALL + "\n\n").replace("\n", "\r\n").encode())
    assert read_pose_list(path).n_frames == 2


@pytest.mark.parametrize(
    ("mutate", "match"),
    [
        (lambda s: "garbage\n" + s, r"line 1: expected 'No of Models: N'"),
        (lambda s: s.replace("No of Models: 2", "No of Models: two"), r"line 1: .*whole"),
        (lambda s: s.replace("No of Models: 2", "No of Models: 1"), r"line 1: need at least 2"),
        (
            lambda s: s.replace("No of Models: 2", "No of Models: 3"),
            r"expected 3 model paths, found 2",
        ),
        (
            lambda s: s.replace(".\\hole.step\n", ".\\hole.step\nextra.step\n"),
            r"line 4: expected 2 model paths, found more",
        ),
        (lambda s: s.replace("No of Scenes: 2", "Scenes 2"), r"line 5: expected 'No of Scenes: N'"),
        (lambda s: s.replace("No of Scenes: 2", "No of Scenes: 3"), r"expected 3 scenes .*found 2"),
        (
            lambda s: s.replace("No of Scenes: 2", "No of Scenes: 1"),
            r"line 9: expected 1 scenes .*found 2",
        ),
        (lambda s: s.split("\n2 10")[0].replace("Scenes: 2", "Scenes: 0"), r"no scenes \(empty"),
        (lambda s: s.replace("2 10 20 30", "2 abc 20 30"), r"line 6: x is not a number: 'abc'"),
        (lambda s: s.replace("2 10 20 30", "2 nan 20 30"), r"line 6: x is not finite"),
        (lambda s: s.replace("0 0 1 0\n\n", "0 0 inf 0\n\n"), r"line 7: az is not finite"),
        (lambda s: s.replace("2 10 20 30", "x 10 20 30"), r"line 6: tag is not an integer"),
        (lambda s: s.replace("0 0 2 1.57", "0 0 0 1.57"), r"line 6: rotation axis is zero"),
        (lambda s: s.replace("1 0 0 0\n", "1 0 0\n"), r"line 10: expected 8 fields"),
        (
            lambda s: s.replace("0 0 0 100  1 0 0 0\n", ""),
            r"line 9: scene 2 has 1 pose lines, expected 2",
        ),
    ],
)
def test_pose_list_errors_name_file_and_line(tmp_path, mutate, match):
    path = write(tmp_path, mutate(SMALL), "bad.pose.list")
    with pytest.raises(InputFormatError, match=match) as info:
        read_pose_list(path)
    assert "bad.pose.list" in str(info.value)


def test_pose_list_zero_axis_with_zero_angle_is_identity(tmp_path):
    dem = read_pose_list(write(tmp_path, SMALL.replace("0 0 2 1.5707963267948966", "0 0 0 0")))
    np.testing.assert_allclose(dem.X_CG[0][:3, :3], np.eye(3))


def test_missing_file_and_bad_units(tmp_path):
    with pytest.raises(InputFormatError, match=r"nope.pose.list: file not found"):
        read_pose_list(tmp_path / "nope.pose.list")
    with pytest.raises(InputFormatError, match=r"unknown units 'km'"):
        read_pose_list(write(tmp_path, SMALL), units="km")
    with pytest.raises(InputFormatError, match=r"fps must be positive"):
        read_pose_list(write(tmp_path, SMALL), fps=0.0)


@pytest.mark.realdata
def test_real_pose_list():
    data = real_data_dir()
    dem = read_pose_list(data / "peg_in_hole.pose.list")
    assert dem.n_frames == 41 and dem.X_EG.shape == (41, 4, 4) and dem.X_C.shape == (41, 2, 4, 4)
    assert dem.grasped_path == data / "peg.step" and dem.grasped_path.is_file()
    assert dem.environment_path == data / "hole.step" and dem.environment_path.is_file()
    assert {tuple(t) for t in dem.tags} == {(2, 0)}
    r = dem.X_EG[:, :3, :3]
    np.testing.assert_allclose(
        np.einsum("nij,nkj->nik", r, r), np.broadcast_to(np.eye(3), r.shape), atol=1e-12
    )
    # first scene from the file by hand: peg line "2 -27.240726 999.618286 1429.929565 ..."
    x_cg = pose([-0.049679, 0.001101, 0.998765], 3.140531, [-0.027240726, 0.999618286, 1.429929565])
    np.testing.assert_allclose(dem.X_CG[0], x_cg, atol=1e-12)
    np.testing.assert_allclose(dem.X_EG[0], np.linalg.inv(dem.X_CE[0]) @ x_cg, atol=1e-12)
    # the peg starts away from the hole and ends within a few mm of the hole's origin,
    # while the hole hardly moves in the camera frame (tracking jitter: < 3 mm)
    assert np.linalg.norm(dem.X_EG[0][:3, 3]) > 0.1
    assert np.linalg.norm(dem.X_EG[-1][:3, 3]) < 0.005
    ce = dem.X_CE[:, :3, 3]
    assert np.ptp(ce, axis=0).max() < 0.003


# ---------------------------------------------------------------------------------------------
# CSV
# ---------------------------------------------------------------------------------------------


def random_poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = np.zeros((n, 4, 4))
    for k in range(n):
        q = rng.normal(size=4)
        out[k] = pose_from_position_quaternion(rng.uniform(-0.2, 0.2, 3), q)
    return out


def test_csv_round_trip(tmp_path):
    x = random_poses(7, seed=1)
    t = np.cumsum(np.full(7, 1 / 30))
    conf = np.linspace(0.5, 1.0, 7)
    conf[3] = np.nan
    path = write_pose_csv(tmp_path / "p.csv", t, x, units="mm", extra={"confidence": conf})
    assert path.read_text().splitlines()[0] == "t,x,y,z,qw,qx,qy,qz,confidence"
    dem = read_pose_csv(path, units="mm")
    np.testing.assert_array_equal(dem.times, t)
    np.testing.assert_allclose(dem.X_EG, x, atol=1e-14)
    np.testing.assert_array_equal(dem.extra["confidence"], conf)
    assert dem.X_C is None and dem.tags is None and dem.grasped_path is None
    np.testing.assert_array_equal(dem.lines, np.arange(2, 9))


def test_csv_without_header_comments_and_unnormalised_quaternion(tmp_path):
    text = "# recorded by hand\n0.0,1,2,3,2,0,0,0,0.9\n\n0.5,1,2,4,1,0,0,1,0.8\n"
    # normalised, and the norms far from 1 are reported with their lines (issue 12)
    with pytest.warns(
        UserWarning, match=r"2 line\(s\) .*norm far from 1.*line 2 \(norm 2\), line 4"
    ):
        dem = read_pose_csv(write(tmp_path, text, "p.csv"), units="cm")
    np.testing.assert_allclose(dem.X_EG[0], pose([0, 0, 1], 0, [0.01, 0.02, 0.03]))
    np.testing.assert_allclose(
        dem.X_EG[1][:3, :3], matrix_from_axis_angle([0, 0, 1], np.pi / 2), atol=1e-15
    )
    np.testing.assert_array_equal(dem.extra["col8"], [0.9, 0.8])
    np.testing.assert_array_equal(dem.lines, [2, 4])


HEAD = "t,x,y,z,qw,qx,qy,qz\n"


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", r"no rows \(empty"),
        (HEAD, r"header only"),
        ("time,x,y,z,qw,qx,qy,qz\n0,0,0,0,1,0,0,0\n", r"line 1: header must begin with t,x"),
        (HEAD.strip() + ",a,a\n0,0,0,0,1,0,0,0,1,2\n", r"line 1: repeated column names \['a'\]"),
        ("0,0,0,0,1,0,0\n", r"line 1: expected at least 8 columns"),
        (HEAD + "0,0,0,0,1,0,0,0\n1,0,0\n", r"line 3: expected 8 fields, got 3"),
        (HEAD + "0,0,0,0,1,0,0,0\n1,0,zz,0,1,0,0,0\n", r"line 3: y is not a number: 'zz'"),
        (HEAD + "0,0,0,nan,1,0,0,0\n", r"line 2: z is not finite"),
        (HEAD + "0,0,0,0,0,0,0,0\n", r"line 2: quaternion .* is zero"),
        (
            HEAD + "0,0,0,0,1,0,0,0\n0,0,0,0,1,0,0,0\n",
            r"line 3: time stamps must strictly increase",
        ),
        (HEAD.strip() + ",c\n0,0,0,0,1,0,0,0,high\n", r"line 2: column 'c' is not a number"),
    ],
)
def test_csv_errors_name_file_and_line(tmp_path, text, match):
    path = write(tmp_path, text, "bad.csv")
    with pytest.raises(InputFormatError, match=match) as info:
        read_pose_csv(path, units="m")
    assert "bad.csv" in str(info.value)


@pytest.mark.parametrize(
    ("times", "poses", "extra", "match"),
    [
        ([], np.zeros((0, 4, 4)), None, r"N > 0"),
        ([0.0, 1.0], np.stack([np.eye(4)] * 3), None, r"shape \(2, 4, 4\)"),
        ([1.0, 1.0], np.stack([np.eye(4)] * 2), None, r"frame 1 has t = 1.0 after 1.0"),
        ([0.0], np.eye(4)[None] * 2, None, r"X_EG\[0\] has no rotation"),
        ([0.0], np.diag([1.0, 1.0, 1.0, 2.0])[None], None, r"X_EG\[0\] last row is not 0 0 0 1"),
        ([0.0], np.full((1, 4, 4), np.nan), None, r"finite"),
        ([0.0], np.eye(4)[None], {"qw": [1.0]}, r"bad extra column name 'qw'"),
        ([0.0], np.eye(4)[None], {"a,b": [1.0]}, r"bad extra column name"),
        ([0.0], np.eye(4)[None], {"c": [1.0, 2.0]}, r"'c' must have shape \(1,\)"),
    ],
)
def test_write_pose_csv_rejects(tmp_path, times, poses, extra, match):
    with pytest.raises(InputFormatError, match=match):
        write_pose_csv(tmp_path / "o.csv", times, poses, units="m", extra=extra)


# ---------------------------------------------------------------------------------------------
# load_demonstration
# ---------------------------------------------------------------------------------------------


def test_load_demonstration_dispatches_and_overrides(tmp_path):
    dem = load_demonstration(write(tmp_path, SMALL), grasped="g.stl")
    assert dem.grasped_path == Path("g.stl") and dem.environment_path == tmp_path / "hole.step"
    assert dem.units == "mm"
    csv_path = write_pose_csv(tmp_path / "p.csv", [0.0], np.eye(4)[None], units="m")
    dem2 = load_demonstration(csv_path, units="m", environment=tmp_path / "e.step")
    assert dem2.n_frames == 1 and dem2.environment_path == tmp_path / "e.step"
    with pytest.raises(InputFormatError, match=r"unknown demonstration format '.txt'"):
        load_demonstration(write(tmp_path, SMALL, "demo.txt"))


def test_quaternions_within_the_tolerance_are_normalised_silently(tmp_path):
    from apo.io.poses import QUATERNION_NORM_TOLERANCE

    rng = np.random.default_rng(7)
    rows = [HEAD.strip()]
    for k in range(50):
        q = rng.normal(size=4)
        q *= (1.0 + rng.uniform(-0.9, 0.9) * QUATERNION_NORM_TOLERANCE) / np.linalg.norm(q)
        rows.append(",".join(repr(float(v)) for v in [k, 1, 2, 3, *q]))
    dem = read_pose_csv(write(tmp_path, "\n".join(rows) + "\n", "p.csv"), units="mm")
    assert dem.n_frames == 50
    rows[12] = rows[12].rsplit(",", 4)[0] + ",4,0,0,0"
    rows[30] = rows[30].rsplit(",", 4)[0] + ",0,0,0.25,0"
    with pytest.warns(UserWarning, match=r"p2.csv: 2 line\(s\).*line 13 \(norm 4\), line 31"):
        read_pose_csv(write(tmp_path, "\n".join(rows) + "\n", "p2.csv"), units="mm")


def test_a_long_garbage_line_is_quoted_cut(tmp_path):
    from apo.errors import InputFormatError
    from apo.io.poses import EXCERPT_CHARS

    text = "t,x," + "y" * 5000 + "\n1,2,3\n"
    with pytest.raises(InputFormatError) as exc:
        read_pose_csv(write(tmp_path, text, "g.csv"), units="mm")
    msg = str(exc.value)
    assert "line 1" in msg and "(5004 characters)" in msg
    assert len(msg) < EXCERPT_CHARS + 200


@pytest.mark.parametrize("suffix", [".pose.list", ".csv"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_binary_files_are_blamed_on_their_first_binary_line(tmp_path, suffix, seed):
    from apo.errors import InputFormatError
    from apo.io.poses import load_demonstration

    rng = np.random.default_rng(seed)
    good = "No of Models: 2\n" if suffix == ".pose.list" else HEAD
    for body, line in ((rng.bytes(4000), 2), (bytes(300) + b"\n1\n", 2)):
        p = tmp_path / f"b{suffix}"
        p.write_bytes(good.encode() + body)
        with pytest.raises(InputFormatError, match=rf"b{suffix}: line {line}: not a text file"):
            load_demonstration(p, grasped=p, environment=p)
