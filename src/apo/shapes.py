"""Builders of simple polyhedra for tests, examples and benchmarks (pure numpy, metres).

Every builder returns a :class:`~apo.geometry.Polyhedron` made by
:func:`~apo.geometry.polyhedron_from_triangles`, so it goes through the same merging and
checks as a loaded model. Frames: ``z`` is up (the extrusion or insertion axis) unless a
docstring says otherwise; each docstring says where the origin is.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from apo.geometry import (
    Polyhedron,
    _plane_basis,
    polyhedron_from_triangles,
    triangulate_polygon,
)
from apo.typing import FloatArray, IntArray

__all__ = [
    "block_with_square_hole",
    "box",
    "cylinder",
    "icosphere",
    "l_prism",
    "prism",
    "t_peg",
    "triangles_from_polygons",
    "u_block",
]


def triangles_from_polygons(
    vertices: npt.ArrayLike,
    polygons: list[tuple[list[int], list[list[int]]]],
) -> IntArray:
    """Triangulate planar polygonal faces given by vertex loops.

    Parameters
    ----------
    vertices : array_like, shape (N, 3)
        Vertex positions, metres.
    polygons : list of (outer, holes)
        ``outer`` is a loop of vertex indices counter-clockwise seen from outside; ``holes``
        a list of loops clockwise seen from outside.

    Returns
    -------
    ndarray of int, shape (T, 3)
        Triangles, counter-clockwise seen from outside.
    """
    V = np.asarray(vertices, dtype=np.float64)
    out = []
    for outer, holes in polygons:
        loops = [np.asarray(outer, dtype=np.int64)] + [np.asarray(h, np.int64) for h in holes]
        normal = _newell_normal(V[loops[0]])
        u, w = _plane_basis(normal)
        xy = [np.stack([V[lp] @ u, V[lp] @ w], axis=1) for lp in loops]
        local = triangulate_polygon(xy[0], xy[1:])
        out.append(np.concatenate(loops)[local])
    return np.concatenate(out).astype(np.int64)


def _newell_normal(p: FloatArray) -> FloatArray:
    q = np.roll(p, -1, axis=0)
    n = np.array(
        [
            np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
            np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
            np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1])),
        ]
    )
    unit: FloatArray = n / np.linalg.norm(n)
    return unit


def box(
    size: npt.ArrayLike = (1.0, 1.0, 1.0),
    *,
    center: npt.ArrayLike = (0.0, 0.0, 0.0),
    name: str = "box",
) -> Polyhedron:
    """Axis-aligned box.

    Parameters
    ----------
    size : array_like, shape (3,)
        Edge lengths along x, y, z, metres.
    center : array_like, shape (3,)
        Centre of the box in the model frame, metres.
    name : str
        Model name.

    Returns
    -------
    Polyhedron
        6 faces, 12 convex edges, 8 vertices.

    Examples
    --------
    >>> b = box([0.1, 0.2, 0.3])
    >>> len(b.faces), len(b.edges), len(b.vertices), round(b.volume, 9)
    (6, 12, 8, 0.006)
    """
    sx, sy, sz = (0.5 * np.asarray(size, dtype=np.float64)).tolist()
    return prism(
        [[-sx, -sy], [sx, -sy], [sx, sy], [-sx, sy]],
        2.0 * sz,
        origin=np.asarray(center, dtype=np.float64) - [0.0, 0.0, sz],
        name=name,
    )


def prism(
    polygon: npt.ArrayLike,
    height: float,
    *,
    origin: npt.ArrayLike = (0.0, 0.0, 0.0),
    name: str = "prism",
) -> Polyhedron:
    """Extrude a simple 2D polygon along +z.

    Parameters
    ----------
    polygon : array_like, shape (N, 2)
        Simple polygon in the xy-plane, metres, possibly non-convex; either orientation (it
        is made counter-clockwise).
    height : float
        Extrusion length along +z, metres.
    origin : array_like, shape (3,)
        Translation added to every vertex: the bottom face lies at ``z = origin[2]``.
    name : str
        Model name.

    Returns
    -------
    Polyhedron
        ``N + 2`` faces; the vertical edges at reflex polygon corners are concave.
    """
    poly2 = np.asarray(polygon, dtype=np.float64)
    if poly2.ndim != 2 or poly2.shape[1] != 2 or len(poly2) < 3:
        raise ValueError(f"polygon must have shape (N >= 3, 2), got {poly2.shape}")
    if not height > 0:
        raise ValueError(f"height must be positive, got {height}")
    x, y = poly2[:, 0], poly2[:, 1]
    if np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y) < 0:
        poly2 = poly2[::-1]
    n = len(poly2)
    bottom = np.column_stack([poly2, np.zeros(n)])
    top = np.column_stack([poly2, np.full(n, float(height))])
    V = np.concatenate([bottom, top]) + np.asarray(origin, dtype=np.float64)
    polys: list[tuple[list[int], list[list[int]]]] = [
        (list(range(n - 1, -1, -1)), []),
        (list(range(n, 2 * n)), []),
    ]
    for i in range(n):
        j = (i + 1) % n
        polys.append(([i, j, n + j, n + i], []))
    return polyhedron_from_triangles(V, triangles_from_polygons(V, polys), name=name)


def t_peg(
    *,
    stem_width: float = 0.035,
    stem_length: float = 0.070,
    bar_width: float = 0.070,
    bar_height: float = 0.018,
    thickness: float = 0.035,
    name: str = "t_peg",
) -> Polyhedron:
    """T-shaped peg (paper Fig. 21): a crossbar on top of a stem, extruded.

    The T lies in the xy-plane and is extruded along z, centred on ``z = 0``; the stem
    points down (-y) and the origin is at the centre of the stem's bottom face's midline, so
    the peg spans ``y`` in ``[0, stem_length + bar_height]``. Defaults (metres) have the
    proportions of the first author's peg (70 mm crossbar, 35 mm thick).

    Parameters
    ----------
    stem_width, stem_length : float
        Stem size along x and y, metres.
    bar_width, bar_height : float
        Crossbar size along x and y, metres; ``bar_width > stem_width``.
    thickness : float
        Extrusion length along z, metres.
    name : str
        Model name.

    Returns
    -------
    Polyhedron
        10 faces, 24 edges (2 concave), 16 vertices.
    """
    if not bar_width > stem_width:
        raise ValueError("bar_width must exceed stem_width")
    s, b, h = 0.5 * stem_width, 0.5 * bar_width, stem_length
    outline = [
        [-s, 0.0],
        [s, 0.0],
        [s, h],
        [b, h],
        [b, h + bar_height],
        [-b, h + bar_height],
        [-b, h],
        [-s, h],
    ]
    return prism(outline, thickness, origin=(0.0, 0.0, -0.5 * thickness), name=name)


def l_prism(
    *, size: float = 0.04, notch: float = 0.02, height: float = 0.02, name: str = "l_prism"
) -> Polyhedron:
    """L-shaped prism: a ``size`` square with a ``notch`` square cut from its +x+y corner.

    Origin at the bottom face's corner ``(0, 0, 0)``; the L spans ``[0, size]^2`` in xy and is
    extruded along +z by ``height`` (metres). 8 faces, 18 edges (1 concave), 12 vertices.
    """
    a, c = size, size - notch
    outline = [[0.0, 0.0], [a, 0.0], [a, c], [c, c], [c, a], [0.0, a]]
    return prism(outline, height, name=name)


def u_block(
    *,
    width: float = 0.14,
    height: float = 0.088,
    thickness: float = 0.035,
    slot_width: float = 0.035,
    slot_depth: float = 0.053,
    name: str = "u_block",
) -> Polyhedron:
    """Block with a U-shaped slot open at the top, through along z.

    The outline lies in the xy-plane, ``y`` is up: the block spans x in
    ``[-width/2, width/2]``, y in ``[0, height]``, z in ``[-thickness/2, thickness/2]``; the
    slot is centred on ``x = 0`` and goes down from ``y = height`` to
    ``y = height - slot_depth``. Metres.

    Parameters
    ----------
    width, height, thickness : float
        Block size along x, y, z.
    slot_width, slot_depth : float
        Slot size along x and y.
    name : str
        Model name.

    Returns
    -------
    Polyhedron
        10 faces (the front and back faces are U-shaped), 24 edges (2 concave, at the
        bottom of the slot), 16 vertices.
    """
    if not (0 < slot_width < width and 0 < slot_depth < height):
        raise ValueError("the slot must be smaller than the block")
    w, s, d = 0.5 * width, 0.5 * slot_width, height - slot_depth
    outline = [
        [-w, 0.0],
        [w, 0.0],
        [w, height],
        [s, height],
        [s, d],
        [-s, d],
        [-s, height],
        [-w, height],
    ]
    return prism(outline, thickness, origin=(0.0, 0.0, -0.5 * thickness), name=name)


def block_with_square_hole(
    *,
    size: npt.ArrayLike = (0.1, 0.1, 0.05),
    hole: float = 0.04,
    depth: float = 0.03,
    name: str = "block_with_square_hole",
) -> Polyhedron:
    """Block with a blind square pocket in the middle of its top face.

    The block spans x, y in ``[-size/2, size/2]`` and z in ``[0, size[2]]`` (origin at the
    centre of the bottom face, z up); the pocket is ``hole`` wide (x and y) and ``depth``
    deep from the top face. Metres.

    Returns
    -------
    Polyhedron
        11 faces (the top face has a hole), 24 edges (8 concave: the pocket's 4 vertical
        edges and the 4 edges of its floor; the 4 rim edges are convex), 16 vertices.
    """
    sx, sy, sz = (0.5 * np.asarray(size, dtype=np.float64)).tolist()
    sz *= 2.0
    r = 0.5 * hole
    if not (0 < r < min(sx, sy) and 0 < depth < sz):
        raise ValueError("the pocket must fit inside the block")
    fz = sz - depth
    V = np.array(
        [
            [-sx, -sy, 0], [sx, -sy, 0], [sx, sy, 0], [-sx, sy, 0],  # 0-3 bottom
            [-sx, -sy, sz], [sx, -sy, sz], [sx, sy, sz], [-sx, sy, sz],  # 4-7 top
            [-r, -r, sz], [r, -r, sz], [r, r, sz], [-r, r, sz],  # 8-11 rim
            [-r, -r, fz], [r, -r, fz], [r, r, fz], [-r, r, fz],  # 12-15 floor
        ],
        dtype=np.float64,
    )  # fmt: skip
    polys: list[tuple[list[int], list[list[int]]]] = [
        ([3, 2, 1, 0], []),
        ([4, 5, 6, 7], [[11, 10, 9, 8]]),
        ([0, 1, 5, 4], []),
        ([1, 2, 6, 5], []),
        ([2, 3, 7, 6], []),
        ([3, 0, 4, 7], []),
        ([12, 13, 14, 15], []),
        # Pocket walls face inward (towards the pocket's axis).
        ([8, 9, 13, 12], []),
        ([9, 10, 14, 13], []),
        ([10, 11, 15, 14], []),
        ([11, 8, 12, 15], []),
    ]
    return polyhedron_from_triangles(V, triangles_from_polygons(V, polys), name=name)


def cylinder(
    radius: float = 0.01, height: float = 0.02, sections: int = 5000, *, name: str = "cylinder"
) -> Polyhedron:
    """Right prism over a regular ``sections``-gon approximating a cylinder.

    Axis along z, bottom face at ``z = 0`` centred on the origin; metres. The caps are fans
    around a centre vertex, so the mesh has ``4 * sections`` triangles (the caps merge into
    one face each; the centre vertices disappear).

    Returns
    -------
    Polyhedron
        ``sections + 2`` faces, ``3 * sections`` edges, ``2 * sections`` vertices.
    """
    if sections < 3:
        raise ValueError(f"sections must be >= 3, got {sections}")
    ang = 2.0 * math.pi * np.arange(sections) / sections
    ring = np.column_stack([radius * np.cos(ang), radius * np.sin(ang)])
    n = sections
    V = np.concatenate(
        [
            np.column_stack([ring, np.zeros(n)]),
            np.column_stack([ring, np.full(n, height)]),
            [[0.0, 0.0, 0.0], [0.0, 0.0, height]],
        ]
    )
    i = np.arange(n)
    j = (i + 1) % n
    cb, ct = 2 * n, 2 * n + 1
    tris = np.concatenate(
        [
            np.column_stack([np.full(n, cb), j, i]),
            np.column_stack([np.full(n, ct), n + i, n + j]),
            np.column_stack([i, j, n + j]),
            np.column_stack([i, n + j, n + i]),
        ]
    )
    return polyhedron_from_triangles(V, tris, name=name)


def icosphere(
    subdivisions: int = 3, radius: float = 0.01, *, name: str = "icosphere"
) -> Polyhedron:
    """Geodesic sphere: an icosahedron whose triangles are split in 4, ``subdivisions`` times.

    Centred on the origin, metres. ``20 * 4**subdivisions`` triangular faces (no two
    coplanar), all edges convex; ``subdivisions=3`` gives 1280 faces, 4 gives 5120, 5 gives
    20480.
    """
    if subdivisions < 0:
        raise ValueError(f"subdivisions must be >= 0, got {subdivisions}")
    t = (1.0 + math.sqrt(5.0)) / 2.0
    verts = [
        [-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0],
        [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
        [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1],
    ]  # fmt: skip
    faces = np.array(
        [
            [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
            [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
            [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
            [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
        ],
        dtype=np.int64,
    )  # fmt: skip
    V = np.asarray(verts, dtype=np.float64)
    V /= np.linalg.norm(V, axis=1)[:, None]
    for _ in range(subdivisions):
        e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        uniq, inv = np.unique(e, axis=0, return_inverse=True)
        mid = V[uniq[:, 0]] + V[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1)[:, None]
        m = (len(V) + inv.reshape(-1, 3)).astype(np.int64)
        V = np.concatenate([V, mid])
        a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
        ab, bc, ca = m[:, 0], m[:, 1], m[:, 2]
        faces = np.concatenate(
            [
                np.column_stack([a, ab, ca]),
                np.column_stack([b, bc, ab]),
                np.column_stack([c, ca, bc]),
                np.column_stack([ab, bc, ca]),
            ]
        )
    return polyhedron_from_triangles(radius * V, faces, name=name)
