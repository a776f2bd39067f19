"""Tests of ``apo contacts``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from apo.cli import main
from apo.geometry import Polyhedron
from apo.shapes import block_with_square_hole, box


def write_obj(path: Path, poly: Polyhedron, unit: float = 1e-3) -> Path:
    """Write a model as OBJ with coordinates in ``unit`` metres (default mm)."""
    tris = np.concatenate(poly.face_triangles)
    lines = [f"v {x / unit:.9g} {y / unit:.9g} {z / unit:.9g}" for x, y, z in poly.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in tris]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def models(tmp_path: Path) -> tuple[str, str]:
    peg = write_obj(tmp_path / "peg.obj", box([0.04, 0.04, 0.06], center=[0.0, 0.0, 0.03]))
    hole = write_obj(tmp_path / "hole.obj", block_with_square_hole())
    return str(peg), str(hole)


def test_json_seated_peg(models: tuple[str, str], capsys: pytest.CaptureFixture[str]) -> None:
    peg, hole = models
    # Peg seated on the pocket floor (z = 20 mm), identity rotation.
    assert main(["contacts", peg, hole, "--pose", "0 0 20 1 0 0 0", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    kinds = sorted(e["kind"] for e in out["elements"])
    assert kinds == ["EE"] * 8 + ["VF"] * 12  # as test_contact's peg_seated
    for key in ("singular", "fig25", "translation", "rotation", "all", "singular_dof",
                "restraining"):  # fmt: skip
        assert key in out
    assert out["fig25"] == [0, 1, 2, 0, 0, 3, 3, 3]
    # Points in the given units (mm): the bottom corners at z = 20 mm.
    zs = sorted(round(e["point"][2], 6) for e in out["elements"])
    assert zs[0] == pytest.approx(20.0) and zs[-1] == pytest.approx(50.0)
    el = out["elements"][0]
    assert set(el) == {"kind", "grasped", "environment", "point", "normals"}


def test_units_and_threshold(
    models: tuple[str, str], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    peg, hole = models
    # 0.3 mm above the floor: no floor contact with the default threshold (~0.06 mm) ...
    assert main(["contacts", peg, hole, "--pose", "0 0 20.3 1 0 0 0", "--json"]) == 0
    assert len(json.loads(capsys.readouterr().out)["elements"]) == 16
    # ... but with a 0.05 cm threshold; --units also applies to the mesh files.
    peg_cm = write_obj(tmp_path / "peg_cm.obj", box([0.04, 0.04, 0.06], center=[0, 0, 0.03]), 1e-2)
    hole_cm = write_obj(tmp_path / "hole_cm.obj", block_with_square_hole(), 1e-2)
    args = ["contacts", str(peg_cm), str(hole_cm), "--pose", "0 0 2.03 1 0 0 0", "--units", "cm"]
    assert main([*args, "--threshold", "0.05", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["elements"]) == 20
    assert min(e["point"][2] for e in out["elements"]) == pytest.approx(2.0)  # cm


def test_text_output(models: tuple[str, str], capsys: pytest.CaptureFixture[str]) -> None:
    peg, hole = models
    assert main(["contacts", peg, hole, "--pose", "0 0 20 1 0 0 0"]) == 0
    out = capsys.readouterr().out
    assert "20 contact element(s)" in out
    assert "translation M D C: 0 1 2" in out
    assert "frame: environment" in out


@pytest.mark.parametrize(
    ("pose", "units", "match"),
    [
        ("0 0 20 1 0 0", "mm", "expected 7 numbers"),
        ("0 0 nan 1 0 0 0", "mm", "non-finite"),
        ("0 0 x 1 0 0 0", "mm", "not a number"),
        ("0 0 0 0 0 0 0", "mm", "zero norm"),
        ("0 0 20 1 0 0 0", "furlong", "unknown unit"),
    ],
)
def test_bad_input_exits_2(
    models: tuple[str, str],
    capsys: pytest.CaptureFixture[str],
    pose: str,
    units: str,
    match: str,
) -> None:
    peg, hole = models
    assert main(["contacts", peg, hole, "--pose", pose, "--units", units]) == 2
    err = capsys.readouterr().err
    assert match in err and "Traceback" not in err


def test_missing_file_exits_2(
    models: tuple[str, str], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    peg, _ = models
    missing = str(tmp_path / "nope.stl")
    assert main(["contacts", peg, missing, "--pose", "0 0 0 1 0 0 0"]) == 2
    assert "nope.stl" in capsys.readouterr().err
    assert main(["contacts", peg, peg, "--pose", "0 0 0 1 0 0 0", "--threshold", "-1"]) == 2
    assert "--threshold" in capsys.readouterr().err


# ---- added by the audit of issue 2 --------------------------------------------------------


def final_pose_argument(pose_list: Path) -> str:
    """``"x y z qw qx qy qz"`` (mm) of the grasped peg in the hole's frame at the last scene.

    Computed from the raw ``.pose.list`` without apo: each scene lists object 0 (peg.step,
    grasped) then object 1 (hole.step, environment) as ``tag x y z ax ay az angle`` (mm,
    camera frame); ``X_EG = X_CE^-1 X_CG``.
    """
    from scipy.spatial.transform import Rotation

    rows = [ln.split() for ln in pose_list.read_text().splitlines() if len(ln.split()) == 8]
    X = []
    for row in rows[-2:]:
        x, y, z, ax, ay, az, angle = (float(v) for v in row[1:])
        M = np.eye(4)
        M[:3, :3] = Rotation.from_rotvec(np.array([ax, ay, az]) / np.linalg.norm([ax, ay, az])
                                         * angle).as_matrix()  # fmt: skip
        M[:3, 3] = [x, y, z]
        X.append(M)
    X_CG, X_CE = X
    X_EG = np.linalg.inv(X_CE) @ X_CG
    qx, qy, qz, qw = Rotation.from_matrix(X_EG[:3, :3]).as_quat()
    return " ".join(f"{v:.9f}" for v in (*X_EG[:3, 3], qw, qx, qy, qz))


@pytest.mark.realdata
def test_real_t_peg_in_u_hole_at_the_final_pose(
    real_data_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    peg, hole = str(real_data_dir / "peg.step"), str(real_data_dir / "hole.step")
    pose = final_pose_argument(real_data_dir / "peg_in_hole.pose.list")
    # The observed pose is ~1 mm off and tilted 3.4 deg: a 4 mm threshold finds the seated
    # state (docs/contacts.md). Stem bottom corners flush at the slot floor's front/back
    # edges (VE, +y and +-x), crossbar outer corners on the posts' front/back edges (VE,
    # +y), the peg's reflex corners on the slot rim vertices (EV, +y and +-x).
    assert main(["contacts", peg, hole, "--pose", pose, "--threshold", "4", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    keys = {"singular", "fig25", "translation", "rotation", "all", "singular_dof", "restraining"}
    assert set(out) == {"frame", "units", "threshold", "elements", *keys}
    assert (out["frame"], out["units"], out["threshold"]) == ("environment", "mm", 4.0)
    assert sorted(e["kind"] for e in out["elements"]) == ["EV"] * 8 + ["VE"] * 12
    normals = sorted(tuple(n) for e in out["elements"] for n in e["normals"])
    assert normals == [(-1.0, 0.0, 0.0)] * 4 + [(0.0, 1.0, 0.0)] * 12 + [(1.0, 0.0, 0.0)] * 4
    # points in mm: the slot floor (y = -35) and the posts' tops (y = +35), +-17.5 deep in z
    ys = sorted(round(e["point"][1]) for e in out["elements"])
    assert ys == [-35] * 8 + [35] * 12
    assert all(abs(abs(e["point"][2]) - 17.5) < 4.0 for e in out["elements"])
    # slide along z (M), lift along +y (D), x held by the slot walls (C); tipping about x
    # lifts either way (type I), turning about y and z is blocked at both walls (C).
    assert out["singular"] is False
    assert out["fig25"] == [1, 1, 1, 0, 1, 2, 2, 3]
    assert out["rotation"] == {"maintaining": 0, "detaching": 1, "constraining": 2,
                               "detaching_type1": 1, "detaching_type2": 0}  # fmt: skip
    assert out["all"] == {"maintaining": 1, "detaching": 2, "constraining": 3}
    assert out["restraining"] == {"translation": 2, "rotation": 3, "all": 5}
    assert out["singular_dof"]["translation"] == {"maintaining": 0, "detaching": 0,
                                                  "constraining": 0}  # fmt: skip
    # the same in metres (the STEP files declare mm and are read in their own unit)
    p = pose.split()
    in_m = " ".join([*(f"{float(v) / 1000:.12f}" for v in p[:3]), *p[3:]])
    # (no warning escapes: the CLI prints them; pytest would turn one into an error)
    assert main(["contacts", peg, hole, "--pose", in_m, "--units", "m", "--threshold",
                 "0.004", "--json"]) == 0  # fmt: skip
    captured = capsys.readouterr()
    assert json.loads(captured.out)["fig25"] == [1, 1, 1, 0, 1, 2, 2, 3]
    assert captured.err.count("apo contacts: warning: ") == 2
    assert "declares its lengths in 'mm'; ignoring units='m'" in captured.err


def test_default_threshold_is_reported(
    models: tuple[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    peg, hole = models
    assert main(["contacts", peg, hole, "--pose", "0 0 20 1 0 0 0", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    # 1e-3 of the smaller bounding diagonal: the peg's sqrt(40^2 + 40^2 + 60^2) mm
    assert out["threshold"] == pytest.approx(1e-3 * np.sqrt(40**2 + 40**2 + 60**2))
    assert main(["contacts", peg, hole, "--pose", "0 0 20 1 0 0 0"]) == 0
    assert "threshold: 0.0824621" in capsys.readouterr().out


def test_singular_state_text_says_singular(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A cube corner on a table's convex edge (VE, two normals): singular; with no regular
    # element left the singular M is 3 in both spaces; r_t = 2 (normals perpendicular to
    # the edge), r_r = 0 (one point).
    from apo.spatial import matrix_from_axis_angle, quaternion_from_matrix

    cube = write_obj(tmp_path / "cube.obj", box([0.1, 0.1, 0.1], center=[0, 0, 0.05]))
    table = write_obj(tmp_path / "table.obj", box([1.0, 1.0, 0.1], center=[0, 0, -0.05]))
    R = matrix_from_axis_angle([1, 1, 1], 0.5)
    t = (np.array([0.5, 0.0, 0.0]) - R @ np.array([-0.05, -0.05, 0.0])) * 1000.0
    pose = " ".join(f"{v:.12f}" for v in (*t, *quaternion_from_matrix(R)))
    assert main(["contacts", str(cube), str(table), "--pose", pose]) == 0
    out = capsys.readouterr().out
    assert "1 contact element(s) (singular state)" in out
    assert "  VE G:v" in out
    assert "translation singular M D C: 3 0 0   rotation singular M D C: 3 0 0" in out
    assert "restraining t r: 2 0" in out


def test_bad_models_exit_2_naming_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    good = write_obj(tmp_path / "cube.obj", box([0.04, 0.04, 0.04]))
    tris = np.concatenate(box([0.04, 0.04, 0.04]).face_triangles)
    verts = box([0.04, 0.04, 0.04]).vertices * 1000.0
    open_mesh = tmp_path / "open.obj"
    open_mesh.write_text(
        "".join(f"v {x} {y} {z}\n" for x, y, z in verts)
        + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in tris[1:])
    )
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(b"\x00\x01 not a mesh \xff" * 3)
    for bad, message in [
        (open_mesh, f"{open_mesh}: mesh is not closed"),
        (garbage, f"{garbage}: "),
        (tmp_path / "model.dae", "unknown model file type '.dae'"),
    ]:
        assert main(["contacts", str(good), str(bad), "--pose", "0 0 0 1 0 0 0"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("apo contacts: error: ") and message in err
        assert "Traceback" not in err


def test_mesh_warnings_are_printed_not_raised(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # An inside-out mesh is flipped (analysis proceeds) and the user is told, by file.
    cube = box([0.04, 0.04, 0.04], center=[0, 0, 0.02])
    tris = np.concatenate(cube.face_triangles)[:, ::-1]
    inside_out = tmp_path / "inside_out.obj"
    inside_out.write_text(
        "".join(f"v {x * 1e3:.9g} {y * 1e3:.9g} {z * 1e3:.9g}\n" for x, y, z in cube.vertices)
        + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in tris)
    )
    table = write_obj(tmp_path / "table.obj", box([1.0, 1.0, 0.1], center=[0, 0, -0.05]))
    assert main(["contacts", str(inside_out), str(table), "--pose", "0 0 0 1 0 0 0"]) == 0
    captured = capsys.readouterr()
    assert f"apo contacts: warning: {inside_out}: the mesh is inside-out" in captured.err
    assert "4 contact element(s)" in captured.out  # outward normals after the flip: on top
    assert "translation M D C: 2 1 0" in captured.out


def test_units_table_matches_the_io_package() -> None:
    from apo.cli.contacts import _UNITS
    from apo.io.meshes import UNITS

    assert _UNITS == UNITS


@pytest.mark.parametrize(
    "args",
    [
        ["contacts", "nope.stl", "nope.stl", "--pose", "0 0 0 1 0 0 0"],
        ["contacts", "a.stl", "b.stl", "--pose", "0 0 0 1 0 0 0", "--units", "ft"],
        ["dof", "nope.json"],
    ],
)
def test_entry_point_exits_2_without_traceback(tmp_path: Path, args: list[str]) -> None:
    # The installed entry point itself (python -m apo.cli), as a user runs it.
    import subprocess
    import sys

    proc = subprocess.run(
        [sys.executable, "-m", "apo.cli", *args],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 2
    assert proc.stderr.startswith(f"apo {args[0]}: error: ")
    assert "Traceback" not in proc.stderr
