"""Segmentation of the two objects in registered colour and depth frames (paper section 4.2).

Three steps, as in the paper, with the environment model added at the end:

1. **Background subtraction** against recorded background frames
   (:func:`foreground_from_background`) or, without them, against the supporting plane
   learnt from the sequence (:func:`fit_support_plane`, :func:`foreground_from_plane`).
2. **Object colour** (:class:`ColourModel`): the paper's objects were white; the model is a
   reference chromaticity with a tolerance and a minimum brightness, so it is insensitive to
   shading and configurable for any object colour.
3. **Occupancy histogram** (:func:`occupancy`): the fraction of frames in which each pixel
   shows an object. The environment does not move, so its pixels are occupied (almost)
   always; pixels occupied only sometimes belong to the grasped object
   (:func:`static_mask`). Once the environment's pose is known, a pixel is the environment's
   if its depth agrees with the environment model rendered at that pose
   (:func:`grasped_mask`): the grasped object is also found where it passes in front of the
   environment, which the histogram alone cannot do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from apo.perception.frames import Camera
from apo.typing import BoolArray, FloatArray

__all__ = [
    "ColourModel",
    "DepthNoiseModel",
    "Plane",
    "estimate_depth_noise",
    "fit_support_plane",
    "foreground_from_background",
    "foreground_from_plane",
    "grasped_mask",
    "learn_colour",
    "occupancy",
    "static_mask",
]


@dataclass(frozen=True)
class ColourModel:
    """Colour of the two objects: a reference chromaticity and a brightness threshold.

    A pixel ``(r, g, b)`` (0..1) matches when its brightness ``max(r, g, b)`` is at least
    ``min_value`` and its chromaticity ``(r, g, b) / (r + g + b)`` is within ``max_chroma``
    (Euclidean) of the reference's. Chromaticity does not change with shading, so a white
    object in shadow still matches and a grey-brown table or a skin-coloured hand does not.

    Attributes
    ----------
    reference : (float, float, float)
        Colour of the objects, 0..1 (only its chromaticity matters).
    max_chroma : float
        Chromaticity tolerance (0.04 to 0.1 typical).
    min_value : float
        Minimum brightness, 0..1.
    """

    reference: tuple[float, float, float] = (1.0, 1.0, 1.0)
    max_chroma: float = 0.05
    min_value: float = 0.3

    @classmethod
    def white(cls) -> ColourModel:
        """Return the paper's model: white (or grey) objects."""
        return cls()

    @classmethod
    def any_colour(cls) -> ColourModel:
        """Return a model that accepts every pixel (colour not used)."""
        return cls((1.0, 1.0, 1.0), 2.0, 0.0)

    @property
    def used(self) -> bool:
        """False for a model every pixel passes (:meth:`any_colour`): the colour is not a cue."""
        return not (self.max_chroma >= 2.0 and self.min_value <= 0.0)

    def mask(self, rgb: npt.ArrayLike) -> BoolArray:
        """Return the pixels of ``rgb`` (uint8, shape (H, W, 3)) that have the objects' colour."""
        im = np.asarray(rgb)
        if not self.used:
            return np.ones(im.shape[:2], dtype=bool)
        c = im.astype(np.float32)
        s = c.sum(axis=2)
        ok = c.max(axis=2) >= np.float32(self.min_value * 255.0)
        ref = np.asarray(self.reference, dtype=np.float32)
        ref = ref / max(float(ref.sum()), 1e-9)
        s = np.maximum(s, 1.0)
        d2 = np.zeros(s.shape, dtype=np.float32)
        for k in range(3):
            d2 += (c[:, :, k] / s - ref[k]) ** 2
        return np.asarray(ok & (d2 <= np.float32(self.max_chroma**2)), dtype=bool)


@dataclass(frozen=True)
class DepthNoiseModel:
    """Depth noise of a sensor: ``sigma(z) = sqrt((c z^2)^2 + q^2 / 12)`` (metres).

    Structured-light and time-of-flight sensors have a noise growing with the square of the
    distance (``c`` in metres per square metre: 1e-3 to 6e-3 for common RGB-D cameras) and a
    quantisation step ``q`` (the depth unit of the recording).

    Attributes
    ----------
    c : float
        Metres per square metre.
    quantum : float
        Depth quantisation step, metres.
    """

    c: float
    quantum: float = 0.0

    def sigma(self, z: npt.ArrayLike) -> FloatArray:
        """Return the standard deviation (metres) of a depth ``z`` (metres)."""
        zz = np.asarray(z)
        if zz.dtype != np.float32:  # float32 images stay float32 (a frame: 5x faster)
            zz = zz.astype(np.float64)
        s = zz * zz * zz.dtype.type(self.c)
        if self.quantum == 0.0:
            return np.asarray(s)
        return np.asarray(np.sqrt(s * s + zz.dtype.type(self.quantum**2 / 12.0)))


