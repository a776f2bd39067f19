"""Projective data association point-to-plane ICP of a model to a depth image (numpy only).

The frame-to-frame tracker's registration. At each iteration the model is rendered at the
current pose into the (subsampled) depth window, and every observed pixel of the object is
paired with the model face **visible at that pixel** (the z-buffer's triangle): the pair's
residual is the observed point's signed distance to that face's plane. Closest-point
association (Open3D's ICP) pairs a point with whichever model surface is nearest in 3-D,
visible or not; with depth noise of a few millimetres (1 m from the sensor), the points
near an edge are nearer the hidden face behind it, which biased the pose by about 2 mm at
the true pose. The projective pairing is exact at the true pose (a point's noise moves it
along its own ray, into no other pixel), needs no k-d tree, and only ever uses the surface
the camera can see.

Each iteration (see :func:`projective_icp`):

1. render the model's faces at the pose (:func:`apo.perception.render.rasterize`) into the
   window, at every ``step``-th pixel (``step`` keeps at most ``max_pixels`` object pixels),
   the pixels the known occluder (the environment model) hides dropped;
2. **surface rows**: pair each object pixel with the face rendered there, except faces seen
   at a grazing angle (normal more than ``max_angle`` from the viewing ray: there the pixel
   grid, not the surface, decides which face a pixel falls on); the residual is the
   observed point's signed distance to the face's plane, its Jacobian that of the distance
   along the pixel's ray (the noise's direction; :func:`_normal_equations`). Pixels left
   out of the mask for being within the noise of the environment (``shared``) count here
   too where the model renders the part in front of the environment: the cut alone keeps
   only those whose noise took them nearer the camera;
3. **contour rows**: a pixel that the observation and the rendering put on opposite sides
   of the silhouette (an object pixel where the model renders nothing; a model pixel where
   the sensor sees more than ``4 sigma`` behind it) is paired with the plane through the
   camera centre and the nearest silhouette edge of the model (an edge between a face
   turned to the camera and one turned away), the pixel's ray taken at the edge's depth:
   the residual is the lateral distance the edge must move to pass through the pixel's
   centre, continuous in the pose (sub-pixel), and free of the depth noise. Faces alone
   leave directions unconstrained (one face in view; the top of a part hidden by a hand):
   measured on a square peg seen from 22 deg, three directions rested on the silhouette.
   A contour row weighs ``(sigma_depth / sigma_lateral)^2`` surface rows (at most
   ``CONTOUR_WEIGHT_MAX``), ``sigma_lateral`` half a pixel at the object's distance.
   These rows are one-sided: a pose whose outline passes between the same pixel centres
   as the observed one has none, so along a direction only the outline constrains, the
   pose stops anywhere in a band up to a pixel wide (measured: the environment of a
   square-peg variant seen at 0.81 m, 1 px = 2.1 mm, ended 0.9 mm off or 0.4 mm the other
   way depending on the start). With ``outline``, **outline rows** are two-sided: each
   pair of 4-neighbours where the observed surface ends (an object pixel and one seen
   farther by more than a surface steps between pixels) gives the edge half-way between
   them, against the model's nearest silhouette edge: a residual on both sides of the
   outline, whose minimum is the middle of that band (:func:`_outline`);
4. optional **constraint rows** (``constraint``), e.g. non-penetration of the other object
   (:func:`apo.perception.register.register_projective`);
   **Ownership** with ``clutter`` (the mask is not the object's own, e.g. depth alone: a
   hand holding the part is in it; no colour needed): an object pixel counts as the
   model's only where its depth agrees with the model rendered at the current pose. A
   pixel observed in front of the rendered surface by more than the current Tukey scale is
   an occluder (a hand, an arm), and so is every pixel connected to it (8-neighbours)
   through pixels in front by more than the depth noise ``sigma`` (the occluder's surface
   where it comes within the Tukey scale of the model's, e.g. fingers pressed on a face):
   they give no surface row. Object pixels outside the rendered silhouette give no contour
   row either (they cannot be told from a hand beside the part; measured, they pulled the
   T-peg 16 mm into the hand from its true pose at 1 m); the silhouette then rests on the
   pixels where the sensor sees through the model, which no occluder can produce;
5. weigh the rows by Tukey's biweight of their residual, with scale ``max(floor, k sigma(z))``
   for the depth noise ``sigma(z)`` of the pixel
   (:class:`apo.perception.segment.DepthNoiseModel`); the scale starts at ``start_scale``
   (the prediction's uncertainty) and halves at each iteration down to the noise's;
6. one Gauss-Newton step of the weighted objective (a 6x6 solve, Levenberg-Marquardt damped
   per parameter), shortened so that no point of the model moves farther than the current
   Tukey scale (a trust region: beyond it the pairs are not valid; unbounded, a square peg
   deep in its hole, a few pixels in view, once turned 90 deg in one step).

It stops when a step moves the model by less than ``tolerance`` and the scale has reached
the noise's, or after ``iterations`` steps. A run that goes round a cycle of poses at the
final scale (the model back within ``CYCLE_TOLERANCE`` of where it was 2 to
``CYCLE_LONGEST`` steps before: Tukey weights and contour pixels switching) stops at once
with the pose the iteration limit would have ended on (the steps left go round the cycle);
measured on variant seed 1, a fifth of the runs, up to 10 steps each, the pose the limit
gives within 0.03 micrometres but in a few runs (two-step cycles, session 5; cycles of 3
steps appeared at 1 m with the ray distance's Jacobian, session 6).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import numpy.typing as npt

from apo.perception.camera import Camera
from apo.perception.meshdistance import is_solid
from apo.perception.render import rasterize
from apo.spatial import orthonormalised, transform_points
from apo.typing import FloatArray

if TYPE_CHECKING:
    from concurrent.futures import Executor

__all__ = [
    "FacePlanes", "ProjectiveResult", "face_planes", "occluders", "projective_icp",
    "tukey_weights",
]  # fmt: skip

TUKEY_K = 4.685
"""Tukey's biweight constant in standard deviations (95 % efficiency under Gaussian noise)."""

