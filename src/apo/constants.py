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
        Feasibility tolerance of the cone LPs, on unit-normalised generators; the least
        tolerance of the sign tests on null vectors, which follow the rank rule's null-space
        error up to ``cone_max`` (:func:`apo.dof._null_space_eta`).
    cone_max : float
        The largest tolerance of those sign tests (a null space barely above the rank cut is
        ill-posed at this precision whatever the tolerance).
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
    correction_stall : float
        A Gauss-Newton step of pose correction that does not lower the cost below this
        fraction of the previous cost counts as a stall.
    correction_rcond : float
        Rank cut of the correction's SVD step: singular values below ``rcond * s_max`` of
        the scaled (dimensionless, O(1)) Jacobian are treated as zero.
    slide_motion_rotation, slide_motion_translation : float
        Smallest demonstrated motion along a slide's direction between the two states'
        poses (rad about the axis; m of the contact centroid) that fixes the slide's sign
        (``apo.transitions``; ``docs/recognition.md``).

    Numerically zero (rounding of order-1 numbers, not a physical size):

    zero_norm : float
        A vector of order-1 data (rotation axis, rotation vector, contact normal, cross
        product of unit vectors) or a relative area whose norm is at most this is zero;
        also the floor that keeps such a norm from dividing by zero.
    quaternion_zero_norm : float
        A quaternion (from a file or a caller, entries of order 1) shorter than this has no
        direction and is refused rather than normalised (:func:`apo.spatial.check_quaternion`).
    division_floor : float
        Floor of a norm that is only divided by (never compared): keeps ``0 / 0`` out of
        vectorised code whose result is then masked.
    twist_series_angle : float
        Below this rotation angle (rad) the batched exponential of twists (pose correction)
        uses the Taylor series of ``sin t / t``, ``(1 - cos t) / t^2``, ``(t - sin t) / t^3``:
        they are exact to rounding there while the closed forms lose digits to cancellation
        (:func:`apo.spatial.pose_from_twist`, one twist at a time, switches to its first-order
        form only at ``zero_norm``).

    orthogonal_rtol, orthogonal_atol : float
        A matrix converted to a quaternion (:func:`apo.spatial.quaternions_from_matrices`)
        is used as it is when its Gram matrix is the identity within these
        (``numpy.isclose``), else replaced by its nearest rotation first: scipy's
        ``Rotation.from_matrix`` rule, kept so the quaternions equal scipy's bit for bit.

    Model data (exact geometry, rounding only):

    rigid_transform : float
        A transform applied to a model's vertices (:func:`apo.geometry.transformed`) is
        rigid when ``R^T R`` is within this of the identity (``numpy.allclose`` absolute
        part): it changes the model itself, so it must be rigid to rounding, unlike an
        observed pose (``rotation``).
    model_cone : float
        Tangent cones of a model's vertices and edges: relative rank cut of the face normals,
        zero cross products, feasibility of candidate extreme rays.
    model_cone_merge : float
        Extreme rays of one tangent cone closer than this angle (rad) are one ray; looser
        than ``model_cone`` because the rays are cross products of face normals of models
        read from files (rounded coordinates).

    Separating normals and the contact search (``apo.contact``):

    ray_sum_norm : float
        A sum of unit rays in a plane shorter than this has no mean direction (the rays
        cancel): no separating normal is taken from it.
    ray_merge : float
        Separating normals snapped to exact model normals closer than this angle (rad) are
        the same normal (only rounding separates them).
    ray_merge_factor : float
        Rays of separating normals closer than this many angular tolerances of the search
        are one ray: within one pair of convex pieces and across the pairs of one element.
    parallel_cos : float
        Two lineality directions whose ``|cos|`` exceeds this (2.6 deg) are treated as
        parallel: no common perpendicular is solved in closed form (the general path is
        taken); the scalar reference and the vectorised search use the same bound.
    sphere_margin : float
        Bounding-sphere tests of the contact search use ``radius * (1 + sphere_margin)``, so
        rounding never drops a pair within the threshold.
    threshold_fraction : float
        Default contact threshold for exact (synthetic or corrected) poses, as a fraction of
        the smaller model's bounding diagonal
        (``apo.contact.DEFAULT_THRESHOLD_FRACTION``).
    observed_threshold_fraction : float
        Default contact threshold for observed poses (recognition), as a fraction of the
        smaller model's bounding diagonal (``apo.contact.OBSERVED_THRESHOLD_FRACTION``, where
        the 3.5 % is explained).

    Sub-skills (``apo.transitions``):

    subskill_direction : float
        A sub-skill direction or axis shorter than this is zero, and the relative rank cut
        of the subspaces sub-skills act in: their rows come from the DOF analysis (unit to
        rounding), so the cut is tighter than ``rank``, which faces measured normals.
    twist_axis_match : float
        A maintaining twist belongs to a rotation axis of a sub-skill when its rotation part
        equals the axis within this (both unit vectors from one DOF analysis).

    JSON documents (task.json, motion.json: ``apo.task``, ``apo.jsonform``):

    json_quaternion_norm : float
        A pose quaternion is accepted when ``| |q| - 1 |`` is at most this (apo writes 9
        decimals; this admits hand-written files with 6-7 digits). Tighter than
        ``json_unit_norm`` because an error in ``q`` is an error in the pose itself.
    json_unit_norm : float
        A unit vector (contact normal, direction, axis) is accepted when ``| |n| - 1 |`` is
        at most this, and orthonormal rows when their Gram matrix is the identity within it
        (as loose as ``rotation``: vectors printed with 5 significant digits).
    """

    rank: float = 1e-6
    cone: float = 1e-7
    cone_max: float = 1e-5
    coplanar_angle: float = 1e-4
    coplanar_distance: float = 1e-7
    merge: float = 1e-8
    normal_angle: float = 1e-3
    rotation: float = 1e-4
    correction: float = 1e-12
    correction_screening: float = 1e-7
    correction_rcond: float = 1e-7
    correction_stall: float = 0.999
    zero_norm: float = 1e-12
    quaternion_zero_norm: float = 1e-9
    division_floor: float = 1e-300
    twist_series_angle: float = 1e-8
    orthogonal_rtol: float = 1e-5
    orthogonal_atol: float = 1e-12
    rigid_transform: float = 1e-9
    model_cone: float = 1e-9
    model_cone_merge: float = 1e-7
    ray_sum_norm: float = 1e-9
    ray_merge: float = 1e-9
    ray_merge_factor: float = 3.0
    parallel_cos: float = 0.999
    sphere_margin: float = 1e-9
    threshold_fraction: float = 1e-3
    observed_threshold_fraction: float = 0.035
    subskill_direction: float = 1e-9
    slide_motion_rotation: float = 0.0349065850398866  # 2 degrees
    slide_motion_translation: float = 0.002
    twist_axis_match: float = 1e-6
    json_quaternion_norm: float = 1e-6
    json_unit_norm: float = 1e-4


tol = Tolerances()
