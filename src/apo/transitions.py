"""DOF transitions between contact states, sub-skills and critical transitions (paper section 3).

Between two consecutive contact states the six DOF numbers ``(M, D, C, SM, SD, SC)`` of each
space (translation, rotation; :meth:`apo.dof.DofResult.six`) change; the change is written as
a multiset of unit *DOF transitions* ``X -> Y`` (X loses one, Y gains one). Of the 30 ordered
pairs only the 20 in :data:`PRACTICAL` occur in practical assembly (paper 3.1, Fig. 6).

- :func:`decompose` lists every decomposition of a change into practical unit transitions
  (a small transportation problem) and ranks them by how well the before/after subspaces of
  :class:`apo.dof.DofGeometry` overlap.
- :func:`analyze_transition` picks the best decomposition per space and assigns the
  sub-skills of paper 3.5 (push-to, release, slide) with their motion direction or rotation
  axis, and marks critical transitions (SM -> C or SD -> C).
- :func:`direct_transition_possible` is the direct-transition test of paper 4.3.2.

Everything is in the environment frame E, metres and radians; twists are ``[S0; S1]``
(rotation first, ``docs/conventions.md``). See ``docs/transitions.md`` for the rules and the
choices made where the paper is silent.
"""

from __future__ import annotations

import enum
from collections.abc import Iterator, Mapping, Sequence, Set
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal, NamedTuple

import numpy as np
import numpy.typing as npt

from apo.constants import tol
from apo.dof import DofGeometry, DofResult
from apo.errors import InputFormatError
from apo.spatial import check_pose, rotation_angle
from apo.typing import FloatArray

if TYPE_CHECKING:
    from apo.contact import ContactState

Six = tuple[int, int, int, int, int, int]
Space = Literal["translation", "rotation"]

__all__ = [
    "CRITICAL",
    "IMPRACTICAL",
    "PRACTICAL",
    "SPACES",
    "Decomposition",
    "DirectCheck",
    "DofKind",
    "SubSkill",
    "SubSkillKind",
    "Subskill",
    "SubskillKind",
    "Transition",
    "TransitionAnalysis",
    "analyze_transition",
    "check_six",
    "decompose",
    "direct_transition_possible",
    "is_practical",
    "kind_subspaces",
    "transition_pairs",
]

SPACES: tuple[Space, Space] = ("translation", "rotation")
"""The two spaces analysed, in report order."""


class DofKind(enum.StrEnum):
    """The six kinds of DOF of one space; the order is that of :meth:`DofResult.six`."""

    M = "M"
    D = "D"
    C = "C"
    SM = "SM"
    SD = "SD"
    SC = "SC"


class SubSkillKind(enum.StrEnum):
    """Sub-skills of paper section 3.3 (push-to = tsukiate, release, slide = suberashi)."""

    PUSH_TO = "push_to"
    RELEASE = "release"
    SLIDE = "slide"


_KINDS: tuple[DofKind, ...] = tuple(DofKind)
_SINGULAR = frozenset({DofKind.SM, DofKind.SD, DofKind.SC})

IMPRACTICAL: frozenset[tuple[DofKind, DofKind]] = frozenset(
    # the 6 among the singular kinds (moving while keeping a singular contact, paper 3.1)
    {(x, y) for x in _SINGULAR for y in _SINGULAR if x != y}
    # the 4 of M <-> C and M <-> SC (paper Fig. 5)
    | {
        (DofKind.M, DofKind.C),
        (DofKind.C, DofKind.M),
        (DofKind.M, DofKind.SC),
        (DofKind.SC, DofKind.M),
    }
)
"""The 10 ordered pairs that do not occur in practical assembly (paper 3.1)."""

PRACTICAL: frozenset[tuple[DofKind, DofKind]] = frozenset(
    (x, y) for x in _KINDS for y in _KINDS if x != y and (x, y) not in IMPRACTICAL
)
"""The 20 practical DOF transitions of paper Fig. 6."""

CRITICAL: frozenset[tuple[DofKind, DofKind]] = frozenset(
    {(DofKind.SM, DofKind.C), (DofKind.SD, DofKind.C)}
)
"""DOF transitions that make a state transition critical (paper 3.4)."""

_PUSH = frozenset({(DofKind.M, DofKind.D), (DofKind.M, DofKind.SD)})
_RELEASE = frozenset({(DofKind.D, DofKind.M), (DofKind.SD, DofKind.M)})
_SLIDE = frozenset({(DofKind.M, DofKind.SM)})

#: A sub-skill direction shorter than this is zero; relative rank cut of its subspaces.
_EPS_NORM = tol.subskill_direction


def is_practical(source: DofKind | str, target: DofKind | str) -> bool:
    """Return True if the unit DOF transition ``source -> target`` is one of the 20 practical.

    Examples
    --------
    >>> is_practical("M", "D"), is_practical("M", "C"), is_practical("SM", "SD")
    (True, False, False)
    """
    return (DofKind(source), DofKind(target)) in PRACTICAL