CONTOUR_WEIGHT_MAX = 25.0
"""Largest weight of a contour or constraint row relative to a surface row."""

CYCLE_TOLERANCE = 1e-6
"""Metres: a step at the final scale that brings the model (every vertex) back within this of
where it was 2 to ``CYCLE_LONGEST`` steps before closes a limit cycle (see
:func:`projective_icp`)."""

CYCLE_LONGEST = 4
"""The longest limit cycle (steps) :func:`projective_icp` detects."""

OUTLINE_REACH = 2.0
"""Pixels: an observed outline pair is matched with a silhouette edge of the model this near
(:func:`_outline`)."""

OUTLINE_SLOPE = 4.0
"""Pixels' widths: the most a surface seen at up to about 75 deg (``max_angle``; ``tan 75 deg``
is 3.7) steps in depth between two neighbouring pixels. A larger step, beyond the depth
noise's bound too, is an outline (:func:`_outline_pairs`)."""


@dataclass(frozen=True)
class FacePlanes:
    """The planes of a triangle mesh's faces, model frame: ``normals @ x = offsets``.

    Attributes
    ----------
    vertices : ndarray, shape (N, 3)
        Metres.
    triangles : ndarray of int, shape (T, 3)
    normals : ndarray, shape (T, 3)
        Unit outward normals (right-hand order of the triangle's vertices).
    offsets : ndarray, shape (T,)
        ``normals[i] @ vertices[triangles[i, 0]]``, metres.
    edges : ndarray of int, shape (E, 2)
        Vertex indices of each edge (once).
    edge_faces : ndarray of int, shape (E, 2)
        The two triangles of each edge (the second -1 on an open boundary).
    solid : bool
        The mesh bounds a solid, normals out (:func:`apo.perception.meshdistance.is_solid`):
        it is rendered without its back faces (``rasterize(..., cull=True)``).
    """

    vertices: FloatArray
    triangles: npt.NDArray[np.int64]
    normals: FloatArray
    offsets: FloatArray
    edges: npt.NDArray[np.int64]
    edge_faces: npt.NDArray[np.int64]
    solid: bool = False

    def silhouette_edges(self, X_CM: FloatArray) -> npt.NDArray[np.int64]:
        """Return the edges between a face turned to the camera and one turned away (indices)."""
        eye = -X_CM[:3, :3].T @ X_CM[:3, 3]  # the camera centre, model frame
        front = self.normals @ eye - self.offsets > 0
        f0, f1 = self.edge_faces[:, 0], self.edge_faces[:, 1]
        other = np.where(f1 >= 0, front[np.maximum(f1, 0)], ~front[f0])
        return np.nonzero(front[f0] != other)[0]


def face_planes(vertices: npt.ArrayLike, triangles: npt.ArrayLike) -> FacePlanes:
    """Return the :class:`FacePlanes` of a mesh (degenerate triangles get a zero normal).

    The edges join the triangles by their corners' coordinates, not their indices: an STL
    file repeats each vertex per triangle, and with the indices as given every edge had one
    triangle, so every edge of a face turned to the camera (a face's diagonal, the rim
    between the top and a side in view) was a silhouette edge (:meth:`FacePlanes.silhouette_edges`)
    for the contour and outline rows. ``triangles`` and ``edges`` index the first of the
    vertices at equal coordinates (the same triangles).
    """
    V = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(triangles, dtype=np.int64)
    cross = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
    length = np.linalg.norm(cross, axis=1, keepdims=True)
    n = np.where(length > 0, cross / np.where(length > 0, length, 1.0), 0.0)
    _, first, same = np.unique(V, axis=0, return_index=True, return_inverse=True)
    T = first[same.ravel()][T]  # each corner as the first vertex at its coordinates
    e = np.sort(np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]]), axis=1)
    face = np.tile(np.arange(len(T)), 3)
    edges, inv = np.unique(e, axis=0, return_inverse=True)
    order = np.argsort(inv.ravel(), kind="stable")
    inv_s, face_s = inv.ravel()[order], face[order]
    start = np.nonzero(np.r_[True, inv_s[1:] != inv_s[:-1]])[0]
    count = np.diff(np.r_[start, len(inv_s)])
    second = np.where(count > 1, face_s[np.minimum(start + 1, len(face_s) - 1)], -1)
    edge_faces = np.column_stack([face_s[start], second])
    offsets = np.einsum("ij,ij->i", n, V[T[:, 0]])
    return FacePlanes(V, T, n, offsets, edges, edge_faces, is_solid(V, T))


@dataclass(frozen=True)
class ProjectiveResult:
    """Result of :func:`projective_icp`.

    Attributes
    ----------
    X_CM : ndarray, shape (4, 4)
        Pose of the model in the camera frame, metres.
    pairs : int
        Observed pixels paired with a visible face and weighted (Tukey weight > 0) at the
        last iteration.
    observed : int
        Observed pixels used (after subsampling).
    rms : float
        RMS point-to-plane residual of the weighted pairs, metres (inf without pairs).
    iterations : int
        Gauss-Newton steps taken.
    converged : bool
        The last step moved the model by less than the tolerance at the final scale.
    """

    X_CM: FloatArray
    pairs: int
    observed: int
    rms: float
    iterations: int
    converged: bool


def tukey_weights(residuals: npt.ArrayLike, scale: npt.ArrayLike) -> FloatArray:
    """Tukey's biweight ``(1 - (r / c)^2)^2`` for ``|r| < c``, else 0 (``c`` per residual)."""
    u = np.asarray(residuals, dtype=np.float64) / np.asarray(scale, dtype=np.float64)
    return np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)