def estimate_depth_noise(
    depths: npt.ArrayLike, *, quantum: float = 0.0, min_pixels: int = 1000
) -> DepthNoiseModel:
    """Estimate ``c`` of ``sigma(z) = c z^2`` from several depth frames of one recording.

    Differences of a pixel's depth between consecutive frames are noise where the scene is
    static (most of an image: the table, the environment): ``d_k - d_(k-1)`` has standard
    deviation ``sqrt(2) sigma(z)``. The median of ``|d_k - d_(k-1)| / z^2`` over all pixels
    valid in both frames, divided by ``0.6745 sqrt(2)`` (the median absolute value of a unit
    normal, times the square root of 2), is a robust estimate of ``c``: moving pixels (fewer
    than half) do not shift a median much.

    Parameters
    ----------
    depths : ndarray, shape (N >= 2, H, W)
        Depth frames, metres, 0 where none.
    quantum : float, optional
        The recording's depth unit (metres), kept in the model.
    min_pixels : int, optional
        Fewer valid pixel pairs than this: ValueError.

    Returns
    -------
    DepthNoiseModel
    """
    D = np.asarray(depths, dtype=np.float64)
    if D.ndim != 3 or len(D) < 2:
        raise ValueError(f"need at least 2 depth frames of shape (H, W), got {D.shape}")
    a, b = D[1:], D[:-1]
    ok = (a > 0) & (b > 0)
    if int(np.count_nonzero(ok)) < min_pixels:
        raise ValueError(f"only {int(np.count_nonzero(ok))} pixels with depth in two frames")
    z = (a[ok] + b[ok]) / 2
    ratio = np.abs(a[ok] - b[ok]) / (z * z)
    c = float(np.median(ratio)) / (0.6745 * np.sqrt(2.0))
    return DepthNoiseModel(c, quantum)


@dataclass(frozen=True)
class Plane:
    """A plane ``normal . p = offset`` in the camera frame; ``normal`` points to the camera.

    Attributes
    ----------
    normal : ndarray, shape (3,)
        Unit normal, camera frame.
    offset : float
        Metres.
    """

    normal: FloatArray
    offset: float

    def height(self, points_C: npt.ArrayLike) -> FloatArray:
        """Signed distance (metres) of points above the plane (towards the camera)."""
        return np.asarray(np.asarray(points_C, dtype=np.float64) @ self.normal - self.offset)