# --------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Decomposition:
    """One way to write the change of a space's six numbers as unit DOF transitions.

    Attributes
    ----------
    space : str
        ``"translation"`` or ``"rotation"``.
    pairs : tuple of (DofKind, DofKind)
        The unit transitions ``X -> Y``, with repetition, in the order of :class:`DofKind`.
    score : float
        Geometric support: ``sum over pairs min(n_XY, O_XY)`` with ``n_XY`` the number of
        ``X -> Y`` units and ``O_XY = ||B_X A_Y^T||_F^2`` the overlap (sum of squared cosines
        of the principal angles) of the before-subspace of X and the after-subspace of Y.
        Zero when either state has no usable geometry.
    overlap : float
        ``sum n_XY O_XY``; second key of the ranking.
    """

    space: str
    pairs: tuple[tuple[DofKind, DofKind], ...]
    score: float = 0.0
    overlap: float = 0.0

    @property
    def critical(self) -> bool:
        """True if the decomposition contains SM -> C or SD -> C."""
        return any(p in CRITICAL for p in self.pairs)

    def as_strings(self) -> tuple[tuple[str, str], ...]:
        """Return the pairs as plain strings, e.g. ``(("M", "D"),)``."""
        return tuple((str(x.value), str(y.value)) for x, y in self.pairs)


@dataclass(frozen=True)
class SubSkill:
    """A sub-skill assigned to a state transition (paper 3.5), environment frame.

    The one sub-skill type: :func:`analyze_transition` returns it and the task model stores
    it (``apo.task.SubSkill`` is this class).

    Attributes
    ----------
    kind : SubSkillKind
        Given as a :class:`SubSkillKind` or its string (``"push_to"``).
    space : str
        ``"translation"`` or ``"rotation"``.
    type : str or None
        ``"I"`` or ``"II"`` for a rotational push-to (which of ``d_r1``, ``d_r2`` grows), else
        None (also None when neither the numbers nor the geometry tell).
    direction : ndarray, shape (3,), or None
        Translation: unit direction of the motion (push-to: into the new contact; release:
        away from the lost one; slide: towards where the support ends). Rotation: unit axis,
        the motion being a positive (right-handed) turn about it. None when the sign cannot
        be determined from the data given; the task model stores zeros instead of None.
    point : ndarray, shape (3,), metres, or None
        Rotation only: the point of the rotation axis closest to the origin of E,
        ``C = S0 x S1 / |S0|^2`` of the motion twist. None for translation or when unknown.
    source : str
        Where ``direction`` came from: ``"contacts"`` (separating normals of the new or lost
        contact elements), ``"detaching_direction"`` (``DofGeometry``), ``"poses"`` (the
        displacement between the two poses), or ``"none"``.
    subspace : ndarray, shape (k, 3)
        Orthonormal rows spanning the directions (axes) the sub-skill acts in, sign-free:
        the principal directions shared by the two subspaces of its DOF transitions. Empty
        when the states carry no geometry.
    """

    kind: SubSkillKind
    space: str
    type: str | None = None
    direction: FloatArray | None = None
    point: FloatArray | None = None
    source: str = "none"
    subspace: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))

    def __post_init__(self) -> None:
        if type(self.kind) is not SubSkillKind:
            object.__setattr__(self, "kind", SubSkillKind(self.kind))


@dataclass(frozen=True)
class TransitionAnalysis:
    """The analysis of one transition between two contact states.

    Attributes
    ----------
    dof_transitions : dict
        ``{"translation": ((X, Y), ...), "rotation": (...)}`` with X, Y :class:`DofKind`
        (a ``str`` enum: ``("M", "D") == (DofKind.M, DofKind.D)``); the chosen decomposition
        of each space; empty for a space without a practical decomposition.
    subskills : tuple of SubSkill
        Translation first, then rotation; within a space push-to, slide, release.
    critical : bool
        True if a chosen decomposition contains SM -> C or SD -> C.
    feasible : bool
        True if both spaces decompose into practical transitions (and, when both contact
        states were given, Donald's inclusion test holds).
    alternatives : dict
        Per space, the other decompositions considered, best first.
    choice : dict
        Per space, why the chosen decomposition was chosen: ``"unique"``, ``"geometry"``,
        ``"tie"`` (no geometric preference; first in canonical order), ``"no change"`` or
        ``"none"`` (no practical decomposition).
    reason : str
        Empty when feasible, else why not.
    dof_changed : bool
        False if no DOF number changed (a change of elements only: no sub-skill, not
        critical, still a state change).
    before_six, after_six : dict
        ``{"translation": (M, D, C, SM, SD, SC), "rotation": (...)}`` of the two states.
    """

    dof_transitions: Mapping[str, tuple[tuple[DofKind, DofKind], ...]]
    subskills: tuple[SubSkill, ...]
    critical: bool
    feasible: bool
    alternatives: Mapping[str, tuple[Decomposition, ...]]
    choice: Mapping[str, str]
    reason: str = ""
    dof_changed: bool = True
    before_six: Mapping[str, Six] = field(default_factory=dict)
    after_six: Mapping[str, Six] = field(default_factory=dict)


Subskill = SubSkill
"""Former name of :class:`SubSkill` (kept working)."""
SubskillKind = SubSkillKind
"""Former name of :class:`SubSkillKind` (kept working)."""
Transition = TransitionAnalysis
"""Former name of :class:`TransitionAnalysis` (kept working); ``apo.task.Transition`` is the
transition of a task model (between named states, at a frame), which carries this analysis's
DOF transitions and sub-skills."""


