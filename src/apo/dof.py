"""Admissible-displacement cones and DOF indices of a contact state (paper section 2).

Every cone quantity reduces to one primitive, :func:`maximal_support`: the indices ``i`` with
``-g_i`` in ``cone(G)`` (the implicit equalities of ``{x : G^T x >= 0}``), found from the
numerical null space of ``G`` and, when needed, one small LP solved with HiGHS. See
``docs/dof.md`` for the derivation, the tolerances and the singular-state convention.

Twists are ``[S0; S1]`` (rotation first, paper section 2.1) in the environment frame; a contact
constraint is ``(P_i x F_i) . S0 + F_i . S1 >= 0`` (paper eq. 2).
"""

from __future__ import annotations

import itertools
import math
import os
import sys
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import numpy.typing as npt

from apo.constants import Tolerances, tol
from apo.errors import GeometryError, InputFormatError
from apo.typing import BoolArray, FloatArray

if TYPE_CHECKING:
    import highspy


@dataclass(frozen=True, slots=True)
class ContactPoint:
    """One contact point with its separating normals (environment frame, metres).

    Attributes
    ----------
    point : ndarray, shape (3,)
        Contact point P_i.
    normals : ndarray, shape (M, 3)
        Unit separating normals F_i1..F_iM, pointing from the environment towards the
        grasped object. M > 1 makes the point singular.
    """

    point: FloatArray
    normals: FloatArray

    @property
    def singular(self) -> bool:
        """True if the point has more than one separating normal."""
        return int(self.normals.shape[0]) > 1


@dataclass(frozen=True)
class SpaceDof:
    """Maintaining / detaching / constraining DOF of one space (translation or all)."""

    maintaining: int
    detaching: int
    constraining: int


@dataclass(frozen=True)
class RotationDof(SpaceDof):
    """Rotation DOF; detaching split into type I (both ways) and type II (one way)."""

    detaching_type1: int = 0
    detaching_type2: int = 0


@dataclass(frozen=True)
class Restraining:
    """Restraining DOF r_t, r_r, r_a (paper section 3.5), over all elements and normals."""

    translation: int
    rotation: int
    all: int


@dataclass(frozen=True)
class DofGeometry:
    """Orthonormal bases (as rows) of the subspaces behind the numbers (environment frame).

    Attributes
    ----------
    translation_maintaining : ndarray, shape (m_t, 3)
        Translations that keep every contact (null space of R_t^T).
    translation_constraining : ndarray, shape (c_t, 3)
        Translation directions removed by the contacts (span of the lineality of cone(F)).
    translation_detaching : ndarray, shape (d_t, 3)
        Complement of the two above: translations that break some contact one way only.
    rotation_maintaining : ndarray, shape (m_r, 3)
        Rotation axes of maintaining twists (S0 parts of the maintaining twists).
    rotation_constraining : ndarray, shape (c_r, 3)
        Orthogonal complement of span(V_r).
    rotation_detaching : ndarray, shape (d_r, 3)
        The rest; ``rotation_detaching_type1`` (d_r1, 3) the two-way part.
    rotation_detaching_type1 : ndarray, shape (d_r1, 3)
        Axes of detaching rotations possible both ways: ``lin(V_r)`` minus the maintaining
        axes (orthogonal complement of ``rotation_maintaining`` inside ``lin(V_r)``).
    maintaining_twists : ndarray, shape (m_a, 6)
        Basis of maintaining twists ``[S0; S1]`` (null space of ``R_a^T``), in a canonical
        form (paper Fig. 3): the first ``m_t`` rows are the pure translations
        ``[0; t]`` with ``t`` the rows of ``translation_maintaining``; the next ``m_r`` rows
        have ``S0`` = the rows of ``rotation_maintaining`` (unit, rad) and ``S1`` (metres per
        rad) orthogonal to every maintaining translation. Not orthonormal as 6-vectors.
    rotation_detaching_type2 : ndarray, shape (d_r2, 3)
        ``span(V_r)`` minus ``lin(V_r)``: axes about which the object turns one way only.
    translation_detaching_direction : ndarray, shape (3,)
        Unit translation in the relative interior of ``V_t`` inside the detaching subspace:
        moving along it keeps every contact that translation cannot break and breaks all the
        others (it minimises ``sum F_i . u`` subject to ``F_i . u >= 1`` on the breakable
        contacts, then is normalised). Zero vector when ``d_t = 0``.

    Notes
    -----
    In a singular state the subspaces are those of the analysis of the non-singular elements
    (the ``singular_dof_*`` numbers). Rows are orthonormal unless said otherwise; the
    partitions are orthogonal: ``translation_maintaining``, ``translation_detaching`` and
    ``translation_constraining`` together span R^3, and so do ``rotation_maintaining``,
    ``rotation_detaching`` and ``rotation_constraining``; ``rotation_detaching`` is spanned by
    ``rotation_detaching_type1`` and ``rotation_detaching_type2``.
    """

    translation_maintaining: FloatArray
    translation_detaching: FloatArray
    translation_constraining: FloatArray
    rotation_maintaining: FloatArray
    rotation_detaching: FloatArray
    rotation_detaching_type1: FloatArray
    rotation_constraining: FloatArray
    maintaining_twists: FloatArray
    rotation_detaching_type2: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    translation_detaching_direction: FloatArray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True)
