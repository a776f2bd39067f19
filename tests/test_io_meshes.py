from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from apo import shapes
from apo.errors import GeometryError, InputFormatError
from apo.io import load_polyhedron, load_triangles, step_length_unit

trimesh = pytest.importorskip("trimesh")


def write_mesh(path: Path, vertices: np.ndarray, triangles: np.ndarray) -> Path:
    trimesh.Trimesh(vertices, triangles, process=False).export(str(path))
    return path


def peg_triangles() -> tuple[np.ndarray, np.ndarray]:
    p = shapes.t_peg()
    return p.vertices, np.concatenate(p.face_triangles)


# ---- the first author's STEP models ---------------------------------------------------------


@pytest.mark.realdata
def test_authors_peg(real_data_dir: Path) -> None:
    peg = load_polyhedron(real_data_dir / "peg.step")
    assert peg.name == "peg.step"
    assert (len(peg.faces), len(peg.edges), len(peg.vertices)) == (10, 24, 16)
    assert peg.n_concave_edges == 2
    # 70 mm wide crossbar, 88 mm tall, 35 mm thick: metres, converted once.
    assert np.allclose(np.ptp(peg.vertices, axis=0), [0.070, 0.088, 0.035], atol=1e-7)
    assert peg.volume > 0
    assert peg.volume == pytest.approx((0.035 * 0.070 + 0.070 * 0.018) * 0.035, rel=1e-5)


@pytest.mark.realdata
def test_authors_hole(real_data_dir: Path) -> None:
    hole = load_polyhedron(real_data_dir / "hole.step")
    assert (len(hole.faces), len(hole.edges), len(hole.vertices)) == (14, 36, 24)
    assert hole.n_concave_edges == 4
    assert np.allclose(np.ptp(hole.vertices, axis=0), [0.140, 0.088, 0.035], atol=1e-7)
    assert hole.volume > 0


@pytest.mark.realdata
def test_step_declared_unit_is_honoured(real_data_dir: Path, tmp_path: Path) -> None:
    src = real_data_dir / "peg.step"
    assert step_length_unit(src) == "mm"
    # The same file declaring metres: the numbers are now metres, so it is 1000 x larger.
    text = src.read_text(encoding="latin-1").replace(
        "SI_UNIT(.MILLI.,.METRE.)", "SI_UNIT($,.METRE.)"
    )
    in_m = tmp_path / "peg_in_m.STEP"
    in_m.write_text(text, encoding="latin-1")
    assert step_length_unit(in_m) == "m"
    peg = load_polyhedron(in_m)
    assert np.allclose(np.ptp(peg.vertices, axis=0), [70.0, 88.0, 35.0], atol=1e-4)


@pytest.mark.realdata
def test_step_units_argument_does_not_double_convert(real_data_dir: Path) -> None:
    a = load_polyhedron(real_data_dir / "peg.step", units="mm")  # agrees: silent
    b = load_polyhedron(real_data_dir / "peg.step")
    assert np.array_equal(a.vertices, b.vertices)
    with pytest.warns(UserWarning, match=r"declares its lengths in 'mm'; ignoring units='m'"):
        c = load_polyhedron(real_data_dir / "peg.step", units="m")
    assert np.array_equal(c.vertices, b.vertices)


# ---- unitless mesh formats ------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".stl", ".obj", ".ply", ".STL"])
@pytest.mark.parametrize(
    ("units", "factor"), [("mm", 1e-3), ("cm", 1e-2), ("m", 1.0), ("in", 0.0254)]
)
def test_round_trip_with_units(tmp_path: Path, suffix: str, units: str, factor: float) -> None:
    v, t = peg_triangles()
    path = write_mesh(tmp_path / f"peg{suffix}", v / factor, t)  # numbers in `units`
    p = load_polyhedron(path, units=units)
    ref = shapes.t_peg()
    assert (len(p.faces), len(p.edges), len(p.vertices)) == (10, 24, 16)
    assert np.allclose(np.sort(p.vertices, axis=0), np.sort(ref.vertices, axis=0), atol=1e-9)
    assert p.volume == pytest.approx(ref.volume, rel=1e-6)


def test_mesh_default_units_are_millimetres(tmp_path: Path) -> None:
    v, t = peg_triangles()
    path = write_mesh(tmp_path / "peg.stl", v * 1000.0, t)
    verts, tris = load_triangles(path)
    assert np.allclose(np.ptp(verts, axis=0), [0.070, 0.088, 0.035], atol=1e-9)
    assert tris.shape[1] == 3


def test_name_argument(tmp_path: Path) -> None:
    v, t = peg_triangles()
    path = write_mesh(tmp_path / "peg.ply", v * 1000.0, t)
    assert load_polyhedron(path, name="grasped").name == "grasped"


# ---- bad input ------------------------------------------------------------------------------


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputFormatError, match=r"nothere\.stl: no such file"):
        load_polyhedron(tmp_path / "nothere.stl")


def test_unknown_suffix(tmp_path: Path) -> None:
    path = tmp_path / "model.dae"
    path.write_text("x")
    with pytest.raises(InputFormatError, match=r"model\.dae: unknown model file type '\.dae'"):
        load_polyhedron(path)


def test_unknown_units(tmp_path: Path) -> None:
    v, t = peg_triangles()
    path = write_mesh(tmp_path / "peg.stl", v, t)
    with pytest.raises(InputFormatError, match=r"peg\.stl: unknown units 'ft'"):
        load_polyhedron(path, units="ft")


@pytest.mark.parametrize("suffix", [".stl", ".ply", ".step"])
def test_unreadable_file(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"garbage{suffix}"
    path.write_bytes(b"\x00\x01 this is not a mesh \xff" * 3)
    with pytest.raises(InputFormatError, match=rf"garbage\{suffix}: (cannot read|the file)"):
        load_polyhedron(path)


def test_empty_file(tmp_path: Path) -> None:
    path = tmp_path / "empty.obj"
    path.write_text("# nothing here\n")
    with pytest.raises(InputFormatError, match=r"empty\.obj: the file contains no triangles"):
        load_polyhedron(path)


def test_open_mesh_names_the_file(tmp_path: Path) -> None:
    v, t = peg_triangles()
    path = write_mesh(tmp_path / "open.stl", v * 1000.0, t[1:])
    with pytest.raises(GeometryError, match=r"^open\.stl: mesh is not closed"):
        load_polyhedron(path)
