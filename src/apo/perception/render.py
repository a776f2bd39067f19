"""Synthetic depth and colour frames of posed triangle meshes (for tests, demos, benchmarks).

The renderer is a vectorised numpy z-buffer rasteriser (no OpenGL, no optional dependency):
every triangle is expanded to the pixel centres of its bounding box, kept where the
screen-space barycentric coordinates are all non-negative, and depth is interpolated
perspective-correctly (``1/z`` is linear in the image). It was measured against Open3D's
``RaycastingScene`` at 640x480 (``docs/perception.md``) and is as fast for the few hundred
triangles of assembly parts, without the optional dependency.

The depth noise model (:class:`DepthNoise`) is that of active stereo / structured-light
sensors: Gaussian noise with a standard deviation growing with the square of the distance,
pixels lost at depth discontinuities (the sensor sees both surfaces) and a few random holes.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from apo.errors import InputFormatError
from apo.perception.frames import (
    Camera,
    write_background,
    write_camera,
    write_frame,
    write_timestamps,
)
from apo.spatial import invert_pose, transform_points
from apo.typing import FloatArray, IntArray

__all__ = [
    "DepthNoise",
    "Rendering",
    "add_depth_noise",
    "box_triangles",
    "concatenate",
    "hand_triangles",
    "mesh_triangles",
    "pose_looking_at",
    "rasterize",
    "render_demonstration",
    "render_scene",
]

Triangles = tuple[FloatArray, IntArray]

WHITE = (0.92, 0.92, 0.90)
"""Albedo of the two objects in rendered frames (the paper used white parts)."""
TABLE = (0.35, 0.30, 0.25)
"""Albedo of the supporting table (textured)."""
SKIN = (0.85, 0.60, 0.45)
TABLE_COLOURS: dict[str, tuple[float, float, float]] = {
    "textured": TABLE,
    "grey": (0.55, 0.55, 0.55),
    "white": WHITE,
}
"""Albedo of the table of :func:`render_demonstration` by ``table_colour``."""
"""Albedo of the occluding hand."""


def mesh_triangles(mesh: Any, *, units: str | None = "m") -> Triangles:
    """Return ``(vertices, triangles)`` in metres of a mesh given in any accepted form.

    Parameters
    ----------
    mesh : trimesh.Trimesh, (vertices, triangles) or str or Path
        A trimesh mesh or a pair of arrays (vertices in ``units``), or a model file read with
        :func:`apo.io.meshes.load_triangles` (STEP files carry their own unit).
    units : {"m", "mm", "cm", "in"}, optional
        Unit of the vertex coordinates of arrays, meshes and mesh files.

    Returns
    -------
    vertices : ndarray, shape (N, 3)
        Metres, model frame.
    triangles : ndarray of int, shape (T, 3)
        Vertex indices.

    Raises
    ------
    InputFormatError
        Unknown units, unreadable file, or arrays of the wrong shape.
    """
    from apo.io.meshes import UNITS, load_triangles

    if isinstance(mesh, str | Path):
        return load_triangles(mesh, units=units)
    if units is None:
        units = "m"
    if units not in UNITS:
        raise InputFormatError(f"unknown units {units!r}; expected one of {', '.join(UNITS)}")
    if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        V, T = mesh.vertices, mesh.faces
    elif isinstance(mesh, tuple | list) and len(mesh) == 2:
        V, T = mesh
    else:
        raise InputFormatError(
            f"expected a trimesh.Trimesh, a (vertices, triangles) pair or a path, "
            f"got {type(mesh).__name__}"
        )
    Va = np.asarray(V, dtype=np.float64) * UNITS[units]
    Ta = np.asarray(T, dtype=np.int64)
    if Va.ndim != 2 or Va.shape[1] != 3 or Ta.ndim != 2 or Ta.shape[1] != 3 or len(Ta) == 0:
        raise InputFormatError(
            f"expected vertices of shape (N, 3) and triangles of shape (T, 3), got "
            f"{Va.shape} and {Ta.shape}"
        )
    if Ta.min() < 0 or Ta.max() >= len(Va):
        raise InputFormatError("triangle indices out of range of the vertices")
    return Va, Ta


def box_triangles(extents: Sequence[float], center: Sequence[float] = (0.0, 0.0, 0.0)) -> Triangles:
    """Return the 12 outward-facing triangles of an axis-aligned box (same units as inputs)."""
    e = np.asarray(extents, dtype=np.float64) / 2
    c = np.asarray(center, dtype=np.float64)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    V = corners * e + c
    T = np.array(
        [
            [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5],  # x- , x+
            [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],  # y- , y+
            [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3],  # z- , z+
        ],
        dtype=np.int64,
    )  # fmt: skip
    return V, T


def concatenate(parts: Iterable[Triangles]) -> Triangles:
    """Return the union (as one triangle list) of several ``(vertices, triangles)``."""
    Vs: list[FloatArray] = []
    Ts: list[IntArray] = []
    offset = 0
    for V, T in parts:
        Vs.append(np.asarray(V, dtype=np.float64))
        Ts.append(np.asarray(T, dtype=np.int64) + offset)
        offset += len(V)
    return np.vstack(Vs), np.vstack(Ts)


def pose_looking_at(
    eye: npt.ArrayLike, target: npt.ArrayLike, up: npt.ArrayLike = (0.0, 0.0, 1.0)
) -> FloatArray:
    """Return ``X_WC``: a camera at ``eye`` looking at ``target`` (OpenCV axes, metres).

    The camera ``z`` axis points at the target, ``y`` points down in the image, i.e. away
    from ``up``.
    """
    e = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - e
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("eye-target direction is parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    X = np.eye(4)
    X[:3, :3] = np.column_stack((x, y, z))
    X[:3, 3] = e
    return X


def rasterize(
    vertices_C: npt.ArrayLike, triangles: npt.ArrayLike, camera: Camera, *, near: float = 0.01,
    cull: bool = False,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int64]]:  # fmt: skip
    """Z-buffer rasterisation of triangles given in the camera frame.

    Parameters
    ----------
    vertices_C : ndarray, shape (N, 3)
        Vertices in the camera frame ``C`` (metres).
    triangles : ndarray of int, shape (T, 3)
        Vertex indices.
    camera : Camera
        Pinhole model; pixel centres at integer image coordinates.
    near : float, optional
        Triangles with a vertex closer than this (metres) are skipped.
    cull : bool, optional
        Skip the triangles turned away from the camera. Only for a solid whose normals
        point out (:func:`apo.perception.meshdistance.is_solid`): those are hidden behind
        the ones turned to it, so the depth is the same, at about two thirds of the time
        (half the candidate pixels); a tie at a silhouette edge's pixel, which a back face
        could win by its lower index, goes to the face in view.

    Returns
    -------
    depth : ndarray of float32, shape (height, width)
        ``z`` of the nearest surface, metres; 0 where no triangle covers the pixel.
    triangle : ndarray of int, shape (height, width)
        Index of the visible triangle, -1 where none.
    """
    W, H = camera.width, camera.height
    depth = np.zeros((H, W), dtype=np.float32)
    tri_img = np.full((H, W), -1, dtype=np.int64)
    tris = _projected(vertices_C, triangles, camera, near, cull)
    if tris is None:
        return depth, tri_img
    ids, U, Vv, Z, umin, umax, vmin, wv, area = tris
    # One span of candidate pixels per triangle and row (not its whole bounding box).
    tr, y, px, k = _spans(U, Vv, area, umin, umax, vmin, wv, W)
    t = tr[k]
    # Screen-space barycentric coordinates (edge functions), then perspective-correct 1/z;
    # the row terms are computed once per span (the same values as per pixel).
    dv0, dv1, dv2 = (Vv[tr, j] - y for j in range(3))
    u0, u1, u2 = (U[t, j] for j in range(3))
    w0 = (u1 - px) * dv2[k] - (u2 - px) * dv1[k]
    w1 = (u2 - px) * dv0[k] - (u0 - px) * dv2[k]
    a = area[t]
    b0 = w0 / a
    b1 = w1 / a
    b2 = 1.0 - b0 - b1
    eps = -1e-9
    sel = np.nonzero((b0 >= eps) & (b1 >= eps) & (b2 >= eps))[0]
    ts = t[sel]
    inv_z = b0[sel] / Z[ts, 0] + b1[sel] / Z[ts, 1] + b2[sel] / Z[ts, 2]
    pos = inv_z > 0
    pix = y[k[sel[pos]]] * W + px[sel[pos]]
    _zbuffer(pix, 1.0 / inv_z[pos], ts[pos], ids, depth, tri_img)
    return depth, tri_img


_Projected = tuple[
    IntArray, FloatArray, FloatArray, FloatArray, IntArray, IntArray, IntArray, IntArray, FloatArray
]


def _projected(
    vertices_C: npt.ArrayLike, triangles: npt.ArrayLike, camera: Camera, near: float,
    cull: bool = False,
) -> _Projected | None:  # fmt: skip
    """Return the triangles :func:`rasterize` draws, projected (None when there is none).

    Returns their indices, pixel coordinates ``U``, ``V`` and depths ``Z`` of their corners
    (``(t, 3)`` each), pixel bounding boxes (first column, last column, first row, rows) and
    twice their signed pixel areas. Left out: a corner nearer than ``near``, a zero area, no
    pixel centre in the box; with ``cull``, a triangle turned away from the camera (its
    pixel area has the sign of ``a . ((b - a) x (c - a))`` for ``fx fy > 0``: positive).
    """
    V = np.asarray(vertices_C, dtype=np.float64)
    T = np.asarray(triangles, dtype=np.int64)
    W, H = camera.width, camera.height
    z = V[:, 2]
    ids = np.nonzero(np.all(z[T] > near, axis=1))[0]
    if len(ids) == 0:
        return None
    Tz = T[ids]
    zv = np.where(z > near, z, 1.0)
    u = camera.fx * V[:, 0] / zv + camera.cx
    v = camera.fy * V[:, 1] / zv + camera.cy
    U, Vv, Z = u[Tz], v[Tz], z[Tz]  # (t, 3)
    umin = np.clip(np.ceil(U.min(1)), 0, W).astype(np.int64)
    umax = np.clip(np.floor(U.max(1)), -1, W - 1).astype(np.int64)
    vmin = np.clip(np.ceil(Vv.min(1)), 0, H).astype(np.int64)
    vmax = np.clip(np.floor(Vv.max(1)), -1, H - 1).astype(np.int64)
    wu = np.maximum(umax - umin + 1, 0)
    wv = np.maximum(vmax - vmin + 1, 0)
    area = (U[:, 1] - U[:, 0]) * (Vv[:, 2] - Vv[:, 0]) - (U[:, 2] - U[:, 0]) * (Vv[:, 1] - Vv[:, 0])
    keep = (wu * wv > 0) & (np.abs(area) >= 1e-12)
    if cull:
        keep &= area * (camera.fx * camera.fy) < 0.0
    if not keep.any():
        return None
    return (
        ids[keep],
        U[keep],
        Vv[keep],
        Z[keep],
        umin[keep],
        umax[keep],
        vmin[keep],
        wv[keep],
        area[keep],
    )


SPAN_MARGIN = 1.0
"""Pixels added at each end of a triangle's span in a row (the exact test decides inside)."""


