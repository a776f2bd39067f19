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
