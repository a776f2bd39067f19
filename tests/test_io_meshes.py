from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from apo import shapes
from apo.constants import UNITS
from apo.errors import GeometryError, InputFormatError
from apo.geometry import Polyhedron
from apo.io import load_polyhedron, load_triangles, step_length_unit
from test_synthetic import winding  # generalised winding number of a closed surface

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
    # an 88 m peg is read as declared, with a warning that the units look wrong
    with pytest.warns(UserWarning, match=r"the model is 88 m across .*are the units right"):
        peg = load_polyhedron(in_m)
    assert np.allclose(np.ptp(peg.vertices, axis=0), [70.0, 88.0, 35.0], atol=1e-4)


def test_implausible_sizes_warn_that_the_units_may_be_wrong(tmp_path: Path) -> None:
    import trimesh

    path = tmp_path / "cube.stl"
    trimesh.creation.box(extents=[50.0, 50.0, 50.0]).export(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_polyhedron(path, units="mm")  # 50 mm: plausible, silent
    with pytest.warns(
        UserWarning, match=r"cube.stl: the model is 50 m across \(read with units='m'\)"
    ):
        load_polyhedron(path, units="m")


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
    with pytest.raises(GeometryError, match=rf"^{re.escape(str(path))}: mesh is not closed"):
        load_polyhedron(path)
    # also when the model is given another name: the message still names the file
    with pytest.raises(GeometryError, match=rf"^{re.escape(str(path))}: mesh is not closed"):
        load_polyhedron(path, name="grasped")


def cube_mm() -> tuple[np.ndarray, np.ndarray]:
    """A 40 mm cube (numbers in mm), outward triangles."""
    c = shapes.box([0.04, 0.04, 0.04])
    return c.vertices * 1000.0, np.concatenate(c.face_triangles)


@pytest.mark.parametrize("suffix", [".stl", ".obj", ".ply"])
def test_inconsistent_orientation_names_the_file(tmp_path: Path, suffix: str) -> None:
    v, t = cube_mm()
    t = t.copy()
    t[0] = t[0][::-1]  # one triangle turned over: its 3 edges run the same way as neighbours'
    path = write_mesh(tmp_path / f"flipped{suffix}", v, t)
    with pytest.raises(
        GeometryError, match=rf"^{re.escape(str(path))}: inconsistent orientation: 3 edge"
    ):
        load_polyhedron(path)


def test_non_manifold_mesh_names_the_file(tmp_path: Path) -> None:
    v, t = cube_mm()
    path = write_mesh(tmp_path / "dup.ply", v, np.vstack([t, t[:1]]))  # a triangle twice
    with pytest.raises(GeometryError, match=rf"^{re.escape(str(path))}: non-manifold mesh"):
        load_polyhedron(path)


def test_flat_mesh_is_degenerate(tmp_path: Path) -> None:
    # two copies of one triangle, back to back: closed and oriented, but no volume
    v = np.array([[0.0, 0.0, 0.0], [40.0, 0.0, 0.0], [0.0, 40.0, 0.0]])
    path = write_mesh(tmp_path / "flat.obj", v, np.array([[0, 1, 2], [0, 2, 1]]))
    with pytest.raises(
        GeometryError, match=rf"^{re.escape(str(path))}: degenerate mesh: zero volume"
    ):
        load_polyhedron(path)


def test_inside_out_mesh_warns_naming_the_file_and_is_flipped(tmp_path: Path) -> None:
    v, t = cube_mm()
    path = write_mesh(tmp_path / "inside_out.ply", v, t[:, ::-1])
    with pytest.warns(UserWarning, match=rf"^{re.escape(str(path))}: the mesh is inside-out"):
        p = load_polyhedron(path)
    assert p.volume == pytest.approx(0.04**3)
    # outward normals: the face at x = +20 mm has normal +x
    k = int(np.argmax(p.face_normals[:, 0]))
    np.testing.assert_allclose(p.face_normals[k], [1, 0, 0], atol=1e-12)
    assert p.face_offsets[k] == pytest.approx(0.02)


def test_zero_area_triangle_warns_naming_the_file(tmp_path: Path) -> None:
    # Split the cube edge (a, b) at its midpoint m on one side only and close the gap with
    # the zero-area triangle (a, m, b): closed and oriented, one degenerate face.
    v, t = cube_mm()
    a, b = int(t[0, 0]), int(t[0, 1])
    m = len(v)
    v = np.vstack([v, 0.5 * (v[a] + v[b])])
    # the other triangle on edge (a, b) traverses it from b to a
    other = next(i for i in range(1, len(t)) if {a, b} <= set(t[i].tolist()))
    k = next(x for x in t[other].tolist() if x not in (a, b))
    keep = [tri.tolist() for i, tri in enumerate(t) if i != other]
    tris = np.array([*keep, [b, m, k], [m, a, k], [a, m, b]])
    path = write_mesh(tmp_path / "sliver.obj", v, tris)
    with pytest.warns(UserWarning, match=rf"^{re.escape(str(path))}: absorbed 1 zero-area"):
        p = load_polyhedron(path)
    assert (len(p.faces), len(p.edges), len(p.vertices)) == (6, 12, 8)  # m is dropped
    assert bool(p.edge_convex.all())


@pytest.mark.realdata
@pytest.mark.parametrize(
    ("name", "n_triangles", "concave"),
    [
        # the T-peg's two reflex corners where the stem meets the crossbar (x = +-17.5 mm)
        ("peg.step", 28, [(-17.5, 35.0), (17.5, 35.0)]),
        # the hole's slot bottom (x = +-17.5) and its two outer ledges (x = +-52.5), y = -35
        ("hole.step", 44, [(-52.5, -35.0), (-17.5, -35.0), (17.5, -35.0), (52.5, -35.0)]),
    ],
)
def test_authors_models_faces_normals_convexity(
    real_data_dir: Path, name: str, n_triangles: int, concave: list[tuple[float, float]]
) -> None:
    _, tris = load_triangles(real_data_dir / name)
    p = load_polyhedron(real_data_dir / name)
    assert len(tris) == n_triangles  # coplanar triangles merged into len(p.faces) faces
    assert len(p.faces) < len(tris)
    # every face is planar: its vertices lie on its plane (float32 STEP coordinates)
    for f, loop in enumerate(p.faces):
        assert np.allclose(p.vertices[loop] @ p.face_normals[f], p.face_offsets[f], atol=1e-7)
    # outward normals: just outside each face the winding number is 0, just inside 1
    for f, tri in enumerate(p.face_triangles):
        centre = p.vertices[tri[0]].mean(axis=0)
        probes = centre + 1e-4 * np.outer([1.0, -1.0], p.face_normals[f])
        np.testing.assert_allclose(winding(p, probes), [0.0, 1.0], atol=1e-6)
    # concave edges: exactly the extruded (along z) edges at the reflex outline corners
    ends = p.vertices[p.edges[~p.edge_convex]] * 1000.0
    assert np.allclose(np.abs(ends[:, 0, 2]), 17.5) and np.allclose(ends[:, 1, 2], -ends[:, 0, 2])
    got = sorted((round(float(x), 3), round(float(y), 3)) for x, y in ends[:, 0, :2])
    assert got == sorted(concave)


@pytest.mark.realdata
@pytest.mark.parametrize(("suffix", "units", "factor"), [(".stl", "mm", 1e-3), (".ply", "m", 1.0)])
def test_step_and_mesh_formats_agree(
    real_data_dir: Path, tmp_path: Path, suffix: str, units: str, factor: float
) -> None:
    # The author's hole re-exported as a mesh in the given units reads as the same solid.
    step = load_polyhedron(real_data_dir / "hole.step")
    v, t = load_triangles(real_data_dir / "hole.step")
    mesh = load_polyhedron(write_mesh(tmp_path / f"hole{suffix}", v / factor, t), units=units)
    assert (len(mesh.faces), len(mesh.edges), len(mesh.vertices)) == (14, 36, 24)
    # (ids follow the order of each file, so compare by coordinates; STEP arrives through
    # float32 glTF in metres, binary STL is float32 in mm: agreement to ~1e-7 relative)
    sv, mv = np.sort(step.vertices, axis=0), np.sort(mesh.vertices, axis=0)
    np.testing.assert_allclose(mv, sv, rtol=0, atol=1e-8)
    assert mesh.volume == pytest.approx(step.volume, rel=1e-6)

    def concave(p: Polyhedron) -> list[list[float]]:
        ends = np.sort(np.round(p.vertices[p.edges[~p.edge_convex]] * 1e4), axis=1)
        return sorted(ends.reshape(-1, 6).tolist())

    assert concave(mesh) == concave(step)


# ---- the triangle cache ---------------------------------------------------------------------


def test_cache_returns_the_same_triangles_without_reading_the_file_again(tmp_path, monkeypatch):
    import trimesh

    from apo.io.meshes import load_triangles

    monkeypatch.setenv("APO_CACHE_DIR", str(tmp_path / "cache"))
    path = tmp_path / "cube.obj"  # binary STL is read without trimesh, uncached
    trimesh.creation.box(extents=[50.0, 40.0, 30.0]).export(path)
    v1, t1 = load_triangles(path, units="mm")
    assert len(list((tmp_path / "cache" / "meshes").glob("*.npz"))) == 1

    def refuse(*args, **kwargs):
        raise AssertionError("trimesh.load called on a cached file")

    monkeypatch.setattr(trimesh, "load", refuse)
    v2, t2 = load_triangles(path, units="mm")
    np.testing.assert_array_equal(v1, v2)
    np.testing.assert_array_equal(t1, t2)
    # other units or other bytes are other entries (and need the reader again)
    with pytest.raises(InputFormatError, match="cannot read"):
        load_triangles(path, units="cm")
    monkeypatch.undo()
    monkeypatch.setenv("APO_CACHE_DIR", str(tmp_path / "cache"))
    v3, _ = load_triangles(path, units="cm")
    np.testing.assert_allclose(v3, v1 * 10)
    trimesh.creation.box(extents=[60.0, 40.0, 30.0]).export(path)
    v4, _ = load_triangles(path, units="mm")
    assert np.ptp(v4[:, 0]) == pytest.approx(0.06)


def test_cache_off_or_unwritable_still_reads(tmp_path, monkeypatch):
    import trimesh

    from apo.io.meshes import cache_dir, load_triangles

    path = tmp_path / "cube.obj"  # binary STL is read without trimesh, uncached
    trimesh.creation.box(extents=[50.0, 40.0, 30.0]).export(path)
    monkeypatch.setenv("APO_CACHE", "0")
    assert cache_dir() is None
    v, _ = load_triangles(path)
    assert np.ptp(v[:, 0]) == pytest.approx(0.05)
    monkeypatch.setenv("APO_CACHE", "1")
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("x")
    monkeypatch.setenv("APO_CACHE_DIR", str(blocker))
    v, _ = load_triangles(path)  # the cache cannot be made: read, no error
    assert np.ptp(v[:, 0]) == pytest.approx(0.05)
    # a corrupt entry is read past
    monkeypatch.setenv("APO_CACHE_DIR", str(tmp_path / "c2"))
    load_triangles(path)
    (entry,) = (tmp_path / "c2" / "meshes").glob("*.npz")
    entry.write_bytes(b"garbage")
    v, _ = load_triangles(path)
    assert np.ptp(v[:, 0]) == pytest.approx(0.05)


@pytest.mark.parametrize(("units", "k"), [("mm", 1e3), ("cm", 1e2), ("in", 1 / 0.0254)])
def test_mesh_errors_and_warnings_speak_the_models_units(tmp_path: Path, units: str, k: float):
    """Points, lengths and volumes in messages are in the file's units, not metres (issue 12)."""
    rng = np.random.default_rng(3)
    v, t = peg_triangles()
    shift = rng.uniform(-0.05, 0.05, size=3)
    numbers = (v + shift) * k
    path = write_mesh(tmp_path / "open.stl", numbers, t[1:])
    with pytest.raises(GeometryError) as info:
        load_polyhedron(path, units=units)
    msg = str(info.value)
    found = re.findall(rf"\[([^\]]+)\] {re.escape(units)}\b", msg)
    assert len(found) == 2, msg
    for text in found:
        p = np.array([float(x) for x in text.split(",")])
        # the point is one of the file's own vertices, as written in the file
        assert np.min(np.abs(numbers - p).max(axis=1)) < 1e-4 * k * 0.1, msg
    c = shapes.box([0.04, 0.04, 0.04])
    tri = np.concatenate(c.face_triangles)
    path = write_mesh(tmp_path / "inside_out.stl", c.vertices * k, tri[:, ::-1])
    with pytest.warns(
        UserWarning, match=r"negative volume -6\.4e\+0?4 mm\^3" if units == "mm" else "inside-out"
    ) as rec:
        load_polyhedron(path, units=units)
    assert f" {units}^3" in str(rec[0].message) and " m^3" not in str(rec[0].message)


def test_messages_in_metres_are_left_alone() -> None:
    from apo.io.meshes import in_model_units

    text = "mesh is not closed: e.g. between [0.1, 0.2, 0.3] and [0.4, 0.5, 0.6]; 1e-06 m"
    assert in_model_units(text, "m") == text
    assert in_model_units(text, "mm") == (
        "mesh is not closed: e.g. between [100, 200, 300] mm and [400, 500, 600] mm; 0.001 mm"
    )
    assert in_model_units("volume -0.001 m^3", "mm") == "volume -1e+06 mm^3"


# ---- binary STL read without trimesh ----------------------------------------------------------


@pytest.mark.parametrize("seed", range(5))
def test_binary_stl_reads_as_trimesh_does(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, seed: int
) -> None:
    """The same float64 vertices and triangles as ``trimesh.load(process=False)``, no import."""
    from apo.io.meshes import load_triangles

    monkeypatch.setenv("APO_CACHE", "0")
    rng = np.random.default_rng(seed)
    V = rng.normal(0, 30.0, (int(rng.integers(3, 60)), 3))
    T = rng.integers(0, len(V), (int(rng.integers(1, 80)), 3))
    path = tmp_path / "m.stl"
    trimesh.Trimesh(V, T, process=False).export(str(path))  # binary STL
    ref = trimesh.load(str(path), file_type="stl", process=False)
    monkeypatch.setattr(trimesh, "load", lambda *a, **k: pytest.fail("trimesh.load called"))
    for units in ("mm", "m", "in"):
        v, t = load_triangles(path, units=units)
        np.testing.assert_array_equal(v, np.asarray(ref.vertices, dtype=np.float64) * UNITS[units])
        np.testing.assert_array_equal(t, ref.faces)
        assert v.dtype == np.float64 and t.dtype == np.int64


def test_ascii_and_empty_stl_still_go_to_trimesh(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from apo.io.meshes import load_triangles

    monkeypatch.setenv("APO_CACHE", "0")
    path = tmp_path / "a.stl"
    box = trimesh.creation.box(extents=[50.0, 40.0, 30.0])
    path.write_bytes(trimesh.exchange.stl.export_stl_ascii(box).encode())
    v, t = load_triangles(path)
    assert len(t) == 12 and np.ptp(v[:, 0]) == pytest.approx(0.05)
    empty = tmp_path / "e.stl"
    empty.write_bytes(bytes(80) + np.uint32(0).tobytes())
    with pytest.raises(InputFormatError, match=r"e\.stl"):
        load_triangles(empty)
