"""Read polyhedral models from STEP, STL, OBJ and PLY files (via trimesh, imported lazily).

Units
-----
apo works in metres. Mesh formats (STL, OBJ, PLY) carry no unit: the ``units`` argument
says what their numbers mean and defaults to millimetres (``"mm"``), the unit of the first
author's data and of most CAD exports. STEP files declare their own length unit; trimesh
reads them through cascadio (OpenCASCADE), which converts the declared unit to metres while
writing its intermediate glTF (a metre format), so STEP coordinates arrive in metres and are
never scaled again. For STEP, ``units`` may be left out (``None``); if it is given and the
file declares another unit, the file's unit wins and a warning says so. Note that glTF
stores float32, so STEP coordinates are exact to about 1e-7 relative.
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
import tempfile
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from apo.constants import UNITS
from apo.errors import GeometryError, InputFormatError
from apo.geometry import Polyhedron, polyhedron_from_triangles

__all__ = [
    "MESH_SUFFIXES",
    "UNITS",
    "cache_dir",
    "in_model_units",
    "load_polyhedron",
    "load_triangles",
    "step_length_unit",
]


MESH_SUFFIXES: dict[str, str] = {
    ".step": "step",
    ".stp": "step",
    ".stl": "stl",
    ".obj": "obj",
    ".ply": "ply",
}
"""File name suffixes (lower case) apo reads, and their format."""

DEFAULT_MESH_UNITS = "mm"

_SI_PREFIX_UNITS = {"": "m", "MILLI": "mm", "CENTI": "cm", "MICRO": "um", "KILO": "km"}
_CONVERSION_UNITS = {"INCH": "in", "FOOT": "ft", "MILLIMETRE": "mm", "CENTIMETRE": "cm"}


def _check_units(units: str | None, path: Path) -> None:
    if units is not None and units not in UNITS:
        raise InputFormatError(
            f"{path}: unknown units {units!r}; expected one of {', '.join(sorted(UNITS))}"
        )


def step_length_unit(path: str | Path) -> str | None:
    """Length unit a STEP file declares for its geometry, e.g. ``"mm"``, or None if unclear.

    Parameters
    ----------
    path : str or Path
        STEP file (ISO 10303-21).

    Returns
    -------
    str or None
        ``"m"``, ``"cm"``, ``"mm"``, ``"um"``, ``"km"``, ``"in"`` or ``"ft"``: the unit of the
        ``LENGTH_UNIT`` that the file's ``GLOBAL_UNIT_ASSIGNED_CONTEXT`` entities use, when
        they all use the same one; None otherwise.
    """
    try:
        st = os.stat(path)
    except OSError:
        return _step_length_unit(os.path.abspath(path), -1, -1)  # raises as the read does
    return _step_length_unit(os.path.abspath(path), st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=64)
def _step_length_unit(path: str, size: int, mtime_ns: int) -> str | None:
    """Return :func:`step_length_unit` of the file of this size and mtime (read once).

    Loading a STEP model asks twice (the cache key, the messages' unit); a changed file
    (another size or mtime) is read again.
    """
    text = Path(path).read_text(encoding="latin-1", errors="replace")
    entities = {
        m.group(1): m.group(2)
        for m in re.finditer(r"#(\d+)\s*=\s*(.*?);\s*(?=#\d+\s*=|ENDSEC)", text, re.S)
    }
    referenced: set[str] = set()
    for body in entities.values():
        for ctx in re.finditer(r"GLOBAL_UNIT_ASSIGNED_CONTEXT\s*\(\s*\(([^)]*)\)", body):
            referenced.update(re.findall(r"#(\d+)", ctx.group(1)))
    found: set[str] = set()
    for ref in referenced:
        body = entities.get(ref, "")
        if "LENGTH_UNIT" not in body:
            continue
        si = re.search(r"SI_UNIT\s*\(\s*(\$|\.(\w+)\.)\s*,\s*\.METRE\.\s*\)", body)
        conv = re.search(r"CONVERSION_BASED_UNIT\s*\(\s*'([^']*)'", body)
        if si:
            found.add(_SI_PREFIX_UNITS.get(si.group(2) or "", "?"))
        elif conv:
            found.add(_CONVERSION_UNITS.get(conv.group(1).upper(), "?"))
        else:
            found.add("?")
    if len(found) == 1 and "?" not in found:
        return found.pop()
    return None


def load_triangles(
    path: str | Path, *, units: str | None = None
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
    """Read the triangles of a model file, in metres.

    Parameters
    ----------
    path : str or Path
        ``.step``/``.stp``, ``.stl``, ``.obj`` or ``.ply`` (case-insensitive suffix).
    units : {"mm", "cm", "m", "in"} or None
        Unit of the numbers in a mesh file (None: ``"mm"``). For STEP files the file's own
        unit is used (see the module notes).

    Returns
    -------
    vertices : ndarray, shape (N, 3)
        Metres, model frame (duplicates not merged).
    triangles : ndarray of int, shape (T, 3)
        Vertex indices, as stored in the file.

    Raises
    ------
    InputFormatError
        Missing file, unknown suffix, unknown units, unreadable or empty file.
    """
    path = Path(path)
    fmt, scale, cache = _triangle_source(path, units, stacklevel=4)
    return _read_triangles(path, fmt, scale, cache)


def _triangle_source(
    path: Path, units: str | None, *, stacklevel: int
) -> tuple[str, float, Path | None]:
    """Check a model file and its units: ``(format, scale, triangle cache entry)``.

    Warns where a STEP file declares another unit than ``units``; the cache entry is None
    for a binary STL (read directly) or with the cache off.
    """
    _check_units(units, path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise InputFormatError(
            f"{path}: unknown model file type {path.suffix!r}; expected one of "
            f"{', '.join(sorted(MESH_SUFFIXES))}"
        )
    if not path.is_file():
        raise InputFormatError(f"{path}: no such file")
    fmt = MESH_SUFFIXES[suffix]
    if fmt == "step":
        scale = 1.0
        if units is not None:
            declared = step_length_unit(path)
            if declared is not None and declared != units:
                warnings.warn(
                    f"{path}: STEP file declares its lengths in {declared!r}; "
                    f"ignoring units={units!r}",
                    stacklevel=stacklevel,
                )
    else:
        scale = UNITS[units if units is not None else DEFAULT_MESH_UNITS]
    if fmt == "stl" and _is_binary_stl(path):  # read directly: no trimesh, no cache needed
        return fmt, scale, None
    return fmt, scale, _cache_file(path, fmt, scale)


def _read_triangles(
    path: Path, fmt: str, scale: float, cache: Path | None
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
    """Return the triangles of :func:`load_triangles` from the file or its cache entry."""
    if fmt == "stl":
        binary = _binary_stl(path)
        if binary is not None:  # read here: no trimesh import (0.35 s), no cache needed
            return binary[0] * scale, binary[1]
    if cache is not None:
        hit = _cache_read(cache)
        if hit is not None:
            return hit

    import trimesh  # lazy: keeps `import apo` cheap

    try:
        loaded = trimesh.load(str(path), file_type=fmt, process=False)
    except Exception as exc:  # trimesh and cascadio raise many types
        raise InputFormatError(f"{path}: cannot read as {fmt.upper()}: {exc}") from exc
    if isinstance(loaded, trimesh.Scene):
        if len(loaded.geometry) == 0:
            raise InputFormatError(f"{path}: the file contains no triangles")
        mesh = loaded.to_mesh()
    elif isinstance(loaded, trimesh.Trimesh):
        mesh = loaded
    else:
        raise InputFormatError(
            f"{path}: the file holds a {type(loaded).__name__}, not a triangle mesh"
        )
    vertices = np.asarray(mesh.vertices, dtype=np.float64) * scale
    triangles = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    if len(triangles) == 0 or len(vertices) == 0:
        raise InputFormatError(f"{path}: the file contains no triangles")
    if cache is not None:
        _cache_write(cache, vertices, triangles)
    return vertices, triangles


_STL_RECORD = np.dtype([("normal", "<f4", 3), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")])


def _is_binary_stl(path: Path) -> bool:
    """Whether :func:`_binary_stl` reads the file (its size fits the count it announces)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(84)
            size = os.fstat(fh.fileno()).st_size
    except OSError:
        return False
    if len(head) < 84:
        return False
    count = int.from_bytes(head[80:84], "little")
    return count > 0 and size - 84 == count * _STL_RECORD.itemsize


def _binary_stl(path: Path) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]] | None:
    """Return a binary STL file's triangles as trimesh reads them, or None if not one.

    Binary when the file is 84 bytes of header and count plus 50 bytes per triangle (the test
    trimesh makes; anything else, an empty file included, goes to trimesh). Every triangle
    gets its own three vertices, in file order (trimesh's ``process=False``), as float64.
    """
    data = path.read_bytes()
    if len(data) < 84:
        return None
    count = int(np.frombuffer(data, dtype="<u4", count=1, offset=80)[0])
    if count == 0 or len(data) - 84 != count * _STL_RECORD.itemsize:
        return None
    records = np.frombuffer(data, dtype=_STL_RECORD, count=count, offset=84)
    vertices = records["vertices"].reshape(-1, 3).astype(np.float64)
    return vertices, np.arange(3 * count, dtype=np.int64).reshape(-1, 3)


