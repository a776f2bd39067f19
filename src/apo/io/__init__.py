"""Input and output at the boundary of apo: model files (and, elsewhere, pose files).

Readers convert to SI units (metres) on the way in; heavy third-party libraries (trimesh,
cascadio) are imported only when a file is read. The model readers below are loaded on first
use, so importing a light module of the package (``apo.io.jsonfile``) does not load the mesh
reader and the geometry.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from apo.io.meshes import load_polyhedron, load_triangles, step_length_unit

__all__ = ["load_polyhedron", "load_triangles", "step_length_unit"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from apo.io import meshes

        return getattr(meshes, name)
    raise AttributeError(f"module 'apo.io' has no attribute {name!r}")