def _spans(
    U: FloatArray, V: FloatArray, area: FloatArray, umin: IntArray, umax: IntArray,
    vmin: IntArray, rows: IntArray, width: int,
) -> tuple[IntArray, IntArray, IntArray, IntArray]:  # fmt: skip
    """Candidate pixels of :func:`rasterize`: each triangle's span in each row of its box.

    Along a row each barycentric coordinate is linear in the column, so the columns where
    all three are non-negative form one interval; it is widened by :data:`SPAN_MARGIN`
    (plus the coordinates' tolerance) so that rounding never drops a pixel, and left
    unbounded by an edge nearly parallel to the row. Returns the span's triangle and row
    (one per span), and per candidate pixel its column and span.
    """
    tr = np.repeat(np.arange(len(U)), rows)
    y = vmin[tr] + (np.arange(len(tr)) - (np.cumsum(rows) - rows)[tr])
    dv = [V[tr, j] - y for j in range(3)]
    u = [U[tr, j] for j in range(3)]
    a = area[tr]
    # b0 = (c0 - s0 px) / a, b1 = (c1 - s1 px) / a, b2 = 1 - b0 - b1
    c0, s0 = u[1] * dv[2] - u[2] * dv[1], dv[2] - dv[1]
    c1, s1 = u[2] * dv[0] - u[0] * dv[2], dv[0] - dv[2]
    lo, hi = umin[tr].astype(np.float64), umax[tr].astype(np.float64)
    for g0, gs, s in (
        (c0 / a, -s0 / a, s0), (c1 / a, -s1 / a, s1), (1.0 - (c0 + c1) / a, (s0 + s1) / a, s0 + s1),
    ):  # fmt: skip
        ok = np.abs(s) >= 1e-6  # else nearly parallel to the row: no bound from this edge
        g = np.where(ok, gs, 1.0)
        x, m = -g0 / g, SPAN_MARGIN + 2e-9 / np.abs(g)
        lo = np.where(ok & (gs > 0), np.maximum(lo, x - m), lo)
        hi = np.where(ok & (gs < 0), np.minimum(hi, x + m), hi)
    lo_i = np.maximum(np.ceil(np.clip(lo, -1, width)), umin[tr]).astype(np.int64)
    hi_i = np.minimum(np.floor(np.clip(hi, -1, width)), umax[tr]).astype(np.int64)
    n = np.maximum(hi_i - lo_i + 1, 0)
    k = np.repeat(np.arange(len(tr)), n)
    px = lo_i[k] + (np.arange(len(k)) - (np.cumsum(n) - n)[k])
    return tr, y, px, k


