"""Input checks of recognition: the pose sequence, its units, the default threshold."""

from __future__ import annotations

import functools

import numpy as np
import numpy.typing as npt

from apo.contact import OBSERVED_THRESHOLD_FRACTION
from apo.contact import default_threshold as contact_default_threshold
from apo.errors import InputFormatError
from apo.geometry import Polyhedron
from apo.recognition.types import FloatArray
from apo.spatial import pose_defect

__all__ = ["FAR_FACTOR", "THRESHOLD_FRACTION", "check_scale", "check_sequence", "default_threshold"]

THRESHOLD_FRACTION = OBSERVED_THRESHOLD_FRACTION
"""Default contact threshold of recognition, as a fraction of the smaller model's ``scale``
(``apo.contact.OBSERVED_THRESHOLD_FRACTION``, where the choice is explained)."""

default_threshold = functools.partial(contact_default_threshold, observed=True)
"""``default_threshold(grasped, environment)``: the default contact threshold for observed
poses (metres), :func:`apo.contact.default_threshold` with ``observed=True``."""


def check_sequence(
    times: npt.ArrayLike, X_EG_seq: npt.ArrayLike, *, source: str = "demonstration"
) -> tuple[FloatArray, FloatArray]:
    """Validate a pose sequence; return ``(times, X_EG_seq)`` as float arrays.

    Raises
    ------
    InputFormatError
        Empty sequence, wrong shapes, non-finite values, non-rigid poses, or times that go
        backwards; the message names ``source`` and the frame.
    """
    X = np.asarray(X_EG_seq, dtype=np.float64)
    if X.ndim != 3 or X.shape[1:] != (4, 4):
        raise InputFormatError(f"{source}: expected poses of shape (N, 4, 4), got {X.shape}")
    n = X.shape[0]
    if n == 0:
        raise InputFormatError(f"{source}: empty sequence (no frames)")
    t = np.arange(n, dtype=np.float64) if times is None else np.asarray(times, dtype=np.float64)
    if t.shape != (n,):
        raise InputFormatError(f"{source}: expected {n} time stamps, got shape {t.shape}")
    defect = pose_defect(X)  # the one rule of a valid pose (apo.spatial)
    if defect is not None and defect[1] == "finite":
        raise InputFormatError(f"{source}: frame {defect[0]}: pose is not finite")
    if not np.isfinite(t).all():
        raise InputFormatError(
            f"{source}: frame {int(np.argmax(~np.isfinite(t)))}: time is not finite"
        )
    back = np.diff(t) < 0
    if back.any():
        raise InputFormatError(f"{source}: frame {int(np.argmax(back)) + 1}: time goes backwards")
    if defect is not None:
        raise InputFormatError(f"{source}: frame {defect[0]}: not a rigid pose ({defect[2]})")
    return t, X


#: Poses that never bring G within this many model sizes of E suggest wrong units.
FAR_FACTOR = 50.0


def check_scale(grasped: Polyhedron, environment: Polyhedron, X: FloatArray, source: str) -> None:
    """Raise if G is never near E: the poses or the models are in the wrong units."""
    centre_g = 0.5 * (grasped.vertices.min(axis=0) + grasped.vertices.max(axis=0))
    lo, hi = environment.vertices.min(axis=0), environment.vertices.max(axis=0)
    c = np.einsum("nij,j->ni", X[:, :3, :3], centre_g) + X[:, :3, 3]
    gap = np.linalg.norm(np.maximum(0.0, np.maximum(lo - c, c - hi)), axis=1)
    size = max(grasped.scale, environment.scale)
    if float(gap.min()) > FAR_FACTOR * size:
        raise InputFormatError(
            f"{source}: the grasped object is never near the environment (closest "
            f"{gap.min():.4g} m for models of {size:.4g} m): are the poses and the models in "
            "the same units (--units)?"
        )


# --------------------------------------------------------------------------------------------
# Distances of contact elements over a sequence of poses
# --------------------------------------------------------------------------------------------
