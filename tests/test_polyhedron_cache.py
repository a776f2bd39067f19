"""The model cache keeps built polyhedra: the same polyhedron as built, and built anew when due."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

from apo import shapes
from apo.geometry import Polyhedron
from apo.io import load_polyhedron


def _same_array(a: Any, b: Any, what: str) -> None:
    assert isinstance(b, np.ndarray), what
    assert a.dtype == b.dtype and a.shape == b.shape, what
    assert a.flags.c_contiguous == b.flags.c_contiguous, what
    np.testing.assert_array_equal(a, b, err_msg=what)


def assert_same_polyhedron(p: Polyhedron, q: Polyhedron) -> None:
    """Every field equal: values, dtypes, shapes (and the corners derived from them)."""
    for f in dataclasses.fields(p):
        x, y = getattr(p, f.name), getattr(q, f.name)
        if isinstance(x, np.ndarray):
            _same_array(x, y, f.name)
        elif isinstance(x, tuple):
            assert isinstance(y, tuple) and len(x) == len(y), f.name
            for i, (u, v) in enumerate(zip(x, y, strict=True)):
                if isinstance(u, tuple):
                    assert isinstance(v, tuple) and len(u) == len(v), f"{f.name}[{i}]"
                    for a, b in zip(u, v, strict=True):
                        _same_array(a, b, f"{f.name}[{i}]")
                else:
                    _same_array(u, v, f"{f.name}[{i}]")
        else:
            assert type(x) is type(y) and x == y, f.name
    for a, b in zip(p.vertex_corners, q.vertex_corners, strict=True):
        _same_array(a, b, "vertex_corners")


def _ascii_stl(path: Path, poly: Polyhedron, scale: float = 1000.0) -> Path:
    """``poly`` as an ASCII STL (millimetres): read through trimesh and the cache."""
    tris = np.concatenate(poly.face_triangles)
    corners = poly.vertices[tris].reshape(-1, 3) * scale
    mesh = trimesh.Trimesh(corners, np.arange(len(corners)).reshape(-1, 3), process=False)
    path.write_text(trimesh.exchange.stl.export_stl_ascii(mesh))
    return path


@pytest.mark.parametrize(
    "make",
    [
        shapes.t_peg,
        shapes.block_with_square_hole,
        shapes.u_block,
        lambda: shapes.cylinder(sections=40),
    ],
    ids=["t_peg", "hole", "u_block", "cylinder"],
)
def test_cached_polyhedron_is_the_built_one(tmp_path, monkeypatch, make: Any) -> None:
    monkeypatch.setenv("APO_CACHE_DIR", str(tmp_path / "cache"))
    path = _ascii_stl(tmp_path / "model.stl", make())
    built = load_polyhedron(path, name="m")  # builds and stores
    assert len(list((tmp_path / "cache" / "meshes").glob("*.poly.npy"))) == 1
    monkeypatch.setattr("apo.io.meshes.polyhedron_from_triangles", _refuse)
    cached = load_polyhedron(path, name="m")
    assert_same_polyhedron(built, cached)
    assert load_polyhedron(path).name == "model.stl"


def _refuse(*args: Any, **kwargs: Any) -> Any:
    raise AssertionError("built again although cached")


@pytest.mark.realdata
def test_authors_models_from_the_cache(real_data_dir: Path, tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("APO_CACHE_DIR", str(tmp_path / "cache"))
    for name in ("peg.step", "hole.step"):
        built = load_polyhedron(real_data_dir / name, units="mm")
        assert_same_polyhedron(built, load_polyhedron(real_data_dir / name, units="mm"))


def test_a_mesh_that_warns_is_built_each_time(tmp_path, monkeypatch) -> None:
    """A cached polyhedron would not warn: inside-out meshes are not kept, and warn again."""
    monkeypatch.setenv("APO_CACHE_DIR", str(tmp_path / "cache"))
    p = shapes.box((0.05, 0.04, 0.03))
    tris = np.concatenate(p.face_triangles)[:, ::-1]
    mesh = trimesh.Trimesh(p.vertices * 1000.0, tris, process=False)
    path = tmp_path / "inside_out.stl"
    path.write_text(trimesh.exchange.stl.export_stl_ascii(mesh))
    for _ in range(2):
        with pytest.warns(UserWarning, match="inside-out"):
            load_polyhedron(path)
    assert not list((tmp_path / "cache" / "meshes").glob("*.poly.npy"))


def test_a_corrupt_or_stale_entry_is_built_again(tmp_path, monkeypatch) -> None:
    import apo.io.meshes as meshes

    monkeypatch.setenv("APO_CACHE_DIR", str(tmp_path / "cache"))
    path = _ascii_stl(tmp_path / "peg.stl", shapes.t_peg())
    built = load_polyhedron(path)
    (entry,) = (tmp_path / "cache" / "meshes").glob("*.poly.npy")
    for bad in (b"garbage", None):
        if bad is None:  # a well-formed file of the wrong length
            np.save(entry, np.arange(40, dtype=np.float64) % 3)
        else:
            entry.write_bytes(bad)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert_same_polyhedron(built, load_polyhedron(path))
    # another builder (apo.geometry changed) is another entry
    monkeypatch.setattr(meshes, "_file_stamp", lambda path: "changed")
    monkeypatch.setattr("apo.io.meshes.polyhedron_from_triangles", _refuse)
    with pytest.raises(AssertionError, match="built again"):
        load_polyhedron(path)