def _zbuffer(
    pix: IntArray, z: FloatArray, t: IntArray, ids: IntArray,
    depth: npt.NDArray[np.float32], tri_img: npt.NDArray[np.int64],
) -> None:  # fmt: skip
    """Write the nearest candidate of each pixel (``pix``: flat index) into the images.

    Of equal depths the lowest ``t`` wins (as a stable sort by pixel and depth would). The
    buffers span the candidates' pixels only (a small part of a large window).
    """
    if len(pix) == 0:
        return
    lo = int(pix.min())
    p = pix - lo
    size = int(p.max()) + 1
    zbuf = np.full(size, np.inf)
    np.minimum.at(zbuf, p, z)
    tie = np.nonzero(z == zbuf[p])[0]
    tbuf = np.full(size, len(ids), dtype=np.int64)
    np.minimum.at(tbuf, p[tie], t[tie])
    hit = np.flatnonzero(tbuf < len(ids))
    depth.ravel()[lo + hit] = zbuf[hit]
    tri_img.ravel()[lo + hit] = ids[tbuf[hit]]


@dataclass(frozen=True)
class Rendering:
    """One rendered frame.

    Attributes
    ----------
    rgb : ndarray of uint8, shape (height, width, 3)
        Shaded colour image.
    depth : ndarray of float32, shape (height, width)
        Depth (camera ``z``), metres, 0 where nothing is seen.
    label : ndarray of int, shape (height, width)
        Index of the visible mesh in the list given to :func:`render_scene`, -1 for none.
    """

    rgb: npt.NDArray[np.uint8]
    depth: npt.NDArray[np.float32]
    label: npt.NDArray[np.int64]