def _exp_se3(delta: FloatArray) -> FloatArray:
    """Return the rigid motion of the twist ``[omega; v]`` (Rodrigues)."""
    w, v = delta[:3], delta[3:]
    theta = float(np.linalg.norm(w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-12:
        R = np.eye(3) + K
    else:
        R = np.eye(3) + np.sin(theta) / theta * K + (1 - np.cos(theta)) / theta**2 * (K @ K)
    X = np.eye(4)
    X[:3, :3] = R
    X[:3, 3] = v
    return X


@dataclass
class _Window:
    """The observation of one window, subsampled (every ``step``-th pixel): fixed over the ICP."""

    camera: Camera
    depth: FloatArray  # (h, w) metres, 0 where none
    mask: npt.NDArray[np.bool_]  # (h, w) the object's pixels with depth
    points: FloatArray  # (h, w, 3) back-projected pixels (camera frame)
    rays: FloatArray  # (h, w, 3) unit viewing rays
    scale: FloatArray  # (h, w) final Tukey scale
    sigma: FloatArray  # (h, w) depth noise
    free: FloatArray  # (h, w) depth beyond which the sensor sees through the model
    occluder: npt.NDArray[np.float32] | None
    box: tuple[int, int, int, int] = (0, 0, 0, 0)  # rows and columns holding the mask
    depth_sigma: float | None = None  # the median depth noise of the mask (None: no mask)
    v0: int = 0  # a crop's first row and column in the window (:func:`_cropped`)
    u0: int = 0
    shared: npt.NDArray[np.bool_] | None = None  # object pixels within the occluder's noise
    outline: _Pairs | None = None  # the observed outline's pixel pairs (:func:`_outline_pairs`)


class _Pairs(NamedTuple):
    """The observed outline: 4-neighbours ``p``, an object pixel, and ``q``, seen past it.

    Whole-window (subsampled) pixel coordinates; the edge is taken half-way between them.
    """

    vp: npt.NDArray[np.intp]
    up: npt.NDArray[np.intp]
    vq: npt.NDArray[np.intp]
    uq: npt.NDArray[np.intp]
    depth: FloatArray  # the observed depth at p (the surface that ends there)
    free: FloatArray  # the depth noise's bound at p


def _bounds(image: npt.NDArray[np.bool_]) -> tuple[int, int, int, int]:
    """Return ``(first row, last row + 1, first column, last column + 1)`` of the True pixels."""
    r, c = np.flatnonzero(image.any(axis=1)), np.flatnonzero(image.any(axis=0))
    if len(r) == 0:
        return (0, 0, 0, 0)
    return int(r[0]), int(r[-1]) + 1, int(c[0]), int(c[-1]) + 1


def _cropped(
    win: _Window, rendered: npt.NDArray[np.float32], tri: npt.NDArray[np.int64]
) -> tuple[_Window, npt.NDArray[np.float32], npt.NDArray[np.int64]]:
    """Return the window, the rendering and its triangles on the box of the mask and the model.

    No row of :func:`_rows` comes from a pixel that neither the mask nor the rendered model
    holds, so the rows are those of the whole window, in the same order (row-major), at a
    fraction of the work (the window is the model's box grown by the motion margin; the
    object and the model fill a third of it or less). Views, not copies.
    """
    boxes = [b for b in (win.box, _bounds(tri >= 0)) if b[1] > b[0]] or [(0, 0, 0, 0)]
    r0, c0 = min(b[0] for b in boxes), min(b[2] for b in boxes)
    r1, c1 = max(b[1] for b in boxes), max(b[3] for b in boxes)
    box = np.s_[r0:r1, c0:c1]
    crop = replace(
        win, depth=win.depth[box], mask=win.mask[box], points=win.points[box],
        rays=win.rays[box], scale=win.scale[box], sigma=win.sigma[box], free=win.free[box],
        occluder=None if win.occluder is None else win.occluder[box],
        shared=None if win.shared is None else win.shared[box], v0=r0, u0=c0,
    )  # fmt: skip
    return crop, rendered[box], tri[box]


def _window(
    depth: npt.ArrayLike, camera: Camera, mask: npt.ArrayLike | None,
    occluder: npt.ArrayLike | None, sigma: npt.ArrayLike | None, floor: float, k: float,
    max_pixels: int, shared: npt.ArrayLike | None = None, outline: bool = False,
) -> _Window:  # fmt: skip
    full = np.asarray(depth)
    ok = np.isfinite(full) & (full > 0)
    near = None if shared is None else ok & np.asarray(shared, dtype=bool)
    if mask is not None:
        ok &= np.asarray(mask, dtype=bool)
    count = int(np.count_nonzero(ok))
    step = max(1, int(np.ceil(np.sqrt(count / max_pixels)))) if count else 1
    cam = camera.subsampled(step)
    # Only the pixels kept are converted (the same values as converting the whole window).
    d = np.asarray(full[::step, ::step], dtype=np.float64)
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0)
    ok = ok[::step, ::step]
    # The rays per column and row, broadcast (the same numbers as per pixel).
    x = ((np.arange(d.shape[1]) - cam.cx) / cam.fx)[None, :]
    y = ((np.arange(d.shape[0]) - cam.cy) / cam.fy)[:, None]
    rays = np.empty((*d.shape, 3))
    rays[..., 0], rays[..., 1], rays[..., 2] = x, y, 1.0
    P = rays * d[..., None]
    rays /= np.sqrt(x * x + y * y + 1.0)[..., None]
    sig = np.zeros(d.shape) if sigma is None else np.asarray(sigma, np.float64)[::step, ::step]
    occ = None if occluder is None else np.asarray(occluder, dtype=np.float32)[::step, ::step]
    scale, free = np.maximum(floor, k * sig), np.maximum(floor, 4.0 * sig)
    box = _bounds(ok)
    depth_sigma = float(np.median(scale[ok])) / TUKEY_K if box[1] > box[0] else None
    near = None if near is None else near[::step, ::step] & ~ok
    pairs = _outline_pairs(d, ok, cam, free) if outline else None
    return _Window(
        cam, d, ok, P, rays, scale, sig, free, occ, box, depth_sigma, shared=near, outline=pairs
    )


def _outline_pairs(
    d: FloatArray, ok: npt.NDArray[np.bool_], camera: Camera, free: FloatArray
) -> _Pairs:
    """Return the observed outline's pairs of 4-neighbours (see :class:`_Pairs`).

    ``p`` is an object pixel (``ok``), ``q`` has a depth farther than ``p``'s by more than
    the noise's bound ``free`` and ``OUTLINE_SLOPE`` pixels' widths (more than a surface
    seen at up to 75 deg steps between two pixels): the surface at ``p`` ends between them.
    """
    h, w = d.shape
    out: list[tuple[npt.NDArray[np.intp], ...]] = []
    for dv, du in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        v, u = np.nonzero(ok[max(0, -dv) : h - max(0, dv), max(0, -du) : w - max(0, du)])
        v, u = v + max(0, -dv), u + max(0, -du)
        dp, dq = d[v, u], d[v + dv, u + du]
        edge = dq - dp > free[v, u] + OUTLINE_SLOPE * dp / camera.fx
        out.append((v[edge], u[edge], v[edge] + dv, u[edge] + du))
    vp, up, vq, uq = (np.concatenate([o[k] for o in out]) for k in range(4))
    return _Pairs(vp, up, vq, uq, d[vp, up], free[vp, up])


_Rows = tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]


