"""The pose noise of a demonstration, estimated from the poses themselves.

Observed poses are a smooth motion plus noise. The second difference of a smooth motion
sampled densely is small, while that of white noise of standard deviation ``s`` has
standard deviation ``sqrt(6) s``; a robust scale (the median absolute deviation) of the
second differences of G's centroid and of its rotation therefore estimates the noise,
ignoring the few frames where the motion itself changes fast. The estimate sets the
contact threshold (a contact whose distance is blurred by the noise must still be seen) and
marks outlier frames (a pose far from what its neighbours predict).

A slow drift (a tracker's bias wandering over seconds) is invisible to second differences:
it looks like motion. Inside contact states it is not: the contacts must hold, so the
residuals of their elements at the observed poses measure the whole pose error, drift
included (:func:`contact_noise`); :func:`apo.recognition.recognize_frames` recognises
again with that noise when it is clearly larger.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from apo.arrays import median
from apo.contact import ContactElement
from apo.correction import ContactConstraints
from apo.geometry import Polyhedron
from apo.recognition.types import BoolArray, FloatArray

__all__ = [
    "CONTACT_NOISE_RATIO",
    "CONTACT_SAMPLES",
    "NOISE_THRESHOLD_FACTOR",
    "OUTLIER_FACTOR",
    "NoiseEstimate",
    "contact_noise",
    "distance_sigma",
    "estimate_noise",
    "outlier_frames",
]

#: The contact threshold is at least this many standard deviations of a vertex distance.
NOISE_THRESHOLD_FACTOR = 3.5
#: A frame whose pose is this many noise deviations from the prediction of its two
#: neighbours (and from each of them) is an outlier.
OUTLIER_FACTOR = 5.0
#: Recognise again with the contact residuals' noise when it exceeds the estimate from the
#: second differences by this factor (white noise gives 0.85 to 1.45 on random variants,
#: the first author's demonstration 1.17; a drift of twice the white noise 1.3 to 2.2).
CONTACT_NOISE_RATIO = 1.5
#: Contact frames sampled (evenly) for :func:`contact_noise`.
CONTACT_SAMPLES = 400
#: Median absolute deviation to standard deviation, for Gaussian data.
_MAD = 1.4826


@dataclass(frozen=True)
class NoiseEstimate:
    """Pose noise per axis, and what it means for a contact distance.

    Attributes
    ----------
    position : float
        Standard deviation of the position of G's vertex centroid, per axis (metres).
    rotation : float
        Standard deviation of the rotation, per axis (radians).
    distance : float
        Standard deviation of the distance of a vertex of G from a plane (metres):
        ``sqrt(position^2 + (radius * rotation)^2)``, ``radius`` G's RMS vertex radius.
    source : str
        ``"data"`` (estimated) or ``"given"`` (``--noise``).
    contact : float
        Standard deviation of the contact elements' residuals at the observed poses of the
        frames in contact states (metres; :func:`contact_noise`), 0 when not measured.
        ``distance`` is the larger of it and the second differences' estimate when the
        recognition was run again with it.
    """

    position: float
    rotation: float
    distance: float
    source: str = "data"
    contact: float = 0.0


def _rotvecs(R: FloatArray) -> FloatArray:
    """Rotation vectors (n, 3) of rotation matrices (n, 3, 3) (small angles exact enough)."""
    c = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(c)
    w = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1)
    s = np.sin(th)
    k = np.where(s > 1e-12, th / np.where(s > 1e-12, 2.0 * s, 1.0), 0.5)
    out: FloatArray = w * k[:, None]
    return out


def _second_differences(
    grasped: Polyhedron, X: FloatArray, block: int | None = None
) -> tuple[FloatArray, FloatArray]:
    """Second differences (n-2, 3) of G's centroid and of its rotation vector increments.

    Computed ``block`` frames at a time (default ``NOISE_BLOCK``): the same values as over
    every frame at once, in working memory of one block.
    """
    cg = grasped.vertices.mean(axis=0)
    n = len(X)
    dc, dr = np.empty((max(n - 2, 0), 3)), np.empty((max(n - 2, 0), 3))
    size = max(1, NOISE_BLOCK if block is None else block)
    for a in range(0, n - 2, size):
        b = min(n - 2, a + size)
        Xb = X[a : b + 2]
        c = np.einsum("nij,j->ni", Xb[:, :3, :3], cg) + Xb[:, :3, 3]
        dc[a:b] = c[2:] - 2.0 * c[1:-1] + c[:-2]
        R = Xb[:, :3, :3]
        inc = _rotvecs(np.einsum("nij,nkj->nik", R[1:], R[:-1]))  # R_{t+1} R_t^T
        dr[a:b] = inc[1:] - inc[:-1]
    return dc, dr


def _robust_sigma(d: FloatArray) -> float:
    """Return the standard deviation per axis of white noise whose second differences are ``d``."""
    if len(d) == 0:
        return 0.0
    return float(_MAD * median(np.abs(d - median(d, axis=0))) / math.sqrt(6.0))


def estimate_noise(grasped: Polyhedron, X_EG: FloatArray) -> NoiseEstimate:
    """Estimate the pose noise of a sequence of poses of G (metres, radians).

    Fewer than 5 frames give zero noise (nothing to estimate from).
    """
    X = np.asarray(X_EG, dtype=np.float64)
    if len(X) < 5:
        return NoiseEstimate(0.0, 0.0, 0.0)
    dc, dr = _second_differences(grasped, X)
    sp, sr = _robust_sigma(dc), _robust_sigma(dr)
    return NoiseEstimate(sp, sr, distance_sigma(grasped, sp, sr))


def distance_sigma(grasped: Polyhedron, position: float, rotation: float) -> float:
    """Return the standard deviation (metres) of a vertex-plane distance under pose noise."""
    v = grasped.vertices - grasped.vertices.mean(axis=0)
    radius = float(np.sqrt((v**2).sum(axis=1).mean()))
    return math.hypot(position, radius * rotation)


def outlier_frames(
    grasped: Polyhedron, X_EG: FloatArray, noise: NoiseEstimate, *, floor: float = 0.0
) -> BoolArray:
    """Frames whose pose is far from both neighbours and from their midpoint, shape (N,).

    The corners of G's bounding box are compared: at frame ``t`` some corner must be more
    than ``OUTLIER_FACTOR`` deviations of the difference of two noisy corner positions
    (``sqrt(2) hypot(position, r rotation)``, ``r`` the corners' largest radius) from its
    position at ``t - 1``,
    at ``t + 1`` and from their mean (and at least ``floor`` metres), while those two agree
    with each other better than with it. Where the motion is fast (G moves between the
    neighbours by as much as an outlier), a frame far from both one-sided extrapolations
    ``2 X[t-1] - X[t-2]`` and ``2 X[t+1] - X[t+2]`` (``OUTLIER_FACTOR`` deviations of a
    second difference, ``sqrt(6)`` corner deviations) is one too, when no frame within two
    of it is one. The first (last) frame is one when it is that far from the next
    (previous) frame and from the extrapolation of the two after (before) it, and those
    three frames agree with a smooth motion (within the first limit, none an outlier).
    """
    X = np.asarray(X_EG, dtype=np.float64)
    n = len(X)
    out = np.zeros(n, dtype=bool)
    if n < 3 or max(noise.distance, floor) <= 0:
        return out
    lo, hi = grasped.vertices.min(axis=0), grasped.vertices.max(axis=0)
    corners = np.array([[(lo, hi)[(i >> k) & 1][k] for k in range(3)] for i in range(8)])
    r_c = float(np.linalg.norm(corners - grasped.vertices.mean(axis=0), axis=1).max())
    sigma_c = math.hypot(noise.position, r_c * noise.rotation)  # a corner, per axis
    lim = max(OUTLIER_FACTOR * math.sqrt(2.0) * sigma_c, floor)
    lim_x = max(OUTLIER_FACTOR * math.sqrt(6.0) * sigma_c, floor)
    mid_d, far, closer, left, right = _corner_tests(X, corners, lim)
    out[1:-1] = far & closer
    if n >= 5:
        # A fast motion (few frames per second) moves G between the two neighbours by as
        # much as an outlier: a frame far from both one-sided extrapolations (2 X[t-1] -
        # X[t-2], 2 X[t+1] - X[t+2]) is an outlier too, unless a frame it extrapolates from
        # is one (a kink of the motion lies on one side's line)
        near = np.convolve(out.astype(np.float64), np.ones(5), mode="valid") > 0  # t-2..t+2
        out[2:-2] |= far[1:-1] & (left > lim_x) & (right > lim_x) & ~near
        # The first and last frames: far from the next (previous) frame and from the
        # extrapolation of the two after (before) it, where those three frames agree
        ends = np.concatenate([np.arange(4), np.arange(n - 4, n)])
        pts = dict(zip(ends.tolist(), _corners_at(X[ends], corners), strict=True))
        for end, a, b, c in ((0, 1, 2, 3), (n - 1, n - 2, n - 3, n - 4)):
            ext = _apart(pts[end], 2.0 * pts[a] - pts[b])
            clean = _apart(pts[a], 2.0 * pts[b] - pts[c]) <= lim and not (out[a] or out[b])
            out[end] = _apart(pts[end], pts[a]) > lim and ext > lim_x and clean
    for t in np.flatnonzero(out[1:-2] & out[2:-1]) + 1:  # two in a row: an outlier's neighbour
        out[t + int(mid_d[t - 1] > mid_d[t])] = False  # is off its own neighbours' midpoint too
    return out


#: Frames whose corner positions are computed at once (:func:`outlier_frames`,
#: :func:`estimate_noise`): their working arrays are of this many frames.
NOISE_BLOCK = 1024


def _corners_at(X: FloatArray, corners: FloatArray) -> FloatArray:
    """Return the corners (8, 3) of G's box at the poses ``X``: shape (n, 8, 3)."""
    pts: FloatArray = np.einsum("nij,cj->nci", X[:, :3, :3], corners) + X[:, None, :3, 3]
    return pts


def _apart(p: FloatArray, q: FloatArray) -> FloatArray:
    """Largest corner distance between the corner sets ``p`` and ``q``, per frame."""
    d: FloatArray = np.linalg.norm(p - q, axis=-1).max(axis=-1)
    return d


def _corner_tests(
    X: FloatArray, corners: FloatArray, lim: float, block: int | None = None
) -> tuple[FloatArray, BoolArray, BoolArray, FloatArray, FloatArray]:
    """Return the corner distances of :func:`outlier_frames`, ``block`` frames at a time.

    For the inner frames ``t = 1 .. n-2``: the distance from the neighbours' midpoint
    ``mid_d``, whether ``t`` is far from both neighbours and the midpoint, whether the two
    neighbours are closer to each other than ``t`` to their midpoint; for ``t = 2 .. n-3``
    the distances from the left and right extrapolations. The same values as over every
    frame at once (each is a function of frames ``t-2 .. t+2``).
    """
    n = len(X)
    size = max(1, NOISE_BLOCK if block is None else block)
    mid_d, far, closer = np.empty(n - 2), np.empty(n - 2, dtype=bool), np.empty(n - 2, dtype=bool)
    left, right = np.empty(max(n - 4, 0)), np.empty(max(n - 4, 0))
    for a in range(1, n - 1, size):
        b = min(n - 1, a + size)
        lo = max(0, a - 2)
        pts = _corners_at(X[lo : min(n, b + 2)], corners)

        def at(t0: int, t1: int, pts: FloatArray = pts, lo: int = lo) -> FloatArray:
            return pts[t0 - lo : t1 - lo]

        prev, here, nxt = at(a - 1, b - 1), at(a, b), at(a + 1, b + 1)
        md = _apart(here, 0.5 * (prev + nxt))
        mid_d[a - 1 : b - 1] = md
        far[a - 1 : b - 1] = (_apart(here, prev) > lim) & (_apart(here, nxt) > lim) & (md > lim)
        closer[a - 1 : b - 1] = _apart(nxt, prev) < md
        a2, b2 = max(a, 2), min(b, n - 2)
        if b2 > a2:
            mid = at(a2, b2)
            left[a2 - 2 : b2 - 2] = _apart(mid, 2.0 * at(a2 - 1, b2 - 1) - at(a2 - 2, b2 - 2))
            right[a2 - 2 : b2 - 2] = _apart(mid, 2.0 * at(a2 + 1, b2 + 1) - at(a2 + 2, b2 + 2))
    return mid_d, far, closer, left, right


def contact_noise(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG: FloatArray,
    elements: list[tuple[ContactElement, ...]],
    *,
    samples: int = CONTACT_SAMPLES,
) -> float:
    """Return the noise (metres) of the contact residuals of a recognised sequence.

    ``elements[t]`` are the contact elements of the state chosen at frame ``t`` (empty:
    free, or a frame to ignore). At most ``samples`` of the frames in contact, evenly
    spread, give their element residuals ``f_i`` at the observed pose (signed distances
    along the contact normals, ``apo.contact.element_residuals``, batched per state by
    ``apo.correction.ContactConstraints``; zero when the contact
    holds); the noise is ``1.4826 median |f_i|``, the standard deviation of Gaussian
    residuals, robust to the few frames whose chosen state is wrong. Fewer than 8
    residuals give 0.
    """
    frames = [t for t, els in enumerate(elements) if els]
    if len(frames) > samples:
        frames = [frames[int(i)] for i in np.linspace(0, len(frames) - 1, samples)]
    groups: dict[tuple[object, ...], list[int]] = {}
    for t in frames:
        groups.setdefault(tuple(e.key for e in elements[t]), []).append(t)
    # one batched evaluation per state (apo.correction.ContactConstraints: the rows and signs
    # of apo.contact.element_residuals)
    res = [
        ContactConstraints(grasped, environment, elements[ts[0]]).residuals(X_EG[ts])[0].ravel()
        for ts in groups.values()
    ]
    f = np.concatenate(res) if res else np.zeros(0)
    if len(f) < 8:
        return 0.0
    return float(_MAD * median(np.abs(f)))