def fit_support_plane(
    points_C: npt.ArrayLike,
    *,
    threshold: float = 0.003,
    iterations: int = 200,
    seed: int | np.random.Generator | None = 0,
) -> Plane:
    """Fit the dominant plane (the table) to a point cloud by RANSAC and least squares.

    Parameters
    ----------
    points_C : ndarray, shape (N, 3)
        Points in the camera frame, metres.
    threshold : float, optional
        Inlier distance, metres.
    iterations : int, optional
        RANSAC samples.
    seed : int or Generator or None, optional
        Random seed.

    Returns
    -------
    Plane
        With its normal pointing towards the camera (the origin).

    Raises
    ------
    ValueError
        Fewer than 3 points.
    """
    P = np.asarray(points_C, dtype=np.float64)
    if len(P) < 3:
        raise ValueError(f"need at least 3 points to fit a plane, got {len(P)}")
    rng = np.random.default_rng(seed)
    sample = P if len(P) <= 20000 else P[rng.choice(len(P), 20000, replace=False)]
    best_n, best_d, best_count = np.array([0.0, 0.0, -1.0]), 0.0, -1
    for _ in range(iterations):
        a, b, c = sample[rng.choice(len(sample), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            continue
        n /= norm
        d = float(n @ a)
        count = int(np.count_nonzero(np.abs(sample @ n - d) < threshold))
        if count > best_count:
            best_n, best_d, best_count = n, d, count
    inliers = sample[np.abs(sample @ best_n - best_d) < threshold]
    if len(inliers) >= 3:
        centre = inliers.mean(axis=0)
        _, _, vt = np.linalg.svd(inliers - centre, full_matrices=False)
        n = vt[2]
        if n @ best_n < 0:
            n = -n
        best_n, best_d = n, float(n @ centre)
    if best_d > 0:  # the camera (origin) must be on the positive side
        best_n, best_d = -best_n, -best_d
    return Plane(best_n, best_d)


def foreground_from_background(
    depth: npt.ArrayLike,
    background_depth: npt.ArrayLike,
    *,
    threshold: float | npt.ArrayLike = 0.004,
) -> BoolArray:
    """Pixels in front of the recorded background by more than ``threshold`` (metres).

    Parameters
    ----------
    depth, background_depth : ndarray, shape (H, W)
        Depth in metres, 0 where there is no measurement. Pixels without background depth
        count as foreground when they have a depth.
    threshold : float or ndarray of shape (H, W), optional
        Metres; a few standard deviations of the difference of the two depths (per pixel
        when an array: the noise grows with the distance).

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    d = np.asarray(depth)
    bg = np.asarray(background_depth)
    valid = d > 0
    return np.asarray(valid & ((bg <= 0) | (d < bg - threshold)), dtype=bool)


def foreground_from_plane(
    depth: npt.ArrayLike,
    camera: Camera,
    plane: Plane,
    *,
    threshold: float | npt.ArrayLike = 0.004,
) -> BoolArray:
    """Pixels whose 3-D point is more than ``threshold`` (metres; or per pixel) above the plane."""
    d = np.asarray(depth)
    if d.dtype != np.float32:
        d = d.astype(np.float64)
    H, W = d.shape
    n = plane.normal
    # The height of the pixel's point: depth times the plane's normal along its ray.
    ray = (n[0] * (np.arange(W) - camera.cx) / camera.fx)[None, :] + (
        n[1] * (np.arange(H) - camera.cy) / camera.fy + n[2]
    )[:, None]
    h = d * ray.astype(d.dtype) - d.dtype.type(plane.offset)
    return np.asarray((d > 0) & (h > threshold), dtype=bool)


def occupancy(masks: npt.ArrayLike) -> FloatArray:
    """Per-pixel occupancy histogram: the fraction of frames in which a pixel is an object.

    Parameters
    ----------
    masks : ndarray of bool, shape (N, H, W)
        Object pixels (after background subtraction and colour extraction) of N frames.

    Returns
    -------
    ndarray, shape (H, W)
        Values in [0, 1].
    """
    m = np.asarray(masks, dtype=bool)
    return np.asarray(m.mean(axis=0), dtype=np.float64)


def static_mask(histogram: npt.ArrayLike, *, static_fraction: float = 0.7) -> BoolArray:
    """Pixels of the environment: occupied in at least ``static_fraction`` of the frames."""
    return np.asarray(np.asarray(histogram) >= static_fraction, dtype=bool)


def grasped_mask(
    objects: npt.ArrayLike,
    depth: npt.ArrayLike,
    environment_depth: npt.ArrayLike,
    *,
    threshold: float | npt.ArrayLike = 0.004,
) -> BoolArray:
    """Object pixels not explained by the environment: the grasped object's (and clutter).

    Parameters
    ----------
    objects : ndarray of bool, shape (H, W)
        Object pixels of the frame (background subtracted, colour extracted).
    depth : ndarray, shape (H, W)
        The frame's depth, metres.
    environment_depth : ndarray, shape (H, W)
        Depth of the environment alone (its model rendered at its pose), 0 where absent.
    threshold : float or ndarray of shape (H, W), optional
        A pixel within this depth (metres; per pixel when an array) of the environment is
        the environment's.

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    d = np.asarray(depth)
    env = np.asarray(environment_depth)
    on_env = (env > 0) & (np.abs(d - env) <= threshold)
    return np.asarray(np.asarray(objects, dtype=bool) & ~on_env, dtype=bool)


def learn_colour(rgb: npt.ArrayLike, *, min_pixels: int = 200) -> ColourModel:
    """Learn an object's colour model from pixels known to show it (e.g. the environment's).

    The reference is the median chromaticity of the pixels; the chromaticity tolerance 1.5
    times the 95th percentile of their distances to it (within 0.03 to 0.12: shading,
    sensor noise and mixed pixels at edges); the minimum brightness half the 5th percentile
    of theirs (shadows). Fewer than ``min_pixels`` pixels: :meth:`ColourModel.any_colour`.

    Parameters
    ----------
    rgb : ndarray of uint8, shape (N, 3)
        The pixels' colours.
    """
    c = np.asarray(rgb, dtype=np.float64).reshape(-1, 3)
    if len(c) < min_pixels:
        return ColourModel.any_colour()
    chroma = c / np.maximum(c.sum(axis=1, keepdims=True), 1.0)
    ref = np.median(chroma, axis=0)
    ref = ref / max(float(ref.sum()), 1e-9)
    spread = float(np.percentile(np.linalg.norm(chroma - ref, axis=1), 95))
    value = float(np.percentile(c.max(axis=1), 5)) / 255.0
    return ColourModel(
        (float(ref[0]), float(ref[1]), float(ref[2])),
        float(np.clip(1.5 * spread, 0.03, 0.12)),
        float(np.clip(0.5 * value, 0.0, 0.5)),
    )