def projective_icp(
    depth: npt.ArrayLike,
    camera: Camera,
    model: FacePlanes,
    X_CM_init: npt.ArrayLike,
    *,
    mask: npt.ArrayLike | None = None,
    sigma: npt.ArrayLike | None = None,
    floor: float = 0.001,
    tukey_k: float = TUKEY_K,
    start_scale: float = 0.006,
    iterations: int = 15,
    occluder: npt.ArrayLike | None = None,
    max_pixels: int = 4000,
    max_angle: float = np.radians(75.0),
    tolerance: float = 1e-5,
    damping: float = 1e-4,
    silhouette: bool = True,
    constraint: Callable[[FloatArray], tuple[FloatArray, FloatArray, FloatArray]] | None = None,
    clutter: bool = False,
    shared: npt.ArrayLike | None = None,
    outline: bool = False,
    extrapolate: bool = False,
    pool: Executor | None = None,
) -> ProjectiveResult:
    """Projective point-to-plane ICP of a model to the object's pixels of a depth image.

    Parameters
    ----------
    depth : ndarray, shape (H, W)
        Observed depth of the window, metres, 0 where none.
    camera : Camera
        The window's camera (:meth:`Camera.crop`).
    model : FacePlanes
        The model's faces (:func:`face_planes`), model frame, metres.
    X_CM_init : ndarray, shape (4, 4)
        Start pose (the prediction), camera frame, metres.
    mask : ndarray of bool, shape (H, W), optional
        The object's pixels (segmentation); default every pixel with depth.
    sigma : ndarray, shape (H, W), optional
        Depth noise standard deviation per pixel, metres (``DepthNoiseModel.sigma(depth)``);
        the final Tukey scale of a pixel is ``max(floor, tukey_k * sigma)``.
    floor : float, optional
        Least Tukey scale, metres (calibration and model errors do not shrink with noise).
    tukey_k : float, optional
        Tukey's constant in noise standard deviations.
    start_scale : float, optional
        Tukey scale of the first iteration, metres (how far off the start may be); halved
        at each iteration down to the final one.
    iterations : int, optional
        Most Gauss-Newton steps (one rendering each).
    occluder : ndarray, shape (H, W), optional
        Depth of a known object in front (the environment rendered at its pose), 0 where
        none: model pixels it hides are not paired.
    max_pixels : int, optional
        The window is subsampled (every ``step``-th pixel) to at most this many object pixels.
    max_angle : float, optional
        Faces whose normal is more than this from the viewing ray (radians) are not paired.
    tolerance : float, optional
        Stop when a step moves the model's farthest vertex by less than this (metres).
    damping : float, optional
        Levenberg-Marquardt damping, relative to each diagonal entry of the normal matrix
        (per parameter: the rotation entries are ``radius^2`` times the translation ones,
        and a damping relative to the mean diagonal froze the rotations only silhouettes
        constrain).
    silhouette : bool, optional
        Add the silhouette rows (see the module notes).
    constraint : callable, optional
        ``constraint(X_CM) -> (q_M, n_M, r)``: extra rows ``r + J delta`` for model points
        ``q_M`` (model frame) whose residual ``r`` grows along ``n_M`` (model frame) as the
        model moves, weighted 1 (e.g. non-penetration of a known obstacle:
        :func:`apo.perception.register.register_projective`).
    clutter : bool, optional
        The mask may hold other things' pixels (no colour cue: a hand holding the part):
        occluders in front of the model (:func:`occluders`) give no rows, nor do its pixels
        outside the rendered silhouette (see the module notes).
    shared : ndarray of bool, shape (H, W), optional
        Object pixels left out of ``mask`` for being within the noise of the ``occluder``'s
        surface (the environment's pixels, and the part's where it is near the
        environment: only those whose noise took them nearer the camera pass the cut, so
        the cut alone biases the part's pose). Each gives a surface row where the model
        renders the part at the pose, in front of the occluder, and no contour row.
    outline : bool, optional
        Add the two-sided outline rows (with ``silhouette``, not with ``clutter``; see the
        module notes and :func:`_outline`): the observed edge half-way between an object
        pixel and its neighbour seen past it, against the model's silhouette edge.
    extrapolate : bool, optional
        Also stop once the steps left, estimated from the last two at the final scale as a
        geometric series, sum to less than ``tolerance`` (:func:`_settled`): a step sooner
        on most runs of the frame-to-frame tracker. Off, a run stops at a step below it.
    pool : Executor, optional
        Each step's ``constraint`` rows are computed on a thread of it (their k-d queries
        release the GIL) while this one renders the model and forms the other rows: the
        same rows. ``constraint`` must then be safe to call from another thread.

    Returns
    -------
    ProjectiveResult
    """
    X = np.asarray(X_CM_init, dtype=np.float64).copy()
    win = _window(
        depth, camera, mask, occluder, sigma, floor, tukey_k, max_pixels, shared, outline
    )  # fmt: skip
    n_obs = int(np.count_nonzero(win.mask))
    radius = float(np.linalg.norm(model.vertices - model.vertices.mean(0), axis=1).max())
    final_scale = float(win.scale[win.mask].max(initial=floor))
    scale_k = max(start_scale, final_scale)
    cos_min = float(np.cos(max_angle))
    pairs, rms, converged, steps = 0, float("inf"), False, 0
    back: list[FloatArray] = []  # the poses before the last steps at the final scale
    last = float("inf")  # the last step's motion, if at the final scale
    for it in range(1, iterations + 1 if n_obs else 1):  # no object pixel: no evidence
        steps = it
        extra = None if pool is None or constraint is None else pool.submit(constraint, X)
        rows = _rows(X, model, win, cos_min, scale_k, silhouette=silhouette, clutter=clutter)
        if constraint is not None:
            rows = _with_constraint(rows, constraint(X) if extra is None else extra.result())
        system = _normal_equations(rows, scale_k)
        if system is None:
            break
        A, b, pairs, rms = system
        A = A + np.diag(damping * np.diag(A) + 1e-9 * np.trace(A) + 1e-300)
        delta = np.asarray(np.linalg.solve(A, -b), dtype=np.float64)
        moved = float(np.linalg.norm(delta[:3]) * radius + np.linalg.norm(delta[3:]))
        if moved > scale_k:  # trust region: no farther than the pairs' reach
            delta *= scale_k / moved
        back = [*back[1 - CYCLE_LONGEST :], X] if scale_k <= final_scale else []
        X = X @ np.linalg.inv(_exp_se3(delta))
        if scale_k <= final_scale and _settled(moved, last if extrapolate else np.inf, tolerance):
            converged = True
            break
        last = moved if scale_k <= final_scale else float("inf")
        cycle = _cycle(model.vertices, X, back)
        if cycle:
            # Back where it was p steps ago: the steps left go round the same p poses
            # (Tukey weights and contour pixels switching); the limit's pose, at once.
            X = cycle[(iterations - it) % len(cycle)]
            break
        scale_k = max(scale_k / 2.0, final_scale)
    return ProjectiveResult(orthonormalised(X), pairs, n_obs, rms, steps, converged)