# --------------------------------------------------------------------------------------------
# Cache of read triangles
# --------------------------------------------------------------------------------------------

_CACHE_FORMAT = 1


def cache_dir() -> Path | None:
    """Folder of the triangle cache, or None when it is off.

    ``APO_CACHE_DIR`` names it; otherwise ``$XDG_CACHE_HOME/apo`` (default
    ``~/.cache/apo``). ``APO_CACHE=0`` turns the cache off.
    """
    if os.environ.get("APO_CACHE", "1") == "0":
        return None
    named = os.environ.get("APO_CACHE_DIR")
    if named:
        return Path(named)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "apo"


def _cache_file(path: Path, fmt: str, scale: float) -> Path | None:
    """Cache entry of a model file: keyed by its bytes, the scale and the readers' versions.

    Reading a STEP file means importing trimesh and OpenCASCADE and tessellating, about a
    quarter of a second before any analysis; the triangles of a file already read are
    taken from here instead. A changed file, scale, trimesh or cascadio (installed anew:
    :func:`_installed`) gives a new key.
    """
    root = cache_dir()
    if root is None:
        return None
    h = hashlib.sha256()
    h.update(path.read_bytes())
    versions = [_installed(dist) for dist in ("trimesh", "cascadio")]
    h.update(f"|{fmt}|{scale!r}|{_CACHE_FORMAT}|{'|'.join(versions)}".encode())
    return root / "meshes" / f"{h.hexdigest()}.npz"