class DofResult:
    """Every DOF index of a contact state (docs/theory.md, paper sections 2.2 and 3.5).

    In a singular state the regular ``translation``/``rotation``/``all`` are all zero and the
    analysis of the non-singular elements is in ``singular_dof``; in a non-singular state
    ``singular_dof`` is all zero.
    """

    singular: bool
    translation: SpaceDof
    rotation: RotationDof
    all: SpaceDof
    singular_dof_translation: SpaceDof
    singular_dof_rotation: RotationDof
    singular_dof_all: SpaceDof
    restraining: Restraining
    geometry: DofGeometry = field(compare=False, repr=False)

    @property
    def fig25(self) -> tuple[int, int, int, int, int, int, int, int]:
        """The eight numbers as the paper's Fig. 25 prints them.

        Translation M, D, C, rotation M, D, C (singular variants in a singular state),
        translation restraining, rotation restraining.
        """
        t = self.singular_dof_translation if self.singular else self.translation
        r = self.singular_dof_rotation if self.singular else self.rotation
        return (
            t.maintaining, t.detaching, t.constraining,
            r.maintaining, r.detaching, r.constraining,
            self.restraining.translation, self.restraining.rotation,
        )  # fmt: skip

    def six(self, space: str) -> tuple[int, int, int, int, int, int]:
        """Return (M, D, C, SM, SD, SC) of ``space`` ('translation' or 'rotation'); sums to 3."""
        if space == "translation":
            a, b = self.translation, self.singular_dof_translation
        elif space == "rotation":
            a, b = self.rotation, self.singular_dof_rotation
        else:
            raise ValueError(f"space must be 'translation' or 'rotation', got {space!r}")
        return (
            a.maintaining, a.detaching, a.constraining,
            b.maintaining, b.detaching, b.constraining,
        )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------


def check_contacts(
    contacts: Sequence[ContactPoint],
) -> tuple[FloatArray, list[FloatArray]]:
    """Validate contact points and return them as arrays with unit normals.

    Parameters
    ----------
    contacts : sequence of ContactPoint
        Contact points (environment frame, metres) with separating normals (any length > 0).

    Returns
    -------
    points : ndarray, shape (N, 3)
        The contact points.
    normals : list of ndarray, shape (M_i, 3)
        The normals of each point, scaled to unit length.

    Raises
    ------
    InputFormatError
        A point is not 3 finite numbers, a normals array is not ``(M, 3)`` with ``M >= 1``, or a
        normal is non-finite or zero. The message names the contact (0-based) and what was
        received.
    """
    return check_arrays(
        [c.point for c in contacts],
        [c.normals for c in contacts],
    )


def check_arrays(
    points: Sequence[Any] | FloatArray, normals_list: Sequence[Any]
) -> tuple[FloatArray, list[FloatArray]]:
    """Array version of :func:`check_contacts`: ``points[i]`` with normals ``normals_list[i]``.

    Raises
    ------
    InputFormatError
        As :func:`check_contacts`; also when the two sequences differ in length.
    """
    if len(points) != len(normals_list):
        raise InputFormatError(
            f"got {len(points)} points but {len(normals_list)} normal lists; they must match"
        )
    n = len(points)
    if n == 0:
        return np.zeros((0, 3)), []
    # Fast path: everything well formed (checked vectorised); else find the culprit.
    try:
        pts = np.array(points, dtype=np.float64)
        arrs = [np.asarray(ns, dtype=np.float64) for ns in normals_list]
        arrs = [a[None, :] if a.shape == (3,) else a for a in arrs]
        ok = pts.shape == (n, 3) and all(a.ndim == 2 and a.shape[1] == 3 for a in arrs)
        if ok:
            alln = np.concatenate(arrs)
            ok = (
                alln.shape[0] >= n
                and all(a.shape[0] >= 1 for a in arrs)
                and bool(np.isfinite(pts).all())
                and bool(np.isfinite(alln).all())
            )
        if ok:
            unit, nonzero = _directions(alln)
            ok = bool(nonzero.all())
        if ok:
            splits = np.cumsum([a.shape[0] for a in arrs])[:-1]
            return pts, list(np.split(unit, splits))
    except (TypeError, ValueError):
        pass
    for i, (p, ns) in enumerate(zip(points, normals_list, strict=True)):
        _check_one(i, p, ns)
    raise InputFormatError("contacts are malformed")  # pragma: no cover - _check_one raises


def _directions(normals: FloatArray) -> tuple[FloatArray, BoolArray]:
    """Return the unit directions of finite normals (rows, shape (M, 3)) and which are non-zero.

    A normal only matters by its direction: each row is first scaled by the power of two
    ``2**-e`` that brings its largest absolute component into [0.5, 1), which is exact, so
    no finite length overflows (components up to 1e308) and the directions are those of
    ``normals / |normals|`` bit for bit wherever that does not overflow. A row is zero when
    its length is at most ``tol.zero_norm`` (1e-12; its direction is then not meaningful).
    """
    _, e = np.frexp(np.abs(normals).max(axis=1))  # e = 0 for a zero row
    scaled = np.ldexp(normals, -e[:, None])
    length = np.sqrt(np.einsum("ij,ij->i", scaled, scaled))  # in [0.5, sqrt(3)), or 0
    # The true length is length * 2**e; where e > 0 it is at least 1, so only e <= 0 needs
    # the (exact, never overflowing) rescaling for the comparison.
    nonzero = np.ldexp(length, np.minimum(e, 0)) > tol.zero_norm
    unit = scaled / np.where(nonzero, length, 1.0)[:, None]
    return unit, nonzero


