"""Offline smoothing of a tracked pose sequence that keeps its jumps and kinks sharp.

``apo track`` writes the whole sequence at once, so each frame's pose can be estimated from
its neighbours on both sides. One frame's pose of a part about 1 m from a depth camera with
``sigma`` about 3 mm per pixel is determined to about 0.7 deg (the rotation; the position
to a few tenths of a millimetre); the noise of neighbouring frames is nearly independent,
and the motion between them is smooth except where a contact starts or ends: there the
part stops, turns or jumps within one frame, and recognition needs those frames exact.

:func:`smooth_poses` is a **local linear fit on SE(3) with one-sided window selection**
(an edge-preserving local regression, as the Kuwahara filter is for images): for frame
``i``, every window of ``2 h + 1`` consecutive tracked frames that contains ``i`` is fitted
by a constant-velocity motion (a straight line in time, per coordinate: the rotation
vector of ``R_j R_i^T`` and the displacement of the model's centre, camera frame), and the
window whose residuals are smallest (in units of the sequence's noise, :func:`pose_noise`)
gives frame ``i``'s pose, its line evaluated at ``t_i``. A window across a jump or a kink
fits badly and is not chosen; a frame between two events closer than the window (a state
held one or two frames) finds no window that fits, and shorter windows are tried down to
the frame alone (its pose unchanged). Of the windows that fit about as well as the best,
the most central one is chosen (the line at the window's centre averages most).

The noise of each coordinate is estimated from the sequence itself (the median absolute
deviation of the frames from the line through their two neighbours), so the test adapts
to the sensor, the distance and the part without settings.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from apo.typing import BoolArray, FloatArray

__all__ = ["pose_noise", "smooth_poses"]

HALF_WINDOW = 3
"""Frames on each side of the centre of the longest window (7 frames)."""

FIT_LIMIT = 3.0
"""A window fits when its mean squared residual is at most this many noise variances."""

FRAME_LIMIT = 22.5
"""...and when no frame of it is off its line by more than this (the sum of its 6 squared
standardised residuals: the 99.9th percentile of chi-square with 6 degrees of freedom)."""

MIN_HALF_WINDOW = 2
"""The shortest window has ``2 MIN_HALF_WINDOW + 1`` frames: 3 frames cannot tell an event of
a few noise sigmas from the noise (a line through 3 frames across a 3 deg kink at 0.7 deg
of noise passed the test and moved the frame 3 deg; measured), so a frame that no window of
5 fits is left as registered."""

MIN_DEVIATIONS = 20
"""The noise is estimated from at least this many frames with both neighbours tracked (a
shorter sequence is returned as registered: 8 frames of a whole insertion, each far from
the line through its neighbours, gave a noise as large as the motion, and the smoothing
moved the part by 1.6 mm; measured)."""

CENTRAL_SLACK = 0.5
"""A window more central than the best fit is chosen when it is worse by less than this (in
mean squared residual per noise variance)."""


def _runs(ok: BoolArray, restart: BoolArray) -> npt.NDArray[np.int64]:
    """Run label of each valid frame: runs of consecutive tracked frames, cut at restarts."""
    idx = np.nonzero(ok)[0]
    new = np.ones(len(idx), dtype=bool)
    new[1:] = (np.diff(idx) != 1) | restart[idx[1:]]
    return np.cumsum(new)


def pose_noise(
    times: npt.ArrayLike, X: npt.ArrayLike, valid: npt.ArrayLike | None = None,
    centre: npt.ArrayLike | None = None, restart: npt.ArrayLike | None = None,
) -> FloatArray:  # fmt: skip
    """Noise standard deviation of each pose coordinate (3 rotation, rad; 3 position, m).

    From the frames whose two neighbours are tracked (in the same run: no lost frame and no
    re-initialisation, ``restart``, between them): the deviation of a frame from the
    straight line (in time) through its neighbours has variance ``(1 + a^2 + b^2) sigma^2``
    (``a``, ``b`` the interpolation weights) under independent noise; a robust scale of
    these deviations (1.4826 times their median absolute value) is taken, so jumps and
    kinks (a few frames) do not count. Floors: 1e-5 rad and 1e-6 m. NaN when fewer than
    ``MIN_DEVIATIONS`` frames have both neighbours: too few to tell noise from motion.
    """
    t = np.asarray(times, dtype=np.float64)
    P = np.asarray(X, dtype=np.float64)
    ok = np.ones(len(P), dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    rs = np.zeros(len(P), dtype=bool) if restart is None else np.asarray(restart, dtype=bool)
    c = np.zeros(3) if centre is None else np.asarray(centre, dtype=np.float64)
    idx = np.nonzero(ok)[0]
    y = _neighbours(t[idx], P[idx], c, 1, _runs(ok, rs))
    prev, nxt = y[:, 0, :6], y[:, 2, :6]
    both = np.isfinite(prev[:, 0]) & np.isfinite(nxt[:, 0])
    if np.count_nonzero(both) < MIN_DEVIATIONS:
        return np.full(6, np.nan)
    wa = (y[both, 2, 6] / np.maximum(y[both, 2, 6] - y[both, 0, 6], 1e-12))[:, None]
    dev = (wa * prev[both] + (1 - wa) * nxt[both]) / np.sqrt(1 + wa**2 + (1 - wa) ** 2)
    floor = np.array([1e-5] * 3 + [1e-6] * 3)
    return np.asarray(np.maximum(1.4826 * np.median(np.abs(dev), axis=0), floor))


def _neighbours(
    t: FloatArray, X: FloatArray, centre: FloatArray, reach: int, run: npt.NDArray[np.int64]
) -> FloatArray:
    """Coordinates of frames ``i + d`` (``|d| <= reach``) relative to frame ``i``: (N, 2r+1, 7).

    The last column is the time offset; NaN where ``i + d`` is outside the sequence or in
    another run (``run``: a label per frame).
    """
    from scipy.spatial.transform import Rotation

    n = len(X)
    d = np.arange(-reach, reach + 1)
    j = np.arange(n)[:, None] + d[None, :]
    jj = np.clip(j, 0, n - 1)
    inside = (j >= 0) & (j < n) & (run[jj] == run[:, None])
    R = np.einsum("nkij,nlj->nkil", X[jj, :3, :3], X[:, :3, :3])  # R_j R_i^T
    w = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(n, len(d), 3)
    p = np.einsum("nij,j->ni", X[:, :3, :3], centre) + X[:, :3, 3]
    out = np.concatenate([w, p[jj] - p[:, None, :], (t[jj] - t[:, None])[..., None]], axis=2)
    out[~inside] = np.nan
    return out


def _window_fits(
    y: FloatArray, scale: FloatArray, lo: int, hi: int
) -> tuple[FloatArray, FloatArray]:
    """Straight lines through columns ``lo:hi`` of :func:`_neighbours`, per frame.

    Returns the values at the frame's own time (N, 6) and the mean squared residual per
    degree of freedom in units of ``scale`` (N,; inf where the window leaves the sequence).
    """
    v = y[:, lo:hi, :6] / scale
    tau = y[:, lo:hi, 6]
    m = len(range(lo, hi))
    st, stt = tau.sum(1), (tau * tau).sum(1)
    sy, sty = v.sum(1), (tau[..., None] * v).sum(1)
    den = m * stt - st * st
    b = (m * sty - st[:, None] * sy) / np.where(den > 0, den, 1.0)[:, None]
    a = (sy - b * st[:, None]) / m
    r = v - a[:, None, :] - tau[..., None] * b[:, None, :]
    msr = (r * r).sum(axis=(1, 2)) / (6 * max(m - 2, 1))
    # One frame off the line (an event at the window's end) is diluted in the mean: each
    # frame's standardised residual (leverage 1/m + (tau - mean)^2 / Stt) is tested too.
    lev = 1.0 / m + (tau - (st / m)[:, None]) ** 2 / np.where(den > 0, den / m, 1.0)[:, None]
    frame = (r * r).sum(axis=2) / np.maximum(1.0 - lev, 1e-3)
    msr = np.where(frame.max(axis=1) <= FRAME_LIMIT, msr, np.inf)
    return a * scale, np.where(np.isfinite(msr), msr, np.inf)


def _apply(X: FloatArray, value: FloatArray, centre: FloatArray) -> FloatArray:
    """Poses moved by ``value`` (rotation vector, centre displacement; camera frame)."""
    from scipy.spatial.transform import Rotation

    out = np.repeat(np.eye(4)[None], len(X), axis=0)
    out[:, :3, :3] = Rotation.from_rotvec(value[:, :3]).as_matrix() @ X[:, :3, :3]
    p = np.einsum("nij,j->ni", X[:, :3, :3], centre) + X[:, :3, 3] + value[:, 3:]
    out[:, :3, 3] = p - np.einsum("nij,j->ni", out[:, :3, :3], centre)
    return out


def smooth_poses(
    times: npt.ArrayLike,
    X: npt.ArrayLike,
    valid: npt.ArrayLike | None = None,
    *,
    centre: npt.ArrayLike | None = None,
    half_window: int = HALF_WINDOW,
    noise: npt.ArrayLike | None = None,
    restart: npt.ArrayLike | None = None,
) -> FloatArray:
    """Smooth a pose sequence, keeping its jumps and kinks (see the module notes).

    Parameters
    ----------
    times : array_like, shape (N,)
        Seconds (increasing).
    X : array_like, shape (N, 4, 4)
        Poses (e.g. ``X_CG``, metres); rows where not ``valid`` are returned unchanged.
    valid : array_like of bool, shape (N,), optional
        The tracked frames (default all).
    centre : array_like, shape (3,), optional
        The point of the model whose displacement is fitted (its centre: rotation and
        position then decouple), model frame; default the origin.
    half_window : int, optional
        The longest window has ``2 half_window + 1`` tracked frames; 0 returns the poses.
    noise : array_like, shape (6,), optional
        Noise of the coordinates (:func:`pose_noise`); default estimated from the sequence
        (too short a sequence to estimate it is returned unchanged).
    restart : array_like of bool, shape (N,), optional
        Frames where tracking started afresh (re-initialised): no window spans one, nor a
        lost frame.

    Returns
    -------
    ndarray, shape (N, 4, 4)
    """
    t = np.asarray(times, dtype=np.float64)
    P = np.asarray(X, dtype=np.float64)
    ok: BoolArray = (
        np.ones(len(P), dtype=bool) if valid is None else np.asarray(valid, dtype=bool).copy()
    )
    ok &= np.isfinite(P).all(axis=(1, 2))
    c = np.zeros(3) if centre is None else np.asarray(centre, dtype=np.float64)
    rs = np.zeros(len(P), dtype=bool) if restart is None else np.asarray(restart, dtype=bool)
    scale = pose_noise(t, P, ok, c, rs) if noise is None else np.asarray(noise, dtype=np.float64)
    out = P.copy()
    idx = np.nonzero(ok)[0]
    if half_window < 1 or len(idx) < 3 or not np.isfinite(scale).all():
        return out
    Xv = P[idx]
    y = _neighbours(t[idx], Xv, c, 2 * half_window, _runs(ok, rs))
    mid = 2 * half_window  # the column of the frame itself
    value = np.zeros((len(idx), 6))
    done = np.zeros(len(idx), dtype=bool)
    for h in range(half_window, min(MIN_HALF_WINDOW, half_window) - 1, -1):  # longest first
        fits = [_window_fits(y, scale, mid - h + s, mid + h + s + 1) for s in range(-h, h + 1)]
        msr = np.stack([f[1] for f in fits])  # (2h + 1, N)
        best = msr.min(axis=0)
        # the most central window within CENTRAL_SLACK of the best
        off = np.abs(np.arange(-h, h + 1))[:, None] + np.where(msr <= best + CENTRAL_SLACK, 0, 99)
        pick = np.argmin(off, axis=0)
        use = ~done & (best <= FIT_LIMIT)
        vals = np.stack([f[0] for f in fits])  # (2h + 1, N, 6)
        value[use] = vals[pick[use], np.nonzero(use)[0]]
        done |= use
    out[idx[done]] = _apply(Xv[done], value[done], c)
    return out
