"""Building the task model: states, transitions with sub-skills, rejected runs."""

from __future__ import annotations

import enum
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from apo.contact import ContactElement
from apo.recognition.candidates import analysed_at
from apo.recognition.correction import Corrected
from apo.recognition.decoding import run_bounds
from apo.recognition.types import (
    BoolArray,
    CandidateState,
    ElementKey,
    FloatArray,
    IntArray,
    SegmentationCosts,
    Six,
    StateKey,
)
from apo.spatial import invert_pose
from apo.task import (
    Element,
    Rejected,
    StateKind,
    StateTable,
    SubSkill,
    Transition,
    TransitionTable,
    state_letters,
)
from apo.transitions import analyze_transition

if TYPE_CHECKING:
    from apo.recognition.segmentation import Segmentation

__all__ = [
    "build_states",
    "build_transitions",
    "element_record",
    "rejected_runs",
    "state_kind",
    "state_runs",
    "transition_record",
]


def _enum_str(x: Any) -> str:
    """Return an enum's value (or the thing itself) as a string."""
    return str(x.value) if isinstance(x, enum.Enum) else str(x)


def transition_record(
    a: CandidateState, b: CandidateState, from_id: str, to_id: str, frame: int, direct: bool
) -> Transition:
    """Return the task's record of the transition between two analysed candidates.

    ``apo.transitions.analyze_transition`` at the candidates' representative poses: DOF
    transitions, sub-skills with directions, critical mark; ``direct`` is the result of the
    direct-transition test.
    """
    tr = analyze_transition(
        a.dof,
        b.dof,
        before_state=a.state,
        after_state=b.state,
        X_EG_before=a.X_EG,
        X_EG_after=b.X_EG,
    )
    dof_t = {
        sp: tuple(_pair(x) for x in tr.dof_transitions.get(sp, ()))
        for sp in ("translation", "rotation")
    }
    subs = tuple(
        SubSkill(
            kind=s.kind,
            space=_enum_str(s.space),
            type=None if s.type is None else _enum_str(s.type),
            direction=np.zeros(3)
            if s.direction is None
            else np.asarray(s.direction, dtype=np.float64).reshape(3),
            point=None if s.point is None else np.asarray(s.point, dtype=np.float64).reshape(3),
            source=s.source,
            subspace=np.asarray(s.subspace, dtype=np.float64).reshape(-1, 3),
        )
        for s in tr.subskills
    )
    return Transition(
        from_id=from_id,
        to_id=to_id,
        frame=frame,
        dof_transitions=dof_t,
        subskills=subs,
        critical=bool(tr.critical),
        direct=direct,
        choice={sp: str(tr.choice.get(sp, "none")) for sp in ("translation", "rotation")},
        alternatives={
            sp: tuple(tuple(_pair(x) for x in alt.pairs) for alt in tr.alternatives.get(sp, ()))
            for sp in ("translation", "rotation")
        },
    )


def _pair(x: tuple[Any, Any]) -> tuple[str, str]:
    """Return a unit DOF transition ``(DofKind, DofKind)`` as ``("M", "D")``."""
    return (_enum_str(x[0]), _enum_str(x[1]))


# --------------------------------------------------------------------------------------------
# The pipeline
# --------------------------------------------------------------------------------------------


def _label(key: ElementKey) -> str:
    """``"VF v3-f1"``: an element key as printed in ``rejected``."""
    kind, (gk, gi), (ek, ei) = key
    return f"{kind} {gk}{gi}-{ek}{ei}"


def element_record(e: ContactElement) -> Element:
    """Return the task's record of a contact element."""
    return Element(
        kind=e.kind.value,
        grasped=e.grasped,
        environment=e.environment,
        point=np.asarray(e.point, dtype=np.float64),
        normals=np.asarray(e.normals, dtype=np.float64).reshape(-1, 3),
    )