@dataclass(frozen=True)
class DirectCheck:
    """Verdict of :func:`direct_transition_possible`; unpacks as ``(possible, reason)``.

    ``bool(check)`` is ``check.possible``, so both ``ok, why = check`` and ``if check:`` work.
    """

    possible: bool
    reason: str

    def __bool__(self) -> bool:
        return self.possible

    def __iter__(self) -> Iterator[Any]:
        return iter((self.possible, self.reason))


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------


def check_six(six: Sequence[int] | npt.ArrayLike, *, name: str = "six") -> Six:
    """Validate a 6-tuple ``(M, D, C, SM, SD, SC)`` of one space and return it as ints.

    Raises
    ------
    InputFormatError
        Not six non-negative integers summing to 3, or both regular and singular numbers
        non-zero.
    """
    arr = np.asarray(six)
    if arr.shape != (6,):
        raise InputFormatError(f"{name}: expected 6 numbers (M, D, C, SM, SD, SC), got {arr!r}")
    try:
        vals = [int(v) for v in arr.tolist()]
    except (TypeError, ValueError):
        raise InputFormatError(f"{name}: not integers: {arr.tolist()}") from None
    if any(v < 0 for v in vals) or vals != [float(v) for v in arr.tolist()]:
        raise InputFormatError(f"{name}: DOF numbers must be non-negative integers, got {vals}")
    if sum(vals) != 3:
        raise InputFormatError(f"{name}: DOF numbers must sum to 3, got {vals}")
    if sum(vals[:3]) not in (0, 3):
        raise InputFormatError(
            f"{name}: regular and singular numbers mixed (one triple must be zero): {vals}"
        )
    return (vals[0], vals[1], vals[2], vals[3], vals[4], vals[5])


def _check_space(space: str) -> Space:
    if space == "translation":
        return "translation"
    if space == "rotation":
        return "rotation"
    raise InputFormatError(f"space must be 'translation' or 'rotation', got {space!r}")


# --------------------------------------------------------------------------------------------
# Subspaces and overlaps
# --------------------------------------------------------------------------------------------


def _empty() -> FloatArray:
    return np.zeros((0, 3))


def kind_subspaces(six: Six, geometry: DofGeometry | None, space: str) -> dict[DofKind, FloatArray]:
    """Orthonormal bases (rows, environment frame) of each DOF kind's subspace in one state.

    Parameters
    ----------
    six : tuple of 6 int
        ``(M, D, C, SM, SD, SC)`` of the state in ``space``.
    geometry : DofGeometry or None
        The state's geometry (:attr:`apo.dof.DofResult.geometry`).
    space : str
        ``"translation"`` (subspaces of translations) or ``"rotation"`` (of rotation axes S0).

    Returns
    -------
    dict
        ``DofKind -> ndarray, shape (k, 3)``. A singular state (``M + D + C = 0``) maps its
        geometry, which is that of the analysis of its non-singular elements (``apo.dof``),
        to SM / SD / SC and gives M / D / C empty bases; a non-singular state the other way
        round. Empty dict when ``geometry`` is None or its dimensions disagree with ``six``
        (e.g. hand-built results without geometry).
    """
    sp = _check_space(space)
    if geometry is None:
        return {}
    if sp == "translation":
        bases = (
            geometry.translation_maintaining,
            geometry.translation_detaching,
            geometry.translation_constraining,
        )
    else:
        bases = (
            geometry.rotation_maintaining,
            geometry.rotation_detaching,
            geometry.rotation_constraining,
        )
    arrs = [np.asarray(b, dtype=np.float64).reshape(-1, 3) for b in bases]
    singular = sum(six[:3]) == 0
    counts = six[3:] if singular else six[:3]
    if tuple(a.shape[0] for a in arrs) != tuple(counts):
        return {}
    regular_kinds = (DofKind.M, DofKind.D, DofKind.C)
    singular_kinds = (DofKind.SM, DofKind.SD, DofKind.SC)
    filled, empty = (singular_kinds, regular_kinds) if singular else (regular_kinds, singular_kinds)
    out: dict[DofKind, FloatArray] = dict(zip(filled, arrs, strict=True))
    out.update({k: _empty() for k in empty})
    return out


def _overlap(a: FloatArray, b: FloatArray) -> float:
    """Return ``||a b^T||_F^2``, the sum of squared cosines of the principal angles of two bases."""
    if a.shape[0] == 0 or b.shape[0] == 0:
        return 0.0
    return float(np.sum((a @ b.T) ** 2))


def _principal(a: FloatArray, b: FloatArray, k: int) -> FloatArray:
    """Return the ``k`` directions of span(a) closest to span(b) (orthonormal rows in span(a))."""
    if a.shape[0] == 0 or k <= 0:
        return _empty()
    if b.shape[0] == 0:
        return a[: min(k, a.shape[0])].copy()
    u, _, _ = np.linalg.svd(a @ b.T, full_matrices=True)
    return np.asarray(u[:, : min(k, a.shape[0])].T @ a, dtype=np.float64)


# --------------------------------------------------------------------------------------------
# Decomposition
# --------------------------------------------------------------------------------------------


