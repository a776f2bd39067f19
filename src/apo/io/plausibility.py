"""Do the poses and the models agree in scale? (metres read as millimetres, or the reverse).

A pose file in metres read as millimetres puts the grasped object 1,000 times too close to
the environment's origin, and the reverse 1,000 times too far: the recognition then runs to
"1 state, 0 transitions" without a word. :func:`scale_warnings` looks at two facts that do
not depend on the contact search:

- **Reach.** Every point of G lies within ``R_G`` (its farthest vertex from its own origin)
  of G's origin, and every point of E within ``R_E`` of E's origin; so if G's origin stays
  farther than ``R_G + R_E + threshold`` from E's origin in every frame, the models never
  come within the threshold of each other (a proof, not a guess).
- **Extent.** The diagonal of the box swept by G's origin, over the smaller model's
  diagonal, lies between :data:`EXTENT_RATIO` in every demonstration of an assembly we
  know (the first author's: 1.7; the built-in example: 1.4); 1,000 times off is far outside.

When either fails it names the length unit in which the poses would pass both tests (the
one closest to a ratio of 1), or says that none of apo's units would.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from apo.constants import UNITS

if TYPE_CHECKING:
    from apo.geometry import Polyhedron

__all__ = ["EXTENT_RATIO", "scale_warnings"]

EXTENT_RATIO = (1e-2, 1e2)
"""Plausible range of (extent of G's motion) / (smaller model's bounding-box diagonal)."""

_UNITS = UNITS


def _facts(
    G: Polyhedron, E: Polyhedron, p: npt.NDArray[np.float64], threshold: float
) -> tuple[float, float, float, float]:
    """``(closest origin distance, reach, motion extent, model size)``, metres."""
    reach = float(
        np.linalg.norm(G.vertices, axis=1).max() + np.linalg.norm(E.vertices, axis=1).max()
    )
    size = float(
        min(np.linalg.norm(np.ptp(G.vertices, axis=0)), np.linalg.norm(np.ptp(E.vertices, axis=0)))
    )
    closest = float(np.linalg.norm(p, axis=1).min())
    extent = float(np.linalg.norm(np.ptp(p, axis=0)))
    return closest, reach + threshold, extent, size


def _fits(closest: float, reach: float, extent: float, size: float, f: float) -> bool:
    """Return True if positions scaled by ``f`` can touch and move plausibly for the models."""
    if closest * f > reach:
        return False
    if extent == 0.0:  # a single pose, or no motion: nothing to judge
        return True
    return EXTENT_RATIO[0] <= extent * f / size <= EXTENT_RATIO[1]


def scale_warnings(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG: npt.ArrayLike,
    *,
    units: str,
    threshold: float | None = None,
    models_follow_units: bool = False,
) -> list[str]:
    """Warnings (one line each) if the poses do not fit the models' size; empty if they do.

    Parameters
    ----------
    grasped, environment : Polyhedron
        The models, metres, each in its own frame.
    X_EG : array_like, shape (N, 4, 4)
        Poses of G in E, metres, as read with ``units``.
    units : {"mm", "cm", "m", "in"}
        The unit the poses were read in (named in the message).
    threshold : float, optional
        Contact distance threshold, metres (default 0: touching).
    models_follow_units : bool
        True if the models were read in ``units`` too (mesh files and ``--units``): then the
        hint says to convert a file rather than to pass ``--units``.

    Returns
    -------
    list of str
        At most one line: what is wrong, the figures in ``units``, and the unit that would fit.
    """
    X = np.asarray(X_EG, dtype=np.float64)
    if X.ndim != 3 or X.shape[0] == 0:
        return []
    k = _UNITS[units]
    closest, reach, extent, size = _facts(grasped, environment, X[:, :3, 3], threshold or 0.0)
    if _fits(closest, reach, extent, size, 1.0):
        return []
    if closest > reach:
        what = (
            f"the grasped model never comes within the threshold of the environment "
            f"(its origin stays {closest / k:.4g} {units} or more from the environment's; "
            f"they could touch only within {reach / k:.4g} {units})"
        )
    else:
        what = (
            f"the grasped object's motion spans {extent / k:.4g} {units}, for models "
            f"{size / k:.4g} {units} across"
        )
    fitting = [
        u for u in _UNITS if u != units and _fits(closest, reach, extent, size, _UNITS[u] / k)
    ]
    ratio = extent / size if extent > 0 else closest / reach
    if fitting:
        best = min(fitting, key=lambda u: abs(math.log(max(ratio * _UNITS[u] / k, 1e-300))))
        hint = f"the poses would fit the models in {best}" + (
            f" (convert the pose file: --units {best} would rescale the models too)"
            if models_follow_units
            else f" (--units {best})"
        )
    else:
        factor = 1.0 / ratio if extent > 0 else reach / closest
        hint = (
            f"no unit of {', '.join(_UNITS)} fits: the positions look about "
            f"{_round_factor(factor)} times too {'small' if factor > 1 else 'large'}"
        )
    return [f"poses read in {units} do not fit the models' size: {what}; {hint}"]


def _round_factor(f: float) -> str:
    """``1000`` for 873.2 or 1/1130.5 (the power of ten nearest to the factor or its inverse)."""
    g = f if f >= 1 else 1.0 / f
    return f"{10 ** round(math.log10(g)):g}"
