"""Default distance threshold and angular tolerance of the contact search."""

from __future__ import annotations

import numpy as np

from apo.constants import tol
from apo.geometry import Polyhedron

DEFAULT_THRESHOLD_FRACTION = tol.threshold_fraction
"""Default threshold as a fraction of the smaller model's ``scale`` (bounding diagonal)."""


OBSERVED_THRESHOLD_FRACTION = tol.observed_threshold_fraction
"""Default threshold for observed poses, as a fraction of the smaller model's ``scale``.

Observed poses carry vision noise of millimetres; :data:`DEFAULT_THRESHOLD_FRACTION` (a
fraction of a millimetre for a 10 cm part) suits exact poses, not observations. 3.5 % of the
bounding diagonal is 4.1 mm for the first author's 118 mm peg, the order of the paper's
threshold for its stereo data. Recognition uses it (``apo.recognition.default_threshold``).
"""


def default_threshold(
    grasped: Polyhedron, environment: Polyhedron, *, observed: bool = False
) -> float:
    """Default contact threshold: a fraction of the smaller model's ``scale`` (metres).

    Parameters
    ----------
    grasped, environment : Polyhedron
        The two models.
    observed : bool
        False (default): :data:`DEFAULT_THRESHOLD_FRACTION`, for exact (synthetic or
        corrected) poses. True: :data:`OBSERVED_THRESHOLD_FRACTION`, for observed poses (the
        default of recognition, ``apo.recognition.default_threshold``).

    Returns
    -------
    float
        Metres; e.g. 0.12 mm (exact) or 4.1 mm (observed) for the 118 mm T-peg.
    """
    fraction = OBSERVED_THRESHOLD_FRACTION if observed else DEFAULT_THRESHOLD_FRACTION
    return fraction * min(grasped.scale, environment.scale)


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