def occluders(
    diff: FloatArray, candidates: npt.NDArray[np.bool_], far: FloatArray, near: FloatArray
) -> npt.NDArray[np.bool_]:
    """Pixels of ``candidates`` that something in front of the model occupies.

    ``diff`` is the model's rendered depth less the observed depth (positive: observed in
    front). Seeds are candidates in front by more than ``far``; the occluder is every
    candidate in front by more than ``near`` connected to a seed (8-neighbours): an
    occluder's surface reaches the model's where it touches it, so a fixed cut leaves a
    band of it within the noise of the model's surface, and a hand's band of pixels then
    pulls the pose (hysteresis, as in edge detection).
    """
    from scipy import ndimage

    seeds = candidates & (diff > far)
    if not seeds.any():
        return seeds
    weak = candidates & (diff > near)
    labels, _ = ndimage.label(weak, structure=np.ones((3, 3), dtype=bool))
    hit = np.unique(labels[seeds])
    return weak & np.isin(labels, hit[hit > 0])


CONTRACTION_MAX = 0.5
"""Largest ratio of two steps' motions at the final scale from which :func:`_settled` takes the
steps left as a geometric series."""


def _settled(moved: float, last: float, tolerance: float) -> bool:
    """Return whether the steps left after a step of ``moved`` (before it: ``last``) are small.

    Small: below ``tolerance`` in all. At the final scale the Gauss-Newton steps shrink
    geometrically (by the ratio ``q = moved / last``; 0.05 to 0.15 measured): the steps left
    sum to about ``moved q / (1 - q)``. A step below ``tolerance`` settles it as well.
    Without this, a run whose second step moved 25 micrometres took a third (2 micrometres)
    only to see it below the tolerance. ``last`` infinite: no ratio, only the step itself.
    """
    if moved < tolerance:
        return True
    if not np.isfinite(last):
        return False
    q = moved / last
    return q <= CONTRACTION_MAX and moved * q / (1.0 - q) < tolerance


def _cycle(V: FloatArray, X: FloatArray, back: list[FloatArray]) -> list[FloatArray]:
    """Return the poses of the limit cycle ``X`` closes (``X`` first), or [] if none.

    ``back`` holds the poses before the last steps, oldest first: ``X`` back within
    ``CYCLE_TOLERANCE`` of ``back[-p]`` goes round ``X, back[-p + 1], ..., back[-1]``.
    """
    for p in range(2, len(back) + 1):
        if _moved(V, X, back[-p]) < CYCLE_TOLERANCE:
            return [X, *back[len(back) - p + 1 :]]
    return []


def _moved(V: FloatArray, X: FloatArray, Y: FloatArray) -> float:
    """Largest displacement (metres) of the vertices ``V`` between the poses ``X`` and ``Y``."""
    d = V @ (X[:3, :3] - Y[:3, :3]).T + (X[:3, 3] - Y[:3, 3])
    return float(np.sqrt(np.max(np.einsum("ij,ij->i", d, d))))