def _plans(
    sources: list[tuple[DofKind, int]], targets: list[tuple[DofKind, int]]
) -> Iterator[dict[tuple[DofKind, DofKind], int]]:
    """Every transport plan from ``sources`` to ``targets`` over practical pairs only.

    Plans come in "north-west corner first" order: the earliest source gets as much of the
    earliest target as it can first.
    """
    cells = [(x, y) for x, _ in sources for y, _ in targets if (x, y) in PRACTICAL]
    need_src = dict(sources)
    need_tgt = dict(targets)

    def rec(i: int, plan: dict[tuple[DofKind, DofKind], int]) -> Iterator[dict[Any, int]]:
        if i == len(cells):
            if all(v == 0 for v in need_src.values()) and all(v == 0 for v in need_tgt.values()):
                yield {c: n for c, n in plan.items() if n}
            return
        x, y = cells[i]
        for n in range(min(need_src[x], need_tgt[y]), -1, -1):
            need_src[x] -= n
            need_tgt[y] -= n
            plan[(x, y)] = n
            yield from rec(i + 1, plan)
            need_src[x] += n
            need_tgt[y] += n
        plan.pop((x, y), None)

    yield from rec(0, {})


def decompose(
    before: Sequence[int],
    after: Sequence[int],
    *,
    before_geom: DofGeometry | None = None,
    after_geom: DofGeometry | None = None,
    space: str,
) -> list[Decomposition]:
    """Decompose the change of one space's DOF numbers into practical unit DOF transitions.

    Parameters
    ----------
    before, after : sequence of 6 int
        ``(M, D, C, SM, SD, SC)`` of the two states in ``space`` (each sums to 3).
    before_geom, after_geom : DofGeometry, optional
        The states' subspaces (:attr:`apo.dof.DofResult.geometry`), used to rank the
        decompositions; see :func:`kind_subspaces` for singular states.
    space : str
        ``"translation"`` or ``"rotation"``.

    Returns
    -------
    list of Decomposition
        Every decomposition, best first (highest ``score``, then ``overlap``, then canonical
        north-west-corner order); ``[Decomposition(space, ())]`` when nothing changes; empty
        when the change has no practical decomposition (then it is not a direct transition).

    Raises
    ------
    InputFormatError
        ``before`` or ``after`` is not six non-negative integers summing to 3, or ``space``
        is neither space.

    Notes
    -----
    Only the net change is decomposed: a kind that loses DOF only gives, a kind that gains only
    receives (no chains ``X -> Y -> Z`` through a kind whose number does not change, which
    would make every change decomposable, e.g. M -> C as M -> D -> C). With ``g_X`` the loss
    of X and ``h_Y`` the gain of Y this is the transportation problem ``sum_Y n_XY = g_X``,
    ``sum_X n_XY = h_Y``, ``n_XY >= 0`` integer, ``n_XY = 0`` off :data:`PRACTICAL`. At most
    three units move per space, so enumerating every plan is cheap.

    Examples
    --------
    >>> [d.as_strings() for d in decompose((3, 0, 0, 0, 0, 0), (2, 1, 0, 0, 0, 0),
    ...                                    space="translation")]
    [(('M', 'D'),)]
    >>> decompose((2, 1, 0, 0, 0, 0), (2, 0, 1, 0, 0, 0), space="rotation")[0].as_strings()
    (('D', 'C'),)
    >>> decompose((3, 0, 0, 0, 0, 0), (2, 0, 1, 0, 0, 0), space="translation")
    []
    """
    sp = _check_space(space)
    b = check_six(before, name=f"{sp} before")
    a = check_six(after, name=f"{sp} after")
    delta = [y - x for x, y in zip(b, a, strict=True)]
    if not any(delta):
        return [Decomposition(sp, ())]
    sources = [(k, -d) for k, d in zip(_KINDS, delta, strict=True) if d < 0]
    targets = [(k, d) for k, d in zip(_KINDS, delta, strict=True) if d > 0]
    sb = kind_subspaces(b, before_geom, sp)
    sa = kind_subspaces(a, after_geom, sp)
    geometric = bool(sb) and bool(sa)
    out: list[tuple[float, float, int, Decomposition]] = []
    for idx, plan in enumerate(_plans(sources, targets)):
        score = overlap = 0.0
        if geometric:
            for (x, y), n in plan.items():
                o = _overlap(sb[x], sa[y])
                score += min(float(n), o)
                overlap += n * o
        pairs = tuple(
            p
            for p in sorted(plan, key=lambda q: (_KINDS.index(q[0]), _KINDS.index(q[1])))
            for _ in range(plan[p])
        )
        dec = Decomposition(sp, pairs, round(score, 9), round(overlap, 9))
        out.append((-dec.score, -dec.overlap, idx, dec))
    out.sort(key=lambda t: t[:3])
    return [t[3] for t in out]


# --------------------------------------------------------------------------------------------
# Direct-transition test
# --------------------------------------------------------------------------------------------


def _touching(state: ContactState | Set[Any]) -> Set[Any]:
    touching = getattr(state, "touching", None)
    if touching is not None:
        return frozenset(touching)
    if isinstance(state, Set):
        return state
    raise InputFormatError(
        f"expected a ContactState or a set of touching feature pairs, got {type(state).__name__}"
    )


def _sixes(dof: DofResult) -> dict[str, Six]:
    return {sp: check_six(dof.six(sp), name=sp) for sp in SPACES}