def render_scene(
    meshes: Sequence[Triangles],
    poses_C: Sequence[npt.ArrayLike],
    camera: Camera,
    *,
    albedo: Sequence[Sequence[float]] | None = None,
    textured: Sequence[bool] | None = None,
    ambient: float = 0.35,
) -> Rendering:
    """Render posed meshes into a colour, depth and label image (no noise).

    Parameters
    ----------
    meshes : sequence of (vertices, triangles)
        Meshes in their own frames ``M_i``, metres.
    poses_C : sequence of ndarray, shape (4, 4)
        ``X_CM_i``: pose of each mesh in the camera frame (metres).
    camera : Camera
        The pinhole camera.
    albedo : sequence of (r, g, b) in [0, 1], optional
        Colour of each mesh (default white).
    textured : sequence of bool, optional
        Give a mesh a fine procedural texture (so that stereo matching works on it).
    ambient : float, optional
        Ambient share of the shading; the rest is Lambertian with a light at the camera.

    Returns
    -------
    Rendering
        Colour, depth and label images.
    """
    Vs, Ts, owner = [], [], []
    offset = 0
    for k, ((V, T), X) in enumerate(zip(meshes, poses_C, strict=True)):
        VC = transform_points(X, V)
        Vs.append(VC)
        Ts.append(np.asarray(T, dtype=np.int64) + offset)
        owner.append(np.full(len(T), k))
        offset += len(V)
    V_all = np.vstack(Vs)
    T_all = np.vstack(Ts)
    own = np.concatenate(owner)
    depth, tri = rasterize(V_all, T_all, camera)
    hit = tri >= 0
    label = np.where(hit, own[np.maximum(tri, 0)], -1)
    n = np.cross(V_all[T_all[:, 1]] - V_all[T_all[:, 0]], V_all[T_all[:, 2]] - V_all[T_all[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    rows, cols = np.nonzero(hit)
    rays = np.column_stack(
        ((cols - camera.cx) / camera.fx, (rows - camera.cy) / camera.fy, np.ones(len(rows)))
    )
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    t_hit = tri[rows, cols]
    shade = ambient + (1 - ambient) * np.abs(np.einsum("ij,ij->i", n[t_hit], rays))
    alb = np.asarray(albedo if albedo is not None else [WHITE] * len(meshes), dtype=np.float64)
    lab = label[rows, cols]
    colour = alb[lab] * shade[:, None]
    if textured is not None and any(textured):
        tex = np.asarray(textured, dtype=bool)[lab]
        if tex.any():
            z = depth[rows, cols].astype(np.float64)
            P = rays * (z / rays[:, 2])[:, None]  # camera-frame surface points
            # A fine 3-D texture fixed on each mesh (so that two views see the same pattern).
            for k in np.unique(lab[tex]):
                sel = tex & (lab == k)
                P[sel] = transform_points(invert_pose(poses_C[k]), P[sel])
            ph = 157.0 * P[:, 0] + 211.0 * P[:, 1] + 97.0 * P[:, 2]
            ps = 401.0 * P[:, 0] - 353.0 * P[:, 1] + 271.0 * P[:, 2]
            cell = np.floor(P / 0.003) @ np.array([12.9898, 78.233, 37.719])
            noise = np.modf(np.abs(np.sin(cell)) * 43758.5453)[0]  # aperiodic, in [0, 1)
            pattern = 0.5 * noise + 0.25 + 0.125 * np.sin(ph * 3.1) + 0.125 * np.sin(ps * 2.3)
            colour[tex] *= (0.55 + 0.9 * pattern[tex])[:, None]
    rgb = np.zeros((camera.height, camera.width, 3), dtype=np.uint8)
    rgb[rows, cols] = np.clip(colour * 255.0, 0, 255).astype(np.uint8)
    return Rendering(rgb, depth, label)


@dataclass(frozen=True)
class DepthNoise:
    """Depth sensor noise model.

    Attributes
    ----------
    sigma_1m : float
        Standard deviation of the depth noise at 1 m, metres; it grows with ``z**2``
        (``sigma(z) = sigma_1m * z**2``). 1e-3 (0.25 mm at 0.5 m) is a good structured-light
        sensor; Kinect-v1-class sensors are about 1.5e-3 to 3e-3.
    edge_jump : float
        A pixel whose depth differs from a 4-neighbour by more than this (metres) lies on a
        depth edge.
    edge_dropout : float
        Probability that an edge pixel has no measurement.
    dropout : float
        Probability that any other pixel has no measurement.
    colour_sigma : float
        Standard deviation of the colour noise, in 8-bit levels.
    """

    sigma_1m: float = 1e-3
    edge_jump: float = 0.01
    edge_dropout: float = 0.7
    dropout: float = 0.002
    colour_sigma: float = 2.0

    @classmethod
    def none(cls) -> DepthNoise:
        """Return the noiseless model."""
        return cls(0.0, 0.01, 0.0, 0.0, 0.0)


def add_depth_noise(
    depth: npt.ArrayLike, noise: DepthNoise, rng: np.random.Generator
) -> npt.NDArray[np.float32]:
    """Return ``depth`` (metres, 0 = none) with sensor noise and dropouts (see DepthNoise)."""
    d = np.asarray(depth, dtype=np.float32).copy()
    valid = d > 0
    if noise.sigma_1m > 0:
        sigma = noise.sigma_1m * d.astype(np.float64) ** 2
        d = np.where(valid, d + rng.standard_normal(d.shape) * sigma, 0.0).astype(np.float32)
    edge = np.zeros(d.shape, dtype=bool)
    big = np.where(valid, np.asarray(depth, dtype=np.float32), np.float32(1e3))
    for axis in (0, 1):
        jump = np.abs(np.diff(big, axis=axis)) > noise.edge_jump
        if axis == 0:
            edge[1:] |= jump
            edge[:-1] |= jump
        else:
            edge[:, 1:] |= jump
            edge[:, :-1] |= jump
    drop = (edge & (rng.random(d.shape) < noise.edge_dropout)) | (
        rng.random(d.shape) < noise.dropout
    )
    d[drop] = 0.0
    return d


def _frame_with_z_up(up: npt.ArrayLike) -> FloatArray:
    """Return the rotation ``R`` (rows: new x, y, z axes) that maps ``up`` onto ``+z``.

    The new x axis is the first coordinate axis not parallel to ``up``, made orthogonal to
    it, so ``up = +z`` gives the identity and ``up = +y`` maps ``(x, y, z)`` to
    ``(x, -z, y)``.
    """
    u = np.asarray(up, dtype=np.float64)
    norm = float(np.linalg.norm(u))
    if u.shape != (3,) or not np.isfinite(norm) or norm == 0.0:
        raise ValueError(f"up must be a non-zero 3-vector, got {np.asarray(up).tolist()}")
    u = u / norm
    for axis in np.eye(3):
        a = axis - (axis @ u) * u
        if np.linalg.norm(a) > 1e-6:
            break
    a /= np.linalg.norm(a)
    return np.vstack((a, np.cross(u, a), u))


def _rotated(mesh: Triangles, R: FloatArray) -> Triangles:
    return np.asarray(mesh[0], dtype=np.float64) @ R.T, mesh[1]


def hand_triangles(
    grasped: Triangles, *, up: npt.ArrayLike = (0.0, 0.0, 1.0), arm: bool = False
) -> Triangles:
    """Return a simple hand (thumb, finger and wrist boxes) holding ``grasped`` from the side.

    The boxes are in the grasped object's frame (metres). With ``up = +z``: two 12 mm-thick
    fingers press on the ``+-y`` faces of the upper third of its bounding box, joined by a
    wrist box that leaves towards ``+x`` and up, so the hand occludes part of the object
    from most views. ``arm`` adds a forearm (0.25 m long, 60 mm thick) leaving the wrist
    upwards and outwards, as a person's would. Another ``up`` (a direction in the grasped
    object's frame) turns the whole construction so that ``+z`` becomes ``up`` (see
    :func:`_frame_with_z_up`).
    """
    R = _frame_with_z_up(up)
    V = np.asarray(grasped[0], dtype=np.float64) @ R.T
    lo, hi = V.min(0), V.max(0)
    size = hi - lo
    c = (lo + hi) / 2
    zc = hi[2] - size[2] / 6
    t = 0.012
    finger = (size[0] * 0.6, t, size[2] / 3)
    thumb = box_triangles(finger, (c[0], lo[1] - t / 2, zc))
    index = box_triangles(finger, (c[0], hi[1] + t / 2, zc))
    wrist_len = 0.08
    wrist = box_triangles(
        (wrist_len, size[1] + 2 * t, 0.03),
        (c[0] + size[0] * 0.3 + wrist_len / 2, c[1], hi[2] + 0.015),
    )
    parts = [thumb, index, wrist]
    if arm:
        L = 0.25
        parts.append(
            box_triangles(
                (L * 0.8, 0.06, 0.06),
                (c[0] + size[0] * 0.3 + wrist_len + 0.4 * L, c[1], hi[2] + 0.015 + 0.35 * L),
            )
        )
    return _rotated(concatenate(parts), R.T)


def _table_triangles(
    environment: Triangles,
    size: float = 2.0,
    cells: int = 40,
    *,
    up: npt.ArrayLike = (0.0, 0.0, 1.0),
) -> Triangles:
    """Return a square table top under the environment (at its lowest point along ``up``).

    The grid lets the rasteriser drop only the cells behind the camera (it culls whole
    triangles at the near plane instead of clipping them).
    """
    R = _frame_with_z_up(up)
    z0 = float((np.asarray(environment[0], dtype=np.float64) @ R.T)[:, 2].min())
    g = np.linspace(-size / 2, size / 2, cells + 1)
    X, Y = np.meshgrid(g, g, indexing="ij")
    V = np.column_stack((X.ravel(), Y.ravel(), np.full(X.size, z0)))
    i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    a = (i * (cells + 1) + j).ravel()
    b, c, d = a + cells + 1, a + cells + 2, a + 1
    T = np.vstack((np.column_stack((a, b, c)), np.column_stack((a, c, d))))
    return _rotated((V, T.astype(np.int64)), R.T)


def render_demonstration(
    grasped_mesh: Any,
    environment_mesh: Any,
    X_CE: npt.ArrayLike,
    X_EG_seq: npt.ArrayLike,
    times: npt.ArrayLike,
    camera: Camera,
    out_dir: str | Path,
    *,
    units: str = "m",
    noise: DepthNoise | float | None = None,
    seed: int | None = 0,
    hand: bool = False,
    table: bool = True,
    background: bool = True,
    up: npt.ArrayLike = (0.0, 0.0, 1.0),
    table_colour: str = "textured",
    arm: bool = False,
    background_frames: int = 1,
    part_colour: tuple[float, float, float] = WHITE,
) -> Path:
    """Render a demonstration into a frames folder (the layout of ``docs/perception.md``).

    Parameters
    ----------
    grasped_mesh, environment_mesh : trimesh.Trimesh, (vertices, triangles) or path
        The two models, in ``units`` (see :func:`mesh_triangles`).
    X_CE : ndarray, shape (4, 4)
        Pose of the environment object in the camera frame; translation in ``units``.
    X_EG_seq : ndarray, shape (N, 4, 4)
        Pose of the grasped object in the environment frame at each frame; translation in
        ``units``.
    times : ndarray, shape (N,)
        Frame times, seconds (written to ``timestamps.txt``).
    camera : Camera
        The depth camera (written to ``camera.json``; ``camera.X_WC`` becomes its pose).
    out_dir : str or Path
        Folder to create (or fill).
    units : {"m", "mm", "cm", "in"}, optional
        Units of the meshes and of the pose translations.
    noise : DepthNoise or float or None, optional
        Sensor model; a float is ``DepthNoise(sigma_1m=noise)``; None is ``DepthNoise()``.
    seed : int or None, optional
        Seed of the noise.
    hand : bool, optional
        Add a hand (:func:`hand_triangles`) that holds the grasped object.
    table : bool, optional
        Put the environment on a textured table (the plane ``z = min z`` of its model).
    background : bool, optional
        Also write ``background/`` (the table alone, with its own noise).
    up : array_like, shape (3,), optional
        The up direction, in the environment's frame for the table (perpendicular to it,
        under the environment's lowest point) and in the grasped object's frame for the
        hand (which holds its upper part). Default ``+z``.
    table_colour : {"textured", "grey", "white"}, optional
        The table: a brown procedural texture, plain mid grey (which passes a "white"
        chromaticity test), or plain white (the parts' own colour).
    arm : bool, optional
        With ``hand``, add the forearm (:func:`hand_triangles`).
    background_frames : int, optional
        Depth frames of the background, each with its own noise (``background/depth.png``,
        ``depth_000001.png``, ...).
    part_colour : (float, float, float), optional
        Albedo of the two parts, 0..1 (default :data:`WHITE`, as the paper's).

    Returns
    -------
    Path
        ``out_dir``.
    """
    from apo.io.meshes import UNITS

    if units not in UNITS:
        raise InputFormatError(f"unknown units {units!r}; expected one of {', '.join(UNITS)}")
    s = UNITS[units]
    G = mesh_triangles(grasped_mesh, units=units)
    E = mesh_triangles(environment_mesh, units=units)
    XCE = np.asarray(X_CE, dtype=np.float64).copy()
    XCE[:3, 3] *= s
    XEG = np.asarray(X_EG_seq, dtype=np.float64).copy()
    if XEG.ndim != 3 or XEG.shape[1:] != (4, 4):
        raise ValueError(f"X_EG_seq must have shape (N, 4, 4), got {XEG.shape}")
    XEG[:, :3, 3] *= s
    t = np.asarray(times, dtype=np.float64)
    if t.shape != (len(XEG),):
        raise ValueError(f"times has shape {t.shape}, expected ({len(XEG)},)")
    if noise is None:
        model = DepthNoise()
    elif isinstance(noise, DepthNoise):
        model = noise
    else:
        model = DepthNoise(sigma_1m=float(noise))
    rng = np.random.default_rng(seed)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_camera(out / "camera.json", camera)
    write_timestamps(out, t)
    static: list[Triangles] = []
    static_poses: list[FloatArray] = []
    static_albedo: list[tuple[float, float, float]] = []
    if table_colour not in TABLE_COLOURS:
        raise ValueError(
            f"table_colour must be one of {', '.join(TABLE_COLOURS)}, got {table_colour!r}"
        )
    tex = table_colour == "textured"
    if table:
        static.append(_table_triangles(E, up=up))
        static_poses.append(XCE)
        static_albedo.append(TABLE_COLOURS[table_colour])
    if background:
        if static:
            bg = render_scene(static, static_poses, camera, albedo=static_albedo, textured=[tex])
            bg_rgb, bg_depth = _noisy(bg, model, rng)
            more = [_noisy(bg, model, rng)[1] for _ in range(background_frames - 1)]
        else:
            bg_rgb = np.zeros((camera.height, camera.width, 3), dtype=np.uint8)
            bg_depth = np.zeros((camera.height, camera.width), dtype=np.float32)
            more = [bg_depth] * (background_frames - 1)
        write_background(out, bg_rgb, bg_depth, camera, *more)
    H = hand_triangles(G, up=up, arm=arm) if hand else None
    # The table and the environment do not move: render them once, then only the grasped
    # object (and the hand) per frame, composited by depth (the same z-buffer test).
    still = render_scene(
        [*static, E], [*static_poses, XCE], camera,
        albedo=[*static_albedo, part_colour],
        textured=[tex] + [False] * len(static) if table else None,
    )  # fmt: skip
    for i, X in enumerate(XEG):
        XCG = XCE @ X
        moving = [G] if H is None else [G, H]
        r = render_scene(
            moving, [XCG] * len(moving), camera, albedo=[part_colour, SKIN][: len(moving)]
        )
        rgb, depth = _noisy(_composite(still, r), model, rng)
        write_frame(out, i, rgb, depth, camera)
    return out


def _composite(back: Rendering, front: Rendering) -> Rendering:
    """Return the nearer surface of two renderings at each pixel (labels: ``front``'s +1000)."""
    near = (front.depth > 0) & ((back.depth == 0) | (front.depth < back.depth))
    return Rendering(
        np.where(near[..., None], front.rgb, back.rgb),
        np.where(near, front.depth, back.depth),
        np.where(near, front.label + 1000, back.label),
    )


def _noisy(
    r: Rendering, model: DepthNoise, rng: np.random.Generator
) -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.float32]]:
    depth = add_depth_noise(r.depth, model, rng)
    rgb = r.rgb
    if model.colour_sigma > 0:
        noisy = rgb.astype(np.float32) + rng.standard_normal(rgb.shape).astype(np.float32) * (
            np.float32(model.colour_sigma)
        )
        rgb = np.clip(noisy, 0, 255).astype(np.uint8)
    return rgb, depth