def _rows(
    X: FloatArray, model: FacePlanes, win: _Window, cos_min: float, scale_k: float, *,
    silhouette: bool, clutter: bool,
) -> _Rows:  # fmt: skip
    """Return the residual rows at ``X``.

    Observed points and normals (model frame), residuals, Tukey scales and prior weights.

    Surface rows (weight 1): an object pixel and the plane of the face rendered there.
    Contour rows: a pixel on one side of the model's rendered silhouette while the
    observation puts it on the other (an object pixel where the model renders nothing; a
    model pixel where the sensor sees through it), and the plane through the camera centre
    and the nearest silhouette edge of the model (see :func:`_contour`). With ``clutter``,
    object pixels an occluder holds (:func:`occluders`; in front by more than the Tukey
    scale ``scale_k``, or connected to such through pixels in front by more than the noise)
    give no row, nor do object pixels outside the rendered silhouette.
    """
    V_C = transform_points(X, model.vertices)
    rendered, tri = rasterize(V_C, model.triangles, win.camera, cull=model.solid)
    win, rendered, tri = _cropped(win, rendered, tri)
    R, t = X[:3, :3], X[:3, 3]
    on = tri >= 0
    vis = on.copy()
    if win.occluder is not None:
        vis &= ~((win.occluder > 0) & (win.occluder < rendered))
    diff = rendered - win.depth
    surf = win.mask & vis
    if win.shared is not None:  # the part's where the model renders it, within the noise
        surf |= win.shared & vis & (-diff <= win.free)
    if clutter:
        surf &= ~occluders(diff, surf, np.maximum(win.scale, scale_k), np.maximum(1e-3, win.sigma))
    out = [_surface(R, t, model, win, surf, tri, cos_min)]
    if silhouette and on.any():
        wrong = vis & ~win.mask & (-diff > win.free)  # the sensor sees through the model
        if not clutter:
            wrong |= win.mask & ~on  # an object pixel where the model renders nothing
        if wrong.any():
            out.append(_contour(X, model, win, wrong, float(np.median(rendered[on]))))
        if win.outline is not None and len(win.outline.vp) and not clutter:
            out.append(_outline(X, model, win, rendered, cos_min))
    x, n, r, scale, weight, g = (np.concatenate([o[k] for o in out]) for k in range(6))
    return x, n, r, scale, weight, g


def _surface(
    R: FloatArray, t: FloatArray, model: FacePlanes, win: _Window,
    surf: npt.NDArray[np.bool_], tri: npt.NDArray[np.int64], cos_min: float,
) -> _Rows:  # fmt: skip
    """Surface rows of the pixels ``surf`` (see :func:`_rows`), faces at a grazing angle left out.

    The pixels are gathered once (row and column indices), not by a boolean mask per array
    and again for the faces kept: the same numbers.
    """
    v, u = np.nonzero(surf)
    face = tri[v, u]
    rays = win.rays[v, u]
    normals = model.normals[face]
    keep = np.flatnonzero(np.abs(np.einsum("ij,ij->i", rays, normals @ R.T)) >= cos_min)
    v, u, face = v[keep], u[keep], face[keep]
    n_M = normals[keep]
    x = (win.points[v, u] - t) @ R
    r = np.einsum("ij,ij->i", n_M, x) - model.offsets[face]
    # The noise moves a point along its ray: the row's Jacobian is that of the distance
    # along the ray (times the ray's cosine to the face), whose noise does not depend on
    # the pose (see _normal_equations).
    u_M = rays[keep] @ R
    g = _cross(u_M, n_M) / np.einsum("ij,ij->i", u_M, n_M)[:, None]
    return x, n_M, r, win.scale[v, u], np.ones(len(r)), g


def _contour(
    X: FloatArray, model: FacePlanes, win: _Window, wrong: npt.NDArray[np.bool_], z: float
) -> _Rows:
    """Contour rows of the pixels ``wrong`` (see :func:`_rows`).

    Each pixel's ray, at the depth of the nearest silhouette edge (in the image), is paired
    with the plane through the camera centre and that edge: the residual is the lateral
    distance (metres) the edge must move to pass through the pixel's centre. Continuous in
    the pose, so a sub-pixel misalignment pulls in proportion. Weight ``(sigma_depth /
    sigma_lateral)^2`` (at most ``CONTOUR_WEIGHT_MAX``), ``sigma_lateral`` half a pixel.
    """
    R, t = X[:3, :3], X[:3, 3]
    sil = model.silhouette_edges(X)
    A = transform_points(X, model.vertices[model.edges[sil, 0]])
    B = transform_points(X, model.vertices[model.edges[sil, 1]])
    if len(sil) == 0 or np.any(A[:, 2] <= 0) or np.any(B[:, 2] <= 0):
        e = np.zeros(0)
        return np.zeros((0, 3)), np.zeros((0, 3)), e, e, e, np.zeros((0, 3))
    cam = win.camera
    a2 = np.column_stack((cam.fx * A[:, 0] / A[:, 2] + cam.cx, cam.fy * A[:, 1] / A[:, 2] + cam.cy))
    ab = (
        np.column_stack((cam.fx * B[:, 0] / B[:, 2] + cam.cx, cam.fy * B[:, 1] / B[:, 2] + cam.cy))
        - a2
    )
    v, u = np.nonzero(wrong)
    k, sk = _nearest_edge(u + win.u0, v + win.v0, a2, ab)  # in the whole window
    t3 = sk * A[k, 2] / np.maximum((1 - sk) * B[k, 2] + sk * A[k, 2], 1e-12)  # perspective
    E = A[k] + t3[:, None] * (B[k] - A[k])
    Pe = win.rays[v, u] / win.rays[v, u, 2:3] * E[:, 2:3]  # the pixel's ray at the edge's depth
    m = _cross(B[k] - A[k], E)
    m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-300)
    m *= np.where(np.einsum("ij,ij->i", m, Pe) < 0, -1.0, 1.0)[:, None]
    n_M = m @ R
    x = (Pe - t) @ R
    r = np.einsum("ij,ij->i", n_M, x - (E - t) @ R)
    lateral = 0.5 * z / cam.fx
    depth_sigma = lateral if win.depth_sigma is None else win.depth_sigma
    w = min(CONTOUR_WEIGHT_MAX, (depth_sigma / lateral) ** 2)
    return x, n_M, r, win.scale[v, u], np.full(len(r), w), np.zeros((len(r), 3))