def direct_transition_possible(
    state_a: ContactState | Set[Any],
    state_b: ContactState | Set[Any],
    dof_a: DofResult,
    dof_b: DofResult,
) -> DirectCheck:
    """Direct-transition test between two contact states (paper 4.3.2).

    Parameters
    ----------
    state_a, state_b : ContactState or set
        The two states, or directly their sets of touching (grasped feature, environment
        feature) pairs (``ContactState.touching``: every pair within the threshold).
    dof_a, dof_b : DofResult
        Their DOF analyses.

    Returns
    -------
    DirectCheck
        ``possible`` is True iff (1) one touching set contains the other (Donald's necessary
        condition, on the FULL sets of touching pairs, not on a minimal list of elements)
        and (2) the change of the six numbers decomposes into practical DOF transitions in
        both spaces. ``reason`` says which condition failed (empty when possible). Unpacks
        as ``(possible, reason)``; ``bool()`` gives ``possible``.

    Notes
    -----
    The test is symmetric: a direct transition A -> B exists iff B -> A does (the practical
    set is closed under reversal).
    """
    ta, tb = _touching(state_a), _touching(state_b)
    if not (ta <= tb or tb <= ta):
        return DirectCheck(
            False,
            f"touching pairs are not nested: {len(ta - tb)} only in the first state, "
            f"{len(tb - ta)} only in the second (Donald's condition)",
        )
    sa, sb = _sixes(dof_a), _sixes(dof_b)
    for sp in SPACES:
        if not decompose(sa[sp], sb[sp], space=sp):
            return DirectCheck(
                False,
                f"{sp} change {sa[sp]} -> {sb[sp]} (M, D, C, SM, SD, SC) has no decomposition "
                "into practical DOF transitions",
            )
    return DirectCheck(True, "")


# --------------------------------------------------------------------------------------------
# Sub-skills
# --------------------------------------------------------------------------------------------


def _unit(v: FloatArray) -> FloatArray | None:
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n <= _EPS_NORM:
        return None
    return np.asarray(v / n, dtype=np.float64)


def _effective_rotation(dof: DofResult) -> tuple[int, int]:
    """``(d_r1, d_r2)`` of whichever analysis holds the state's numbers."""
    r = dof.singular_dof_rotation if dof.singular else dof.rotation
    return r.detaching_type1, r.detaching_type2


def _element_normals(
    state: ContactState | None, exclude: ContactState | None
) -> list[tuple[FloatArray, FloatArray]]:
    """``(point, normals)`` of the elements of ``state`` whose key is not in ``exclude``."""
    if state is None:
        return []
    keys = {e.key for e in exclude.elements} if exclude is not None else set()
    return [
        (np.asarray(e.point, dtype=np.float64), np.asarray(e.normals, dtype=np.float64))
        for e in state.elements
        if e.key not in keys
    ]


def _changed_elements(kind: SubSkillKind, ctx: _Ctx) -> list[tuple[FloatArray, FloatArray]]:
    """``(point, normals)`` of the elements a sub-skill is about.

    The lost ones for a release, the new ones for a push-to or a slide.
    """
    if kind is SubSkillKind.RELEASE:
        return _element_normals(ctx.before_state, ctx.after_state)
    return _element_normals(ctx.after_state, ctx.before_state)


def _rotation_twists(geometry: DofGeometry) -> tuple[FloatArray, FloatArray]:
    """Return the rotational maintaining twists ``(m_r, 6)`` and their axes ``(m_r, 3)``."""
    r_maint = np.asarray(geometry.rotation_maintaining, dtype=np.float64).reshape(-1, 3)
    tw = np.asarray(geometry.maintaining_twists, dtype=np.float64).reshape(-1, 6)
    m_r = r_maint.shape[0]
    if tw.shape[0] < m_r:
        return np.zeros((0, 6)), _empty()
    return tw[tw.shape[0] - m_r :], r_maint


def _twists_for_axes(axes: FloatArray, geometry: DofGeometry | None) -> FloatArray | None:
    """Maintaining twists of ``geometry`` whose S0 are the rows of ``axes`` (or None)."""
    if geometry is None or axes.shape[0] == 0:
        return None
    twists, r_maint = _rotation_twists(geometry)
    if r_maint.shape[0] == 0:
        return None
    coef = axes @ r_maint.T  # axes lie in span(r_maint), which has orthonormal rows
    xi = coef @ twists
    if not np.allclose(xi[:, :3], axes, atol=tol.twist_axis_match):
        return None
    return np.asarray(xi, dtype=np.float64)


def _relative_twist(x_before: FloatArray, x_after: FloatArray) -> FloatArray:
    """Rotation vector and displacement of the origin of ``X_after inv(X_before)``."""
    rel = x_after @ np.linalg.inv(x_before)
    r = rel[:3, :3]
    angle = rotation_angle(r)
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    s = float(np.linalg.norm(w))
    omega = w * (angle / s) if s > tol.zero_norm else np.zeros(3)
    return np.concatenate([omega, rel[:3, 3]])


class _Ctx(NamedTuple):  # not a dataclass: no methods made at import
    before: DofResult
    after: DofResult
    before_state: ContactState | None
    after_state: ContactState | None
    x_before: FloatArray | None
    x_after: FloatArray | None