def _installed(package: str) -> str:
    """Stamp of an installed reader package: its ``__init__.py`` path, size and mtime.

    Any re-installation rewrites the file, so a new trimesh or cascadio gives a new cache
    key; found without importing the package or ``importlib.metadata`` (which alone costs
    more than reading both cached models).
    """
    import importlib.util

    spec = importlib.util.find_spec(package)
    if spec is None or not spec.origin:
        return "-"
    try:
        st = os.stat(spec.origin)
    except OSError:
        return "-"
    return f"{spec.origin}:{st.st_size}:{st.st_mtime_ns}"


def _cache_read(cache: Path) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]] | None:
    """Return the cached triangles, or None (absent or unreadable: the file is read again)."""
    try:
        with np.load(cache, allow_pickle=False) as data:
            vertices = np.asarray(data["vertices"], dtype=np.float64)
            triangles = np.asarray(data["triangles"], dtype=np.int64)
    except (OSError, KeyError, ValueError):
        return None
    if vertices.ndim != 2 or vertices.shape[1:] != (3,) or triangles.shape[1:] != (3,):
        return None
    return vertices, triangles


def _cache_write(
    cache: Path, vertices: npt.NDArray[np.float64], triangles: npt.NDArray[np.int64]
) -> None:
    """Store the triangles (atomically); a cache that cannot be written is skipped."""
    try:
        cache.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=cache.stem, suffix=".npz", dir=cache.parent)
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, vertices=vertices, triangles=triangles)
        os.replace(tmp, cache)
    except OSError:
        return


def _polyhedron_file(triangles: Path) -> Path:
    """Cache entry of the polyhedron built from a triangle cache entry's triangles.

    Keyed as well by the code that builds it (:mod:`apo.geometry` and its tolerances in
    :mod:`apo.constants`: their files' size and mtime), so a changed builder builds anew.
    """
    from apo import constants, geometry

    stamps = "|".join(_file_stamp(m.__file__) for m in (geometry, constants))
    key = hashlib.sha256(f"{triangles.name}|{_POLY_FORMAT}|{stamps}".encode()).hexdigest()
    return triangles.with_name(f"{key}.poly.npy")


def _file_stamp(path: str | None) -> str:
    """``path:size:mtime`` of a source file (``-`` if it cannot be read)."""
    try:
        st = os.stat(path or "")
    except OSError:
        return "-"
    return f"{path}:{st.st_size}:{st.st_mtime_ns}"


_POLY_FORMAT = 1


