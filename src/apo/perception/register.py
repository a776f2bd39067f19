"""Robust model-to-depth registration (the paper's 3DTM: a weighted least-squares ICP).

The observed points of one object (camera frame) are registered to points sampled on its
model, with the exact face normals of the model, by Open3D's point-to-plane ICP with a robust
kernel (Tukey's biweight by default, Huber optionally): iteratively reweighted least squares,
as 3DTM. A coarse-to-fine schedule of correspondence distances widens the basin of
convergence.

Confidence of a registration (:class:`Registration`) is the product of

- the *fitness*: the fraction of observed points within ``inlier_distance`` of the posed model;
- the *free-space consistency*: one minus the fraction of the model's pixels (rendered at the
  estimated pose) where the sensor sees something *behind* the model's surface, which a solid
  object there would have hidden;
- the *non-penetration*: one minus the fraction of the model's surface inside the other
  object (when its pose is known), since two solids cannot overlap.

The first catches a model that explains too few of the points, the second a pose that
explains the points but puts material where the camera sees through, the third a pose that
hides the unseen part of the object inside the other one (a peg whose head is all that
shows). A pose with low confidence is never reported as tracked (:mod:`apo.perception.track`).

Without an initial pose, :func:`initialise` tries many orientations (the 24 rotations of the
cube, aligned by principal axes, and the 60 of the icosahedron) about the points' centroid,
runs a short ICP from each, and keeps the most confident.

Open3D is optional: it is imported by the functions that need it
(``pip install apo[perception]``).
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from apo.errors import ApoError
from apo.perception.frames import Camera
from apo.perception.meshdistance import ClosedMesh, is_closed
from apo.perception.projective import FacePlanes, face_planes, projective_icp
from apo.perception.render import Triangles, rasterize
from apo.spatial import invert_pose, orthonormalised, transform_points
from apo.typing import FloatArray

__all__ = [
    "ModelCloud",
    "Registration",
    "SurfaceCheck",
    "evaluate",
    "free_space_violation",
    "initialise",
    "model_cloud",
    "orthonormalised",
    "penetration",
    "register",
    "register_projective",
    "surface_check",
]


def open3d() -> Any:
    """Import Open3D quietly, or raise an :class:`ApoError` saying how to install it."""
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ApoError(
            f"perception needs Open3D, which could not be imported ({exc}); "
            "install it with `pip install apo[perception]` (on Debian/Ubuntu Open3D also "
            "needs the system library libusb-1.0-0)"
        ) from None
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


INSIDE_TRIANGLES = 200
"""Largest closed mesh (triangles) whose inside is tested by ray parity
(:class:`apo.perception.meshdistance.ClosedMesh`) before its dense samples are queried."""


class ModelCloud:
    """Points and normals sampled on a model's surface, ready for ICP.

    Attributes
    ----------
    vertices : ndarray, shape (N, 3)
        Model vertices, model frame ``M``, metres.
    triangles : ndarray of int, shape (T, 3)
        Vertex indices.
    points, normals : ndarray, shape (K, 3)
        Surface samples (model frame, metres) and their unit face normals.
    diameter : float
        Diagonal of the model's bounding box, metres.
    """

    def __init__(
        self,
        mesh: Triangles,
        *,
        n_points: int = 3000,
        spacing: float = 0.0005,
        max_dense: int = 40000,
        seed: int = 0,
    ) -> None:
        V = np.asarray(mesh[0], dtype=np.float64)
        T = np.asarray(mesh[1], dtype=np.int64)
        a, b, c = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
        cross = np.cross(b - a, c - a)
        area = np.linalg.norm(cross, axis=1) / 2
        if area.sum() <= 0:
            raise ApoError("model has zero surface area")
        rng = np.random.default_rng(seed)
        n = cross / np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-300)

        def sample(count: int) -> tuple[FloatArray, FloatArray]:
            # Stratified area-weighted sampling: a fixed share per triangle, the rest random.
            counts = np.floor(area / area.sum() * count).astype(np.int64)
            extra = rng.choice(len(T), count - int(counts.sum()), p=area / area.sum())
            counts += np.bincount(extra, minlength=len(T))
            tri = np.repeat(np.arange(len(T)), counts)
            r1 = np.sqrt(rng.random(len(tri)))
            r2 = rng.random(len(tri))
            pts = (
                (1 - r1)[:, None] * a[tri]
                + (r1 * (1 - r2))[:, None] * b[tri]
                + (r1 * r2)[:, None] * c[tri]
            )
            return pts, n[tri]

        self.points, self.normals = sample(n_points)
        dense = int(np.clip(area.sum() / spacing**2, n_points, max_dense))
        self.dense_points, self.dense_normals = sample(dense)
        self.spacing = float(np.sqrt(area.sum() / dense))
        self.vertices = V
        self.triangles = T
        self.diameter = float(np.linalg.norm(V.max(0) - V.min(0)))
        self.centroid = self.points.mean(axis=0)
        self._pcd: Any = None
        self._dense: Any = None
        self._tree: Any = None  # k-d trees of the dense and sparse samples (:meth:`tree`)
        self._sparse_tree: Any = None
        self._faces: FacePlanes | None = None
        self._closed: ClosedMesh | bool | None = None  # False: not small and closed

    @property
    def faces(self) -> FacePlanes:
        """The planes of the model's faces (projective ICP, :mod:`apo.perception.projective`)."""
        if self._faces is None:
            self._faces = face_planes(self.vertices, self.triangles)
        return self._faces

    @property
    def pcd(self) -> Any:
        """The Open3D point cloud of the sparse samples (coarse ICP stages)."""
        if self._pcd is None:
            self._pcd = _point_cloud(self.points, self.normals)
        return self._pcd

    @property
    def dense_pcd(self) -> Any:
        """The Open3D point cloud of the dense samples (the final ICP stage)."""
        if self._dense is None:
            self._dense = _point_cloud(self.dense_points, self.dense_normals)
        return self._dense

    def closed(self) -> ClosedMesh | None:
        """Return the mesh's inside test (None unless closed, ``INSIDE_TRIANGLES`` at most)."""
        if self._closed is None:
            small = len(self.triangles) <= INSIDE_TRIANGLES
            ok = small and is_closed(self.vertices, self.triangles)
            self._closed = ClosedMesh(self.vertices, self.triangles) if ok else False
        return self._closed if isinstance(self._closed, ClosedMesh) else None

    def signed_distance(self, points_M: npt.ArrayLike) -> FloatArray:
        """Approximate signed distance (metres, negative inside) of points in the model frame.

        The distance to the nearest dense sample, signed by that sample's outward normal:
        exact enough near the surface, which is where it is used (interpenetration).
        """
        side, point = self._nearest(points_M)
        return np.where(side < 0, -point, point)

    def inside_samples(
        self, points_M: npt.ArrayLike, *, max_distance: float = np.inf
    ) -> tuple[FloatArray, FloatArray, npt.NDArray[np.intp]]:
        """:meth:`nearest_sample` (dense) of the points that may be inside the model.

        For a small closed mesh (:meth:`closed`) the points outside it are known exactly and
        not queried: they get plane distance and distance ``inf`` and index -1, as points
        beyond ``max_distance`` do. Else every point is queried.
        """
        P = np.asarray(points_M, dtype=np.float64).reshape(-1, 3)
        closed = self.closed()
        if closed is None:
            return self.nearest_sample(P, max_distance=max_distance)
        ins = np.flatnonzero(closed.inside(P))
        side, dist = np.full(len(P), np.inf), np.full(len(P), np.inf)
        idx = np.full(len(P), -1, dtype=np.intp)
        if len(ins):
            side[ins], dist[ins], idx[ins] = self.nearest_sample(P[ins], max_distance=max_distance)
        return side, dist, idx

    def residuals(
        self, points_M: npt.ArrayLike, *, max_distance: float = np.inf
    ) -> tuple[FloatArray, FloatArray]:
        """Point-to-plane and point-to-point distances (metres) to the nearest dense sample.

        Both are ``inf`` for a point farther than ``max_distance`` from every sample (the
        k-d tree search stops there: 3 to 6 times faster on a frame's points).
        """
        side, point, _ = self.nearest_sample(points_M, max_distance=max_distance)
        return np.abs(side), point

    def _nearest(self, points_M: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Signed point-to-plane and point-to-point distances to the nearest dense sample."""
        side, dist, _ = self.nearest_sample(points_M)
        return side, dist

    def tree(self, dense: bool = True) -> Any:
        """Return the ``scipy.spatial.cKDTree`` of the dense (or sparse) samples, built once.

        Node boxes are not shrunk to their samples (``compact_nodes=False``): the same nearest
        samples, queries of points millimetres off the surface 2 times faster (measured on
        the environment's 200,000 dense samples; the non-penetration rows).
        """
        from scipy.spatial import cKDTree

        if dense:
            if self._tree is None:
                self._tree = cKDTree(self.dense_points, compact_nodes=False)
            return self._tree
        if self._sparse_tree is None:
            self._sparse_tree = cKDTree(self.points, compact_nodes=False)
        return self._sparse_tree

    def nearest_sample(
        self, points_M: npt.ArrayLike, *, dense: bool = True, max_distance: float = np.inf
    ) -> tuple[FloatArray, FloatArray, npt.NDArray[np.intp]]:
        """Return the nearest sample's signed plane distance, distance and index.

        Points in the model frame; ``dense`` False: among the sparse samples (``points``,
        ``normals``; the plane distance is as exact on flat faces, the choice of face near
        edges coarser). The k-d trees are built once. A point farther than ``max_distance``
        from every sample gets plane distance and distance ``inf`` and index -1.
        """
        P = np.asarray(points_M, dtype=np.float64)
        pts, nrm = (self.dense_points, self.dense_normals) if dense else (self.points, self.normals)
        dist, idx = self.tree(dense).query(P, distance_upper_bound=max_distance)
        idx = np.asarray(idx, dtype=np.intp)
        found = idx < len(pts)
        idx = np.where(found, idx, -1)
        side = np.einsum("ij,ij->i", P - pts[idx], nrm[idx])
        side = np.where(found, side, np.inf)
        return side, np.asarray(dist, dtype=np.float64), idx


def _point_cloud(points: FloatArray, normals: FloatArray) -> Any:
    o3d = open3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.normals = o3d.utility.Vector3dVector(normals)
    return pcd


def model_cloud(mesh: Triangles, *, n_points: int = 4000, seed: int = 0) -> ModelCloud:
    """Return the :class:`ModelCloud` of ``(vertices, triangles)`` (metres)."""
    return ModelCloud(mesh, n_points=n_points, seed=seed)


@dataclass(frozen=True)
class Registration:
    """Result of registering a model to observed points.

    Attributes
    ----------
    X_CM : ndarray, shape (4, 4)
        Pose of the model frame ``M`` in the camera frame ``C`` (metres).
    fitness : float
        Fraction of the observed points within the inlier distance of the model.
    rmse : float
        RMS distance of those inliers, metres.
    violation : float
        Fraction of the model's rendered pixels behind which the sensor sees (0 when no depth
        image was given).
    n_points : int
        Observed points used.
    penetration : float
        Fraction of the model's surface samples inside the obstacle (the other object), 0
        when no obstacle was given.
    """

    X_CM: FloatArray
    fitness: float
    rmse: float
    violation: float
    n_points: int
    penetration: float = 0.0
    surface: SurfaceCheck | None = None

    @property
    def quality(self) -> float:
        """``fitness * (1 - silhouette violation)``: ranks poses of one frame (not a confidence).

        The share of the observed points the pose explains, less the share of its pixels,
        depth edges included, where the sensor sees past it.
        """
        v = self.surface.silhouette_violation if self.surface is not None else self.violation
        return float(self.fitness * (1.0 - v))

    @property
    def confidence(self) -> float:
        """The share of the predicted-visible model surface the observation explains.

        ``surface.score * (1 - penetration)`` (:class:`SurfaceCheck`) when a depth image was
        given; without one, ``fitness * (1 - penetration)``. In [0, 1].
        """
        return self.confidence_at(VISIBLE_MIN)

    def confidence_at(self, visible_min: float) -> float:
        """:attr:`confidence` with ``visible_min`` (see :meth:`SurfaceCheck.score_at`)."""
        if self.surface is not None:
            return float(self.surface.score_at(visible_min) * (1.0 - self.penetration))
        return float(self.fitness * (1.0 - self.violation) * (1.0 - self.penetration))


FREE_SPACE_FULL_PIXELS = 160 * 120
"""Depth windows at least this large are tested at every other pixel (free space)."""
CONVERGED = 1e-9
"""ICP stops when fitness and RMSE change by less than this fraction in one iteration
(looser values, e.g. 1e-6, stopped the tracker short by up to 0.7 mm in fast motion)."""


VISIBLE_MIN = 0.35
"""A pose whose model surface is at least this share unoccluded counts its explained share in
full; below, the confidence falls in proportion (a pose hidden behind other things has no
evidence for it: a wrong pose placed behind a forearm explains nothing, contradicts nothing)."""

CONTINUED_FREE = 0.4
"""Share of a model's outline on which the observed surface may continue beyond its silhouette
at its own depth without lowering the confidence (fingers pressed flush against the part,
contact lines: up to 0.32 at the true poses of variant seeds 1 to 8 with a hand, 0.05 to
0.2 typically)."""
CONTINUED_NONE = 0.7
"""... and the share at which the confidence is 0 (the model sits inside a larger object that
shares its faces: 0.35 to 0.83 for the wrong poses of the same seeds' global search)."""
OUTLINE_GAP = 2
"""Image pixels from a model's outline pixel to the outside pixel the outline test reads
(:func:`_continued`; at least one step of its grid). The pixel next to the silhouette is the
part's own when the pose is a pixel off, and a single frame's depth tilts a small far part's
pose by 1 to 3 deg (correlated noise; independent recording 5, 0.82-0.89 m): read one pixel out,
the outline of the part's pose that fits the depth best continued on 0.51 of it (the part's
own pixels, within the 10.6 mm tolerance), scoring 0.63; two pixels out, 0.08."""
CONTINUED_WEIGHT = 0.1
"""Weight of the outline continued when poses of one frame are ranked (:func:`plausibility`): a
tie-break among about equally confident poses (variant seed 6 with the learnt colour: the true
pose, confidence 1.0 and 0.26 continued by the fingers, against one 34 mm off behind the hand,
0.95 and 0.14; with 1 - continued as a factor the wrong one won)."""
HIDDEN_WEIGHT = 0.1
"""Weight of the model surface hidden by something unknown when poses of one frame are ranked
(:func:`plausibility`): hidden surface is no evidence for a pose. Depth alone, variant seed 5
(30 frames): the true first pose, confidence 1.0 with 0.88 of its surface in view and 0.25 of
its outline continued by the fingers, lost to one 100 mm off behind the forearm, 1.0, 0.41
and 0.10, once the global search's candidates were refined by the projective ICP."""


@dataclass(frozen=True)
class SurfaceCheck:
    """How the observed depth agrees with a model rendered at a pose (pixel counts in shares).

    Every pixel of the rendered model (away from its depth edges, with an observed depth,
    not hidden by a known occluder) is *explained* (observed within the tolerance of the
    model's surface), *behind* (the sensor sees through the model: free space violated) or
    *in front* (something unknown hides it: a hand, an arm).

    Attributes
    ----------
    explained : float
        ``E / (E + B)``: the share of the model surface predicted visible (not hidden) that
        the observation explains.
    visible : float
        ``(E + B) / (E + B + F)``: the share of the model's pixels not hidden by something
        in front.
    violation : float
        ``B / (E + B)``: the free-space violation.
    pixels : int
        ``E + B + F`` (0: the model is not in view).
    silhouette_violation : float
        The free-space violation over all the model's pixels, its depth edges included: a
        pose 1 mm off along a face still explains its surface within the noise, but the
        sensor sees past its silhouette (used to rank poses, not as the confidence).
    continued : float
        The share of the model's outline (its silhouette pixels with a measured depth just
        outside) where the model's surface is observed and the observed surface continues
        beyond the silhouette at the model's depth: the model would sit inside a larger
        object (a hand's or a forearm's box) rather than be one (:func:`_continued`).
    """

    explained: float
    visible: float
    violation: float
    pixels: int
    silhouette_violation: float = 0.0
    continued: float = 0.0

    @property
    def score(self) -> float:
        """``explained * min(1, visible / VISIBLE_MIN) * outline``, in [0, 1].

        ``outline`` is 1 while :attr:`continued` is at most :data:`CONTINUED_FREE`, falling
        linearly to 0 at :data:`CONTINUED_NONE`.
        """
        return self.score_at(VISIBLE_MIN)

    def score_at(self, visible_min: float) -> float:
        """:attr:`score` with ``visible_min`` for :data:`VISIBLE_MIN`.

        A tracker that has seen the part over the last frames knows how much of it the hand
        holding it hides: a pose hidden about as much is no less sure for it
        (:func:`apo.perception.track.track_frames`).
        """
        outline = (CONTINUED_NONE - self.continued) / (CONTINUED_NONE - CONTINUED_FREE)
        outline = min(1.0, max(0.0, outline))
        return float(self.explained * min(1.0, self.visible / visible_min) * outline)


def _interior(rendered: npt.NDArray[np.float32], jump: float) -> npt.NDArray[np.bool_]:
    """Model pixels whose 4 neighbours are model pixels within ``jump`` of their depth."""
    r = rendered.astype(np.float64)
    ok = r > 0
    pad = np.pad(r, 1)
    for dv, du in ((0, 1), (2, 1), (1, 0), (1, 2)):
        nb = pad[dv : dv + r.shape[0], du : du + r.shape[1]]
        ok &= (nb > 0) & (np.abs(nb - r) <= jump)
    return ok


def _model_window(
    X_CM: FloatArray, model: ModelCloud, camera: Camera
) -> tuple[int, int, int, int] | None:
    """Image window ``(u0, v0, w, h)`` (1-pixel margin) of the model's projection, or None."""
    V = transform_points(X_CM, model.vertices)
    if np.any(V[:, 2] <= 0.01):
        V = V[V[:, 2] > 0.01]
        if len(V) == 0:
            return None
    uv = camera.project(V)
    u0 = int(max(np.floor(uv[:, 0].min()) - 1, 0))
    v0 = int(max(np.floor(uv[:, 1].min()) - 1, 0))
    u1 = int(min(np.ceil(uv[:, 0].max()) + 2, camera.width))
    v1 = int(min(np.ceil(uv[:, 1].max()) + 2, camera.height))
    if u1 - u0 < 1 or v1 - v0 < 1:
        return None
    return u0, v0, u1 - u0, v1 - v0


def surface_check(
    X_CM: npt.ArrayLike,
    model: ModelCloud,
    depth: npt.ArrayLike,
    camera: Camera,
    *,
    tolerance: float = 0.005,
    occluder: npt.ArrayLike | None = None,
    max_pixels: int = FREE_SPACE_FULL_PIXELS // 4,
) -> SurfaceCheck:
    """Compare the observed depth with the model rendered at ``X_CM`` (see :class:`SurfaceCheck`).

    Parameters
    ----------
    X_CM : ndarray, shape (4, 4)
        Pose of the model in the camera frame (metres).
    model : ModelCloud
    depth : ndarray, shape (H, W)
        Observed depth, metres, 0 where none (such pixels do not count).
    camera : Camera
        The camera of ``depth``.
    tolerance : float, optional
        Metres (a few standard deviations of the depth noise at the object).
    occluder : ndarray, shape (H, W), optional
        Depth of known objects (the environment model rendered at its pose), 0 where none:
        model pixels behind it are not predicted visible and do not count. Given, the
        outline test runs too (:attr:`SurfaceCheck.continued`; 0 without it).
    max_pixels : int, optional
        The model's window is tested at every ``step``-th pixel of every ``step``-th row,
        with ``step`` the least that keeps it below this many pixels.
    """
    X = np.asarray(X_CM, dtype=np.float64)
    box = _model_window(X, model, camera)
    if box is None:
        return SurfaceCheck(0.0, 0.0, 1.0, 0)
    u0, v0, w, h = box
    step = max(1, int(np.ceil(np.sqrt(w * h / max_pixels))))
    cam = camera.crop(u0, v0, w, h).subsampled(step)
    d = np.asarray(depth)[v0 : v0 + h : step, u0 : u0 + w : step]
    V_C = transform_points(X, model.vertices)
    rendered, _ = rasterize(V_C, model.triangles, cam, cull=model.faces.solid)
    every = (rendered > 0) & (d > 0)
    if occluder is not None:
        occ = np.asarray(occluder)[v0 : v0 + h : step, u0 : u0 + w : step]
        every &= ~((occ > 0) & (occ < rendered - tolerance))
    inner = every
    if min(cam.width, cam.height) > 6:
        inner = every & _interior(rendered, 2.0 * tolerance)
        if not inner.any():
            inner = every
    diff = d.astype(np.float64) - rendered
    behind = diff > tolerance
    n_e = int(np.count_nonzero(inner & (np.abs(diff) <= tolerance)))
    n_b = int(np.count_nonzero(inner & behind))
    n = int(np.count_nonzero(inner))
    if n == 0:
        return SurfaceCheck(0.0, 0.0, 1.0, 0)
    all_b = int(np.count_nonzero(every & behind))
    all_seen = int(np.count_nonzero(every & (diff >= -tolerance)))
    edge = all_b / all_seen if all_seen else 0.0
    seen = n_e + n_b
    if seen == 0:
        return SurfaceCheck(0.0, 0.0, 0.0, n, edge)
    # The outline test needs the other object rendered (contact with it is allowed): the
    # environment, registered alone, stands on the table, whose surface runs on at its base.
    grid = (u0, v0, step)
    cont = 0.0 if occluder is None else _continued(rendered, d, depth, occluder, grid, tolerance)
    return SurfaceCheck(n_e / seen, seen / n, n_b / seen, n, edge, cont)


def _continued(
    rendered: npt.NDArray[np.float32],
    d: npt.NDArray[np.float32],
    depth: npt.ArrayLike,
    occluder: npt.ArrayLike,
    grid: tuple[int, int, int],
    tolerance: float,
) -> float:
    """Share of the model's outline where the observed surface continues past its silhouette.

    ``rendered`` and ``d`` are the model's and the observed depth on the grid ``(u0, v0,
    step)`` of the whole image ``depth`` (and ``occluder``). An outline pixel is a model
    pixel whose grid neighbour on one side is not the model's and on the other side is;
    the pixel :data:`OUTLINE_GAP` image pixels outside (at least one grid step; read from
    the whole image; the model's pixels up to it not the model's) counts when it has a
    depth; it never continues the model where the known occluder explains it (contact
    with the other object is allowed). It *continues* the model when the outline pixel is
    explained (observed within ``tolerance`` of the model) and the outside pixel lies
    within ``tolerance`` of the model's surface extrapolated that far on: a part held by a
    hand shows depth jumps at its outline (to the background behind it, to the hand in
    front), a model placed inside a larger box shows the box's faces running on.
    """
    u0, v0, step = grid
    D = np.asarray(depth)
    occ = np.asarray(occluder)
    r = rendered.astype(np.float64)
    on = r > 0
    h, w = r.shape
    vv, uu = np.nonzero(on)
    n_out = n_cont = 0
    reach = max(1, -(-OUTLINE_GAP // step))  # grid steps to the outside pixel
    for dv, du in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        vi, ui = vv - dv, uu - du  # inward neighbour: a model pixel too
        outward = np.ones(len(vv), dtype=bool)  # the neighbours out to the one read: not it
        for j in range(1, reach + 1):
            vo, uo = vv + j * dv, uu + j * du
            inside = (vo >= 0) & (vo < h) & (uo >= 0) & (uo < w)
            outward[inside] &= ~on[vo[inside], uo[inside]]
        inward = (vi >= 0) & (vi < h) & (ui >= 0) & (ui < w)
        inward[inward] = on[vi[inward], ui[inward]]
        vf, uf = v0 + vo * step, u0 + uo * step  # the outside pixel in the whole image
        rows, cols = D.shape
        k = inward & outward & (vf >= 0) & (vf < rows) & (uf >= 0) & (uf < cols)
        e, vf, uf = np.flatnonzero(k), vf[k], uf[k]
        out = D[vf, uf].astype(np.float64)
        keep = out > 0
        n_out += int(np.count_nonzero(keep))
        o = occ[vf, uf]
        keep &= ~((o > 0) & (np.abs(out - o) <= tolerance))
        e, out = e[keep], out[keep]
        r_e = r[vv[e], uu[e]]
        ext = r_e + reach * (r_e - r[vv[e] - dv, uu[e] - du])
        seen = np.abs(d[vv[e], uu[e]] - r_e) <= tolerance
        n_cont += int(np.count_nonzero(seen & (np.abs(out - ext) <= tolerance)))
    return n_cont / n_out if n_out else 0.0


def _kernel(o3d: Any, loss: str, scale: float) -> Any:
    reg = o3d.pipelines.registration
    if loss == "tukey":
        return reg.TukeyLoss(k=scale)
    if loss == "huber":
        return reg.HuberLoss(k=scale)
    if loss == "l2":
        return reg.L2Loss()
    raise ValueError(f"unknown loss {loss!r}; expected 'tukey', 'huber' or 'l2'")


def free_space_violation(
    X_CM: npt.ArrayLike,
    model: ModelCloud,
    depth: npt.ArrayLike,
    camera: Camera,
    *,
    tolerance: float = 0.005,
    step: int = 1,
) -> float:
    """Fraction of the model's pixels where the sensor sees more than ``tolerance`` behind it.

    Parameters
    ----------
    X_CM : ndarray, shape (4, 4)
        Pose of the model in the camera frame (metres).
    model : ModelCloud
        The model.
    depth : ndarray, shape (H, W)
        Observed depth, metres, 0 where none (such pixels do not count).
    camera : Camera
        The camera.
    tolerance : float, optional
        Metres.
    step : int, optional
        Test every ``step``-th pixel of every ``step``-th row only (a fraction is estimated
        as well from a quarter of the pixels, in a quarter of the time).

    Returns
    -------
    float
        In [0, 1]; 1 when the model is not in view at all.
    """
    d = np.asarray(depth)
    if step > 1:
        camera, d = camera.subsampled(step), d[::step, ::step]
    rendered, _ = rasterize(transform_points(X_CM, model.vertices), model.triangles, camera)
    on = rendered > 0
    n_model = int(np.count_nonzero(on))
    if n_model == 0:
        return 1.0
    seen = on & (d > 0)
    behind = seen & (d > rendered + tolerance)
    return float(np.count_nonzero(behind)) / max(int(np.count_nonzero(seen)), 1)


def penetration(
    X_CM: npt.ArrayLike,
    model: ModelCloud,
    obstacle: tuple[ModelCloud, FloatArray],
    *,
    tolerance: float = 0.0015,
    samples: int = 600,
) -> float:
    """Fraction of the model's surface samples deeper than ``tolerance`` inside the obstacle.

    Parameters
    ----------
    X_CM : ndarray, shape (4, 4)
        Pose of the model in the camera frame (metres).
    model : ModelCloud
        The model.
    obstacle : (ModelCloud, ndarray of shape (4, 4))
        The other object and its pose ``X_CO`` in the camera frame: two solids cannot overlap.
    tolerance : float, optional
        Metres; contact with some pose noise is not penetration.
    samples : int, optional
        Surface samples tested (every k-th of the sparse samples).
    """
    other, X_CO = obstacle
    X_OM = invert_pose(X_CO) @ np.asarray(X_CM, dtype=np.float64)
    pts = model.points[:: max(1, len(model.points) // samples)]
    pts_O = transform_points(X_OM, pts)
    lo, hi = other.vertices.min(0), other.vertices.max(0)
    near = np.all((pts_O > lo - tolerance) & (pts_O < hi + tolerance), axis=1)
    if not near.any():
        return 0.0
    side, dist, _ = other.inside_samples(pts_O[near])  # signed distance < -tolerance:
    inside = (side < 0) & (dist > tolerance)
    return float(np.count_nonzero(inside)) / len(pts_O)


def register(
    points_C: npt.ArrayLike,
    model: ModelCloud,
    X_CM_init: npt.ArrayLike,
    *,
    max_distance: float | None = None,
    inlier_distance: float = 0.002,
    loss: str = "tukey",
    iterations: int = 30,
    depth: npt.ArrayLike | None = None,
    camera: Camera | None = None,
    coarse: bool = True,
    dense: bool = True,
    obstacle: tuple[ModelCloud, FloatArray] | None = None,
    free_space_tolerance: float = 0.005,
    occluder: npt.ArrayLike | None = None,
    engine: str = "open3d",
) -> Registration:
    """Robust point-to-plane ICP of a model to observed points, from an initial pose.

    Parameters
    ----------
    points_C : ndarray, shape (N, 3)
        Observed points of the object, camera frame, metres.
    model : ModelCloud
        The object's model.
    X_CM_init : ndarray, shape (4, 4)
        Initial pose of the model in the camera frame (metres).
    max_distance : float, optional
        Largest correspondence distance of the first stage (metres; default a quarter of the
        model's diameter); later stages use a third, then a ninth of it (not less than twice
        ``inlier_distance``). The last stage uses the dense samples.
    inlier_distance : float, optional
        Distance (metres) within which a point counts as explained, for the fitness; also the
        scale of the robust kernel in the last stage.
    loss : {"tukey", "huber", "l2"}, optional
        Robust kernel.
    iterations : int, optional
        ICP iterations per stage.
    depth : ndarray, shape (H, W), optional
        The frame's depth (metres) with ``camera``: enables the free-space check.
    camera : Camera, optional
        The camera of ``depth``.
    coarse : bool, optional
        Run the coarse-to-fine schedule; False runs only one stage at ``max_distance`` on the
        dense samples (tracking from a good prediction).
    dense : bool, optional
        Use the dense samples in the last stage (False: sparse only, for quick searches).
    obstacle : (ModelCloud, ndarray of shape (4, 4)), optional
        The other object and its pose in the camera frame: enables the interpenetration
        check (see :func:`penetration`).
    free_space_tolerance : float, optional
        Depth (metres) within which an observed pixel is explained by the model, beyond which
        (behind it) it violates free space: a few standard deviations of the depth noise
        (see :func:`surface_check`).
    occluder : ndarray, shape (H, W), optional
        Depth of the other object rendered at its pose (same window as ``depth``): model
        pixels it hides are not predicted visible.
    engine : {"open3d", "numpy"}, optional
        Open3D's ICP (stops when fitness and RMS change by less than :data:`CONVERGED`), or
        :func:`apo.perception.search.batch_icp` (the same point-to-plane ICP, closest sample
        and kernel in numpy; stops when a step is below 1e-9 rad + m): no Open3D import.

    Returns
    -------
    Registration
    """
    if engine == "numpy":
        return _register_numpy(
            points_C, model, X_CM_init, max_distance=max_distance, inlier_distance=inlier_distance,
            loss=loss, iterations=iterations, coarse=coarse, dense=dense,
            scoring={"depth": depth, "camera": camera, "obstacle": obstacle,
                     "free_space_tolerance": free_space_tolerance, "occluder": occluder},
        )  # fmt: skip
    if engine != "open3d":
        raise ValueError(f"unknown engine {engine!r}; expected 'open3d' or 'numpy'")
    o3d = open3d()
    reg = o3d.pipelines.registration
    P = np.asarray(points_C, dtype=np.float64)
    if len(P) < 3:
        return Registration(np.asarray(X_CM_init, dtype=np.float64), 0.0, np.inf, 1.0, len(P))
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    T = invert_pose(orthonormalised(X_CM_init))  # maps camera points into the model frame
    stages = _stages(model, max_distance, coarse)
    criteria = reg.ICPConvergenceCriteria(
        relative_fitness=CONVERGED, relative_rmse=CONVERGED, max_iteration=iterations
    )
    for k, dist in enumerate(stages):
        dist = max(dist, 2 * inlier_distance)
        last = k == len(stages) - 1
        target = model.dense_pcd if last and dense else model.pcd
        kernel = _kernel(o3d, loss, inlier_distance if last else dist / 2)
        est = reg.TransformationEstimationPointToPlane(kernel)
        T = reg.registration_icp(src, target, dist, T, est, criteria).transformation
    return evaluate(
        P, model, invert_pose(orthonormalised(np.asarray(T))), inlier_distance=inlier_distance,
        depth=depth, camera=camera, obstacle=obstacle,
        free_space_tolerance=free_space_tolerance, occluder=occluder,
    )  # fmt: skip


def _stages(model: ModelCloud, max_distance: float | None, coarse: bool) -> list[float]:
    """Return the correspondence distances of :func:`register`'s stages (coarse to fine)."""
    d0 = max_distance if max_distance is not None else model.diameter / 4
    return [d0, d0 / 3, d0 / 9] if coarse else [d0]


def _register_numpy(
    points_C: npt.ArrayLike, model: ModelCloud, X_CM_init: npt.ArrayLike, *,
    max_distance: float | None, inlier_distance: float, loss: str, iterations: int,
    coarse: bool, dense: bool, scoring: dict[str, Any],
) -> Registration:  # fmt: skip
    """Run :func:`register` with :func:`apo.perception.search.batch_icp` (numpy) as its ICP."""
    from apo.perception.search import batch_icp

    P = np.asarray(points_C, dtype=np.float64)
    if len(P) < 3:
        return Registration(np.asarray(X_CM_init, dtype=np.float64), 0.0, np.inf, 1.0, len(P))
    T = invert_pose(orthonormalised(X_CM_init))[None]
    stages = _stages(model, max_distance, coarse)
    for k, dist in enumerate(stages):
        dist = max(dist, 2 * inlier_distance)
        last = k == len(stages) - 1
        T = batch_icp(P, model, T, distance=dist, scale=inlier_distance if last else dist / 2,
                      iterations=iterations, dense=last and dense, loss=loss, tol=1e-9)  # fmt: skip
    X = invert_pose(orthonormalised(T[0]))
    return evaluate(P, model, X, inlier_distance=inlier_distance, **scoring)


def evaluate(
    points_C: npt.ArrayLike,
    model: ModelCloud,
    X_CM: npt.ArrayLike,
    *,
    inlier_distance: float = 0.002,
    depth: npt.ArrayLike | None = None,
    camera: Camera | None = None,
    obstacle: tuple[ModelCloud, FloatArray] | None = None,
    free_space_tolerance: float = 0.005,
    occluder: npt.ArrayLike | None = None,
    pool: Executor | None = None,
) -> Registration:
    """Score a pose of a model against observed points (and the depth image): a Registration.

    The fitness and RMS residual against the dense samples; with ``depth`` and ``camera``,
    the surface check (the confidence); with ``obstacle``, the penetration. The parameters
    are those of :func:`register`. With ``pool``, the fitness's k-d query and the penetration's
    (which release the GIL) run on a thread of it while this one renders the surface check:
    the same numbers.
    """
    P = np.asarray(points_C, dtype=np.float64)
    X = orthonormalised(X_CM)
    reach = inlier_distance + 2 * model.spacing  # no farther point is an inlier: exact
    P_M = transform_points(invert_pose(X), P)
    fit = pen = None
    if pool is not None:
        model.tree()  # built here, never by two threads
        fit = pool.submit(model.residuals, P_M, max_distance=reach)
        if obstacle is not None:
            obstacle[0].tree()
            obstacle[0].closed()
            pen = pool.submit(penetration, X, model, obstacle)
    surface = None
    if depth is not None and camera is not None:
        surface = surface_check(
            X, model, depth, camera, tolerance=free_space_tolerance, occluder=occluder
        )
    plane, point = model.residuals(P_M, max_distance=reach) if fit is None else fit.result()
    inlier = (plane <= inlier_distance) & (point <= reach)
    fitness = float(np.count_nonzero(inlier)) / max(len(P), 1)
    rmse = float(np.sqrt(np.mean(plane[inlier] ** 2))) if inlier.any() else float("inf")
    if pen is not None:
        depth_in = pen.result()
    else:
        depth_in = penetration(X, model, obstacle) if obstacle is not None else 0.0
    violation = surface.violation if surface is not None else 0.0
    return Registration(X, fitness, rmse, violation, len(P), depth_in, surface)


def register_projective(
    depth: npt.ArrayLike,
    camera: Camera,
    model: ModelCloud,
    X_CM_init: npt.ArrayLike,
    *,
    points_C: npt.ArrayLike,
    mask: npt.ArrayLike | None = None,
    sigma: npt.ArrayLike | None = None,
    start_scale: float = 0.006,
    inlier_distance: float = 0.002,
    iterations: int = 15,
    obstacle: tuple[ModelCloud, FloatArray] | None = None,
    free_space_tolerance: float = 0.005,
    occluder: npt.ArrayLike | None = None,
    clutter: bool = False,
    shared: npt.ArrayLike | None = None,
    outline: bool = False,
    pool: Executor | None = None,
) -> Registration:
    """Projective point-to-plane ICP (:func:`apo.perception.projective.projective_icp`), scored.

    The frame-to-frame registration: the model rendered at the pose pairs each object pixel
    (``mask``) of the depth window with the face visible there. The final Tukey scale of a
    pixel is ``max(inlier_distance, 4.685 sigma)``; the result is scored as :func:`register`'s
    (:func:`evaluate`, on ``points_C``, the object's observed points).

    Parameters
    ----------
    depth : ndarray, shape (H, W)
        The window's depth, metres.
    camera : Camera
        The window's camera.
    model : ModelCloud
    X_CM_init : ndarray, shape (4, 4)
        Start pose (the prediction), camera frame, metres.
    points_C : ndarray, shape (N, 3)
        The object's observed points (for the fitness).
    mask : ndarray of bool, shape (H, W), optional
        The object's pixels.
    sigma : ndarray, shape (H, W), optional
        Depth noise per pixel, metres.
    start_scale : float, optional
        Tukey scale of the first iteration, metres (the prediction's uncertainty).
    inlier_distance, obstacle, free_space_tolerance, occluder : optional
        As :func:`register`'s.
    iterations : int, optional
        Most Gauss-Newton steps.
    clutter : bool, optional
        The mask may hold other things beside the object (depth alone): see
        :func:`apo.perception.projective.projective_icp`.
    shared : ndarray of bool, shape (H, W), optional
        Object pixels within the noise of the occluder's surface (not in ``mask``): see
        :func:`apo.perception.projective.projective_icp`.
    outline : bool, optional
        Add the two-sided outline rows (see :func:`apo.perception.projective.projective_icp`).
    pool : Executor, optional
        Computes the non-penetration rows of each step and scores the fitness and the
        penetration on a thread of it (see :func:`evaluate`): the same numbers.

    A run stops once the steps left are below the tolerance in all (``projective_icp(
    extrapolate=True)``), except with ``clutter``: with depth alone a square peg held by a
    hand (dev seed 2) flipped on 52 frames with it and the environment as aa491ac finds it
    (none with bae1349's environment, none stopping at a step below the tolerance): the
    hand's pixels make those runs fragile.
    """
    constraint = None if obstacle is None else _non_penetration(model, obstacle)
    res = projective_icp(
        depth, camera, model.faces, X_CM_init, mask=mask, sigma=sigma, floor=inlier_distance,
        start_scale=start_scale, iterations=iterations, occluder=occluder,
        constraint=constraint, clutter=clutter, shared=shared,
        extrapolate=not clutter,
        outline=outline, pool=pool,
    )  # fmt: skip
    return evaluate(
        points_C, model, res.X_CM, inlier_distance=inlier_distance, depth=depth, camera=camera,
        obstacle=obstacle, free_space_tolerance=free_space_tolerance, occluder=occluder,
        pool=pool,
    )  # fmt: skip


PENETRATION_ALLOWANCE = 0.0005
"""Depth (metres) a model sample may sit inside the obstacle before the projective ICP pushes it
out (the signed distance to the obstacle's nearest dense sample is approximate at its edges)."""


NON_PENETRATION_REACH = 0.01
"""Only model samples within this (metres) of the obstacle's surface get non-penetration rows
(the k-d tree search stops there, 3 times faster): a sample deeper inside is pushed out by the
shallower samples around it."""


def _non_penetration(
    model: ModelCloud, obstacle: tuple[ModelCloud, FloatArray], *, samples: int = 300
) -> Callable[[FloatArray], tuple[FloatArray, FloatArray, FloatArray]]:
    """Return the rows pushing the model's samples out of the obstacle.

    See ``projective_icp``'s ``constraint``: for a sample ``PENETRATION_ALLOWANCE`` or more
    inside, the residual is its depth along the obstacle's outward normal there (two solids
    cannot overlap: where the parts are hidden inside each other, this is what holds the pose).
    300 samples of the model; the obstacle's dense samples give the normal (its sparse
    samples, a tenth of the time, chose wrong faces near its edges: the 95th percentile of
    the rotation error of variant seed 4 went from 0.8 to 1.4 deg), queried only for the
    samples inside it (:meth:`ModelCloud.inside_samples`: exact for a small closed obstacle).
    """
    other, X_CO = obstacle
    X_OC = invert_pose(X_CO)
    pts = model.points[:: max(1, len(model.points) // samples)]
    lo = other.vertices.min(0) - PENETRATION_ALLOWANCE
    hi = other.vertices.max(0) + PENETRATION_ALLOWANCE
    other.tree()  # built here: ``rows`` may run on another thread
    other.closed()

    def rows(X_CM: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        X_OM = X_OC @ X_CM
        q_O = transform_points(X_OM, pts)
        near = np.nonzero(np.all((q_O > lo) & (q_O < hi), axis=1))[0]
        side, _, idx = other.inside_samples(q_O[near], max_distance=NON_PENETRATION_REACH)
        inside = side < -PENETRATION_ALLOWANCE
        n_M = other.dense_normals[idx[inside]] @ X_OM[:3, :3]  # R_OM^T n_O, row-wise
        return pts[near[inside]], n_M, side[inside] + PENETRATION_ALLOWANCE

    return rows


def _candidate_rotations(points_C: FloatArray, model: ModelCloud) -> list[FloatArray]:
    from scipy.spatial.transform import Rotation

    def axes(P: FloatArray) -> FloatArray:
        _, _, vt = np.linalg.svd(P - P.mean(0), full_matrices=False)
        R = vt.T
        if np.linalg.det(R) < 0:
            R[:, 2] = -R[:, 2]
        return np.asarray(R)

    R_obs = axes(points_C)
    R_mod = axes(model.points)
    cube = Rotation.create_group("O").as_matrix()
    ico = Rotation.create_group("I").as_matrix()
    out = [R_obs @ g @ R_mod.T for g in cube]
    out += list(ico)
    return out


def distinct_up_to_symmetry(
    rotations: list[FloatArray], symmetry_rotations: npt.ArrayLike | None, *, angle: float = 0.2
) -> list[FloatArray]:
    """Drop candidate orientations that a symmetry of the model maps near an earlier one.

    ``R`` and ``R @ S`` (``S`` a symmetry's rotation, model frame) show the same object, so a
    search needs one of them: of the 84 candidates, 36 remain for a T-peg (2 symmetries)
    and 21 for a square peg (8). ``angle`` (radians) is the distance below which two are the same.
    """
    if symmetry_rotations is None:
        return rotations
    S = np.asarray(symmetry_rotations, dtype=np.float64).reshape(-1, 3, 3)
    if len(S) <= 1:
        return rotations
    limit = 1.0 + 2.0 * np.cos(angle)  # trace of a rotation by ``angle``
    kept: list[FloatArray] = []
    for R in rotations:
        twins = np.einsum("ij,kjl->kil", R, S)  # (K, 3, 3)
        if any(
            np.max(np.einsum("kji,ji->k", twins, Q)) > limit for Q in kept
        ):  # trace(twin^T Q) > limit: within ``angle``
            continue
        kept.append(R)
    return kept


COARSE_POINTS = 150
"""Points (evenly spread) on which every candidate of the global search is advanced first."""
REFINE_POINTS = 3000
"""Points (evenly spread) on which the global search's best candidates are refined."""
CANDIDATES = 32
"""Distinct candidates of the global search scored on the depth image."""


def initialise(
    points_C: npt.ArrayLike,
    model: ModelCloud,
    *,
    depth: npt.ArrayLike | None = None,
    camera: Camera | None = None,
    inlier_distance: float = 0.002,
    loss: str = "tukey",
    max_points: int = 400,
    keep: int = 3,
    seed: int | np.random.Generator | None = 0,
    obstacle: tuple[ModelCloud, FloatArray] | None = None,
    free_space_tolerance: float = 0.005,
    symmetry_rotations: npt.ArrayLike | None = None,
    occluder: npt.ArrayLike | None = None,
    polish: Callable[[FloatArray], Registration | None] | None = None,
    rank: Callable[[Registration], tuple[float, float]] | None = None,
    polish_below: float = np.inf,
    polish_finalists: bool = False,
    pool: Executor | None = None,
) -> Registration:
    """Find a model's pose from its observed points without an initial guess.

    Every candidate orientation (see the module notes) is placed with the model's centroid
    behind the points' centroid along the viewing ray and refined by a short ICP on at most
    ``max_points`` points; the ``keep`` most confident (fitness, free space, penetration) are
    refined on all points, and the most confident is returned.

    Parameters
    ----------
    points_C : ndarray, shape (N, 3)
        Observed points of the object, camera frame, metres.
    model : ModelCloud
        The object's model.
    depth, camera : optional
        The frame's depth (metres) and camera, for the free-space check.
    inlier_distance : float, optional
        Metres, see :func:`register`.
    loss : {"tukey", "huber", "l2"}, optional
        Robust kernel.
    max_points : int, optional
        Points used for the candidate search.
    keep : int, optional
        Candidates refined fully.
    seed : int or Generator or None, optional
        Seed of the point subsampling.
    obstacle : (ModelCloud, ndarray of shape (4, 4)), optional
        The other object and its pose: candidates that penetrate it lose confidence.
    free_space_tolerance : float, optional
        See :func:`register`.
    symmetry_rotations : ndarray, shape (K, 3, 3), optional
        Rotations of the model's symmetries (:func:`apo.symmetry.symmetries`): candidate
        orientations that differ by one are tried once (:func:`distinct_up_to_symmetry`).
    occluder : ndarray, shape (H, W), optional
        See :func:`register`.
    polish : callable, optional
        ``polish(X_CM) -> Registration or None``: the caller's own registration from a
        pose (the tracker's projective ICP with per-pixel ownership, on a window of the
        frame); run from the :data:`POLISHED` most plausible candidates once they are
        scored, its results compete with the refined ones. Without the colour, the
        closest-point ICP of the search is pulled by the hand's points near the part.
    polish_below : float, optional
        ``polish`` runs only when the most plausible refined candidate ranks below this
        (default: always). With the colour the closest-point refinement is usually good,
        but the hand's and the table's points near the part can leave the true candidate
        a few millimetres off and ranked below a wrong one (dev variant 213, a T-peg held
        by a hand: 2.6 mm off, plausibility 0.935 against 0.937 for one turned 85 deg about
        its axis; polished 0.956).
    polish_finalists : bool, optional
        ``polish`` the ``keep`` candidates refined on all points (from their refined poses)
        instead of the :data:`POLISHED` most plausible ones before that refinement (which
        the hand's points can pull off the part without the colour).
    rank : callable, optional
        ``rank(registration) -> tuple``, greater is better: how candidates are ranked
        (default :func:`plausibility`; :func:`whole_plausibility` for an object that is all
        of its points).
    pool : Executor, optional
        A thread for half of the batched ICP's candidates (:func:`batch_icp`) and the
        candidates' fitness queries (:func:`evaluate`) meanwhile: the same result.

    Returns
    -------
    Registration
        The most plausible candidate (any of its symmetric twins).
    """
    from apo.perception.search import centres

    P = np.asarray(points_C, dtype=np.float64)
    if len(P) < 10:
        return Registration(np.eye(4), 0.0, np.inf, 1.0, len(P))
    rank = rank or plausibility
    rng = np.random.default_rng(seed)
    score: dict[str, Any] = {"inlier_distance": inlier_distance, "depth": depth, "camera": camera,
             "obstacle": obstacle, "free_space_tolerance": free_space_tolerance,
             "occluder": occluder}  # fmt: skip
    search: dict[str, Any] = {"loss": loss, "max_points": max_points, "keep": keep, "rng": rng,
              "symmetry_rotations": symmetry_rotations, "polish": polish, "rank": rank,
              "polish_below": polish_below, "polish_finalists": polish_finalists,
              "pool": pool}  # fmt: skip
    found = centres(P, model.diameter)
    if len(found) == 1:
        return _search(P, model, score, **search)
    # Points spread far wider than the model (a hand and forearm in view when the colour
    # is not used): a search about each dense cluster, on the points near it.
    best: Registration | None = None
    for c in found:
        near = P[np.linalg.norm(P - c, axis=1) <= 0.75 * model.diameter]
        if len(near) < 10:
            continue
        r = _search(near, model, score, **search)
        if best is None or rank(r) > rank(best):
            best = r
    assert best is not None
    return best


def plausibility(r: Registration, visible_min: float = VISIBLE_MIN) -> tuple[float, float]:
    """Rank of poses of one frame: the confidence, less a little for the outline continued.

    ``(confidence - CONTINUED_WEIGHT * continued - HIDDEN_WEIGHT * (1 - visible),
    quality)``: among poses the depth explains about equally well, the one whose outline
    shows depth jumps (a part held by a hand) before one inside a larger object whose faces
    run on past its silhouette (:attr:`SurfaceCheck.continued`, which lowers the
    confidence itself only beyond :data:`CONTINUED_FREE`), and the one with more of its
    surface in view (:attr:`SurfaceCheck.visible`) before one hidden behind something.
    ``visible_min``: see :meth:`Registration.confidence_at`.
    """
    c = r.confidence_at(visible_min)
    if r.surface is None:
        return (c, r.quality)
    s = r.surface
    rank = c - CONTINUED_WEIGHT * s.continued - HIDDEN_WEIGHT * (1.0 - s.visible)
    return (rank, r.quality)


def whole_plausibility(r: Registration) -> tuple[float, float]:
    """Rank of poses of an object that is all of the points: :func:`plausibility` times fitness.

    The environment registered on its static pixels: among poses whose predicted-visible
    surface the depth explains about equally well, the one that explains more of the points.
    A box seen from above fits its top and one side with a side face on the top and the rest
    hidden below the table (every surface it shows explained, a third of the points), and
    :func:`plausibility` alone cannot tell it from the truth (variant seed 206: 0.991 against
    0.990, fitness 0.30 against 1.0).
    """
    rank, quality = plausibility(r)
    return (rank * r.fitness, quality)


POLISHED = 8
"""Candidates of the global search refined by the caller's ``polish`` (see :func:`initialise`)."""


def _search(
    P: FloatArray,
    model: ModelCloud,
    score: dict[str, Any],
    *,
    loss: str,
    max_points: int,
    keep: int,
    rng: np.random.Generator,
    symmetry_rotations: npt.ArrayLike | None,
    polish: Callable[[FloatArray], Registration | None] | None = None,
    rank: Callable[[Registration], tuple[float, float]] = plausibility,
    polish_below: float = np.inf,
    polish_finalists: bool = False,
    pool: Executor | None = None,
) -> Registration:
    """Run the coarse-to-fine search of :func:`initialise` about the centroid of ``P``."""
    from apo.perception.search import batch_icp, distinct_poses, inlier_fraction, voxel_subsample

    inlier_distance = score["inlier_distance"]
    few = voxel_subsample(P, min(max_points, COARSE_POINTS), rng)
    sub = voxel_subsample(P, max_points, rng)
    full = voxel_subsample(P, max(max_points, REFINE_POINTS), rng)
    # Every candidate orientation about the points' centroid pushed back along the ray (the
    # visible surface is nearer than the model's centroid: a sixth and a third of its size).
    c = P.mean(0)
    ray = c / np.linalg.norm(c)
    rotations = distinct_up_to_symmetry(_candidate_rotations(P, model), symmetry_rotations)
    starts = []
    for offset in (model.diameter / 6, model.diameter / 3):
        for R in rotations:
            X = np.eye(4)
            X[:3, :3] = R
            X[:3, 3] = c + ray * offset - R @ model.centroid
            starts.append(invert_pose(X))
    T = np.stack(starts)
    d0 = model.diameter / 4
    for dist in (d0, d0 / 3):  # coarse: every candidate, few points, sparse samples
        dist = max(dist, 2 * inlier_distance)
        T = batch_icp(
            few, model, T, distance=dist, scale=dist / 2, iterations=10, loss=loss, pool=pool
        )
    # The best distinct results on more points; then scored on the depth image.
    order = np.argsort(-inlier_fraction(sub, model, T, 2 * inlier_distance), kind="stable")
    T = T[distinct_poses(T[order], model, symmetry_rotations, limit=CANDIDATES)]
    for dist in (d0 / 9, d0 / 27):
        dist = max(dist, 2 * inlier_distance)
        T = batch_icp(
            sub, model, T, distance=dist, scale=inlier_distance, iterations=15, loss=loss, pool=pool
        )
    scored = [evaluate(sub, model, invert_pose(t), pool=pool, **score) for t in T]
    ranked_all = sorted(range(len(T)), key=lambda k: rank(scored[k]), reverse=True)
    ranked = ranked_all[:keep]
    to_polish = T[ranked_all[:POLISHED]]
    # The most confident, on all points (at most REFINE_POINTS, evenly spread), dense samples.
    T = T[ranked]
    d1 = model.diameter / 12
    for k, dist in enumerate((d1, d1 / 3, d1 / 9)):
        dist = max(dist, 2 * inlier_distance)
        last = k == 2
        T = batch_icp(
            full, model, T, distance=dist, scale=inlier_distance if last else dist / 2,
            iterations=30, dense=last, loss=loss, pool=pool,
        )  # fmt: skip
    best = [evaluate(full, model, invert_pose(t), pool=pool, **score) for t in T]
    if polish is not None and rank(max(best, key=rank))[0] < polish_below:
        starts = [r.X_CM for r in best] if polish_finalists else [invert_pose(t) for t in to_polish]
        best += [r for r in map(polish, starts) if r is not None]
    return max(best, key=rank)