def _translation_direction(
    kind: SubSkillKind, sub: FloatArray, ctx: _Ctx
) -> tuple[FloatArray | None, str]:
    """Signed unit motion direction of a translational sub-skill inside span(sub)."""
    if sub.shape[0] == 0:
        return None, "none"
    proj = sub.T @ sub
    # 1. contact normals: new elements (push-to, slide) or lost ones (release). Release:
    # away from the lost contact, along its separating normal; push-to: into the new contact
    # (-n); slide: towards where the support ends (+n of the edge's other face, which points
    # on in the direction of motion)
    elems = _changed_elements(kind, ctx)
    sign = -1.0 if kind is SubSkillKind.PUSH_TO else 1.0
    if elems:
        n_sum = np.sum([ns.sum(axis=0) for _, ns in elems], axis=0)
        u = _unit(sign * (proj @ n_sum))
        if u is not None:
            return u, "contacts"
    # 2. the detaching direction of the state with the new detaching DOF
    if kind is SubSkillKind.PUSH_TO:
        d = np.asarray(ctx.after.geometry.translation_detaching_direction, dtype=np.float64)
        u = _unit(-(proj @ d))
    elif kind is SubSkillKind.RELEASE:
        d = np.asarray(ctx.before.geometry.translation_detaching_direction, dtype=np.float64)
        u = _unit(proj @ d)
    else:
        u = None
    if u is not None:
        return u, "detaching_direction"
    # 3. the observed displacement
    if ctx.x_before is not None and ctx.x_after is not None:
        xi = _relative_twist(ctx.x_before, ctx.x_after)
        centre = np.zeros(3)
        if ctx.after_state is not None and ctx.after_state.elements:
            centre = np.mean([e.point for e in ctx.after_state.elements], axis=0)
        v = xi[3:] + np.cross(xi[:3], centre)  # displacement of the contact centroid
        u = _unit(proj @ v)
        if u is not None:
            return u, "poses"
    return None, "none"


def _rotation_direction(
    kind: SubSkillKind, sub: FloatArray, ctx: _Ctx
) -> tuple[FloatArray | None, FloatArray | None, str]:
    """Signed unit axis and axis point of a rotational sub-skill inside span(sub)."""
    if sub.shape[0] == 0:
        return None, None, "none"
    # the twists that realise these axes keep the maintaining state's contacts
    maint_geom = ctx.after.geometry if kind is SubSkillKind.RELEASE else ctx.before.geometry
    xis = _twists_for_axes(sub, maint_geom)

    # The maintaining translations can be added to any maintaining twist: of the axes with a
    # given direction, report the one through the pivot (_pivot), which is also frame-invariant.
    ref = _pivot(kind, ctx)
    t_maint = _orthonormal_rows(
        np.asarray(maint_geom.translation_maintaining, dtype=np.float64).reshape(-1, 3)
        if maint_geom is not None
        else _empty()
    )

    def through_pivot(xi: FloatArray) -> FloatArray:
        """Shift the axes of the twists (rows) through the pivot, keeping them maintaining."""
        if ref is None or t_maint.shape[0] == 0:
            return xi
        v_ref = xi[:, 3:] + np.cross(xi[:, :3], ref)  # velocity of the pivot
        out = xi.copy()
        out[:, 3:] -= v_ref @ t_maint.T @ t_maint
        return out

    def finish(xi: FloatArray, src: str) -> tuple[FloatArray | None, FloatArray | None, str]:
        s0, s1 = xi[:3], xi[3:]
        n0 = float(s0 @ s0)
        if n0 <= _EPS_NORM:
            return None, None, "none"
        return s0 / np.sqrt(n0), np.cross(s0, s1) / n0, src

    if xis is not None:
        xis = through_pivot(xis)
        elems = _changed_elements(kind, ctx)
        sign = -1.0 if kind is SubSkillKind.PUSH_TO else 1.0
        if elems:
            # pairing of twist and contact wrench [P x F; F]: > 0 moves away from the contact
            wrench = np.zeros(6)
            for p, ns in elems:
                for n in ns:
                    wrench += np.concatenate([np.cross(p, n), n])
            g = xis @ wrench
            if float(np.linalg.norm(g)) > _EPS_NORM:
                return finish(sign * (g @ xis), "contacts")
    if ctx.x_before is not None and ctx.x_after is not None:
        omega = _relative_twist(ctx.x_before, ctx.x_after)[:3]
        axis = _unit(sub.T @ (sub @ omega))
        if axis is not None:
            xi1 = _twists_for_axes(axis[None, :], maint_geom)
            if xi1 is not None:
                return finish(through_pivot(xi1)[0], "poses")
            return axis, None, "poses"
    return None, None, "none"


def _orthonormal_rows(a: FloatArray) -> FloatArray:
    """Orthonormal rows spanning the rows of ``a`` (numerical rank by SVD)."""
    if a.shape[0] == 0:
        return _empty()
    _u, sv, vt = np.linalg.svd(a, full_matrices=False)
    keep = sv > _EPS_NORM * max(1.0, float(sv[0]))
    return np.asarray(vt[keep], dtype=np.float64)