def _polyhedron_to_array(p: Polyhedron) -> npt.NDArray[np.float64]:
    """One float64 array holding a polyhedron (indices are exact in float64)."""
    holes = [h for hs in p.face_holes for h in hs]
    ragged = (p.faces, holes, p.face_triangles, p.vertex_edges, p.vertex_faces)
    parts: list[Any] = [
        [_POLY_FORMAT, len(p.vertices), len(p.faces), len(holes), len(p.edges), p.scale],
        [len(hs) for hs in p.face_holes],
        *([len(a) for a in group] for group in ragged),
        p.vertices, p.face_normals, p.face_offsets, p.edges, p.edge_faces, p.edge_convex,
        *(np.concatenate([np.ravel(a) for a in group]) if len(group) else [] for group in ragged),
    ]  # fmt: skip
    return np.concatenate([np.ravel(np.asarray(x, dtype=np.float64)) for x in parts])


def _polyhedron_from_array(a: npt.NDArray[np.float64], name: str) -> Polyhedron | None:
    """Return the polyhedron of :func:`_polyhedron_to_array`, or None if ``a`` is not one."""
    fmt, nv, nf, nh, ne, scale = a[:6].tolist()
    if fmt != _POLY_FORMAT:
        return None
    nv, nf, nh, ne = int(nv), int(nf), int(nh), int(ne)
    ints = a.astype(np.int64)
    pos = 6

    def take(n: int, values: npt.NDArray[Any] = ints) -> npt.NDArray[Any]:
        nonlocal pos
        pos += n
        return values[pos - n : pos]

    holes_per_face = take(nf).tolist()
    lengths = [take(k).tolist() for k in (nf, nh, nf, nv, nv)]
    vertices = take(3 * nv, a).reshape(nv, 3).copy()
    normals, offsets = take(3 * nf, a).reshape(nf, 3).copy(), take(nf, a).copy()
    edges, edge_faces = take(2 * ne).reshape(ne, 2), take(2 * ne).reshape(ne, 2)
    convex = take(ne).astype(bool)
    groups = []
    for n, width in zip(lengths, (1, 1, 3, 1, 1), strict=True):
        flat = take(width * sum(n)).reshape(-1, width)
        ends = np.cumsum(n).tolist()
        rows = (flat[e - k : e] for k, e in zip(n, ends, strict=True))
        groups.append(tuple(r if width > 1 else r[:, 0] for r in rows))
    if pos != len(a):
        return None
    faces, holes, tris, vedges, vfaces = groups
    it = iter(holes)
    return Polyhedron(
        name=name,
        vertices=vertices,
        faces=faces,
        face_holes=tuple(tuple(next(it) for _ in range(k)) for k in holes_per_face),
        face_normals=normals,
        face_offsets=offsets,
        face_triangles=tris,
        edges=edges,
        edge_faces=edge_faces,
        edge_convex=convex,
        vertex_edges=vedges,
        vertex_faces=vfaces,
        scale=float(scale),
    )


PLAUSIBLE_SIZE = (1e-3, 10.0)
"""Largest extent (metres) of a model outside which :func:`load_polyhedron` warns that the
units may be wrong (a part read in metres from a millimetre file is 1000 times too big)."""


def load_polyhedron(
    path: str | Path, *, units: str | None = None, name: str | None = None
) -> Polyhedron:
    """Read a closed polyhedral model from a STEP, STL, OBJ or PLY file.

    Parameters
    ----------
    path : str or Path
        Model file; the suffix (case-insensitive) selects the reader.
    units : {"mm", "cm", "m", "in"} or None
        Unit of the numbers in a mesh file (None: ``"mm"``). STEP files are read in the unit
        they declare and converted to metres; a different ``units`` there only warns.
    name : str, optional
        Model name (default: the file name), used in messages.

    Returns
    -------
    Polyhedron
        In metres, in the file's frame, with coplanar triangles merged into faces.

    Raises
    ------
    InputFormatError
        Missing file, unknown suffix or units, unreadable or empty file.
    GeometryError
        The mesh is not a closed, manifold, consistently oriented solid, or has zero volume
        or zero-area faces (the message starts with the file path as given).

    Warns
    -----
    UserWarning
        Where the analysis can proceed safely: an inside-out mesh was flipped, triangles
        collapsed by merging vertices or zero-area triangles were dropped (the message
        starts with the file path), a STEP file's own unit overrides ``units``, or the model
        is implausibly large or small for an assembly part (:data:`PLAUSIBLE_SIZE`): the
        units are probably wrong.

    Examples
    --------
    >>> peg = load_polyhedron("peg.step")  # doctest: +SKIP
    >>> len(peg.faces), len(peg.edges), len(peg.vertices)  # doctest: +SKIP
    (10, 24, 16)
    """
    path = Path(path)
    fmt, scale, cache = _triangle_source(path, units, stacklevel=3)
    label = name or path.name
    stored = None if cache is None else _polyhedron_file(cache)
    poly = None if stored is None else _cached_polyhedron(stored, label)
    if poly is None:
        mesh = _read_triangles(path, fmt, scale, cache)
        poly, warned = _build_polyhedron(path, units, label, mesh)
        if stored is not None and not warned:  # a cached one would not warn again
            _store(stored, _polyhedron_to_array(poly))
    size = float(np.ptp(poly.vertices, axis=0).max())
    if not PLAUSIBLE_SIZE[0] <= size <= PLAUSIBLE_SIZE[1]:
        read_as = (
            "its own STEP unit"
            if MESH_SUFFIXES[path.suffix.lower()] == "step"
            else (f"units={units or DEFAULT_MESH_UNITS!r}")
        )
        warnings.warn(
            f"{path}: the model is {size:.4g} m across (read with {read_as}): are the units right?",
            UserWarning,
            stacklevel=2,
        )
    return poly


