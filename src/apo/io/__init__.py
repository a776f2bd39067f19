"""Input and output at the boundary of apo: model files (and, elsewhere, pose files).

Readers convert to SI units (metres) on the way in; heavy third-party libraries (trimesh,
cascadio) are imported only when a file is read.
"""

from apo.io.meshes import load_polyhedron, load_triangles, step_length_unit

__all__ = ["load_polyhedron", "load_triangles", "step_length_unit"]