def rejected_runs(
    obs: IntArray,
    path: IntArray,
    runs: list[tuple[int, int]],
    ids: list[str],
    keys: list[StateKey],
    candidates: Sequence[CandidateState | None],
    feasible: BoolArray,
    seg: Segmentation,
    w: SegmentationCosts,
) -> list[Rejected]:
    """Observed runs the segmentation replaced, with the reason."""
    col = {int(k): c for c, k in enumerate(seg.columns)}
    run_of = np.empty(len(path), dtype=np.int64)
    for r, (a, b) in enumerate(runs):
        run_of[a : b + 1] = r
    out: list[Rejected] = []
    labels: dict[int, tuple[str, ...]] = {}  # per observed state: its labels, one tuple shared
    marks = np.where(obs == path, -1, obs)
    for a, b in run_bounds(marks):
        k = int(marks[a])
        if k < 0:
            continue
        by = sorted({ids[int(run_of[f])] for f in range(a, b + 1)})
        cand = candidates[k]
        reasons = []
        taken = candidates[int(path[a])]
        if cand is None and taken is not None and keys[k] <= taken.state.key:
            reasons.append(
                f"part of {ids[int(run_of[a])]}: its elements are a subset of that state's "
                "(the same contact, partly within the threshold)"
            )
        elif cand is None:
            reasons.append(
                "noise: the cheapest segmentation drops it even without the direct-transition test"
            )
        else:
            prev_k = int(path[a - 1]) if a > 0 else None
            next_k = int(path[b + 1]) if b + 1 < len(path) else None
            if prev_k is not None and not feasible[prev_k, k]:
                reasons.append(f"no direct transition from {ids[int(run_of[a - 1])]}")
            if next_k is not None and not feasible[k, next_k]:
                reasons.append(f"no direct transition to {ids[int(run_of[b + 1])]}")
            if not cand.converged:
                reasons.append("pose correction converged at no frame of this state")
            if not reasons:
                cost = seg.costs[a : b + 1]
                kept = float(cost[:, col[k]].sum())
                taken_cols = [col[int(p)] for p in path[a : b + 1]]
                chosen = float(cost[np.arange(b + 1 - a), taken_cols].sum())
                reasons.append(
                    f"costlier than the neighbouring states ({kept:.2f} + switches "
                    f"{w.switch:g} each vs {chosen:.2f})"
                )
        if k not in labels:
            labels[k] = tuple(_label(e) for e in sorted(keys[k]))
        out.append(
            Rejected(
                frames=(a, b),
                elements=labels[k],
                replaced_by=tuple(by),
                reason="; ".join(reasons),
            )
        )
    return out


def build_states(
    times: FloatArray,
    path: IntArray,
    observed: IntArray,
    corrected: Corrected,
    candidates: Sequence[CandidateState | None],
    named: tuple[list[tuple[int, int]], list[str]] | None = None,
) -> tuple[list[tuple[int, int]], list[str], StateTable]:
    """Make runs of frames with the same chosen state the task's states A, B, ...

    ``path`` is the chosen candidate of each frame, ``observed`` the observed one (up to
    the identification of candidates with the same closure). A state seen again gets a new
    letter and ``same_as``. Returns the runs ``(first, last)``, their ids and the states, as
    a :class:`apo.task.StateTable`: a row of arrays per state, and per candidate one
    :func:`state_kind` (its elements placed at a state's pose when the state is read).
    ``named``: the runs and ids of ``path`` (:func:`state_runs`), if made already.
    """
    runs, ids = state_runs(path) if named is None else named
    n = len(runs)
    poses = np.empty((n, 4, 4))
    pose_frames = np.empty(n, dtype=np.int64)
    converged = np.empty(n, dtype=bool)
    kind = np.empty(n, dtype=np.int64)
    kinds: list[StateKind] = []
    kind_of: dict[int, int] = {}  # candidate -> its index in kinds
    first_id: dict[int, str] = {}
    same_as: list[str | None] = []
    for i, ((a, b), sid) in enumerate(zip(runs, ids, strict=True)):
        k = int(path[a])
        cand = analysed_at(candidates, k)
        poses[i], pose_frames[i], converged[i] = _state_pose(a, b, k, observed, corrected, cand)
        if k not in kind_of:
            kind_of[k] = len(kinds)
            kinds.append(state_kind(cand))
        kind[i] = kind_of[k]
        same_as.append(first_id.get(k))
        first_id.setdefault(k, sid)
    bounds = np.array(runs, dtype=np.int64).reshape(-1, 2)
    t = np.asarray(times, dtype=np.float64)
    table = StateTable(ids, bounds, t[bounds], poses, kind, kinds, pose_frames, converged, same_as)
    return runs, ids, table


