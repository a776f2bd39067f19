"""Track both objects through a recorded sequence: frames -> poses (paper section 4.2).

:func:`track_frames` runs the whole front end:

1. **Object pixels** of each frame: background subtraction (recorded background, or the
   support plane fitted to the first frame) and the objects' colour
   (:mod:`apo.perception.segment`).
2. **Occupancy histogram** over up to ``histogram_frames`` evenly spaced frames: the pixels
   occupied in most frames are the environment's (it does not move).
3. **Environment pose, from many frames at once**: the per-pixel median depth of the
   environment's pixels over those frames (noise averaged, the grasped object's passages
   removed) is registered to the environment model (robust ICP, or global initialisation
   when no initial pose is given).
4. **Grasped object, frame by frame**: object pixels not explained by the environment model
   (rendered once at its pose), in an image window around the predicted pose (constant
   velocity from the previous two frames), are registered to the grasped model by the
   projective ICP (:func:`apo.perception.register.register_projective`) from the
   prediction; when its result is not good, by Open3D's robust ICP from the prediction (once
   more from its result when it moved far: it may have stopped on its iteration limit),
   then from the last pose, then coarse-to-fine, until a result is confident
   (``good_confidence``). The next frame's PNGs are decoded in a background
   thread meanwhile.
5. **Lost tracking**: a frame whose confidence is below ``min_confidence`` (or with too few
   points) is re-initialised globally; if that fails too, the frame is marked lost
   (pose NaN, ``lost`` True) and never reported as a pose.
6. **Smoothing** (``smooth``, default on): once every frame is tracked, each pose is
   re-estimated from the frames on both sides (:mod:`apo.perception.smoothing`), keeping
   the jumps and kinks of contacts sharp.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from apo.errors import TrackingLostError
from apo.perception.environment import refine_environment, surface_depth
from apo.perception.frames import Camera, FrameSource, masked_median, open_frames
from apo.perception.register import (
    VISIBLE_MIN,
    ModelCloud,
    Registration,
    evaluate,
    initialise,
    orthonormalised,
    plausibility,
    register,
    register_projective,
    whole_plausibility,
)
from apo.perception.render import mesh_triangles, rasterize
from apo.perception.segment import (
    ColourModel,
    DepthNoiseModel,
    Plane,
    estimate_depth_noise,
    fit_support_plane,
    foreground_from_background,
    foreground_from_plane,
    grasped_mask,
    learn_colour,
    static_mask,
)
from apo.perception.smoothing import smooth_poses
from apo.spatial import invert_pose, transform_points
from apo.symmetry import Symmetry, nearest_twin, symmetries
from apo.typing import BoolArray, FloatArray

__all__ = ["TrackOptions", "TrackResult", "track_frames"]

VISIBLE_DROP = 0.5
"""A tracked pose's visible share (:attr:`apo.perception.register.SurfaceCheck.visible`) may
fall to this fraction of its median over the last tracked frames before it lowers the
confidence (below :data:`apo.perception.register.VISIBLE_MIN`; see :func:`tracked_visible_min`)."""


@dataclass(frozen=True)
class TrackOptions:
    """Settings of :func:`track_frames` (lengths in metres).

    Attributes
    ----------
    colour : ColourModel or None
        Colour of the two objects, a cue besides the depth. None (default): learnt from the
        recording, from the environment's pixels once the environment is found by depth
        alone (:func:`learn_colour`; the two parts are assumed to share a colour, as in the
        paper, whose parts were white). :meth:`ColourModel.any_colour`: depth alone (the
        colour images are then not decoded).
    foreground_threshold : float
        A pixel is in front of the background (or above the support plane) by more than this.
    environment_threshold : float
        A pixel within this depth of the rendered environment model is the environment's.
    static_fraction : float
        Occupancy above which a pixel is the environment's (occupancy histogram).
    same_surface_fraction : float
        ... and the share of the frames in which it must show the same surface (its median
        depth within ``noise_sigmas`` noise sigmas, at least ``environment_threshold``): a
        hand and forearm moving slowly occupy pixels as often as the environment does, at
        changing depths (0.6 and 0.7 lost the environment's pixels hidden part of the time
        behind the moving part: up to 1.2 mm of error on the variants, measured).
    behind_frames : int
        ... and it is not the environment's when this many frames measured it farther than
        that surface by more than the same bound: nothing is ever seen behind a fixed
        object (one frame can be a flying pixel at a depth edge). A grasped part held over
        the environment for most of the recording is static by both tests above.
    histogram_frames : int
        Frames (evenly spaced) used for the histogram and the environment's pose.
    inlier_distance : float
        Distance within which an observed point is explained by a model (fitness).
    min_confidence : float
        Below this a frame is re-initialised, then marked lost.
    good_confidence : float
        Below this, the frame-to-frame registration also tries the last pose and the
        coarse-to-fine schedule, and keeps the most confident result (at 0.95 a pose
        1.2 deg off with confidence 0.97 was kept where the motion turned; 0.98 costs
        nothing more on the benchmark, whose frames score 0.99 and above).
    track_distance : float
        Correspondence distance of the frame-to-frame ICP (from the predicted pose).
    rmse_factor : float
        A frame-to-frame result is good only if its RMS residual is at most this times the
        median of the last 10 tracked frames' (besides ``good_confidence``): a pose 1.5 deg
        off after a 27 deg turn in one frame scored 0.993 but fitted at 0.45 mm RMS against
        0.17 mm before.
    settle_distance : float
        When the frame-to-frame ICP moves a model vertex farther than this from the
        prediction, it is run once more from its result (it may have stopped on its
        iteration limit short of the minimum: 1.7 mm off, measured, in fast motion).
    start_factor : float or None
        The projective ICP's first Tukey scale from the prediction is this many times the
        largest prediction error of the last three frames (how far the tracked pose was
        from the prediction), within the reach (``track_distance``, or three inlier
        distances) and at least the noise's scale (the ICP's final scale): the
        prediction's own uncertainty, not the reach's. Started at the reach, the scale
        took two halvings to come down to the noise's. Not with depth alone (see
        ``_Tracker.start_scale``). None: always the reach.
    min_points : int
        Fewer observed points than this: the object is not visible (lost).
    max_points : int
        Observed points of the grasped object used per frame (random subset).
    loss : {"tukey", "huber", "l2"}
        Robust kernel of the ICP.
    noise : float or None
        ``c`` of the depth noise ``sigma(z) = c z^2`` (metres per square metre); None:
        estimated from the recording (:func:`apo.perception.segment.estimate_depth_noise`).
    noise_sigmas : float
        Thresholds in units of the noise: a pixel is foreground when it is more than this
        many standard deviations (of the difference) in front of the background or above the
        plane, the environment's when within as many of its rendering, and a point is
        explained (fitness) within ``0.75`` of as many of the model. The fixed thresholds
        above are the floors (calibration and model errors do not shrink with the noise).
    surface_tolerance : float
        Floor of the depth tolerance within which an observed pixel explains the model's
        rendered surface (the confidence; otherwise ``noise_sigmas`` noise sigmas).
    smooth : bool
        Smooth the grasped object's poses over neighbouring frames once all are tracked
        (:func:`apo.perception.smoothing.smooth_poses`: local constant-velocity fits on
        windows of up to 7 frames, the best-fitting window containing the frame, so that
        jumps and kinks at contacts stay sharp); False: each frame's own registration.
    refine_environment : bool
        Refine the environment's pose, once found, by the projective ICP on the mean depth of
        its pixels over the histogram's frames (:mod:`apo.perception.environment`); False:
        the closest-point ICP's pose on their median depth, as before session 4.
    projective : bool
        Register frame to frame by projective point-to-plane ICP first
        (:func:`apo.perception.register.register_projective`); the Open3D closest-point ICP
        from the prediction, the last pose and coarse-to-fine only when its result is not good.
    seed : int
        Seed of every random choice (subsampling, RANSAC).
    environment_confidence : float
        The environment found without ``init_environment`` (a global search's guess) is
        accepted only at this confidence or more; below it, the next static regions are
        searched too, then it is an error asking for ``--init-environment``. Found right,
        the development variants' environments score 0.99 to 1.00; found wrong, 0.87 to 0.90
        (session 5, dev seeds 21 and 34: 26 and 67 mm off); a given pose needs
        ``min_confidence``.
    """

    colour: ColourModel | None = None
    foreground_threshold: float = 0.004
    environment_threshold: float = 0.004
    static_fraction: float = 0.7
    same_surface_fraction: float = 0.5
    behind_frames: int = 2
    histogram_frames: int = 30
    inlier_distance: float = 0.002
    min_confidence: float = 0.8
    good_confidence: float = 0.98
    track_distance: float = 0.006
    settle_distance: float = 0.002
    start_factor: float | None = 3.0
    rmse_factor: float = 2.0
    min_points: int = 60
    max_points: int = 1500
    loss: str = "tukey"
    noise: float | None = None
    noise_sigmas: float = 4.0
    surface_tolerance: float = 0.003
    projective: bool = True
    seed: int = 0
    refine_environment: bool = True
    smooth: bool = True
    environment_confidence: float = 0.95


@dataclass(frozen=True)
class TrackResult:
    """Poses of the two objects through a sequence (metres).

    Attributes
    ----------
    times : ndarray, shape (N,)
        Seconds.
    X_CG : ndarray, shape (N, 4, 4)
        Grasped object in the camera frame; NaN where ``lost``; smoothed over neighbouring
        frames unless ``TrackOptions.smooth`` is False.
    X_CE : ndarray, shape (4, 4)
        Environment object in the camera frame (static: one pose for the whole sequence).
    X_EG : ndarray, shape (N, 4, 4)
        Grasped object in the environment frame, ``inv(X_CE) @ X_CG``; NaN where ``lost``.
    confidence : ndarray, shape (N,)
        Per-frame confidence of the grasped object's pose, in [0, 1].
    lost : ndarray of bool, shape (N,)
        Frames where the grasped object could not be tracked.
    environment_confidence : float
        Confidence of ``X_CE``.
    X_WC : ndarray, shape (4, 4), or None
        The camera in the world frame, from ``camera.json``.
    reinitialised : ndarray of bool, shape (N,)
        Frames where the global search ran because tracking from the previous pose failed
        (not the first frame's own initialisation when no initial pose was given).
    grasped_symmetries, environment_symmetries : tuple of Symmetry
        The models' rigid symmetries (:func:`apo.symmetry.symmetries`; the identity first).
        Every pose is the twin nearest the previous frame's (see :func:`track_frames`).
    """

    times: FloatArray
    X_CG: FloatArray
    X_CE: FloatArray
    X_EG: FloatArray
    confidence: FloatArray
    lost: BoolArray
    environment_confidence: float
    X_WC: FloatArray | None = None
    reinitialised: BoolArray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    grasped_symmetries: tuple[Symmetry, ...] = ()
    environment_symmetries: tuple[Symmetry, ...] = ()

    @property
    def reinitialisations(self) -> int:
        """Number of frames where tracking was re-initialised by the global search."""
        return int(np.count_nonzero(self.reinitialised))


def _twin(
    X: FloatArray, ref: FloatArray | None, syms: tuple[Symmetry, ...], model: ModelCloud
) -> FloatArray:
    """Return the symmetric twin of ``X`` nearest ``ref``; without ``ref``, the canonical twin.

    The canonical twin (first frame without an initial pose) is the one whose axes are
    nearest the camera's (smallest rotation angle from the camera frame, at the pose's own
    position); ties go to the lowest symmetry index. Distances weigh a rotation by the
    model's half-diameter (the displacement of its far points).
    """
    if len(syms) <= 1:
        return X
    if ref is None:
        ref = np.eye(4)
        ref[:3, 3] = X[:3, 3]
    return nearest_twin(X, ref, list(syms), length=model.diameter / 2)[0]


def _displacement(model: ModelCloud, X_a: FloatArray, X_b: FloatArray) -> float:
    """Largest distance (metres) a model vertex moves between two poses."""
    moved = transform_points(X_b, model.vertices) - transform_points(X_a, model.vertices)
    return float(np.linalg.norm(moved, axis=1).max())


def _noise_model(src: FrameSource, options: TrackOptions) -> DepthNoiseModel:
    """Return the recording's depth noise: given (``options.noise``) or estimated from 6 frames."""
    q = float(getattr(src.camera, "depth_scale", 0.0))
    if options.noise is not None:
        return DepthNoiseModel(float(options.noise), q)
    n = len(src)
    if n < 2:
        return DepthNoiseModel(1.5e-3, q)  # one frame: a typical structured-light sensor
    idx = np.unique(np.linspace(0, n - 1, min(n, 6)).round().astype(int))
    try:
        return estimate_depth_noise(np.stack([src.depth(int(i)) for i in idx]), quantum=q)
    except ValueError:
        return DepthNoiseModel(1.5e-3, q)


class _Segmenter:
    """Object pixels of a frame: in front of the background and above the support plane.

    The support plane is fitted robustly (RANSAC, then least squares on its inliers) to the
    background depth when given, else to the first frame; a pixel is an object's when it is
    above the plane by more than the threshold (in noise sigmas) and, with a background,
    also in front of it: either test alone lets the far table's noise through.
    """

    def __init__(self, src: FrameSource, options: TrackOptions, noise: DepthNoiseModel) -> None:
        self.camera = src.camera
        self.options = options
        self.noise = noise
        # Depth alone until the colour is learnt (options.colour None: see learn_colour).
        self.colour = options.colour or _ANY
        _, bg_depth = src.background()
        self.background = bg_depth
        # The difference of a depth and the background's: sqrt(1 + pi / 2n) sigma for the
        # median of n background frames (sqrt(2) for one).
        n_bg = max(int(getattr(src, "background_count", 1)), 1)
        self.difference = float(np.sqrt(1.0 + (1.0 if n_bg == 1 else np.pi / (2 * n_bg))))
        d0 = bg_depth if bg_depth is not None else src.depth(0)
        pts = self.camera.backproject(d0)
        self.plane: Plane | None = None
        if len(pts) >= 3:
            z = float(np.median(pts[:, 2]))
            self.plane = fit_support_plane(
                pts[:: max(1, len(pts) // 20000)],
                threshold=max(0.003, 3.0 * float(noise.sigma(z))),
                seed=options.seed,
            )

    def threshold(self, depth: npt.NDArray[np.float32], floor: float, k: float) -> FloatArray:
        """Per-pixel threshold: ``k`` noise standard deviations at the depth, at least ``floor``."""
        return np.maximum(floor, k * self.options.noise_sigmas * self.noise.sigma(depth))

    def objects(
        self,
        rgb: npt.NDArray[np.uint8],
        depth: npt.NDArray[np.float32],
        window: Window | None = None,
    ) -> BoolArray:
        """Object pixels (of the window when given: all arrays are of the whole frame)."""
        t = self.options.foreground_threshold
        cam, bg = self.camera, self.background
        if window is not None:
            u0, v0, w, h = window
            rgb = rgb[v0 : v0 + h, u0 : u0 + w]
            depth = depth[v0 : v0 + h, u0 : u0 + w]
            cam = cam.crop(u0, v0, w, h)
            if bg is not None:
                bg = bg[v0 : v0 + h, u0 : u0 + w]
        fg = depth > 0
        if self.plane is not None:
            fg = foreground_from_plane(
                depth, cam, self.plane, threshold=self.threshold(depth, t, 1)
            )
        if bg is not None:  # the difference of two noisy depths
            thr = self.threshold(depth, t, self.difference)
            fg &= foreground_from_background(depth, bg, threshold=thr)
        if not self.colour.used:
            return fg
        # The colour test only where the depth found something (a fraction of the pixels).
        out = np.zeros(fg.shape, dtype=bool)
        out[fg] = self.colour.mask(rgb[fg][:, None, :])[:, 0]
        return out


_ANY = ColourModel.any_colour()

Window = tuple[int, int, int, int]
_Frame = tuple[npt.NDArray[np.uint8], npt.NDArray[np.float32]]


def _window(cam: Camera, X_CM: FloatArray, model: ModelCloud, margin: float) -> Window | None:
    """Image window ``(u0, v0, width, height)`` of a model's bounding box grown by ``margin``."""
    lo, hi = model.vertices.min(0) - margin, model.vertices.max(0) + margin
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    P = transform_points(X_CM, corners)
    if np.any(P[:, 2] <= 0.01):
        return None
    uv = cam.project(P)
    u0 = int(max(np.floor(uv[:, 0].min()), 0))
    v0 = int(max(np.floor(uv[:, 1].min()), 0))
    u1 = int(min(np.ceil(uv[:, 0].max()) + 1, cam.width))
    v1 = int(min(np.ceil(uv[:, 1].max()) + 1, cam.height))
    if u1 - u0 < 2 or v1 - v0 < 2:
        return None
    return u0, v0, u1 - u0, v1 - v0


def _histogram_indices(n: int, options: TrackOptions) -> list[int]:
    """Return the frames of the occupancy histogram: up to ``histogram_frames``, evenly spaced."""
    idx = np.unique(np.linspace(0, n - 1, min(n, options.histogram_frames)).round().astype(int))
    return [int(i) for i in idx]


def _prefetch(pool: Executor, src: FrameSource, options: TrackOptions) -> dict[int, Future[_Frame]]:
    """Start decoding the histogram's frames in ``pool`` (Pillow releases the GIL)."""
    colour = options.colour != _ANY
    return {
        i: pool.submit(_read, src, i, colour=colour) for i in _histogram_indices(len(src), options)
    }


def _environment_points(
    src: FrameSource, seg: _Segmenter, options: TrackOptions, cache: dict[int, _Frame],
    prefetch: dict[int, Future[_Frame]] | None = None, *, reach: float = 0.0,
) -> tuple[list[FloatArray], npt.NDArray[np.float32], npt.NDArray[np.float32]]:  # fmt: skip
    """Return the static regions' points (median depth of their pixels) and two depths.

    The median of every pixel over at most 9 frames (for the surface check), and the
    static pixels' surface depth over all the frames (:func:`surface_depth`; 0 elsewhere).

    The regions are groups of connected components of the static pixels, largest first
    (:func:`_object_groups`, at most 3): the largest and every component whose centroid is
    within ``reach`` (the environment's diameter) of its centroid. The environment's image
    can be in pieces (a slot's two sides, when the part passing between them is not static
    and the block below the slot is within the support plane's threshold), and one piece
    fits the model at a wrong pose as well as at the true one. The frames decoded are kept
    in ``cache`` for the tracking loop
    (decoded once); those in ``prefetch`` (:func:`_prefetch`) are taken from there.
    """
    idx = _histogram_indices(len(src), options)
    masks = np.empty((len(idx), src.camera.height, src.camera.width), dtype=bool)
    depths = np.empty(masks.shape, dtype=np.float32)
    pending = prefetch or {}
    for k, i in enumerate(idx):
        frame = pending.pop(i).result() if i in pending else None
        rgb, depth = cache[i] = frame or _read(src, i, colour=options.colour != _ANY)
        masks[k] = seg.objects(rgb, depth)
        depths[k] = depth
    measured = np.maximum((depths > 0).sum(axis=0), 1)  # frames with a depth, per pixel
    static = _static(masks, measured, options.static_fraction)
    median = np.zeros(static.shape, dtype=np.float32)
    median[static] = _static_surface(
        depths[:, static], masks[:, static], measured[static],
        lambda d: seg.threshold(d, options.environment_threshold, 1), options.same_surface_fraction,
        options.behind_frames,
    )  # fmt: skip
    # For the surface check: every pixel, over at most 9 of the frames (the sort is the cost).
    few = depths[:: max(1, -(-len(depths) // 9))]
    median_all = masked_median(few, few > 0)
    regions = _object_groups(static & (median > 0), median, src.camera, reach, share=0.1)
    return regions, median_all, surface_depth(depths, median > 0, seg.noise)


def _static_surface(
    d_s: npt.NDArray[np.float32], m_s: BoolArray, measured: npt.NDArray[np.int64],
    bound: Callable[[npt.NDArray[np.float32]], FloatArray], same_fraction: float,
    behind_frames: int,
) -> npt.NDArray[np.float32]:  # fmt: skip
    """Return the static pixels' median depth, 0 where they are not one fixed surface.

    ``d_s``, ``m_s``: the depth and the object mask of the static pixels in each histogram
    frame, shape ``(frames, pixels)``; ``measured``: how many frames measured each;
    ``bound(depth)``: the noise's bound of a depth difference. The median is over the
    frames where the pixel is an object's (noise averaged; passages removed), sorted at
    those pixels only (a tenth of the image or less). Two tests:

    - the same surface (within ``bound``) in ``same_fraction`` of the frames measured, not
      only something in front of the table: a hand and forearm that move slowly are
      occupied as often as the environment (without the colour cue), but at changing
      depths;
    - never seen behind: the environment does not move, so no frame can measure a pixel
      farther than its surface by more than the noise's bound, unless the sensor erred
      there (a flying pixel at a depth edge); seen so in ``behind_frames`` frames, the
      surface was something that moved away (a grasped part held over the environment
      for most of the recording, occupied and at about the same depth in most frames:
      independent recording 5's T-peg, 6 % of the static points, and the U-block found
      upside down because that pose's fitness covered them).
    """
    med = masked_median(d_s, m_s)
    thr = bound(med)
    same = (m_s & (np.abs(d_s - med) <= thr)).sum(axis=0) >= same_fraction * measured
    behind = (d_s > med + thr).sum(axis=0) >= behind_frames
    return np.where(same & ~behind, med, 0.0).astype(np.float32)


def _static(masks: BoolArray, measured: npt.NDArray[np.int64], fraction: float) -> BoolArray:
    """Pixels occupied in at least ``fraction`` of the frames, the outline's among those measured.

    The sensor drops most pixels at a depth edge (both sides of the jump), so the static
    region's outline pixels are occupied in few frames although every frame that measures
    them sees the surface: counted over all frames, the environment's outline is eroded by
    a pixel (and its silhouette's position is then a pixel off on that side). A pixel
    next to the region is static when it is occupied in ``fraction`` of the frames that
    measured it; elsewhere a frame without a depth counts as unoccupied (nothing within
    the sensor's range: a forearm passing in front of a far background). ``measured``: how
    many frames measured each pixel.
    """
    from scipy import ndimage

    occupied = masks.sum(axis=0)
    static = static_mask(occupied / len(masks), static_fraction=fraction)
    ring = ndimage.binary_dilation(static, structure=np.ones((3, 3), dtype=bool)) & ~static
    return np.asarray(static | (ring & (occupied >= fraction * measured)), dtype=bool)


NO_COLOUR = np.zeros((0, 0, 3), dtype=np.uint8)
"""The colour image of a frame when the colour model is not used (the PNG is not decoded)."""


def _read(
    src: FrameSource, i: int, cache: dict[int, _Frame] | None = None, *, colour: bool = True
) -> _Frame:
    """Return frame ``i``'s colour (:data:`NO_COLOUR` unless ``colour``) and depth images."""
    if cache is not None and i in cache:
        return cache.pop(i)
    return (src.rgb(i) if colour else NO_COLOUR), src.depth(i)


def _as_pose(X: npt.ArrayLike | None, name: str) -> FloatArray | None:
    if X is None:
        return None
    M = np.asarray(X, dtype=np.float64)
    if M.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 pose, got shape {M.shape}")
    return M


def _in_gate(points: FloatArray, centre: FloatArray, radius: float) -> BoolArray:
    """Which points are within ``radius`` of ``centre`` (gating around a prediction)."""
    return np.asarray(np.einsum("ij,ij->i", points - centre, points - centre) <= radius * radius)


def _object_groups(
    mask: BoolArray, depth: npt.NDArray[np.float32], camera: Camera, reach: float,
    *, limit: int = 3, share: float = 0.25,
) -> list[FloatArray]:  # fmt: skip
    """Return the points of the largest components, each with the components near it (3-D).

    The global path has no prediction to gate with. The first group is the largest
    connected component and every other one (of at least 5 % of its size) whose centroid is
    within ``reach`` (the model's diameter) of its centroid: a hand across the part cuts its
    image in two, and the largest piece alone is ambiguous. The next groups start from the
    largest components left (at least ``share`` of the largest; at most ``limit`` groups):
    without the colour, a forearm whose depth jumps away from the hand is the largest
    component, the hand and the part it holds the second.
    """
    from scipy import ndimage

    labels, n = ndimage.label(mask & (depth > 0))
    pts = camera.backproject(depth, labels > 0)
    if n <= 1:
        return [pts]
    lab = labels[labels > 0]  # the same row-major order as the points
    sizes = np.bincount(lab, minlength=n + 1).astype(np.float64)
    sizes[0] = 0.0
    centroids = (
        np.stack([np.bincount(lab, weights=pts[:, k], minlength=n + 1) for k in range(3)], axis=1)
        / np.maximum(sizes, 1.0)[:, None]
    )
    groups: list[FloatArray] = []
    left = sizes.copy()
    while len(groups) < limit:
        big = int(np.argmax(left))
        if left[big] <= 0 or (groups and left[big] < share * sizes.max()):
            break
        near = np.linalg.norm(centroids - centroids[big], axis=1) <= reach
        keep = near & (left >= 0.05 * left[big])
        keep[big] = True
        left[keep] = 0.0
        groups.append(np.asarray(pts[keep[lab]]))
    return groups


@dataclass
class _Scene:
    """Everything fixed for one recording: the models, the noise, the environment's pose."""

    src: FrameSource
    opt: TrackOptions
    G: ModelCloud
    E: ModelCloud
    noise: DepthNoiseModel
    seg: _Segmenter
    syms_G: tuple[Symmetry, ...]
    syms_E: tuple[Symmetry, ...]
    X_CE: FloatArray = field(default_factory=lambda: np.eye(4))
    env: Registration | None = None
    env_depth: npt.NDArray[np.float32] = field(default_factory=lambda: np.zeros((0, 0), np.float32))
    cache: dict[int, _Frame] = field(default_factory=dict)  # frames decoded during the setup
    prefetch: dict[int, Future[_Frame]] = field(default_factory=dict)  # being decoded
    pool: Executor | None = None  # the setup's threads: the environment's search uses one

    @property
    def camera(self) -> Camera:
        return self.src.camera

    def settings(self, points: FloatArray) -> dict[str, Any]:
        """ICP settings at the points' distance: inlier and surface distances in sigmas."""
        opt = self.opt
        z = float(np.median(points[:, 2])) if len(points) else 0.5
        s = float(self.noise.sigma(z))
        return {
            "inlier_distance": max(opt.inlier_distance, 0.75 * opt.noise_sigmas * s),
            "free_space_tolerance": max(opt.surface_tolerance, opt.noise_sigmas * s),
            "loss": opt.loss,
        }


def _open_scene(
    frames: str | Path | FrameSource, grasped: Any, environment: Any, units: str | None,
    opt: TrackOptions,
) -> _Scene:  # fmt: skip
    src: FrameSource = frames if not isinstance(frames, str | Path) else open_frames(frames)
    G = ModelCloud(mesh_triangles(grasped, units=units), seed=opt.seed)
    E = ModelCloud(
        mesh_triangles(environment, units=units), spacing=0.0003, max_dense=200000, seed=opt.seed
    )
    noise = _noise_model(src, opt)
    syms_G = tuple(symmetries(G.vertices, G.triangles))
    syms_E = tuple(symmetries(E.vertices, E.triangles))
    return _Scene(src, opt, G, E, noise, _Segmenter(src, opt, noise), syms_G, syms_E)


def _find_environment(scene: _Scene, XE0: FloatArray | None) -> None:
    """Register the environment on the median depth of its pixels over many frames."""
    opt, E, cam = scene.opt, scene.E, scene.camera
    parts, median_depth, surface = _environment_points(
        scene.src, scene.seg, opt, scene.cache, scene.prefetch, reach=E.diameter
    )
    parts = [p for p in parts if len(p) >= opt.min_points]
    if not parts:
        raise TrackingLostError(
            "environment object not found: too few static object pixels "
            "(check the colour model and the background; or give its pose with "
            "--init-environment)"
        )
    if XE0 is not None:  # the static region nearest the given pose
        centre = transform_points(XE0, E.centroid[None])[0]
        parts = [min(parts, key=lambda p: float(np.linalg.norm(p.mean(0) - centre)))]
    env: Registration | None = None
    # The largest static region first; the next ones (a forearm held still is static too
    # when the colour is not used) while the pose is not sure; the most plausible wins.
    bar = (
        opt.min_confidence
        if XE0 is not None
        else max(opt.min_confidence, opt.environment_confidence)
    )
    for env_pts in parts:
        if len(env_pts) > 20000:
            rng = np.random.default_rng(opt.seed)
            env_pts = env_pts[rng.choice(len(env_pts), 20000, replace=False)]
        kw = scene.settings(env_pts)
        if XE0 is not None:
            r = register(env_pts, E, XE0, depth=median_depth, camera=cam, **kw)
        else:
            r = initialise(
                env_pts, E, depth=median_depth, camera=cam, seed=opt.seed,
                symmetry_rotations=[s.S[:3, :3] for s in scene.syms_E],
                rank=whole_plausibility, pool=scene.pool, **kw,
            )  # fmt: skip
        if env is None or whole_plausibility(r) > whole_plausibility(env):
            env, env_points = r, env_pts
        if env.confidence >= bar:
            break
    assert env is not None
    if XE0 is None:
        env = _trimmed(env, env_points, scene, median_depth)
    if opt.refine_environment:
        env = _refined(env, env_points, scene, median_depth, surface)
    if env.confidence < bar:
        raise TrackingLostError(_unsure(env, bar, given=XE0 is not None))
    scene.env = env
    scene.X_CE = _twin(env.X_CM, XE0, scene.syms_E, E)
    scene.env_depth, _ = rasterize(transform_points(scene.X_CE, E.vertices), E.triangles, cam)
    if opt.colour is None:
        scene.seg.colour = _environment_colour(scene)


def _unsure(env: Registration, bar: float, *, given: bool) -> str:
    """Return the error message of an environment found with too low a confidence."""
    hint = (
        "check --init-environment"
        if given
        else "the global search's pose is a guess: give the environment's pose in the "
        "camera frame with --init-environment (library: init_environment)"
    )
    return (
        f"environment object not found: best pose has confidence {env.confidence:.2f} "
        f"(share of its predicted-visible surface explained by the depth; free-space "
        f"violation {env.violation:.2f}) < {bar:g}; {hint}"
    )


def _trimmed(
    env: Registration, points: FloatArray, scene: _Scene, depth: npt.NDArray[np.float32]
) -> Registration:
    """Refine the environment's pose on the points its model explains.

    The static region can hold more than the environment (a hand held still); the result
    is kept when it is not less confident.
    """
    from apo.perception.search import batch_icp, voxel_subsample

    kw = scene.settings(points)
    inl = kw["inlier_distance"]
    _, dist = scene.E.residuals(transform_points(invert_pose(env.X_CM), points))
    near = points[dist <= 2 * inl]
    if len(near) < scene.opt.min_points:
        return env
    sub = voxel_subsample(near, 3000, np.random.default_rng(scene.opt.seed))
    T = batch_icp(sub, scene.E, invert_pose(env.X_CM)[None], distance=2 * inl, scale=inl,
                  iterations=30, dense=True, loss=scene.opt.loss)  # fmt: skip
    r = evaluate(sub, scene.E, invert_pose(T[0]), inlier_distance=inl, depth=depth,
                 camera=scene.camera, free_space_tolerance=kw["free_space_tolerance"])  # fmt: skip
    return r if r.confidence >= env.confidence else env


def _refined(
    env: Registration, points: FloatArray, scene: _Scene, depth: npt.NDArray[np.float32],
    surface: npt.NDArray[np.float32],
) -> Registration:  # fmt: skip
    """Refine the environment's pose on its surface depth (:func:`refine_environment`).

    Kept when its confidence (on the median depth) is not lower by more than 0.01.
    """
    E, cam, n = scene.E, scene.camera, min(len(scene.src), scene.opt.histogram_frames)
    X = refine_environment(surface, depth, cam, E, env.X_CM, scene.noise, n,
                           _window(cam, env.X_CM, E, 0.01))  # fmt: skip
    kw = scene.settings(points)
    r = evaluate(points, E, X, inlier_distance=kw["inlier_distance"], depth=depth, camera=cam,
                 free_space_tolerance=kw["free_space_tolerance"])  # fmt: skip
    return r if r.confidence >= env.confidence - 0.01 else env


def _environment_colour(scene: _Scene, frames: int = 5) -> ColourModel:
    """Learn the parts' colour from the environment's pixels (depth within the noise)."""
    pixels = []
    for rgb, depth in list(scene.cache.values())[:frames]:
        if rgb.shape[:2] != depth.shape:
            continue
        on = (scene.env_depth > 0) & (depth > 0)
        tol = scene.seg.threshold(depth[on], scene.opt.environment_threshold, 1)
        pixels.append(rgb[on][np.abs(depth[on] - scene.env_depth[on]) <= tol])
    return learn_colour(np.concatenate(pixels) if pixels else np.zeros((0, 3)))


def tracked_visible_min(visibles: list[float]) -> float:
    """Return the visible share below which a tracked pose's confidence falls (``confidence_at``).

    ``visibles``: the visible shares (:attr:`apo.perception.register.SurfaceCheck.visible`)
    of the last tracked frames. :data:`apo.perception.register.VISIBLE_MIN` (the guard
    against a wrong pose hidden behind a forearm, which explains nothing and contradicts
    nothing) until three frames were tracked; then at most :data:`VISIBLE_DROP` times their
    median: a hand holding the part can hide 65-90 % of it for whole recordings, and there
    the guard scaled the true pose's confidence below that of a pose slid out from behind
    the hand with part of its surface seen through (independent recording 0, frame 48: 0.72
    against 0.90, 22 mm off; the tracker took the latter).
    """
    if len(visibles) < 3:
        return VISIBLE_MIN
    return min(VISIBLE_MIN, VISIBLE_DROP * float(np.median(visibles)))


class _Observed(NamedTuple):
    """The grasped object's observation in a window (or the whole frame)."""

    points: FloatArray  # (N, 3) camera frame, at most ``max_points``
    depth: npt.NDArray[np.float32]  # the window's depth
    camera: Camera  # the window's camera
    environment: npt.NDArray[np.float32]  # the environment model's depth in the window
    mask: BoolArray  # the object's pixels in the window (gated)
    shared: BoolArray  # object pixels within the noise of the environment's surface


class _Tracker:
    """The grasped object, frame by frame (see :func:`track_frames`)."""

    def __init__(self, scene: _Scene, XG0: FloatArray | None) -> None:
        self.scene, self.opt, self.G, self.XG0 = scene, scene.opt, scene.G, XG0
        n = len(scene.src)
        self.X_CG = np.full((n, 4, 4), np.nan)
        self.conf = np.zeros(n)
        self.lost = np.ones(n, dtype=bool)
        self.reinit = np.zeros(n, dtype=bool)
        self.history: list[FloatArray] = []  # last tracked poses (for the prediction)
        self.errors: list[float] = []  # how far the last tracked poses were from the predicted
        self.rmses: list[float] = []  # RMS residuals of the last tracked frames
        self.confs: list[float] = []  # and their confidences
        self.fits: list[float] = []  # and qualities
        self.visibles: list[float] = []  # and their visible shares
        self.gap = 0
        self.rng = np.random.default_rng(self.opt.seed)
        self.margin = self.opt.track_distance + 0.1 * self.G.diameter
        self.obstacle = (scene.E, scene.X_CE)
        self.centre = (self.G.vertices.min(0) + self.G.vertices.max(0)) / 2
        self.pool: Executor | None = None  # scores the fitness meanwhile (register.evaluate)

    def predict(self, i: int) -> FloatArray | None:
        """Constant velocity from the last two frames (never across a gap or a re-start)."""
        if i == 0 and self.XG0 is not None:
            return self.XG0
        if not self.history or self.gap > 2:
            return None
        pred = self.history[-1]
        if len(self.history) >= 2 and self.gap == 0:
            pred = orthonormalised(pred @ invert_pose(self.history[-2]) @ pred)
        return pred

    @property
    def visible_min(self) -> float:
        """The visible share below which a pose's confidence falls (:func:`tracked_visible_min`)."""
        return tracked_visible_min(self.visibles)

    def confidence(self, r: Registration) -> float:
        """``r``'s confidence at :attr:`visible_min`."""
        return r.confidence_at(self.visible_min)

    def gate(self, pred: FloatArray) -> tuple[FloatArray, float]:
        """Centre and radius of the sphere the object can be in: its extent + motion margin."""
        speed = 0.0
        if len(self.history) >= 2:
            speed = float(np.linalg.norm(self.history[-1][:3, 3] - self.history[-2][:3, 3]))
        c = transform_points(pred, self.centre[None])[0]
        return c, self.G.diameter / 2 + self.margin + speed

    def _masked(
        self, rgb: npt.NDArray[np.uint8], depth: npt.NDArray[np.float32], window: Window | None
    ) -> tuple[npt.NDArray[np.float32], Camera, npt.NDArray[np.float32], BoolArray, BoolArray]:
        """Return the window's depth, camera, environment depth and the grasped object's pixels.

        And the object pixels the environment's cut removed (within its noise of the
        environment's rendered surface: the part's too where it is near the environment,
        those whose noise took them nearer; see :func:`projective_icp`'s ``shared``).
        """
        s = self.scene
        env_d, d, c = s.env_depth, depth, s.camera
        if window is not None:
            u0, v0, w, h = window
            env_d = env_d[v0 : v0 + h, u0 : u0 + w]
            d = depth[v0 : v0 + h, u0 : u0 + w]
            c = c.crop(u0, v0, w, h)
        env_thr = s.seg.threshold(d, self.opt.environment_threshold, 1)
        objects = s.seg.objects(rgb, depth, window)
        mask = grasped_mask(objects, d, env_d, threshold=env_thr)
        return d, c, env_d, mask, objects & ~mask

    def _subset(self, pts: FloatArray) -> FloatArray:
        """At most ``max_points`` of the points (random subset)."""
        if len(pts) > self.opt.max_points:
            pts = pts[self.rng.choice(len(pts), self.opt.max_points, replace=False)]
        return pts

    def points(
        self, rgb: npt.NDArray[np.uint8], depth: npt.NDArray[np.float32], window: Window | None,
        gate: tuple[FloatArray, float] | None = None,
    ) -> _Observed:  # fmt: skip
        """Observed points of the grasped object; the depth, camera, environment depth, mask.

        Without a window: the first group of :func:`_object_groups` (the largest component
        and those near it).
        """
        d, c, env_d, mask, shared = self._masked(rgb, depth, window)
        if window is None:
            pts = _object_groups(mask, d, c, self.G.diameter, limit=1)[0]
        else:
            pts = c.backproject(d, mask)  # clutter: removed by the 3-D gate
        if gate is not None:
            inside = _in_gate(pts, *gate)
            pts = pts[inside]
            mask = mask & (d > 0)
            mask[mask] = inside  # backproject's row-major order
        return _Observed(self._subset(pts), d, c, env_d, mask, shared)

    @property
    def clutter(self) -> bool:
        """Whether the object pixels hold other things' (a hand holding the part, an arm).

        Without the colour cue, the segmentation cannot tell them from the part's.
        """
        return not self.scene.seg.colour.used

    def good(self, r: Registration) -> bool:
        """Confident, explaining its points and fitting them as closely as the last frames did.

        Each bar is ``good_confidence``, or 0.01 below the median of the last tracked frames'
        (what a correct pose scores depends on the sensor and the scene): the confidence
        (the model surface explained) and the quality (:attr:`Registration.quality`: a pose
        1 mm off along a face still explains its surface within the noise, but the sensor
        sees past its silhouette).
        """

        def bar(history: list[float]) -> float:
            top = self.opt.good_confidence
            return min(top, float(np.median(history)) - 0.01) if len(history) >= 3 else top

        # With clutter the share of the observed points a pose explains (the quality's
        # fitness) is no bar.
        if self.confidence(r) < bar(self.confs) or (
            not self.clutter and r.quality < bar(self.fits)
        ):
            return False
        rm = self.rmses
        return len(rm) < 3 or r.rmse <= self.opt.rmse_factor * float(np.median(rm))

    def start_scale(self, reach: float) -> float:
        """Return the projective ICP's first Tukey scale from the prediction (``start_factor``).

        The reach until three frames were tracked in a row since the last re-start, and
        always with clutter (depth alone): there a pixel in front of the model by more than
        the scale seeds an occluder (:func:`apo.perception.projective.occluders`), and the
        smaller first scale made a hand's pixels the part's (dev seed 2, a square peg held
        by a hand: 43 frames flipped).
        """
        factor = self.opt.start_factor
        if factor is None or self.clutter or len(self.errors) < 3 or self.gap:
            return reach
        return min(reach, factor * max(self.errors[-3:]))

    def track_window(
        self, rgb: npt.NDArray[np.uint8], depth: npt.NDArray[np.float32], pred: FloatArray
    ) -> Registration | None:
        """Register in the window around the prediction: from it, the last pose, coarse-to-fine."""
        seen = self._around(rgb, depth, pred)
        if seen is None:
            return None
        (pts, d, c, env_d, mask, shared), kw, reach = seen
        result: Registration | None = None
        starts = [pred] if len(self.history) < 2 or self.gap else [pred, self.history[-1]]
        if self.opt.projective:  # from the prediction, then from the last pose
            for start in starts:
                first = self.start_scale(reach) if start is pred else reach
                r = self.projective(start, d, c, pts, mask, env_d, reach, kw, shared, first)
                if _better(r, result, self.visible_min):
                    result = r
                if result is not None and self.good(result):
                    return result
        # The closest-point ICP (numpy: no Open3D import) only when the projective ICP is not
        # good from either start.
        for start in starts:
            r = register(pts, self.G, start, max_distance=reach, coarse=False, **kw)
            if _displacement(self.G, start, r.X_CM) > self.opt.settle_distance:
                # Far from the start: the ICP may have stopped on its iteration limit.
                again = register(pts, self.G, r.X_CM, max_distance=reach, coarse=False, **kw)
                if not _better(r, again, self.visible_min):
                    r = again
            if _better(r, result, self.visible_min):
                result = r
            if result is not None and self.good(result):
                return result
        r = register(pts, self.G, pred, **kw)
        return r if _better(r, result, self.visible_min) else result

    def _around(
        self, rgb: npt.NDArray[np.uint8], depth: npt.NDArray[np.float32], X: FloatArray
    ) -> tuple[_Observed, dict[str, Any], float] | None:
        """Return the observation about a pose, the registrations' settings and the reach.

        The window and the gate about ``X``; None when it holds too few points.
        """
        window = _window(self.scene.camera, X, self.G, self.margin)
        if window is None:
            return None
        seen = self.points(rgb, depth, window, self.gate(X))
        if len(seen.points) < self.opt.min_points:
            return None
        kw = {**self.scene.settings(seen.points), "depth": seen.depth, "camera": seen.camera,
              "occluder": seen.environment, "obstacle": self.obstacle,
              "engine": "numpy"}  # fmt: skip
        return seen, kw, max(self.opt.track_distance, 3.0 * kw["inlier_distance"])

    def polish(
        self, rgb: npt.NDArray[np.uint8], depth: npt.NDArray[np.float32], X: FloatArray
    ) -> Registration | None:
        """Register by the projective ICP in the window around a global search's candidate.

        With depth alone the search's closest-point ICP is pulled by the points of a hand
        holding the part; the projective ICP leaves them out (its per-pixel ownership).
        """
        seen = self._around(rgb, depth, X)
        if seen is None:
            return None
        (pts, d, c, env_d, mask, shared), kw, reach = seen
        return self.projective(X, d, c, pts, mask, env_d, reach, kw, shared)

    def projective(
        self, pred: FloatArray, d: npt.NDArray[np.float32], c: Camera, pts: FloatArray,
        mask: BoolArray, env_d: npt.NDArray[np.float32], reach: float, kw: dict[str, Any],
        shared: BoolArray | None = None, first: float | None = None,
    ) -> Registration:  # fmt: skip
        """Projective ICP from the prediction; once more from its result when it moved far.

        Its Tukey scale shrinks from ``first`` (default ``reach``) at every step: after a
        motion larger than the prediction foresaw (right after a re-initialisation there is
        no velocity), the first run can stop short (1.6 mm, measured); the second starts at
        ``reach``. Its result is kept only within ``reach`` of the first (a square peg deep
        in its hole, a few faces in view, once turned 90 deg with the same confidence).
        """
        args = {k: v for k, v in kw.items() if k not in ("loss", "depth", "camera", "engine")}
        sigma = self.scene.noise.sigma(d)
        args["clutter"] = self.clutter
        args["shared"] = shared
        args["pool"] = self.pool
        r = register_projective(d, c, self.G, pred, points_C=pts, mask=mask, sigma=sigma,
                                start_scale=reach if first is None else first,
                                **args)  # fmt: skip
        if _displacement(self.G, pred, r.X_CM) > self.opt.settle_distance:
            again = register_projective(d, c, self.G, r.X_CM, points_C=pts, mask=mask,
                                        sigma=sigma, start_scale=reach, **args)  # fmt: skip
            close = _displacement(self.G, r.X_CM, again.X_CM) <= reach
            if close and not _better(r, again, self.visible_min):
                r = again
        return r

    def reinitialise(
        self, rgb: npt.NDArray[np.uint8], depth: npt.NDArray[np.float32]
    ) -> Registration | None:
        """Run the global search on the whole frame's largest groups of components.

        Each group (:func:`_object_groups`: without the colour, a forearm apart from the
        hand and the part it holds is the largest) is searched; the most plausible result
        (:func:`apo.perception.register.plausibility`) wins. Without the colour, when the
        winner is less plausible than ``good_confidence``, the pixels it leaves unexplained
        (the part beside the hand the winner was fitted into) are searched again, and the
        more plausible of the two results is kept: no start of the first search may reach
        the part when the hand's points surround it (dev seeds 4 and 6, 30 frames: the
        first frame's pick 87 and 145 mm off, plausibility 0.93 and 0.77; the truth scores
        0.97 and 0.95).
        """
        d, c, env_d, mask, _ = self._masked(rgb, depth, None)
        best = self._search_groups(rgb, depth, mask, d, c, env_d)
        if best is None or not self.clutter or plausibility(best)[0] >= self.opt.good_confidence:
            return best
        pts = c.backproject(d, mask)
        _, dist = self.G.residuals(transform_points(invert_pose(best.X_CM), pts))
        left = mask.copy()
        left[mask] = dist > 2.0 * self.scene.settings(pts)["inlier_distance"]
        again = self._search_groups(rgb, depth, left, d, c, env_d)
        if again is not None and plausibility(again) > plausibility(best):
            return again
        return best

    def _search_groups(
        self, rgb: npt.NDArray[np.uint8], depth: npt.NDArray[np.float32], mask: BoolArray,
        d: npt.NDArray[np.float32], c: Camera, env_d: npt.NDArray[np.float32],
    ) -> Registration | None:  # fmt: skip
        """Return the most plausible result of the global searches of ``mask``'s groups."""
        best: Registration | None = None

        def polish(X: FloatArray) -> Registration | None:
            return self.polish(rgb, depth, X)

        for pts in _object_groups(mask, d, c, self.G.diameter):
            pts = self._subset(pts)
            if len(pts) < self.opt.min_points:
                continue
            r = initialise(
                pts, self.G, depth=d, camera=c, seed=self.opt.seed, obstacle=self.obstacle,
                symmetry_rotations=[s.S[:3, :3] for s in self.scene.syms_G], occluder=env_d,
                polish=polish, polish_below=np.inf if self.clutter else self.opt.good_confidence,
                polish_finalists=not self.clutter, pool=self.pool,
                **self.scene.settings(pts),
            )  # fmt: skip
            if best is None or plausibility(r) > plausibility(best):
                best = r
        return best

    def step(self, i: int, rgb: npt.NDArray[np.uint8], depth: npt.NDArray[np.float32]) -> None:
        """Track frame ``i``: from the prediction, else (real loss) by the global search."""
        opt = self.opt
        pred = self.predict(i)
        result = self.track_window(rgb, depth, pred) if pred is not None else None
        fresh = False  # the result comes from the global search
        if result is None or self.confidence(result) < opt.min_confidence:
            self.reinit[i] = i > 0 or self.XG0 is not None
            again = self.reinitialise(rgb, depth)
            if again is not None and (
                result is None or self.confidence(again) > self.confidence(result)
            ):
                result, fresh = again, True
        if result is not None:
            self.conf[i] = self.confidence(result)
        if result is None or self.conf[i] < opt.min_confidence:
            self.gap += 1
            return
        # The twin nearest the last tracked pose (the given one at the first frame).
        ref = self.history[-1] if self.history else self.XG0
        X = _twin(result.X_CM, ref, self.scene.syms_G, self.G)
        self.X_CG[i] = X
        self.lost[i] = False
        # A velocity never spans a re-initialisation: start the history afresh.
        self.history = [X] if fresh else [*self.history[-1:], X]
        moved = _displacement(self.G, pred, X) if pred is not None and not fresh else None
        self.errors = [] if moved is None else [*self.errors[-2:], moved]
        self.rmses = [*self.rmses[-9:], result.rmse]
        self.confs = [*self.confs[-9:], self.conf[i]]
        self.fits = [*self.fits[-9:], result.quality]
        if result.surface is not None:
            self.visibles = [*self.visibles[-9:], result.surface.visible]
        self.gap = 0


def _better(a: Registration, b: Registration | None, visible_min: float = VISIBLE_MIN) -> bool:
    """More plausible; as plausible (within 0.02): higher quality, then smaller RMS residual.

    :func:`apo.perception.register.plausibility`: the confidence less the share of the
    outline the observed surface continues (without the colour, a pose inside the hand's
    boxes explains as much of its surface as the true one). ``visible_min``: see
    :func:`tracked_visible_min`.
    """
    if b is None:
        return True
    pa, pb = plausibility(a, visible_min)[0], plausibility(b, visible_min)[0]
    if abs(pa - pb) > 0.02:
        return pa > pb
    if abs(a.quality - b.quality) > 0.01:
        return a.quality > b.quality
    return a.rmse < b.rmse


def track_frames(
    frames: str | Path | FrameSource,
    grasped_mesh: Any,
    environment_mesh: Any,
    *,
    units: str | None = "mm",
    init_grasped: npt.ArrayLike | None = None,
    init_environment: npt.ArrayLike | None = None,
    options: TrackOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> TrackResult:
    """Poses of the grasped and the environment object through a recorded sequence.

    Parameters
    ----------
    frames : str or Path or FrameSource
        A frames folder or a stereo folder (see :func:`apo.perception.frames.open_frames`),
        or an opened sequence.
    grasped_mesh, environment_mesh : trimesh.Trimesh, (vertices, triangles) or path
        The models (see :func:`apo.perception.render.mesh_triangles`).
    units : {"mm", "cm", "m", "in"} or None, optional
        Units of the models' coordinates (STEP files carry their own).
    init_grasped : ndarray, shape (4, 4), optional
        ``X_CG`` at the first frame, camera frame, **metres**; found by global
        initialisation when None.
    init_environment : ndarray, shape (4, 4), optional
        ``X_CE``, camera frame, metres; found by global initialisation when None.
    options : TrackOptions, optional
        Thresholds and the colour model.
    progress : callable(done, total), optional
        Called after each frame.

    Returns
    -------
    TrackResult
        Poses in metres; lost frames have NaN poses and ``lost`` True.

    Raises
    ------
    TrackingLostError
        The environment cannot be found, or the grasped object is lost in every frame.
    InputFormatError
        The frames folder does not follow the documented layout.
    """
    opt = options or TrackOptions()
    XG0 = _as_pose(init_grasped, "init_grasped")
    XE0 = _as_pose(init_environment, "init_environment")
    src: FrameSource = frames if not isinstance(frames, str | Path) else open_frames(frames)
    with ThreadPoolExecutor(max_workers=2) as pool:
        # The histogram's frames are decoded while the models and the noise are set up.
        prefetch = _prefetch(pool, src, opt)
        try:
            scene = _open_scene(src, grasped_mesh, environment_mesh, units, opt)
            scene.prefetch, scene.pool = prefetch, pool
            _find_environment(scene, XE0)
            scene.pool = None  # shut down with this block
        finally:  # on an error, the frames not started yet are not decoded
            for f in prefetch.values():
                f.cancel()
    n = len(src)
    tracker = _Tracker(scene, XG0)
    # Decode the next frame meanwhile, and score each result's fitness while its surface
    # check renders (register.evaluate).
    with ThreadPoolExecutor(max_workers=2) as pool:
        tracker.pool = pool
        colour = scene.seg.colour.used  # else the colour PNGs are not decoded at all
        pending = pool.submit(_read, src, 0, scene.cache, colour=colour)
        for i in range(n):
            rgb, depth = pending.result()
            if i + 1 < n:
                pending = pool.submit(_read, src, i + 1, scene.cache, colour=colour)
            tracker.step(i, rgb, depth)
            if progress is not None:
                progress(i + 1, n)
    if tracker.lost.all():
        raise TrackingLostError(
            f"grasped object lost in all {n} frames (best confidence "
            f"{tracker.conf.max():.2f} < {opt.min_confidence})"
        )
    assert scene.env is not None
    times = np.asarray(src.times, dtype=np.float64)
    X_CG = tracker.X_CG
    if opt.smooth:  # offline: each pose from the frames on both sides
        X_CG = smooth_poses(
            times, X_CG, ~tracker.lost, centre=tracker.centre, restart=tracker.reinit
        )
    X_EG = np.einsum("ij,njk->nik", invert_pose(scene.X_CE), X_CG)
    return TrackResult(
        times, X_CG, scene.X_CE, X_EG,
        tracker.conf, tracker.lost, scene.env.confidence, src.camera.X_WC,
        tracker.reinit, scene.syms_G, scene.syms_E,
    )  # fmt: skip