def _pivot(kind: SubSkillKind, ctx: _Ctx) -> FloatArray | None:
    """Return the point a rotational sub-skill turns about, a point of its contact elements.

    The elements are the new ones (push-to, slide) or the lost ones (release), else all
    elements of the two states. Of their points, the pivot is the one the observed motion
    moves least between the two states' poses (the point that stays put while the rest
    turns into or out of contact); without poses, the first in element order.
    """
    pts = [p for p, _ in _changed_elements(kind, ctx)]
    if not pts:
        pts = [
            np.asarray(e.point, dtype=np.float64)
            for st in (ctx.after_state, ctx.before_state)
            if st is not None
            for e in st.elements
        ]
    if not pts:
        return None
    if ctx.x_before is None or ctx.x_after is None or len(pts) == 1:
        return pts[0]
    P: FloatArray = np.asarray(pts, dtype=np.float64)
    # the points lie at their own state's pose: carry them (with G) to the other state's pose
    if kind is SubSkillKind.RELEASE:
        rel = ctx.x_after @ np.linalg.inv(ctx.x_before)
    else:
        rel = ctx.x_before @ np.linalg.inv(ctx.x_after)
    moved = P @ rel[:3, :3].T + rel[:3, 3] - P
    pivot: FloatArray = P[int(np.argmin(np.einsum("ij,ij->i", moved, moved)))]
    return pivot


def _push_type(ctx: _Ctx, sub: FloatArray) -> str | None:
    """Type I or II of a rotational push-to: which of ``d_r1``, ``d_r2`` grows (paper 3.3.1)."""
    b1, b2 = _effective_rotation(ctx.before)
    a1, a2 = _effective_rotation(ctx.after)
    g1, g2 = a1 - b1, a2 - b2
    if g1 > 0 >= g2:
        return "I"
    if g2 > 0 >= g1:
        return "II"
    # both or neither grow: ask the geometry where the pushed axes now lie
    if sub.shape[0]:
        geom = ctx.after.geometry
        t1 = np.asarray(geom.rotation_detaching_type1, dtype=np.float64).reshape(-1, 3)
        t2 = np.asarray(geom.rotation_detaching_type2, dtype=np.float64).reshape(-1, 3)
        o1, o2 = _overlap(sub, t1), _overlap(sub, t2)
        if max(o1, o2) > 0.5 and o1 != o2:
            return "I" if o1 > o2 else "II"
    if g1 > 0 and g1 >= g2:
        return "I"
    if g2 > 0:
        return "II"
    return None


#: Smallest demonstrated motion along a slide's direction that fixes its sign: the turn
#: (radians) about a rotational slide's axis, the displacement (metres) of the contact
#: centroid along a translational slide's direction, between the two states' poses.
SLIDE_MIN_ROTATION = tol.slide_motion_rotation
SLIDE_MIN_TRANSLATION = tol.slide_motion_translation


def _slide_motion(space: str, direction: FloatArray, ctx: _Ctx) -> float:
    """Demonstrated motion along a slide's direction between the two states' poses.

    Rotation: the turn (radians) about ``direction``; translation: the displacement
    (metres) of the after state's contact centroid along it. 0 without both poses.
    """
    if ctx.x_before is None or ctx.x_after is None:
        return 0.0
    xi = _relative_twist(ctx.x_before, ctx.x_after)
    if space == "rotation":
        return float(xi[:3] @ direction)
    centre = np.zeros(3)
    if ctx.after_state is not None and ctx.after_state.elements:
        centre = np.mean([e.point for e in ctx.after_state.elements], axis=0)
    return float((xi[3:] + np.cross(xi[:3], centre)) @ direction)


def _signed_by_motion(
    space: str, direction: FloatArray | None, source: str, ctx: _Ctx
) -> tuple[FloatArray | None, str]:
    """Return a slide's direction with the sign of the demonstrated motion, where clear.

    The contacts fix the sign of a push-to (into the new contact) and of a release (away
    from the lost one), but not that of a slide: the sliding contact's normals are
    orthogonal to the motion, and which elements the noise lets appear decides the sign of
    their sum. A slide goes the way the demonstration went: where the motion along the
    direction between the two states' poses is at least :data:`SLIDE_MIN_ROTATION` /
    :data:`SLIDE_MIN_TRANSLATION`, the direction takes its sign (``source`` becomes
    ``"poses"`` when that reverses it).
    """
    if direction is None:
        return direction, source
    moved = _slide_motion(space, direction, ctx)
    least = SLIDE_MIN_ROTATION if space == "rotation" else SLIDE_MIN_TRANSLATION
    if moved <= -least:
        return -direction, "poses"
    return direction, source


def _subskills_of_space(
    space: Space, dec: Decomposition, ctx: _Ctx, restraining_grows: bool
) -> list[SubSkill]:
    sb = kind_subspaces(check_six(ctx.before.six(space)), ctx.before.geometry, space)
    sa = kind_subspaces(check_six(ctx.after.six(space)), ctx.after.geometry, space)
    out: list[SubSkill] = []
    rules: list[tuple[SubSkillKind, frozenset[tuple[DofKind, DofKind]]]] = [
        (SubSkillKind.PUSH_TO, _PUSH),
        (SubSkillKind.SLIDE, _SLIDE),
        (SubSkillKind.RELEASE, _RELEASE),
    ]
    for kind, pairs in rules:
        units = [p for p in dec.pairs if p in pairs]
        if not units or (kind is SubSkillKind.SLIDE and not restraining_grows):
            continue
        # the directions of the maintaining side that the transition moves
        sub = _empty()
        if sb and sa:
            if kind is SubSkillKind.RELEASE:
                other = np.vstack([sb[x] for x in sorted({x for x, _ in units})])
                sub = _principal(sa[DofKind.M], other, len(units))
            else:
                other = np.vstack([sa[y] for y in sorted({y for _, y in units})])
                sub = _principal(sb[DofKind.M], other, len(units))
        if space == "translation":
            direction, source = _translation_direction(kind, sub, ctx)
            point = None
        else:
            direction, point, source = _rotation_direction(kind, sub, ctx)
        if kind is SubSkillKind.SLIDE:
            direction, source = _signed_by_motion(space, direction, source, ctx)
        typ = (
            _push_type(ctx, sub) if (kind is SubSkillKind.PUSH_TO and space == "rotation") else None
        )
        out.append(SubSkill(kind, space, typ, direction, point, source=source, subspace=sub))
    return out