def state_runs(path: IntArray) -> tuple[list[tuple[int, int]], list[str]]:
    """Return the runs ``(first, last)`` of equal chosen states and their ids A, B, ..."""
    runs = run_bounds(path)
    return runs, state_letters(len(runs))


def state_kind(cand: CandidateState) -> StateKind:
    """Return what every state of the candidate ``cand`` shares (:class:`apo.task.StateKind`).

    The candidate's elements were found at its representative pose (``cand.X_EG``, shared by
    every run of the same contact state), the state's pose is the best frame of the run: in
    a sliding state the two lie far apart (a block slid 70 mm along a wall). A point on a
    vertex or edge of the grasped object (kinds VF, VE, VV, EE) moves with it; a point on a
    vertex of the environment (FV, EV) stays (:meth:`apo.task.StateKind.points_at`). So
    ``task.json``'s points hold at its poses. The records, the DOF numbers (``fig25``,
    ``six``: the same objects in every run's state) and the inverse of the representative
    pose are made once per candidate, not per run.
    """
    dof_r = cand.dof
    return StateKind(
        singular=bool(dof_r.singular),
        fig25=cast("tuple[int, int, int, int, int, int, int, int]", tuple(dof_r.fig25)),
        six={sp: cast("Six", tuple(dof_r.six(sp))) for sp in ("translation", "rotation")},
        elements=tuple(element_record(e) for e in cand.state.elements),
        inv_ref=invert_pose(cand.X_EG),
    )


def _state_pose(
    a: int, b: int, k: int, observed: IntArray, corrected: Corrected, cand: CandidateState
) -> tuple[FloatArray, int, bool]:
    """Return a run's pose: its best converged frame, else the candidate's pose.

    Frames where the observation agrees with the chosen state are preferred. Returns
    ``(X_EG, frame, converged)``.
    """
    Xc, res_before, _after, conv = corrected
    seg = np.arange(a, b + 1)
    good = seg[(observed[seg] == k) & conv[seg]]
    if not len(good):
        good = seg[conv[seg]]
    if len(good):
        f = int(good[np.argmin(res_before[good])])
        return Xc[f], f, True
    return cand.X_EG, cand.frame, cand.converged


def build_transitions(
    runs: Sequence[tuple[int, int]],
    ids: Sequence[str],
    path: IntArray,
    candidates: Sequence[CandidateState | None],
    feasible: BoolArray,
) -> TransitionTable:
    """Return the transitions between consecutive runs (each pair of candidates analysed once).

    A :class:`apo.task.TransitionTable`: each transition is the record of its pair of
    candidates with its own states and frame.
    """
    run_cands = [int(path[a]) for a, _b in runs]
    analysed: dict[tuple[int, int], int] = {}
    kinds: list[Transition] = []
    which = np.empty(max(len(runs) - 1, 0), dtype=np.int64)
    for i in range(len(runs) - 1):
        pair = (run_cands[i], run_cands[i + 1])
        if pair not in analysed:
            analysed[pair] = len(kinds)
            kinds.append(transition_record(
                analysed_at(candidates, pair[0]), analysed_at(candidates, pair[1]),
                ids[i], ids[i + 1], runs[i + 1][0], bool(feasible[pair]),
            ))  # fmt: skip
        which[i] = analysed[pair]
    frames = np.array([a for a, _b in runs[1:]], dtype=np.int64)
    return TransitionTable(ids if runs else [], frames, which, kinds)
