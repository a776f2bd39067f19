"""Default distance threshold and angular tolerance of the search, and pose checks."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from apo.constants import tol
from apo.geometry import Polyhedron
from apo.typing import FloatArray

DEFAULT_THRESHOLD_FRACTION = 1e-3
"""Default threshold as a fraction of the smaller model's ``scale`` (bounding diagonal)."""


def _check_pose(X: npt.ArrayLike) -> FloatArray:
    M = np.asarray(X, dtype=np.float64)
    if M.shape != (4, 4):
        raise ValueError(f"X_EG must have shape (4, 4), got shape {M.shape}")
    if not np.all(np.isfinite(M)):
        raise ValueError("X_EG has non-finite entries")
    R = M[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
        raise ValueError("X_EG's rotation part is not a rotation matrix")
    return M


def _check_poses(X_seq: Iterable[npt.ArrayLike] | npt.ArrayLike) -> FloatArray:
    """Validate poses as :func:`_check_pose` does, vectorised; returns shape (N, 4, 4)."""
    if isinstance(X_seq, np.ndarray) and X_seq.ndim == 3:
        M = np.asarray(X_seq, dtype=np.float64)
        items: Sequence[Any] | FloatArray = M
    else:
        items = list(X_seq)  # type: ignore[arg-type]
        if not items:
            return np.zeros((0, 4, 4))
        try:
            M = np.asarray(items, dtype=np.float64)
        except ValueError:
            M = np.zeros((0,))
    ok = M.ndim == 3 and M.shape[1:] == (4, 4)
    if ok:
        R = M[:, :3, :3]
        good = np.all(np.isfinite(M), axis=(1, 2))
        RRt = np.einsum("nij,nkj->nik", R, R)
        with np.errstate(invalid="ignore"):
            good &= np.all(np.isclose(RRt, np.eye(3), atol=1e-6), axis=(1, 2))
            good &= np.linalg.det(np.where(np.isfinite(R), R, 0.0)) > 0
        ok = bool(good.all())
    if not ok:  # find the culprit and say what is wrong with it
        for k, X in enumerate(items):
            try:
                _check_pose(X)
            except ValueError as exc:
                raise ValueError(f"pose {k}: {exc}") from None
        raise ValueError(f"X_EG_seq must have shape (N, 4, 4), got shape {M.shape}")
    return M


def default_threshold(grasped: Polyhedron, environment: Polyhedron) -> float:
    """Default contact threshold: ``DEFAULT_THRESHOLD_FRACTION`` of the smaller ``scale``.

    Parameters
    ----------
    grasped, environment : Polyhedron
        The two models.

    Returns
    -------
    float
        Metres; e.g. 0.12 mm for the 118 mm T-peg.
    """
    return DEFAULT_THRESHOLD_FRACTION * min(grasped.scale, environment.scale)


def default_angle_tolerance(
    grasped: Polyhedron, environment: Polyhedron, threshold: float
) -> float:
    """Default angular tolerance (rad) of the normal-cone intersection and parallel edges.

    Parameters
    ----------
    grasped, environment : Polyhedron
        The two models.
    threshold : float
        Contact threshold, metres.

    Returns
    -------
    float
        ``clip(4 * threshold / min(scale), tol.normal_angle, 0.2)``: a flush face of length
        ``L`` whose ends are both within the threshold may be tilted by up to
        ``2 * threshold / L``; the factor 4 allows faces down to half the bounding diagonal
        with margin.
    """
    s = min(grasped.scale, environment.scale)
    return float(np.clip(4.0 * threshold / s, tol.normal_angle, 0.2))