def _outline(
    X: FloatArray, model: FacePlanes, win: _Window, rendered: npt.NDArray[np.float32],
    cos_min: float,
) -> _Rows:  # fmt: skip
    """Outline rows: the observed edge half-way between each pair (:class:`_Pairs`).

    Each pair is matched with the nearest silhouette edge of the model in the image
    (:func:`_edges_in_image`; within ``OUTLINE_REACH`` pixels, its outward side the way the
    pair steps from the object to what is seen past it). Kept when ``p`` is observed on
    the model's surface (:func:`_on_surface`) and neither pixel renders the model nearer
    than the edge (a face would hide it). The residual is the signed lateral distance
    (metres, at the edge's depth) from the edge to the ray through the pair's midpoint,
    positive outside the model. Two-sided: every pair gives a row whether or not the
    rendering agrees about its two pixels, so the minimum is the pose whose outline passes
    half-way between the pairs; the contour rows alone are zero over a band of poses up to
    a pixel wide (those that put the outline between the same pixel centres), and the
    pose then stops anywhere in it. Weight ``(sigma_depth / sigma_q)^2`` (at most
    ``CONTOUR_WEIGHT_MAX``), ``sigma_q`` the spread of a uniform error over a pixel.
    """
    pr, cam = win.outline, win.camera
    edges = _edges_in_image(X, model, cam, cos_min)
    if pr is None or edges is None:
        return _NO_ROWS
    A, B, a2, ab, out2 = edges
    mu = np.asarray(0.5 * (pr.up + pr.uq), dtype=np.float64)
    mv = np.asarray(0.5 * (pr.vp + pr.vq), dtype=np.float64)
    k, sk = _nearest_edge(mu, mv, a2, ab)
    gap = np.hypot(mu - a2[k, 0] - sk * ab[k, 0], mv - a2[k, 1] - sk * ab[k, 1])
    outward = out2[k, 0] * (pr.uq - pr.up) + out2[k, 1] * (pr.vq - pr.vp)
    t3 = sk * A[k, 2] / np.maximum((1 - sk) * B[k, 2] + sk * A[k, 2], 1e-12)  # perspective
    E = A[k] + t3[:, None] * (B[k] - A[k])
    nearer = np.minimum(_rendered_at(rendered, win, pr.vp, pr.up, np.inf),
                        _rendered_at(rendered, win, pr.vq, pr.uq, np.inf))  # fmt: skip
    width = OUTLINE_SLOPE * E[:, 2] / cam.fx * (gap + 1.0)  # a surface's steps over the gap
    ok = (gap <= OUTLINE_REACH) & (outward > 0.5) & (nearer >= E[:, 2] - pr.free - width)
    ok &= _on_surface(rendered, win, pr)
    if not ok.any():
        return _NO_ROWS
    k, E = k[ok], E[ok]
    Pm = np.column_stack(((mu[ok] - cam.cx) / cam.fx, (mv[ok] - cam.cy) / cam.fy, np.ones(len(k))))
    Pm *= E[:, 2:3]  # the midpoint's ray at the edge's depth
    m = _cross(B[k] - A[k], E)  # the normal of the plane through the camera centre and edge
    m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-300)
    # Outward as the edge's image normal: the image motion of E moved along m.
    du = cam.fx * (m[:, 0] - E[:, 0] * m[:, 2] / E[:, 2])
    dv = cam.fy * (m[:, 1] - E[:, 1] * m[:, 2] / E[:, 2])
    m *= np.where(du * out2[k, 0] + dv * out2[k, 1] < 0, -1.0, 1.0)[:, None]
    R, t = X[:3, :3], X[:3, 3]
    n_M = m @ R
    x = (Pm - t) @ R
    r = np.einsum("ij,ij->i", m, Pm - E)
    lateral = float(np.median(E[:, 2])) / cam.fx  # a pixel's width, metres
    quant = lateral / np.sqrt(12.0)
    depth_sigma = quant if win.depth_sigma is None else win.depth_sigma
    w = min(CONTOUR_WEIGHT_MAX, (depth_sigma / quant) ** 2)
    scale = np.full(len(r), (OUTLINE_REACH + 0.5) * lateral)
    return x, n_M, r, scale, np.full(len(r), w), np.zeros((len(r), 3))


_NO_ROWS: _Rows = (np.zeros((0, 3)), np.zeros((0, 3)), *np.zeros((3, 0)), np.zeros((0, 3)))


def _edges_in_image(
    X: FloatArray, model: FacePlanes, cam: Camera, cos_min: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray] | None:
    """Return the silhouette edges at ``X`` whose face in view is not seen at a grazing angle.

    Returns their ends ``A``, ``B`` (camera frame), ``A``'s image point, the image vector to
    ``B``'s and the unit image normal away from the face in view (outward); None if none.
    Past a face seen at more than ``max_angle`` the observed depth steps like an outline
    from pixel to pixel, so its own edge is left to the contour rows.
    """
    R, t = X[:3, :3], X[:3, 3]
    sil = model.silhouette_edges(X)
    eye = -R.T @ t  # the camera centre, model frame
    front = model.normals @ eye - model.offsets > 0
    f0, f1 = model.edge_faces[sil, 0], model.edge_faces[sil, 1]
    f = np.where(front[f0] | (f1 < 0), f0, f1)  # the face turned to the camera
    ray = model.vertices[model.edges[sil]].mean(axis=1) - eye
    seen = np.abs(np.einsum("ij,ij->i", model.normals[f], ray))
    keep = seen >= cos_min * np.linalg.norm(ray, axis=1)
    sil, f = sil[keep], f[keep]
    third = model.triangles[f].sum(axis=1) - model.edges[sil].sum(axis=1)
    P = transform_points(X, model.vertices[np.concatenate([model.edges[sil].T.ravel(), third])])
    if len(sil) == 0 or np.any(P[:, 2] <= 0):
        return None
    uv = np.column_stack((cam.fx * P[:, 0] / P[:, 2] + cam.cx, cam.fy * P[:, 1] / P[:, 2] + cam.cy))
    n = len(sil)
    a2, ab, c2 = uv[:n], uv[n : 2 * n] - uv[:n], uv[2 * n :]
    out2 = np.column_stack((-ab[:, 1], ab[:, 0]))
    out2 /= np.maximum(np.linalg.norm(out2, axis=1, keepdims=True), 1e-12)
    out2 *= np.where(np.einsum("ij,ij->i", out2, c2 - a2) > 0, -1.0, 1.0)[:, None]
    return P[:n], P[n : 2 * n], a2, ab, out2