# --------------------------------------------------------------------------------------------
# The analysis of one transition
# --------------------------------------------------------------------------------------------


def _check_pose(x: npt.ArrayLike | None, name: str) -> FloatArray | None:
    return None if x is None else check_pose(x, name=name)


def analyze_transition(
    before: DofResult,
    after: DofResult,
    *,
    before_state: ContactState | None = None,
    after_state: ContactState | None = None,
    X_EG_before: npt.ArrayLike | None = None,
    X_EG_after: npt.ArrayLike | None = None,
) -> TransitionAnalysis:
    """Analyse the transition between two consecutive contact states (paper 3.5).

    Parameters
    ----------
    before, after : DofResult
        DOF analyses of the two states (environment frame).
    before_state, after_state : ContactState, optional
        The contact states. With both, Donald's inclusion test enters ``feasible``, and the
        separating normals of the elements that appear (push-to, slide) or disappear
        (release) fix the sign of each sub-skill's direction.
    X_EG_before, X_EG_after : array_like, shape (4, 4), metres, optional
        Poses of the grasped object in E at the two states; their displacement fixes a sign
        the contacts and the detaching direction leave open.

    Returns
    -------
    TransitionAnalysis

    Raises
    ------
    InputFormatError
        Malformed DOF numbers or poses.

    Notes
    -----
    Per space the best decomposition of :func:`decompose` is chosen. Sub-skills (paper 3.5,
    corrected rules): M -> D or M -> SD gives a push-to (rotational: type I or II by which of
    ``d_r1``, ``d_r2`` grows); D -> M or SD -> M a release; M -> SM a slide only if that
    space's restraining DOF grows; SM -> M none. One sub-skill per kind and space, however
    many units. A transition is critical iff it contains SM -> C or SD -> C.
    """
    ctx = _Ctx(
        before,
        after,
        before_state,
        after_state,
        _check_pose(X_EG_before, "X_EG_before"),
        _check_pose(X_EG_after, "X_EG_after"),
    )
    sb, sa = _sixes(before), _sixes(after)
    chosen: dict[str, tuple[tuple[DofKind, DofKind], ...]] = {}
    alternatives: dict[str, tuple[Decomposition, ...]] = {}
    choice: dict[str, str] = {}
    reasons: list[str] = []
    subskills: list[SubSkill] = []
    critical = False
    grows = {
        "translation": after.restraining.translation > before.restraining.translation,
        "rotation": after.restraining.rotation > before.restraining.rotation,
    }
    for sp in SPACES:
        decs = decompose(
            sb[sp], sa[sp], before_geom=before.geometry, after_geom=after.geometry, space=sp
        )
        if not decs:
            chosen[sp], alternatives[sp], choice[sp] = (), (), "none"
            reasons.append(
                f"{sp} change {sb[sp]} -> {sa[sp]} has no decomposition into practical "
                "DOF transitions"
            )
            continue
        best = decs[0]
        chosen[sp], alternatives[sp] = best.pairs, tuple(decs[1:])
        if not best.pairs:
            choice[sp] = "no change"
        elif len(decs) == 1:
            choice[sp] = "unique"
        elif (best.score, best.overlap) != (decs[1].score, decs[1].overlap):
            choice[sp] = "geometry"
        else:
            choice[sp] = "tie"
        critical = critical or best.critical
        subskills.extend(_subskills_of_space(sp, best, ctx, grows[sp]))
    if before_state is not None and after_state is not None:
        ta, tb = frozenset(before_state.touching), frozenset(after_state.touching)
        if not (ta <= tb or tb <= ta):
            reasons.append(
                f"touching pairs are not nested: {len(ta - tb)} only before, "
                f"{len(tb - ta)} only after (Donald's condition)"
            )
    return TransitionAnalysis(
        dof_transitions=chosen,
        subskills=tuple(subskills),
        critical=critical,
        feasible=not reasons,
        alternatives=alternatives,
        choice=choice,
        reason="; ".join(reasons),
        dof_changed=sb != sa,
        before_six=sb,
        after_six=sa,
    )


def transition_pairs(
    transition: TransitionAnalysis,
) -> dict[str, list[tuple[str, str]]]:
    """Return ``dof_transitions`` with plain strings, e.g. ``{"translation": [("M", "D")]}``."""
    return {
        sp: [(str(x.value), str(y.value)) for x, y in pairs]
        for sp, pairs in transition.dof_transitions.items()
    }