def _check_one(i: int, p: Any, ns: Any) -> None:
    """Raise :class:`InputFormatError` describing what is wrong with contact ``i``, if any."""
    try:
        pa = np.asarray(p, dtype=np.float64)
        na = np.asarray(ns, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputFormatError(f"contact {i}: not numeric ({exc})") from None
    if pa.shape != (3,):
        raise InputFormatError(f"contact {i}: point must have shape (3,), got {pa.shape}")
    if not np.all(np.isfinite(pa)):
        raise InputFormatError(f"contact {i}: point is not finite: {pa.tolist()}")
    if na.shape == (3,):
        na = na[None, :]
    if na.ndim != 2 or na.shape[1] != 3 or na.shape[0] < 1:
        raise InputFormatError(
            f"contact {i}: normals must have shape (M, 3) with M >= 1, got {na.shape}"
        )
    if not np.all(np.isfinite(na)):
        raise InputFormatError(f"contact {i}: normals are not finite: {na.tolist()}")
    bad = np.flatnonzero(~_directions(na)[1])
    if bad.size:
        raise InputFormatError(f"contact {i}: normal {int(bad[0])} is zero: {na[bad[0]].tolist()}")


# --------------------------------------------------------------------------------------------
# Linear-algebra primitives
# --------------------------------------------------------------------------------------------


def _rank_from_sv(s: npt.NDArray[np.floating[Any]], tolerances: Tolerances) -> int:
    """Rank rule: count singular values above ``tol.rank * max(s_1, 1)``."""
    if s.size == 0:
        return 0
    return int(np.count_nonzero(s > tolerances.rank * max(float(s[0]), 1.0)))


def numerical_rank(a: FloatArray, *, tolerances: Tolerances = tol) -> int:
    """Numerical rank of ``a``: singular values above ``tolerances.rank * max(sigma_1, 1)``.

    Parameters
    ----------
    a : ndarray, shape (n, k)
        Matrix, normally with unit (or O(1)) columns, so the threshold is relative to the
        largest singular value (which is at least 1 for unit columns).
    tolerances : Tolerances, optional
        Uses ``rank``.

    Returns
    -------
    int
    """
    if a.size == 0:
        return 0
    return _rank_from_sv(np.linalg.svd(a, compute_uv=False), tolerances)


_local = threading.local()

#: Perceptron steps tried for a pointedness certificate before falling back to the LP.
_CERTIFICATE_STEPS = 8


def _quiet_highs() -> highspy.Highs:
    """Return a new HiGHS instance, without the banner HiGHS >= 1.12 prints when built.

    The banner goes to the process's file descriptor 1 from C++ before any option can be
    set, so descriptor 1 is pointed at ``os.devnull`` for the constructor only.
    """
    import highspy  # imported on use (HiGHS only solves the LPs no closed form covers)

    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
            try:
                return highspy.Highs()  # type: ignore[no-untyped-call]
            finally:
                os.dup2(saved, 1)
    finally:
        os.close(saved)


def _highs() -> highspy.Highs:
    """One reusable, silent HiGHS instance per thread (construction costs ~80 us)."""
    h: highspy.Highs | None = getattr(_local, "highs", None)
    if h is None:
        h = _quiet_highs()
        h.setOptionValue("output_flag", False)
        # tiny dense LPs with a feasible start (y = 0, t = 0): presolve only costs time
        h.setOptionValue("presolve", "off")
        h.setOptionValue("solver", "simplex")
        h.setOptionValue("simplex_strategy", 4)  # primal simplex
        _local.highs = h
    h.clearModel()
    return h


def _highs_lp(
    cost: FloatArray,
    col_lower: FloatArray,
    col_upper: FloatArray,
    a: FloatArray,
    row_lower: FloatArray,
    row_upper: FloatArray,
) -> Any:
    """Return the HiGHS model of ``min cost . x``, ``row_lower <= a x <= row_upper``, bounds."""
    import highspy

    n_row, n_col = a.shape
    lp = highspy.HighsLp()
    lp.num_col_ = n_col
    lp.num_row_ = n_row
    lp.col_cost_ = cost
    lp.col_lower_ = col_lower
    lp.col_upper_ = col_upper
    lp.row_lower_ = row_lower
    lp.row_upper_ = row_upper
    lp.a_matrix_.format_ = highspy.MatrixFormat.kRowwise
    lp.a_matrix_.start_ = np.arange(0, n_row * n_col + 1, n_col, dtype=np.int32)
    lp.a_matrix_.index_ = np.tile(np.arange(n_col, dtype=np.int32), n_row)
    lp.a_matrix_.value_ = np.ascontiguousarray(a, dtype=np.float64).ravel()
    lp.a_matrix_.num_col_ = n_col
    lp.a_matrix_.num_row_ = n_row
    return lp


def _solve_lp(lp: Any, feasibility: float) -> FloatArray | None:
    """Solve the model ``lp`` (:func:`_highs_lp`); its solution, or None if not optimal."""
    import highspy

    h = _highs()
    h.setOptionValue("primal_feasibility_tolerance", feasibility)
    h.passModel(lp)
    h.run()
    if h.getModelStatus() != highspy.HighsModelStatus.kOptimal:
        # The fast settings of _highs (primal simplex, no presolve) can stop short on an LP
        # with free variables (seen on a noisy square-peg state: "maximal-support LP
        # failed"); a fresh instance with HiGHS's defaults solves it.
        h = _quiet_highs()
        h.setOptionValue("output_flag", False)
        h.setOptionValue("primal_feasibility_tolerance", feasibility)
        h.passModel(lp)
        h.run()
        if h.getModelStatus() != highspy.HighsModelStatus.kOptimal:
            return None
    return np.asarray(h.getSolution().col_value, dtype=np.float64)


#: HiGHS settings tried, in turn, when no setting proves an optimum (:func:`_support_rescue`).
_RESCUE_SETTINGS: tuple[dict[str, Any], ...] = (
    {},
    {"simplex_scale_strategy": 0},
    {"simplex_strategy": 4},
    {"solver": "ipm"},
)


def _support_rescue(lp: Any, z: FloatArray, eta: float) -> BoolArray:
    """Support from HiGHS's feasible but unproven points of the maximal-support LP.

    On some ill-conditioned cones of noisy contacts HiGHS stops with status "unknown" under
    every setting (seen on a random T-peg variant with a 0.75 mm offset). Each point it
    returns that satisfies ``Z y >= t`` here is a certificate: ``t_i > 1/2`` means
    ``z_i . y > 0``, so ``i`` is in the maximal support, and so is the union over several
    points (their sum is feasible). HiGHS's points may violate ``Z y >= 0`` by more than
    ``eta`` (1.5e-5 was seen): a point is accepted when ``Z y >= -sqrt(eta)`` and
    certifies the ``i`` with ``z_i . y > 1/2``, over a thousand times that slack at the
    default ``eta`` (the LP's ``t_i <= 1`` sets the scale of ``y``). The union over the settings
    tried is returned; it can miss part of the support only where no setting found it.
    """
    import highspy

    k = z.shape[1]
    slack = math.sqrt(eta)
    found = np.zeros(z.shape[0], dtype=bool)
    certified = False
    for settings in _RESCUE_SETTINGS:
        h = _quiet_highs()
        h.setOptionValue("output_flag", False)
        for key, value in settings.items():
            h.setOptionValue(key, value)
        h.passModel(lp)
        h.run()
        x = np.asarray(h.getSolution().col_value, dtype=np.float64)
        if x.shape != (k + z.shape[0],) or not np.isfinite(x).all():
            continue
        zy = z @ x[:k]
        if float(zy.min()) >= -slack:
            found |= zy > 0.5
            certified = True
        if h.getModelStatus() == highspy.HighsModelStatus.kOptimal:
            break
    if not certified:
        raise GeometryError(
            "maximal-support LP failed: HiGHS found no feasible point of the contact cone "
            f"({z.shape[0]} directions, {k}-dimensional null space); the contact state is "
            "numerically degenerate"
        )
    return found


def _support_1d(col: FloatArray, eta: float) -> BoolArray:
    """Support of ``{alpha z >= 0}`` for a unit vector ``z``: entries within ``eta`` are zero."""
    out = np.zeros(col.shape[0], dtype=bool)
    for w in (col, -col):
        if float(w.min()) >= -eta:
            out |= w > eta
    return out


def _support_lp_model(z: FloatArray) -> Any:
    """Return the HiGHS model of :func:`_support_lp`'s LP."""
    n_col, k = z.shape
    inf = float("inf")  # = highspy.kHighsInf
    return _highs_lp(
        np.concatenate([np.zeros(k), -np.ones(n_col)]),
        np.concatenate([np.full(k, -inf), np.zeros(n_col)]),
        np.concatenate([np.full(k, inf), np.ones(n_col)]),
        np.hstack([z, -np.eye(n_col)]),
        np.zeros(n_col),
        np.full(n_col, inf),
    )


def _support_lp(z: FloatArray, eta: float) -> BoolArray:
    """LP for the maximal support of ``{Z y >= 0}``: ``max sum t``, ``Z y >= t``, ``0 <= t <= 1``.

    At the optimum ``t_i = 1`` exactly on the support (sums of feasible points are feasible
    and the cone is scale-invariant); ``i`` is taken in the support when ``t_i > 1/2``.
    """
    lp = _support_lp_model(z)
    x_opt = _solve_lp(lp, eta)
    if x_opt is None:  # always feasible (y = 0, t = 0) and bounded, but HiGHS may stop short
        return _support_rescue(lp, z, eta)
    return np.asarray(x_opt[z.shape[1] :] > 0.5, dtype=bool)


def _null_space_eta(s: FloatArray, rank: int, tolerances: Tolerances) -> float:
    """Tolerance of the sign tests on a numerical null space's vectors (unit scale).

    The rank rule (:func:`_rank_from_sv`) takes ``G`` for a matrix of rank ``r`` plus a
    perturbation of norm up to ``tol.rank * max(sigma_1, 1)``; the null space it returns is
    then that of the nearby rank-``r`` matrix, off by an angle up to that over ``sigma_r``
    (Wedin's bound). A component of a null vector smaller than that is zero at the
    precision the rank rule already decided at: two walls opposite within ``tol.rank`` are
    opposite for the cone tests too (docs/dof.md, "Tolerances and the rank rule"). At least
    ``tol.cone``, at most ``tol.cone_max``.
    """
    if rank == 0:
        return tolerances.cone
    bound = tolerances.rank * max(float(s[0]), 1.0) / float(s[rank - 1])
    return min(max(bound, tolerances.cone), tolerances.cone_max)


def _support(g: FloatArray, s: FloatArray, vt: FloatArray, tolerances: Tolerances) -> BoolArray:
    """Maximal support of ``{lambda >= 0 : G lambda = 0}`` (see :func:`maximal_support`).

    ``g`` has unit columns, ``s`` and ``vt`` are its singular values and right singular
    vectors (full). Exact shortcuts first, the LP only on what they leave undecided.

    A known part ``low`` of the support (with ``cone(G[:, low])`` a subspace ``L``) is grown:
    ``S(G) = low + S(H)`` with ``H`` the other columns projected onto ``L^perp``. Each round
    adds columns inside ``L``, the support of a one-dimensional null space of ``H``, or the
    support of the projection of ``(1, ..., 1)`` onto ``null(H)`` when it is ``>= 0``; it
    stops with a pointedness certificate (``x`` with ``h_j . x > 0`` for all ``j``: then
    ``S(H)`` is empty), with ``null(H) = 0``, or falls back to the LP on ``null(H)``.
    """
    rank = _rank_from_sv(s, tolerances)
    z = vt[rank:].T
    n_col, k = z.shape
    if k == 0 or n_col == 0:
        return np.zeros(n_col, dtype=bool)
    eta = _null_space_eta(s, rank, tolerances)
    if k == 1:
        col = z[:, 0].copy()
        col[np.abs(col) <= eta] = 0.0
        return _support_1d(col, eta)
    # Opposite pairs g_i = -g_j (within tol.rank) are in the support; their cone is L.
    pair = np.linalg.norm(g[:, :, None] + g[:, None, :], axis=0) <= tolerances.rank
    low: BoolArray = np.asarray(pair.any(axis=1), dtype=bool)
    while True:
        rest = np.flatnonzero(~low)
        if rest.size == 0:
            return low
        if low.any():
            ub, sb, _ = np.linalg.svd(g[:, low], full_matrices=False)
            basis = ub[:, : _rank_from_sv(sb, tolerances)]
            h = g[:, rest] - basis @ (basis.T @ g[:, rest])
        else:
            h = g[:, rest]
        hn = np.linalg.norm(h, axis=0)
        inside = hn <= tolerances.rank
        if inside.any():  # g_j in L = cone(G[:, low]): -g_j is in the cone
            low[rest[inside]] = True
            continue
        hu = h / hn
        # pointedness certificate: x = sum of the columns, then a few perceptron steps
        x = hu.sum(axis=1)
        for _ in range(_CERTIFICATE_STEPS):
            nx = float(np.linalg.norm(x))
            violated = hu.T @ x <= eta * nx
            if nx > 0.0 and not violated.any():
                return low
            x = x + hu[:, violated].sum(axis=1)
        _, sh, vht = np.linalg.svd(hu, full_matrices=True)
        rank_h = _rank_from_sv(sh, tolerances)
        zh = vht[rank_h:].T
        if zh.shape[1] == 0:
            return low
        eta = max(eta, _null_space_eta(sh, rank_h, tolerances))
        zh[np.linalg.norm(zh, axis=1) <= eta] = 0.0
        if zh.shape[1] == 1:
            found = _support_1d(zh[:, 0], eta)
            if not found.any():
                return low
        else:
            lam = zh @ zh.sum(axis=0)  # projection of (1, ..., 1) onto null(H)
            nl = float(np.linalg.norm(lam))
            found = np.zeros(rest.size, dtype=bool)
            if nl > 0.0 and float(lam.min()) >= -eta * nl:
                found = lam > eta * nl
            if not found.any():
                low[rest[_support_lp(zh, eta)]] = True
                return low
        low[rest[found]] = True


def maximal_support(g: FloatArray, *, tolerances: Tolerances = tol) -> BoolArray:
    """Maximal support of ``{lambda >= 0 : G lambda = 0}``: the implicit equalities.

    Parameters
    ----------
    g : ndarray, shape (n, N)
        Generators ``g_i`` as columns (normalised to unit length here; zero columns are
        rejected).
    tolerances : Tolerances, optional
        ``rank`` for the numerical null space of ``G``, ``cone`` for the LP feasibility.

    Returns
    -------
    ndarray of bool, shape (N,)
        ``S[i]`` is True iff ``-g_i`` is in ``cone(G)``, i.e. iff ``g_i`` lies in the lineality
        space of ``cone(G)``, i.e. iff ``g_i . x = 0`` for every ``x`` with ``G^T x >= 0``.

    Notes
    -----
    ``i`` is in ``S`` iff some ``lambda >= 0`` with ``G lambda = 0`` has ``lambda_i > 0``
    (write ``-g_i = sum_j mu_j g_j``). The set is computed on the numerical null space
    ``Z`` of ``G`` (right singular vectors of singular values ``<= tol.rank * sigma_1``):
    with ``lambda = Z y``, solve ``max sum t_i`` s.t. ``Z y >= t``, ``0 <= t <= 1``; at the
    optimum ``t_i = 1`` exactly on ``S`` (the sum of feasible points is feasible and the cone
    is scale-invariant). ``i`` is taken in ``S`` when ``t_i > 1/2``. With a one-dimensional
    null space the LP is replaced by its closed form. No ``scipy.optimize.nnls``.
    """
    g = np.asarray(g, dtype=np.float64)
    if g.ndim != 2:
        raise ValueError(f"g must be a 2-D array (n, N), got shape {g.shape}")
    n_col = g.shape[1]
    if n_col == 0:
        return np.zeros(0, dtype=bool)
    lengths = np.linalg.norm(g, axis=0)
    if np.any(lengths <= 0.0) or not np.all(np.isfinite(lengths)):
        raise ValueError("g must have finite, non-zero columns")
    g = g / lengths
    _, s, vt = np.linalg.svd(g, full_matrices=True)
    return _support(g, s, vt, tolerances)


def _orth_complement(basis: FloatArray, remove: FloatArray, count: int, dim: int = 3) -> FloatArray:
    """Orthonormal rows spanning ``span(basis) minus span(remove)`` (the ``count`` largest).

    ``remove`` has orthonormal rows; ``basis`` rows span the containing subspace.
    """
    if count <= 0:
        return np.zeros((0, dim))
    b = basis - (basis @ remove.T) @ remove if remove.shape[0] else basis
    _, _, vt = np.linalg.svd(b, full_matrices=False)
    return np.asarray(vt[:count], dtype=np.float64)


def _canonical_rows(rows: FloatArray) -> FloatArray:
    """Fix the sign of each basis row: its largest-magnitude entry is positive."""
    if rows.shape[0] == 0:
        return rows
    idx = np.argmax(np.abs(rows), axis=1)
    signs = np.sign(rows[np.arange(rows.shape[0]), idx])
    signs[signs == 0] = 1.0
    return np.asarray(rows * signs[:, None], dtype=np.float64)


# --------------------------------------------------------------------------------------------
# The analysis
# --------------------------------------------------------------------------------------------


class _Regular(NamedTuple):  # not a dataclass: no methods made at import
    translation: SpaceDof
    rotation: RotationDof
    all: SpaceDof
    geometry: DofGeometry


def _normalised_columns(
    points: FloatArray, normals: FloatArray, centre: FloatArray, length: float
) -> tuple[FloatArray, FloatArray]:
    """Return unit normals (3, N) and unit ``[q x F; F]`` columns (6, N), ``q`` scaled."""
    f = normals.T
    q = (points - centre) / length
    w = np.vstack([np.cross(q, normals).T, f])
    w = w / np.linalg.norm(w, axis=0)
    return f, w


class _TranslationPart(NamedTuple):
    """Translation DOF of a regular state (eq. 3) and the subspaces that come with it."""

    dof: SpaceDof
    support: BoolArray  # S_t: contacts that must stay closed under every translation
    maintaining: FloatArray  # canonical rows
    constraining: FloatArray
    detaching: FloatArray
    direction: FloatArray
    null_support: FloatArray  # lambda on S_t with F_S lambda = 0


def _translation_part(f: FloatArray, tolerances: Tolerances) -> _TranslationPart:
    """Return the translation part (eq. 3) from the unit normals ``f`` (3, N)."""
    uf, sf, vft = np.linalg.svd(f, full_matrices=True)
    rank_f = _rank_from_sv(sf, tolerances)
    m_t = 3 - rank_f
    s_t = _support(f, sf, vft, tolerances)
    f_s = f[:, s_t]
    if f_s.shape[1]:
        ufs, sfs, vfst = np.linalg.svd(f_s, full_matrices=True)
        c_t = _rank_from_sv(sfs, tolerances)
        t_constr = ufs[:, :c_t].T
        null_fs = vfst[c_t:].T
    else:
        c_t = 0
        t_constr = np.zeros((0, 3))
        null_fs = np.zeros((0, 0))
    d_t = 3 - m_t - c_t
    t_det = _orth_complement(uf[:, :rank_f].T, t_constr, d_t)
    return _TranslationPart(
        dof=SpaceDof(m_t, d_t, c_t),
        support=s_t,
        maintaining=_canonical_rows(uf[:, rank_f:].T),
        constraining=t_constr,
        detaching=t_det,
        direction=_detaching_direction(f, s_t, t_det, tolerances),
        null_support=null_fs,
    )


def _all_part(w: FloatArray, tolerances: Tolerances) -> tuple[SpaceDof, FloatArray, FloatArray]:
    """Whole-motion DOF (eq. 4): the indices, ``null(W^T)`` (6, m_a) and ``span(V_a)``."""
    uw, sw, vwt = np.linalg.svd(w, full_matrices=True)
    rank_w = _rank_from_sv(sw, tolerances)
    m_a = 6 - rank_w
    s_a = _support(w, sw, vwt, tolerances)
    w_s = w[:, s_a]
    if w_s.shape[1]:
        uws, sws, _ = np.linalg.svd(w_s, full_matrices=True)
        c_a = _rank_from_sv(sws, tolerances)
        span_va = uws[:, c_a:]  # (6, 6 - c_a): span(V_a) = null(W_S^T)
    else:
        c_a = 0
        span_va = np.eye(6)
    return SpaceDof(m_a, 6 - m_a - c_a, c_a), uw[:, rank_w:], span_va


def _rotation_dual_lineality(
    w: FloatArray, trans: _TranslationPart, tolerances: Tolerances
) -> tuple[int, FloatArray]:
    """Return the rank of ``span(V_r*)`` and the rows of its orthogonal complement.

    ``V_r* = {sum lambda_i Mo_i : lambda >= 0, sum lambda_i F_i = 0}`` (proposition 5).
    """
    null_fs = trans.null_support
    if not null_fs.size:
        return 0, np.eye(3)
    # moments with the same column scale as the unit normals f (W was rescaled per column)
    ws = w[:, trans.support]
    mo_s = ws[:3] / np.linalg.norm(ws[3:], axis=0)
    ug, sg, _ = np.linalg.svd(mo_s @ null_fs, full_matrices=True)
    rank_g = _rank_from_sv(sg, tolerances)
    return rank_g, ug[:, rank_g:].T


def _analyze_regular(
    points: FloatArray,
    normals: FloatArray,
    centre: FloatArray,
    length: float,
    exponent: int,
    tolerances: Tolerances,
) -> _Regular:
    """Analysis of a non-singular state (one unit normal per point); paper section 2.2.1.

    ``points``, ``centre`` and ``length`` are in units of ``2**exponent`` metres.
    Translation (eq. 3), all motions (eq. 4), then rotation (propositions 1-6).
    """
    f, w = _normalised_columns(points, normals, centre, length)
    trans = _translation_part(f, tolerances)
    all_dof, null_wt, span_va = _all_part(w, tolerances)

    m_r = all_dof.maintaining - trans.dof.maintaining  # proposition 3
    ur, sr, _ = np.linalg.svd(span_va[:3], full_matrices=True)
    dim_vr = _rank_from_sv(sr, tolerances)
    c_r = 3 - dim_vr  # proposition 1
    span_vr = ur[:, :dim_vr].T
    d_r = 3 - m_r - c_r  # proposition 2
    rank_g, lin_vr = _rotation_dual_lineality(w, trans, tolerances)
    d_r1 = min(max(3 - rank_g - m_r, 0), max(d_r, 0))  # proposition 5
    d_r2 = d_r - d_r1  # proposition 6

    # maintaining twists (normalised frame), their axes, canonical form in the input frame
    if m_r > 0:
        ua, _, _ = np.linalg.svd(null_wt[:3], full_matrices=True)
        r_maint = _canonical_rows(ua[:, :m_r].T)
    else:
        r_maint = np.zeros((0, 3))
    geometry = DofGeometry(
        translation_maintaining=trans.maintaining,
        translation_detaching=_canonical_rows(trans.detaching),
        translation_constraining=_canonical_rows(trans.constraining),
        rotation_maintaining=r_maint,
        rotation_detaching=_canonical_rows(_orth_complement(span_vr, r_maint, d_r)),
        rotation_detaching_type1=_canonical_rows(_orth_complement(lin_vr, r_maint, d_r1)),
        rotation_constraining=_canonical_rows(ur[:, dim_vr:].T),
        maintaining_twists=_maintaining_twists(
            null_wt, trans.maintaining, r_maint, centre, length, exponent
        ),
        rotation_detaching_type2=_canonical_rows(_orth_complement(span_vr, lin_vr, d_r2)),
        translation_detaching_direction=trans.direction,
    )
    return _Regular(
        translation=trans.dof,
        rotation=RotationDof(m_r, d_r, c_r, d_r1, d_r2),
        all=all_dof,
        geometry=geometry,
    )


def _detaching_direction(
    f: FloatArray, s_t: BoolArray, t_det: FloatArray, tolerances: Tolerances
) -> FloatArray:
    """Relative-interior direction of ``V_t`` in the detaching subspace (zero if ``d_t = 0``)."""
    d = t_det.shape[0]
    if d == 0:
        return np.zeros(3)
    a = f[:, ~s_t].T @ t_det.T  # (k, d): F_i . (D^T y) for the breakable contacts
    if d == 1:
        u = t_det[0] if float(a.sum()) >= 0.0 else -t_det[0]
        return np.asarray(u, dtype=np.float64)
    if a.shape[0] <= d and numerical_rank(a.T, tolerances=tolerances) == a.shape[0]:
        # independent rows: A y = 1 attains the LP minimum (sum of A y >= rows); min-norm y
        y, *_ = np.linalg.lstsq(a, np.ones(a.shape[0]), rcond=None)
        u = t_det.T @ y
        return np.asarray(u / np.linalg.norm(u), dtype=np.float64)
    x = _detaching_vertex(a, tolerances)
    if x is not None:  # the unique optimum, proven: no LP solver needed (nor imported)
        u = t_det.T @ x
        return np.asarray(u / np.linalg.norm(u), dtype=np.float64)
    inf = float("inf")  # = highspy.kHighsInf
    lp = _highs_lp(
        a.sum(axis=0),
        np.full(d, -inf),
        np.full(d, inf),
        a,
        np.ones(a.shape[0]),
        np.full(a.shape[0], inf),
    )
    x = _solve_lp(lp, tolerances.cone)
    if x is None:  # pragma: no cover - feasible by construction of S_t
        return np.zeros(3)
    u = t_det.T @ x
    return np.asarray(u / np.linalg.norm(u), dtype=np.float64)


#: Rows of the detaching-direction LP up to which :func:`_detaching_vertex` enumerates its
#: bases (``C(k, d)``: 560 at 16 rows in 3 dimensions); beyond, HiGHS solves it.
_VERTEX_LP_ROWS = 16


def _detaching_vertex(a: FloatArray, tolerances: Tolerances) -> FloatArray | None:
    """Solve the LP of :func:`_detaching_direction` at its vertices, where its optimum is unique.

    ``min c . y`` with ``c = sum_i a_i``, s.t. ``a_i . y >= 1`` (``a``: (k, d), d <= 3). Each
    basis ``B`` of ``d`` rows gives the vertex ``y = B^-1 1``; a feasible vertex whose dual
    ``lam = B^-T c`` is positive in every entry is the only optimum (for any feasible ``y``,
    ``c . y - c . y* = lam . (B y - 1) >= 0``, zero only where ``B y = 1``), so any LP solver
    returns it, to rounding (tests/test_dof_vertex_lp.py: HiGHS's solution within 1e-11 on
    random LPs; 5e-14 seen). The HiGHS import (10 ms of a cold start) and its solve are then
    not needed. Returns None where no basis proves it (a tie, a degenerate or ill-conditioned basis,
    more than ``_VERTEX_LP_ROWS`` rows): HiGHS decides.
    """
    k, d = a.shape
    if k > _VERTEX_LP_ROWS or d > 3:
        return None
    rows = np.array(list(itertools.combinations(range(k), d)), dtype=np.int64)
    bases = a[rows]  # (m, d, d)
    sv = np.linalg.svd(bases, compute_uv=False)
    bases = bases[sv[:, -1] > tolerances.rank * sv[:, 0]]  # well-conditioned ones only
    if not len(bases):
        return None
    y = np.linalg.solve(bases, np.ones((len(bases), d, 1)))[..., 0]  # (m, d)
    c = a.sum(axis=0)
    lam = np.linalg.solve(np.swapaxes(bases, 1, 2), np.broadcast_to(c, y.shape)[..., None])[..., 0]
    feasible = (a @ y.T >= 1.0 - tolerances.cone).all(axis=0)
    cost = np.where(feasible, y @ c, np.inf)
    proof = feasible & (lam.min(axis=1) > tolerances.rank * np.abs(lam).sum(axis=1))
    if not proof.any():
        return None
    best = np.flatnonzero(proof)[np.argmin(cost[proof])]
    if cost[best] > cost.min() + tolerances.cone * abs(cost[best]):  # a near tie: HiGHS decides
        return None
    return np.asarray(y[best], dtype=np.float64)


def _maintaining_twists(
    null_wt: FloatArray,
    t_maint: FloatArray,
    r_maint: FloatArray,
    centre: FloatArray,
    length: float,
    exponent: int,
) -> FloatArray:
    """Canonical maintaining-twist basis in the input frame (see :class:`DofGeometry`).

    ``centre`` and ``length`` are in units of ``2**exponent`` metres; so is ``S1`` until
    it is scaled back at the end (exact, as every step commutes with the power of two).
    """
    m_t, m_r = t_maint.shape[0], r_maint.shape[0]
    rows = np.zeros((m_t + m_r, 6))
    rows[:m_t, 3:] = t_maint
    if m_r:
        # normalised frame: S0' = L S0, S1' = S1 + S0 x c  =>  S1 = S1' + c x S0
        coef, *_ = np.linalg.lstsq(null_wt[:3], r_maint.T, rcond=None)
        tw = (null_wt @ coef).T  # (m_r, 6) with S0' = r_maint rows
        s1 = tw[:, 3:] * length + np.cross(centre, r_maint)
        if m_t:
            s1 = s1 - (s1 @ t_maint.T) @ t_maint
        rows[m_t:, :3] = r_maint
        with np.errstate(over="ignore"):  # inf only for coordinates near the float limit
            rows[m_t:, 3:] = np.ldexp(s1, exponent)
    return rows


def analyze_arrays(
    points: Sequence[Any] | FloatArray,
    normals_list: Sequence[Any],
    *,
    tolerances: Tolerances = tol,
) -> DofResult:
    """DOF analysis of contact points given as arrays; see :func:`analyze`.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Contact points P_i (environment frame, metres).
    normals_list : sequence of array_like, each shape (M_i, 3) or (3,)
        Separating normals of each point (from the environment towards the grasped object);
        normalised here.
    tolerances : Tolerances, optional

    Returns
    -------
    DofResult
    """
    pts, normals = check_arrays(points, normals_list)
    return _analyze_checked(pts, normals, tolerances)


def analyze(contacts: Sequence[ContactPoint], *, tolerances: Tolerances = tol) -> DofResult:
    """Every DOF index of a contact state (paper section 2.2 and 3.5).

    Parameters
    ----------
    contacts : sequence of ContactPoint
        The contact points with their separating normals (environment frame, metres).
        Normals are normalised here; a point with several normals is singular.
    tolerances : Tolerances, optional
        ``rank`` (relative singular-value threshold) and ``cone`` (LP feasibility).

    Returns
    -------
    DofResult
        Regular indices for a non-singular state; for a singular state the regular ones are 0
        and the analysis of the non-singular points is in ``singular_dof_*``. Restraining DOF
        over all normals of all points. ``geometry`` holds the subspaces of whichever analysis
        was run.

    Raises
    ------
    InputFormatError
        Malformed contacts (see :func:`check_contacts`).

    Notes
    -----
    With unit normals ``F_i`` and ``W_i = [P_i x F_i; F_i]`` (constraint
    ``W_i . [S0; S1] >= 0``, eq. 2), and ``S(G)`` the :func:`maximal_support`:

    - ``m_t = 3 - rank(F)``, ``c_t = rank(F[:, S(F)])``, ``d_t`` the rest (eq. 3);
    - ``m_a = 6 - rank(W)``, ``c_a = rank(W[:, S(W)])``, ``d_a`` the rest (eq. 4);
    - ``span(V_a) = null(W[:, S(W)]^T)``; ``c_r = 3 - rank`` of its S0 parts (prop. 1);
    - ``m_r = m_a - m_t`` (prop. 3), ``d_r = 3 - m_r - c_r`` (prop. 2);
    - ``d_r1 = 3 - rank(Mo[:, S(F)] null(F[:, S(F)])) - m_r`` (prop. 5: the matrix spans the
      dual of ``V_r``), ``d_r2 = d_r - d_r1`` (prop. 6);
    - ``r_t = rank`` of every normal, ``r_a = rank`` of every ``W_ij``, ``r_r = r_a - r_t``
      (section 3.5).

    Points are shifted to their centroid and divided by their RMS distance from it before
    the ranks (a change of frame maps ``V_a`` linearly and keeps the S0 parts), so results
    do not change under a rigid motion, uniform scaling or reordering of the contacts. Points
    and normals are first scaled by powers of two (exact), so any finite coordinates and
    normal components (up to 1e308) are analysed without overflow.

    Examples
    --------
    >>> import numpy as np
    >>> up = np.array([[0.0, 0.0, 1.0]])
    >>> corners = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
    >>> analyze([ContactPoint(np.array(c, float), up) for c in corners]).fig25
    (2, 1, 0, 1, 2, 0, 1, 2)
    """
    pts, normals = check_contacts(contacts)
    return _analyze_checked(pts, normals, tolerances)


def _analyze_checked(
    pts: FloatArray, normals: list[FloatArray], tolerances: Tolerances
) -> DofResult:
    n = pts.shape[0]
    # Points in units of 2**e (an exact scaling), e the exponent of the largest absolute
    # coordinate, so that the centroid and the RMS length neither overflow nor underflow for
    # any finite coordinates; the moment columns are unchanged (bit for bit where the
    # unscaled sums would not overflow) and the twists are scaled back by 2**e.
    e = int(np.frexp(np.abs(pts).max(initial=0.0))[1])
    pts = np.ldexp(pts, -e)
    if n:
        centre = pts.mean(axis=0)
        length = math.sqrt(float(np.mean(np.sum((pts - centre) ** 2, axis=1))))
        if not length > 0.0:
            length = 1.0
    else:
        centre, length = np.zeros(3), 1.0
    singular_mask = np.array([nm.shape[0] > 1 for nm in normals], dtype=bool)
    singular = bool(singular_mask.any())
    regular_idx = np.flatnonzero(~singular_mask)
    reg = _analyze_regular(
        pts[regular_idx],
        np.array([normals[i][0] for i in regular_idx]).reshape(-1, 3),
        centre,
        length,
        e,
        tolerances,
    )
    # restraining DOF: every normal of every point (section 3.5)
    if singular:
        counts = [nm.shape[0] for nm in normals]
        all_pts = np.repeat(pts, counts, axis=0)
        all_normals = np.vstack(normals)
        f_all, w_all = _normalised_columns(all_pts, all_normals, centre, length)
        r_t = numerical_rank(f_all, tolerances=tolerances)
        r_a = numerical_rank(w_all, tolerances=tolerances)
    else:
        r_t = 3 - reg.translation.maintaining
        r_a = 6 - reg.all.maintaining
    restraining = Restraining(translation=r_t, rotation=r_a - r_t, all=r_a)
    zero = SpaceDof(0, 0, 0)
    zero_r = RotationDof(0, 0, 0, 0, 0)
    if singular:
        return DofResult(
            singular=True,
            translation=zero,
            rotation=zero_r,
            all=zero,
            singular_dof_translation=reg.translation,
            singular_dof_rotation=reg.rotation,
            singular_dof_all=reg.all,
            restraining=restraining,
            geometry=reg.geometry,
        )
    return DofResult(
        singular=False,
        translation=reg.translation,
        rotation=reg.rotation,
        all=reg.all,
        singular_dof_translation=zero,
        singular_dof_rotation=zero_r,
        singular_dof_all=zero,
        restraining=restraining,
        geometry=reg.geometry,
    )


def _space_dict(s: SpaceDof) -> dict[str, int]:
    out = {"maintaining": s.maintaining, "detaching": s.detaching, "constraining": s.constraining}
    if isinstance(s, RotationDof):
        out["detaching_type1"] = s.detaching_type1
        out["detaching_type2"] = s.detaching_type2
    return out


def dof_result_to_dict(result: DofResult) -> dict[str, Any]:
    """JSON-ready dict of a :class:`DofResult` (numbers only; no geometry).

    Keys: ``singular`` (bool), ``fig25`` (eight ints), ``translation``, ``rotation``, ``all``
    (``maintaining``, ``detaching``, ``constraining``; rotation also ``detaching_type1``,
    ``detaching_type2``), ``singular_dof`` (the same three for the singular variants) and
    ``restraining`` (``translation``, ``rotation``, ``all``).
    """
    return {
        "singular": result.singular,
        "fig25": list(result.fig25),
        "translation": _space_dict(result.translation),
        "rotation": _space_dict(result.rotation),
        "all": _space_dict(result.all),
        "singular_dof": {
            "translation": _space_dict(result.singular_dof_translation),
            "rotation": _space_dict(result.singular_dof_rotation),
            "all": _space_dict(result.singular_dof_all),
        },
        "restraining": {
            "translation": result.restraining.translation,
            "rotation": result.restraining.rotation,
            "all": result.restraining.all,
        },
    }