def _rendered_at(
    rendered: npt.NDArray[np.float32], win: _Window, v: npt.NDArray[np.intp],
    u: npt.NDArray[np.intp], none: float = 0.0,
) -> FloatArray:  # fmt: skip
    """Return the (cropped) rendering's depth at whole-window pixels; ``none`` where none."""
    h, w = rendered.shape
    vv, uu = v - win.v0, u - win.u0
    inside = (vv >= 0) & (vv < h) & (uu >= 0) & (uu < w)
    d = np.where(inside, rendered[np.clip(vv, 0, h - 1), np.clip(uu, 0, w - 1)], 0.0)
    return np.where(d > 0, d, none)


def _on_surface(
    rendered: npt.NDArray[np.float32], win: _Window, pr: _Pairs
) -> npt.NDArray[np.bool_]:
    """Whether each pair's ``p`` is observed on the model's surface, within the noise's bound.

    Where the model renders ``p``, its depth there; else the surface continued linearly
    from the two pixels behind ``p`` (the model's edge passes between them and ``p``).
    Something else in view that ends near the model's outline (a part in a slot, flush with
    its rim; a hand) is not the model's outline.
    """
    dv, du = pr.vq - pr.vp, pr.uq - pr.up
    at = _rendered_at(rendered, win, pr.vp, pr.up)
    b1 = _rendered_at(rendered, win, pr.vp - dv, pr.up - du)
    b2 = _rendered_at(rendered, win, pr.vp - 2 * dv, pr.up - 2 * du)
    ref = np.where(at > 0, at, np.where((b1 > 0) & (b2 > 0), 2 * b1 - b2, 0.0))
    return (ref > 0) & (np.abs(pr.depth - ref) <= pr.free)


def _nearest_edge(
    u: npt.NDArray[np.intp] | FloatArray,
    v: npt.NDArray[np.intp] | FloatArray,
    a2: FloatArray,
    ab: FloatArray,
) -> tuple[npt.NDArray[np.intp], FloatArray]:
    """Return the nearest image edge ``a2 + s ab`` (s in [0, 1]) of each pixel, and its s.

    (pixel, edge) arrays by coordinate, not (pixel, edge, 2) ones: the same numbers as the
    broadcast form (but for the sign of a zero ``s``, which no later sum keeps), in less time
    (``tests/test_perception_projective.py``).
    """
    ab2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12)
    px, py = u.astype(np.float64)[:, None], v.astype(np.float64)[:, None]
    ax, ay, bx, by = a2[:, 0], a2[:, 1], ab[:, 0], ab[:, 1]
    s = np.clip(((px - ax) * bx + (py - ay) * by) / ab2, 0.0, 1.0)
    k = np.argmin((ax + s * bx - px) ** 2 + (ay + s * by - py) ** 2, axis=1)
    return k, s[np.arange(len(k)), k]


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise cross products of (n, 3) arrays: ``np.cross``'s numbers without its overhead."""
    out = np.empty(a.shape)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _with_constraint(rows: _Rows, extra: tuple[FloatArray, FloatArray, FloatArray]) -> _Rows:
    """Append rows of a model point ``q_M`` moving with the model (hence the signs)."""
    q, n, r = extra
    if len(r) == 0:
        return rows
    # r' = r + n_M . (-omega x q - v): the rows of an observed point with normal -n_M.
    big = np.full(len(r), np.inf)
    weight = np.full(len(r), CONTOUR_WEIGHT_MAX)
    return (
        np.concatenate([rows[0], q]), np.concatenate([rows[1], -n]),
        np.concatenate([rows[2], r]), np.concatenate([rows[3], big]),
        np.concatenate([rows[4], weight]), np.concatenate([rows[5], np.zeros((len(r), 3))]),
    )  # fmt: skip


def _normal_equations(
    rows: _Rows, scale_k: float
) -> tuple[FloatArray, FloatArray, int, float] | None:
    """Return ``(A, b)`` of the Tukey-weighted rows ``r + J delta``, their count and RMS.

    A surface row's residual ``r = n . x - d`` (the observed point ``x``'s distance to the
    face's plane, model frame) is ``c`` times the point's distance to the plane along its
    ray ``u`` (``c = n . u``); the depth noise moves ``x`` along ``u``. Its Jacobian is
    taken as that of ``c_0 s`` for the ray distance ``s = r / c`` at ``c_0 = c``: ``J - r
    (u x n) / c`` in rotation (``g`` holds ``(u x n) / c``; 0 for the other rows). With the
    plain ``J = [x x n, n]`` the expected squared residual at a pose is the squared error
    plus ``sigma^2 c^2``, which the pose lowers by turning the faces away from the rays:
    the minimum of the surface rows moves by that noise term (measured, T-peg at 1 m,
    ``sigma`` 5 mm, 40 noise draws from the true pose: a mean rotation error of 2.5 deg,
    0.4 with the ray's Jacobian). The ray distance's noise is the sensor's, the same at
    every pose, so the rows' expected gradient is zero at the true pose.
    """
    x, n, r, scale, prior, g = rows
    w = prior * tukey_weights(r, np.maximum(scale, scale_k))
    used = w > 0
    if np.count_nonzero(used) < 6:
        return None
    J = np.hstack([_cross(x[used], n[used]) - r[used, None] * g[used], n[used]])
    w, r = w[used], r[used]
    A = (J * w[:, None]).T @ J
    b = J.T @ (w * r)
    rms = float(np.sqrt(np.sum(w * r * r) / np.sum(w)))
    return A, b, int(np.count_nonzero(used)), rms
