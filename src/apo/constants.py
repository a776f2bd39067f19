"""Tolerances used by the geometry and DOF analysis, gathered in one place.

All lengths are in metres, angles in radians. Contact finding scales length tolerances by the
model size where noted. See ``docs/conventions.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

UNITS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}
"""Length units apo reads and writes, and their size in metres: the one table (``task.UNITS``,
``io.meshes.UNITS``, ``io.poses.UNITS`` are this object)."""


@dataclass(frozen=True)
class Tolerances:
    """Named tolerances (SI units).

    Attributes
    ----------
    rank : float
        Relative singular-value threshold for ranks of unit-column matrices (DOF analysis).
    cone : float
        Feasibility tolerance of the cone LPs, on unit-normalised generators.
    coplanar_angle : float
        Two triangles are one face when their normals differ by less than this (rad).
    coplanar_distance : float
        ... and their planes are closer than this fraction of the model's bounding diagonal.
    merge : float
        Vertices closer than this fraction of the bounding diagonal are merged.
    normal_angle : float
        Angular tolerance (rad) when intersecting local cones of separating normals.
    rotation : float
        A pose's 3x3 block is a rotation when ``max |R R^T - I| <= rotation`` and
        ``det R > 0`` (:func:`apo.spatial.check_poses`, the one pose validator); loose enough
        for rotation matrices printed with 6 significant digits.
    correction : float
        Pose correction has converged when every contact residual is at most this (m): a
        corrected pose of the task model is exact to rounding (Gauss-Newton converges
        quadratically, so this costs at most one step more than 1e-9).
    correction_screening : float
        The same for the correction of every observed frame during recognition (m), which
        only decides whether the contacts can hold: 1e-7 m, 10^4 below any contact
        threshold, stops a few Gauss-Newton steps earlier than ``correction`` on thousands
        of frames.
    correction_rcond : float
        Rank cut of the correction's SVD step: singular values below ``rcond * s_max`` of
        the scaled (dimensionless, O(1)) Jacobian are treated as zero.
    """

    rank: float = 1e-6
    cone: float = 1e-7
    coplanar_angle: float = 1e-4
    coplanar_distance: float = 1e-7
    merge: float = 1e-8
    normal_angle: float = 1e-3
    rotation: float = 1e-4
    correction: float = 1e-12
    correction_screening: float = 1e-7
    correction_rcond: float = 1e-7


tol = Tolerances()