def _cached_polyhedron(stored: Path, name: str) -> Polyhedron | None:
    """Return the polyhedron of a cache entry, or None (absent or unreadable: built again)."""
    try:
        a = np.load(stored, allow_pickle=False)
        return _polyhedron_from_array(a, name) if a.ndim == 1 and a.dtype == np.float64 else None
    except (OSError, ValueError, IndexError, TypeError):
        return None


def _store(entry: Path, a: npt.NDArray[np.float64]) -> None:
    """Write ``a`` as a cache entry (atomically); a cache that cannot be written is skipped."""
    try:
        entry.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=entry.stem, suffix=".npy", dir=entry.parent)
        with os.fdopen(fd, "wb") as fh:
            np.save(fh, a, allow_pickle=False)
        os.replace(tmp, entry)
    except OSError:
        return


def _build_polyhedron(
    path: Path, units: str | None, label: str, mesh: tuple[npt.NDArray[Any], npt.NDArray[Any]]
) -> tuple[Polyhedron, bool]:
    """:func:`apo.geometry.polyhedron_from_triangles` and whether it warned.

    Raises (or warns, with the file's path) as it does, with the lengths in the file's unit.
    """
    vertices, triangles = mesh
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        unit = _model_unit(path, units)
        try:
            poly = polyhedron_from_triangles(vertices, triangles, name=label)
        except GeometryError as exc:
            text = in_model_units(_strip_label(str(exc), label), unit)
            raise GeometryError(f"{path}: {text}") from exc
        finally:
            messages = [
                (w.category, in_model_units(_strip_label(str(w.message), label), unit))
                for w in caught
            ]
    for category, message in messages:
        warnings.warn(f"{path}: {message}", category, stacklevel=3)
    return poly, bool(messages)


_LENGTHS: dict[str, float] = {**UNITS, "um": 1e-6, "km": 1e3, "ft": 0.3048}
_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
# patterns compiled on first use (``re``'s cache): only a warning's message needs them
_POINT = rf"\[\s*({_NUM})[,\s]+({_NUM})[,\s]+({_NUM})\s*\]"
_VOLUME = rf"({_NUM}) m\^3"
_LENGTH = rf"({_NUM}) m\b(?!\^)"


def _model_unit(path: Path, units: str | None) -> str:
    """Return the unit of the model file's numbers (a STEP file's own; else ``units``, mm)."""
    if MESH_SUFFIXES.get(path.suffix.lower()) == "step":
        try:
            return step_length_unit(path) or "m"
        except OSError:
            return "m"
    return units or DEFAULT_MESH_UNITS


def in_model_units(message: str, unit: str) -> str:
    """Rewrite the lengths of a geometry message (metres) in the model file's ``unit``.

    Points ``[x, y, z]`` (or numpy's ``[x y z]``), ``<v> m^3`` and ``<d> m`` are converted;
    points get the unit after them. A message in metres is returned as it is.
    """
    k = _LENGTHS.get(unit)
    if k is None or unit == "m":
        return message

    def point(m: re.Match[str]) -> str:
        a, b, c = (float(m.group(i)) / k for i in (1, 2, 3))
        return f"[{a:.6g}, {b:.6g}, {c:.6g}] {unit}"

    message = re.sub(_POINT, point, message)
    message = re.sub(_VOLUME, lambda m: f"{float(m.group(1)) / k**3:.3g} {unit}^3", message)
    return re.sub(_LENGTH, lambda m: f"{float(m.group(1)) / k:.3g} {unit}", message)


def _strip_label(message: str, label: str) -> str:
    """``message`` without the ``"<label>: "`` prefix that the geometry code puts first."""
    prefix = f"{label}: "
    return message[len(prefix) :] if message.startswith(prefix) else message
