"""The recognised task: contact states, transitions and sub-skills, and its JSON form.

A :class:`TaskModel` is what :func:`apo.recognition.recognize` returns and what
``task.json`` stores (schema ``"apo.task/1"``, ``docs/task-json.md``). Inside, everything is
in SI units (metres) in the environment frame; :func:`task_to_dict` converts lengths to the
task's ``units`` and :func:`task_from_dict` converts them back, validating every field. No
file I/O here: the command line writes the dictionary with :mod:`json`.

Quaternions are ``(qw, qx, qy, qz)``; poses ``X_EG`` are 4x4 matrices of the grasped object
G in the environment frame E (``docs/conventions.md``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal, TypeVar, cast, overload

import numpy as np
import numpy.typing as npt

from apo.constants import UNITS, tol
from apo.contact import ContactElement, Feature
from apo.errors import InputFormatError
from apo.jsonform import (
    JsonItems,
    JsonReader,
    RawJson,
    json_chunks,
    json_str,
    one_line_encoder,
    rounded,
    rounded_list,
    rounded_rows,
    rounded_texts,
)
from apo.spatial import pose_from_position_quaternion, quaternions_from_matrices
from apo.transitions import SubSkill, SubSkillKind
from apo.typing import FloatArray

__all__ = [
    "KINDS",
    "SCHEMA",
    "SUBSKILL_KINDS",
    "UNITS",
    "Element",
    "GraphState",
    "GraphTransition",
    "ModelRef",
    "Rejected",
    "State",
    "StateGraph",
    "StateKind",
    "StateTable",
    "SubSkill",
    "TaskModel",
    "Transition",
    "TransitionTable",
    "check_graph",
    "element_from_dict",
    "element_to_dict",
    "graph_to_dict",
    "model_from_dict",
    "model_to_dict",
    "state_graph",
    "state_letters",
    "state_spans",
    "task_from_dict",
    "task_head",
    "task_json_chunks",
    "task_to_dict",
]

SCHEMA = "apo.task/1"
"""Schema identifier written in and required from ``task.json``."""


KINDS = ("VF", "FV", "EE", "VE", "EV", "VV")
"""Contact element kinds (grasped feature first)."""

SUBSKILL_KINDS = ("push_to", "release", "slide")
"""Sub-skill kinds (paper section 3.5)."""

DOF_KINDS = ("M", "D", "C", "SM", "SD", "SC")
"""DOF kinds in a DOF transition: maintaining, detaching, constraining, singular variants."""

SPACES = ("translation", "rotation")

Space = Literal["translation", "rotation"]


Element = ContactElement
"""A contact element of a state: :class:`apo.contact.ContactElement` (one type everywhere).

``kind`` is a :class:`apo.contact.ContactKind` (a ``str`` enum equal to one of ``KINDS``);
``grasped``, ``environment`` feature ids ``("v" | "e" | "f", index)``; ``point`` (3,) and
``normals`` (M, 3) in the environment frame, metres, normals from E towards G.
"""


@dataclass(frozen=True, slots=True)
class State:
    """One contact state of the demonstration (a run of frames with the same contacts).

    Attributes
    ----------
    id : str
        Letter(s) ``"A"``, ``"B"``, ... in order of appearance (:func:`state_letters`).
    frames : tuple of (int, int)
        First and last frame index (inclusive).
    times : tuple of (float, float)
        Time stamps of the first and last frame, seconds.
    singular : bool
        True if any element is singular.
    fig25 : tuple of 8 int
        The paper's eight numbers (``apo.dof.DofResult.fig25``).
    six : dict
        ``{"translation": (M, D, C, SM, SD, SC), "rotation": (...)}``.
    elements : tuple of Element
    X_EG : ndarray, shape (4, 4)
        Representative pose (metres), corrected so that the contacts hold.
    pose_frame : int or None
        Frame the representative pose was corrected from (None: no frame converged and
        ``X_EG`` is the observed pose of the state's first frame).
    pose_converged : bool
        True if the correction of ``pose_frame`` converged.
    same_as : str or None
        Id of an earlier state with the same contact elements, if any.
    """

    id: str
    frames: tuple[int, int]
    times: tuple[float, float]
    singular: bool
    fig25: tuple[int, int, int, int, int, int, int, int]
    six: Mapping[str, tuple[int, int, int, int, int, int]]
    elements: tuple[Element, ...]
    X_EG: FloatArray
    pose_frame: int | None = None
    pose_converged: bool = True
    same_as: str | None = None


@dataclass(frozen=True, slots=True)
class Transition:
    """A transition between consecutive states.

    Attributes
    ----------
    from_id, to_id : str
        State ids.
    frame : int
        First frame of the ``to`` state.
    dof_transitions : dict
        ``{"translation": ((X, Y), ...), "rotation": (...)}``, X, Y in ``DOF_KINDS``.
    subskills : tuple of SubSkill
    critical : bool
        True if the transition contains SM -> C or SD -> C.
    direct : bool
        True if it passes the direct-transition test (always, after the repair, unless the
        demonstration itself has an unavoidable jump).
    choice : dict
        Per space, why ``dof_transitions`` was chosen among the practical decompositions:
        ``"unique"``, ``"geometry"`` (the before/after subspaces overlap best), ``"tie"``,
        ``"no change"`` or ``"none"`` (no practical decomposition).
    alternatives : dict
        Per space, the other practical decompositions, best first.
    """

    from_id: str
    to_id: str
    frame: int
    dof_transitions: Mapping[str, tuple[tuple[str, str], ...]]
    subskills: tuple[SubSkill, ...]
    critical: bool
    direct: bool = True
    choice: Mapping[str, str] = field(default_factory=dict)
    alternatives: Mapping[str, tuple[tuple[tuple[str, str], ...], ...]] = field(
        default_factory=dict
    )


@dataclass(frozen=True, slots=True)
class Rejected:
    """An observed run of frames the repair replaced.

    Attributes
    ----------
    frames : tuple of (int, int)
        First and last frame of the run (inclusive).
    elements : tuple of str
        The observed contact elements, as ``"VF v3-f7"`` labels.
    replaced_by : tuple of str
        Ids of the states the frames were assigned to instead.
    reason : str
        Why (infeasible transition, failed correction, or costlier than the alternative).
    """

    frames: tuple[int, int]
    elements: tuple[str, ...]
    replaced_by: tuple[str, ...]
    reason: str


#: Kinds of contact element whose point lies on the environment (a vertex of E): it stays
#: where it is when G moves. The others' points lie on G and move with it.
FIXED_POINT_KINDS = ("FV", "EV")


@dataclass(frozen=True, slots=True)
class StateKind:
    """What every visit of one contact state shares in a :class:`StateTable`.

    Attributes
    ----------
    singular, fig25, six
        As in :class:`State` (the same objects in every visit's state).
    elements : tuple of Element
        The contact elements at the reference pose whose inverse is ``inv_ref``.
    inv_ref : ndarray, shape (4, 4)
        Inverse of the reference pose: a visit at the pose ``X`` has its elements moved by
        ``X @ inv_ref`` (:meth:`points_at`).
    """

    singular: bool
    fig25: tuple[int, int, int, int, int, int, int, int]
    six: Mapping[str, tuple[int, int, int, int, int, int]]
    elements: tuple[Element, ...]
    inv_ref: FloatArray

    def points_at(self, X: FloatArray) -> FloatArray:
        """Return the elements' points at the poses ``X`` (m, 4, 4): shape (m, elements, 3).

        A point on G (kinds VF, VE, VV, EE) moves with it: ``T[:3, :3] @ p + T[:3, 3]`` with
        ``T = X @ inv_ref``; a point on a vertex of E (FV, EV) stays. Each pose's numbers
        are those of that pose alone (numpy's stacked products: the same per matrix).
        """
        X = np.asarray(X, dtype=np.float64).reshape(-1, 4, 4)
        T = X @ self.inv_ref
        out = np.empty((len(X), len(self.elements), 3))
        for j, e in enumerate(self.elements):
            fixed = e.kind in FIXED_POINT_KINDS
            out[:, j] = e.point if fixed else T[:, :3, :3] @ e.point + T[:, :3, 3]
        return out

    def elements_at(self, X: FloatArray) -> tuple[Element, ...]:
        """Return the elements with their points at the pose ``X`` (4, 4) (:meth:`points_at`)."""
        points = self.points_at(X)[0]
        return tuple(
            e if e.kind in FIXED_POINT_KINDS
            else Element(e.kind, e.grasped, e.environment, points[j], e.normals)
            for j, e in enumerate(self.elements)
        )  # fmt: skip


_T = TypeVar("_T")


class _Rows(Sequence[_T]):
    """A sequence whose items are made from rows when they are read (the tables below).

    Subclasses give ``__len__``, ``_item(i)`` (``0 <= i < len``) and ``_rows(a, b)`` (the
    items ``a`` to ``b - 1``, ``a < b``, as a table); a slice with a step is a tuple.
    """

    __slots__ = ()

    def _item(self, i: int) -> _T:
        raise NotImplementedError

    def _rows(self, a: int, b: int) -> Sequence[_T]:
        raise NotImplementedError

    @overload
    def __getitem__(self, i: int) -> _T: ...

    @overload
    def __getitem__(self, i: slice) -> Sequence[_T]: ...

    def __getitem__(self, i: int | slice) -> _T | Sequence[_T]:
        if isinstance(i, slice):
            a, b, step = i.indices(len(self))
            if step != 1 or b <= a:
                return tuple(self._item(j) for j in range(a, b, step))
            return self._rows(a, b)
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"index {i} out of range for {n} rows")
        return self._item(i % n)

    def __iter__(self) -> Iterator[_T]:
        return (self._item(i) for i in range(len(self)))

    def __eq__(self, other: object) -> bool:
        same: bool = _same_items(self, other)  # or NotImplemented
        return same

    __hash__ = None  # type: ignore[assignment]


class StateTable(_Rows[State]):
    """A task's states held as arrays, each :class:`State` made when it is read.

    A long demonstration has thousands of visits of a few contact states: the states'
    frames, times, poses and flags are rows of arrays, and what the visits of one contact
    state share (DOF numbers, elements at a reference pose) is one :class:`StateKind`; a
    state's elements are placed at its pose when the state is read (``table[i]``, iteration:
    a new :class:`State` each time, with the values the recognition gives). About 200 bytes
    a state, where the states themselves took 1.4 KB (docs/recognition.md, "Session 7:
    memory"). ``task.json`` is written from the arrays (:func:`task_json_chunks`).

    Attributes
    ----------
    ids : list of str
    frames : ndarray of int, shape (n, 2)
    times : ndarray of float, shape (n, 2)
    poses : ndarray, shape (n, 4, 4)
    kind : ndarray of int, shape (n,)
        Index into ``kinds`` of each state.
    kinds : list of StateKind
    pose_frames : ndarray of int, shape (n,)
        ``State.pose_frame``, -1 for None.
    converged : ndarray of bool, shape (n,)
    same_as : list of (str or None)
    """

    __slots__ = ("converged", "frames", "ids", "kind", "kinds", "pose_frames", "poses",
                 "same_as", "times")  # fmt: skip

    def __init__(
        self,
        ids: Sequence[str],
        frames: npt.ArrayLike,
        times: npt.ArrayLike,
        poses: npt.ArrayLike,
        kind: npt.ArrayLike,
        kinds: Sequence[StateKind],
        pose_frames: npt.ArrayLike,
        converged: npt.ArrayLike,
        same_as: Sequence[str | None],
    ) -> None:
        self.ids = list(ids)
        self.frames = np.asarray(frames, dtype=np.int64).reshape(-1, 2)
        self.times = np.asarray(times, dtype=np.float64).reshape(-1, 2)
        self.poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        self.kind = np.asarray(kind, dtype=np.int64).reshape(-1)
        self.kinds = kinds if isinstance(kinds, list) else list(kinds)
        self.pose_frames = np.asarray(pose_frames, dtype=np.int64).reshape(-1)
        self.converged = np.asarray(converged, dtype=bool).reshape(-1)
        self.same_as = list(same_as)

    def __len__(self) -> int:
        return len(self.ids)

    def _rows(self, a: int, b: int) -> StateTable:
        return StateTable(
            self.ids[a:b], self.frames[a:b], self.times[a:b], self.poses[a:b], self.kind[a:b],
            self.kinds, self.pose_frames[a:b], self.converged[a:b], self.same_as[a:b],
        )  # fmt: skip

    def __repr__(self) -> str:
        return f"<StateTable of {len(self)} states, {len(self.kinds)} distinct>"

    def index(self, value: Any, start: int = 0, stop: int | None = None) -> int:
        """Return the index of the state ``value`` (a state read from here: its id, frames)."""
        stop = len(self) if stop is None else stop
        if isinstance(value, State) and value.id in self.ids[start:stop]:
            i = self.ids.index(value.id, start, stop)
            if tuple(self.frames[i].tolist()) == tuple(value.frames):
                return i
        raise ValueError(f"{value!r} is not in the table")

    def __contains__(self, value: object) -> bool:
        try:
            self.index(value)
        except ValueError:
            return False
        return True

    def _item(self, i: int) -> State:
        kd = self.kinds[int(self.kind[i])]
        X = self.poses[i].copy()
        a, b = self.frames[i].tolist()
        t0, t1 = self.times[i].tolist()
        pf = int(self.pose_frames[i])
        return State(
            id=self.ids[i], frames=(a, b), times=(t0, t1), singular=kd.singular, fig25=kd.fig25,
            six=kd.six, elements=kd.elements_at(X), X_EG=X, pose_frame=None if pf < 0 else pf,
            pose_converged=bool(self.converged[i]), same_as=self.same_as[i],
        )  # fmt: skip

    def placed_points(self) -> FloatArray:
        """Return the points of every state's elements, state by state: shape (elements, 3).

        :meth:`StateKind.points_at` of each kind's states at once (their own poses).
        """
        counts = np.array([len(k.elements) for k in self.kinds], dtype=np.int64)[self.kind]
        start = np.cumsum(counts) - counts
        out = np.empty((int(counts.sum()), 3))
        for k, kd in enumerate(self.kinds):
            rows = np.flatnonzero(self.kind == k)
            if len(rows) and kd.elements:
                at = start[rows][:, None] + np.arange(len(kd.elements))
                out[at] = kd.points_at(self.poses[rows])
        return out


class TransitionTable(_Rows[Transition]):
    """A task's transitions held as rows, each :class:`Transition` made when it is read.

    Transition ``i`` goes from state ``ids[i]`` to ``ids[i + 1]`` at ``frames[i]`` and is
    otherwise ``kinds[which[i]]`` (the record of the first change between the same two
    contact states: its DOF transitions, sub-skills, marks).
    """

    __slots__ = ("frames", "ids", "kinds", "which")

    def __init__(
        self,
        ids: Sequence[str],
        frames: npt.ArrayLike,
        which: npt.ArrayLike,
        kinds: Sequence[Transition],
    ) -> None:
        self.frames = np.asarray(frames, dtype=np.int64).reshape(-1)
        self.which = np.asarray(which, dtype=np.int64).reshape(-1)
        self.ids = list(ids)
        self.kinds = kinds if isinstance(kinds, list) else list(kinds)
        if len(self.ids) != len(self.frames) + 1 and len(self.frames):
            raise ValueError("a transition table needs one state id more than transitions")

    def __len__(self) -> int:
        return len(self.frames)

    def _rows(self, a: int, b: int) -> TransitionTable:
        ids = self.ids[a : b + 1]
        return TransitionTable(ids, self.frames[a:b], self.which[a:b], self.kinds)

    def __repr__(self) -> str:
        return f"<TransitionTable of {len(self)} transitions, {len(self.kinds)} distinct>"

    def _item(self, i: int) -> Transition:
        return replace(
            self.kinds[int(self.which[i])], from_id=self.ids[i], to_id=self.ids[i + 1],
            frame=int(self.frames[i]),
        )  # fmt: skip


def _same_items(table: Sequence[Any], other: object) -> Any:
    """``tuple(table) == tuple(other)`` for another sequence (a table equals its tuple)."""
    if other is table:
        return True
    if not isinstance(other, Sequence) or isinstance(other, str | bytes):
        return NotImplemented
    return len(table) == len(other) and bool(tuple(table) == tuple(other))


def state_spans(states: Sequence[State]) -> list[tuple[str, int, int]]:
    """Return ``(id, first frame, last frame)`` of each state (a table's states not made)."""
    if isinstance(states, StateTable):
        return [(s, a, b) for s, (a, b) in zip(states.ids, states.frames.tolist(), strict=True)]
    return [(s.id, int(s.frames[0]), int(s.frames[1])) for s in states]


@dataclass(frozen=True)
class ModelRef:
    """A model file: path as written (relative to ``task.json`` or absolute) and its hash.

    Attributes
    ----------
    path : str
    sha256 : str or None
        Hex SHA-256 of the file content (None for built-in models without a file).
    name : str
    """

    path: str
    sha256: str | None
    name: str = ""


@dataclass(frozen=True)
class TaskModel:
    """The recognised demonstration.

    Attributes
    ----------
    units : str
        Length unit of the JSON form (``UNITS``); the model itself is in metres.
    grasped, environment : ModelRef
    states : sequence of State
        A tuple, or from the recognition a :class:`StateTable` (the states made as read).
    transitions : sequence of Transition
        ``len(states) - 1`` of them, in order (a tuple or a :class:`TransitionTable`).
    rejected : tuple of Rejected
    n_frames : int
    frame : str
        Frame of every point and direction: ``"environment"``.
    source : str
        Where the demonstration came from (file name or ``"apo demo"``).
    threshold : float
        Contact distance threshold used, metres.
    """

    units: str
    grasped: ModelRef
    environment: ModelRef
    states: Sequence[State]
    transitions: Sequence[Transition]
    rejected: tuple[Rejected, ...] = ()
    n_frames: int = 0
    frame: str = "environment"
    source: str = ""
    threshold: float = 0.0
    extra: Mapping[str, Any] = field(default_factory=dict)

    def state(self, state_id: str) -> State:
        """Return the state with id ``state_id``.

        Raises
        ------
        KeyError
            If there is none.
        """
        if isinstance(self.states, StateTable):
            if state_id in self.states.ids:
                return self.states[self.states.ids.index(state_id)]
            raise KeyError(state_id)
        for s in self.states:
            if s.id == state_id:
                return s
        raise KeyError(state_id)

    def graph(self) -> StateGraph:
        """Return the graph of distinct contact states (:func:`state_graph`)."""
        return state_graph(self)

    def subskill_sequence(self) -> list[tuple[str, str, str | None]]:
        """Return the sub-skills of all transitions in order as ``(kind, space, type)``."""
        return [(k.kind, k.space, k.type) for t in self.transitions for k in t.subskills]


def state_letters(n: int) -> list[str]:
    """Return ``n`` state ids: ``A .. Z``, then ``AA, AB, ...`` (spreadsheet columns).

    Examples
    --------
    >>> state_letters(3), state_letters(28)[-2:]
    (['A', 'B', 'C'], ['AA', 'AB'])
    """
    out: list[str] = []
    for i in range(n):
        s, k = "", i + 1
        while k > 0:
            k, r = divmod(k - 1, 26)
            s = chr(ord("A") + r) + s
        out.append(s)
    return out


# --------------------------------------------------------------------------------------------
# To JSON
# --------------------------------------------------------------------------------------------


def task_to_dict(task: TaskModel) -> dict[str, Any]:
    """Return the JSON form of ``task`` (schema ``"apo.task/1"``, lengths in ``task.units``).

    Parameters
    ----------
    task : TaskModel

    Returns
    -------
    dict
        Plain lists, strings, numbers and booleans, ready for :func:`json.dump`.
    """
    return _task_dict(task, lazy=False)


#: States (and transitions, rejected runs) converted at once by :func:`task_json_chunks`.
JSON_BLOCK_STATES = 256


def task_json_chunks(task: TaskModel, *, depth: int = 2) -> Iterator[str]:
    """Yield ``json_text(task_to_dict(task), depth=depth)`` in chunks (joined: the same text).

    The states, transitions and rejected runs are converted ``JSON_BLOCK_STATES`` at a
    time and written as they are made: the document of a long task (thousands of states)
    is never held whole, as a dictionary or as text. The document's other fields (the
    graph: a list per distinct state of its visits, 1 MB at 6,000 states) are made at the
    first chunk: by the process that writes, not by one that hands the chunks to a forked
    writer (``apo.report.writer.write_recognition``).
    """
    yield from json_chunks(_task_dict(task, lazy=True, lines=depth == 2), depth=depth)


def _task_dict(task: TaskModel, *, lazy: bool, lines: bool = False) -> dict[str, Any]:
    """:func:`task_to_dict`; ``lazy``: its long arrays as :class:`apo.outputs.JsonItems`.

    ``lines`` (with ``lazy``, for a text of depth 2: a state per line): the states are made
    as their lines of text (:func:`_state_lines`) instead of dictionaries.
    """
    head = task_head(task)  # checks the units
    k = 1.0 / UNITS[task.units]
    if lazy and lines:
        memo: dict[Any, Any] = {}
        states = _in_blocks(task.states, lambda b: _state_lines(b, k, memo), lazy)
        transitions = _in_blocks(task.transitions, lambda b: _transition_lines(b, k, memo), lazy)
    else:
        states = _in_blocks(task.states, lambda b: _states_to_dicts(b, k), lazy)
        transitions = _in_blocks(
            task.transitions, lambda b: [_transition_to_dict(t, k) for t in b], lazy
        )
    rejected = _in_blocks(task.rejected, lambda b: [_rejected_to_dict(r) for r in b], lazy)
    extra = head.pop("extra", None)
    return {
        **head,
        "states": states,
        "transitions": transitions,
        "rejected": rejected,
        "graph": graph_to_dict(state_graph(task)),
        **({"extra": extra} if extra is not None else {}),
    }


def task_head(task: TaskModel) -> dict[str, Any]:
    """Return the top-level fields of :func:`task_to_dict` that do not grow with the task.

    All but ``states``, ``transitions``, ``rejected`` and ``graph``, in the document's order.
    """
    if task.units not in UNITS:
        raise ValueError(f"unknown units {task.units!r}; expected one of {sorted(UNITS)}")
    k = 1.0 / UNITS[task.units]
    return {
        "schema": SCHEMA,
        "units": task.units,
        "frame": task.frame,
        "source": task.source,
        "n_frames": int(task.n_frames),
        "threshold": rounded(task.threshold * k),
        "models": {
            "grasped": model_to_dict(task.grasped),
            "environment": model_to_dict(task.environment),
        },
        **({"extra": dict(task.extra)} if task.extra else {}),
    }


def _in_blocks(
    items: Sequence[Any], convert: Callable[[Sequence[Any]], list[Any]], lazy: bool
) -> Any:
    """``convert(items)`` (a list), or with ``lazy`` a :class:`JsonItems` converting blocks."""
    if not lazy:
        return convert(items)

    def each() -> Iterator[Any]:
        for a in range(0, len(items), JSON_BLOCK_STATES):
            yield from convert(items[a : a + JSON_BLOCK_STATES])

    return JsonItems(len(items), each)


def _states_to_dicts(states: Sequence[State], k: float) -> list[dict[str, Any]]:
    """JSON forms of ``states`` (lengths times ``k``), their rotations converted at once."""
    if not states:
        return []
    quats = quaternions_from_matrices(np.array([st.X_EG[:3, :3] for st in states]))
    elements = _elements_by_state(states, k)
    return [
        _state_to_dict(st, k, q, els) for st, q, els in zip(states, quats, elements, strict=True)
    ]


_STATE_LINE = (
    '{{"id": {}, "frames": [{}, {}], "times": [{}, {}], "singular": {}, {}, "elements": [{}], '
    '"pose": {{"position": [{}, {}, {}], "quaternion": [{}, {}, {}, {}]}}, "pose_frame": {}, '
    '"pose_converged": {}, "same_as": {}}}'
)


def _state_lines(states: Sequence[State], k: float, memo: dict[Any, Any]) -> list[Any]:
    """Return the JSON forms of ``states`` as :func:`json_chunks` writes them, as text lines.

    The same text as :func:`_states_to_dicts` encoded (tested), made without the
    dictionaries: the numbers of all the states at once (:func:`rounded_texts`), the parts
    that repeat (DOF counts, an element's features, its normals) once per ``memo``. Where a
    number is not finite, or an id not a string, the dictionaries instead.
    """
    if not states:
        return []
    if isinstance(states, StateTable):
        return _table_state_lines(states, k, memo)
    if not all(isinstance(st.id, str) and isinstance(st.same_as, str | None) for st in states):
        return _states_to_dicts(states, k)
    X = np.array([np.asarray(st.X_EG, dtype=float) for st in states])
    times = np.array([st.times for st in states], dtype=float)
    els = [e for st in states for e in st.elements]
    points = np.array([e.point for e in els], dtype=float).reshape(-1, 3)
    rows = (
        (st.id, int(st.frames[0]), int(st.frames[1]), st.singular, _dof_text(st, memo),
         len(st.elements), None if st.pose_frame is None else int(st.pose_frame),
         st.pose_converged, st.same_as)
        for st in states
    )  # fmt: skip
    return _lines_of_states(states, (times, X, points, els), rows, k, memo)


def _table_state_lines(table: StateTable, k: float, memo: dict[Any, Any]) -> list[Any]:
    """:func:`_state_lines` of a table's states, made from its arrays (the same text).

    The states are not made: the elements' points are placed at the states' poses kind by
    kind (:meth:`StateTable.placed_points`), the DOF counts and the elements' features and
    normals come from each :class:`StateKind`. Where a number is not finite, the states
    are made and written as dictionaries.
    """
    kinds = [table.kinds[kk] for kk in table.kind.tolist()]
    els = [e for kd in kinds for e in kd.elements]  # the kinds' records: features, normals
    rows = (
        (sid, a, b, kd.singular, _dof_text(kd, memo), len(kd.elements),
         None if pf < 0 else pf, conv, same)
        for sid, (a, b), pf, conv, same, kd in zip(
            table.ids, table.frames.tolist(), table.pose_frames.tolist(),
            table.converged.tolist(), table.same_as, kinds, strict=True)
    )  # fmt: skip
    numbers = (table.times, table.poses, table.placed_points(), els)
    return _lines_of_states(table, numbers, rows, k, memo)


def _lines_of_states(
    states: Sequence[State],
    numbers: tuple[FloatArray, FloatArray, FloatArray, list[Element]],
    rows: Iterable[tuple[Any, ...]],
    k: float,
    memo: dict[Any, Any],
) -> list[Any]:
    """Return the text lines of ``states`` from their numbers and the other fields by row.

    ``numbers`` is (times (n, 2), poses (n, 4, 4), the elements' points (m, 3), the m
    elements); ``rows`` gives each state's id, first and last frame, singular, DOF text,
    number of elements, pose frame (or None), converged and same-as. Lengths are scaled by
    ``k``. Where a number is not finite, :func:`_states_to_dicts` of ``states`` instead.
    """
    times, X, points, els = numbers
    quats = quaternions_from_matrices(np.ascontiguousarray(X[:, :3, :3]))
    pos = X[:, :3, 3]
    nums = np.concatenate([times, pos if k == 1.0 else pos * k, quats], axis=1)
    if k != 1.0:
        points = points * k
    if not (np.isfinite(nums).all() and np.isfinite(points).all()):
        return _states_to_dicts(states, k)
    texts = rounded_texts(nums.ravel().tolist() + points.ravel().tolist())
    try:
        elements = _element_texts(els, texts[9 * len(states) :], memo)
    except ValueError:  # a normal that is not finite
        return _states_to_dicts(states, k)
    out: list[Any] = []
    j = 0
    for i, (sid, a, b, singular, dof, n, pf, conv, same) in enumerate(rows):
        t = texts[9 * i : 9 * i + 9]
        out.append(RawJson(_STATE_LINE.format(
            json_str(sid), a, b, t[0], t[1], "true" if singular else "false", dof,
            ", ".join(elements[j : j + n]), *t[2:], "null" if pf is None else pf,
            "true" if conv else "false", "null" if same is None else json_str(same),
        )))  # fmt: skip
        j += n
    return out


def _dof_text(s: State | StateKind, memo: dict[Any, Any]) -> str:
    """``"fig25": [...], "six": {...}`` of a state's JSON line (once per distinct counts)."""
    key = ("dof", tuple(s.fig25), *(tuple(s.six[sp]) for sp in SPACES))
    text = memo.get(key)
    if text is None:
        six = ", ".join(f'"{sp}": [{", ".join(str(int(v)) for v in s.six[sp])}]' for sp in SPACES)
        text = f'"fig25": [{", ".join(str(int(v)) for v in s.fig25)}], "six": {{{six}}}'
        memo[key] = text
    return text


def _element_texts(
    els: Sequence[Element], points: Sequence[str], memo: dict[Any, Any]
) -> list[str]:
    """Return the JSON texts of contact elements given their points' texts (three each).

    The features' and the normals' texts are made once per ``memo``. Raises ValueError at a
    normal that is not finite.
    """
    out = []
    it = iter(points)
    for e, point in zip(els, map(", ".join, zip(it, it, it, strict=True)), strict=True):
        head = memo.get((e.kind, e.grasped, e.environment))
        if head is None:
            head = memo[(e.kind, e.grasped, e.environment)] = (
                f'{{"kind": {json_str(str(e.kind))}, "grasped": [{json_str(e.grasped[0])}, '
                f'{int(e.grasped[1])}], "environment": [{json_str(e.environment[0])}, '
                f'{int(e.environment[1])}], "point": ['
            )
        normals = np.asarray(e.normals, dtype=float)
        tail = memo.get(key := normals.tobytes())
        if tail is None:
            rows = normals.reshape(-1, 3)
            if not np.isfinite(rows).all():
                raise ValueError("normal not finite")
            nums = rounded_texts(rows.ravel().tolist())
            text = ", ".join(f"[{', '.join(nums[r : r + 3])}]" for r in range(0, len(nums), 3))
            tail = memo[key] = f'], "normals": [{text}]}}'
        out.append(head + point + tail)
    return out


def _rejected_to_dict(r: Rejected) -> dict[str, Any]:
    """JSON form of a rejected run."""
    return {
        "frames": [int(r.frames[0]), int(r.frames[1])],
        "elements": list(r.elements),
        "replaced_by": list(r.replaced_by),
        "reason": r.reason,
    }


def _state_to_dict(
    s: State, k: float, q: FloatArray, elements: list[dict[str, Any]]
) -> dict[str, Any]:
    """JSON form of a state, lengths times ``k`` (metres to the units), quaternion q."""
    p = np.asarray(s.X_EG, dtype=float)[:3, 3]
    return {
        "id": s.id,
        "frames": [int(s.frames[0]), int(s.frames[1])],
        "times": [rounded(s.times[0]), rounded(s.times[1])],
        "singular": bool(s.singular),
        "fig25": [int(v) for v in s.fig25],
        "six": {sp: [int(v) for v in s.six[sp]] for sp in SPACES},
        "elements": elements,
        "pose": {"position": rounded_list(p, k), "quaternion": rounded_list(q)},
        "pose_frame": None if s.pose_frame is None else int(s.pose_frame),
        "pose_converged": bool(s.pose_converged),
        "same_as": s.same_as,
    }


def _elements_by_state(states: Sequence[State], k: float) -> list[list[dict[str, Any]]]:
    """``[[element_to_dict(e, k) for e in s.elements] for s in states]``, the same dicts.

    The points and normals of all elements are converted to plain floats at once: one
    ``tolist`` per array instead of three per element (30,000 elements: 0.6 s -> 0.2 s).
    """
    els = [e for s in states for e in s.elements]
    if not els:
        return [[] for _ in states]
    points = np.array([e.point for e in els], dtype=float).reshape(-1, 3)
    pts = (points if k == 1.0 else points * k).tolist()
    normals = [np.asarray(e.normals, dtype=float).reshape(-1, 3) for e in els]
    rows = np.concatenate(normals).tolist()
    ends = np.cumsum([len(n) for n in normals]).tolist()
    out: list[list[dict[str, Any]]] = []
    i = 0
    for s in states:
        mine = []
        for e in s.elements:
            a = ends[i - 1] if i else 0
            mine.append(
                {
                    "kind": str(e.kind),
                    "grasped": [e.grasped[0], int(e.grasped[1])],
                    "environment": [e.environment[0], int(e.environment[1])],
                    "point": [round(v, 9) for v in pts[i]],
                    "normals": [[round(v, 9) for v in r] for r in rows[a : ends[i]]],
                }
            )
            i += 1
        out.append(mine)
    return out


def element_to_dict(e: Element, k: float) -> dict[str, Any]:
    """Return the JSON form of a contact element, its point times ``k`` (to the units)."""
    return {
        "kind": str(e.kind),
        "grasped": [e.grasped[0], int(e.grasped[1])],
        "environment": [e.environment[0], int(e.environment[1])],
        "point": rounded_list(e.point, k),
        "normals": rounded_rows(e.normals),
    }


def _transition_to_dict(t: Transition, k: float) -> dict[str, Any]:
    """JSON form of a transition, lengths times ``k`` (metres to the task's units)."""
    d = _transition_fields(t)
    d["subskills"] = [
        {
            "kind": str(u.kind),
            "space": u.space,
            "type": u.type,
            "direction": rounded_list(np.zeros(3) if u.direction is None else u.direction),
            "point": None if u.point is None else rounded_list(u.point, k),
            "source": u.source,
            "subspace": rounded_rows(u.subspace),
        }
        for u in t.subskills
    ]
    return d


def _transition_lines(
    transitions: Sequence[Transition], k: float, memo: dict[Any, Any]
) -> list[Any]:
    """Return the JSON forms of ``transitions`` as :func:`json_chunks` writes them, as text lines.

    :func:`_transition_to_dict` encoded (tested): the fields but the sub-skills by the JSON
    encoder, the sub-skills' numbers all at once (:func:`rounded_texts`); where one is not
    finite, the dictionaries instead.
    """
    if isinstance(transitions, TransitionTable):
        return _table_transition_lines(transitions, k, memo)
    nums: list[float] = []
    sizes: list[tuple[int, int, int]] = []
    for t in transitions:
        for u in t.subskills:
            d = np.asarray(np.zeros(3) if u.direction is None else u.direction, dtype=float)
            p = np.asarray(() if u.point is None else u.point, dtype=float).ravel()
            r = np.asarray(u.subspace, dtype=float).reshape(-1, 3).ravel()
            nums += d.ravel().tolist() + (p if k == 1.0 else p * k).tolist() + r.tolist()
            sizes.append((d.size, -1 if u.point is None else len(p), len(r)))
    if not np.isfinite(np.array(nums, dtype=float)).all():
        return [_transition_to_dict(t, k) for t in transitions]
    flat, texts, i, j, out = one_line_encoder(), rounded_texts(nums), 0, 0, []
    for t in transitions:
        subs = []
        for u in t.subskills:
            nd, npt, nr = sizes[j]
            key = ("subskill", str(u.kind), u.space, u.type, u.source)
            head, mid = memo.get(key) or memo.setdefault(key, (
                f'{{"kind": {flat(str(u.kind))}, "space": {flat(u.space)}, '
                f'"type": {flat(u.type)}, "direction": [',
                f', "source": {flat(u.source)}, "subspace": ['))  # fmt: skip
            a, b = i + nd, i + nd + max(npt, 0)
            point = "null" if npt < 0 else f"[{', '.join(texts[a:b])}]"
            rows = ", ".join(f"[{', '.join(texts[c : c + 3])}]" for c in range(b, b + nr, 3))
            subs.append(f'{head}{", ".join(texts[i:a])}], "point": {point}{mid}{rows}]}}')
            i, j = b + nr, j + 1
        line = flat(_transition_fields(t))
        if subs:
            line = line.replace('"subskills": []', f'"subskills": [{", ".join(subs)}]', 1)
        out.append(RawJson(line))
    return out


def _table_transition_lines(table: TransitionTable, k: float, memo: dict[Any, Any]) -> list[Any]:
    """:func:`_transition_lines` of a table's transitions (the same text).

    A transition's line is ``{"from": .., "to": .., "frame": ..`` and then the text of its
    record (:attr:`TransitionTable.kinds`), made once per record from the line of its first
    transition here; a record whose line does not start so is written transition by
    transition.
    """
    out: list[Any] = []
    for i, (w, frame) in enumerate(zip(table.which.tolist(), table.frames.tolist(), strict=True)):
        a, b = json_str(table.ids[i]), json_str(table.ids[i + 1])
        head = f'{{"from": {a}, "to": {b}, "frame": {frame}'
        key = ("transition", id(table.kinds), w)
        if key not in memo:
            line = _transition_lines([table[i]], k, memo)[0]
            ok = isinstance(line, RawJson) and line.startswith(head)
            memo[key] = (str(line[len(head) :]) if ok else None, table.kinds)  # kinds kept
        tail: str | None = memo[key][0]
        if tail is None:
            out.append(_transition_lines([table[i]], k, memo)[0])
        else:
            out.append(RawJson(head + tail))
    return out


def _transition_fields(t: Transition) -> dict[str, Any]:
    """:func:`_transition_to_dict` of ``t`` without its sub-skills (``[]``)."""
    return {
        "from": t.from_id,
        "to": t.to_id,
        "frame": int(t.frame),
        "dof_transitions": {
            sp: [[a, b] for a, b in t.dof_transitions.get(sp, ())] for sp in SPACES
        },
        "subskills": [],
        "critical": bool(t.critical),
        "direct": bool(t.direct),
        "decomposition": {
            sp: {
                "choice": t.choice.get(sp, "unique"),
                "alternatives": [[[a, b] for a, b in alt] for alt in t.alternatives.get(sp, ())],
            }
            for sp in SPACES
        },
    }


def model_to_dict(m: ModelRef) -> dict[str, Any]:
    """Return the JSON form ``{"path", "sha256", "name"}`` of a model reference."""
    return {"path": m.path, "sha256": m.sha256, "name": m.name}


# --------------------------------------------------------------------------------------------
# From JSON, with validation
# --------------------------------------------------------------------------------------------


def task_from_dict(data: Any, *, source: str = "") -> TaskModel:
    """Validate the JSON form of a task and return the :class:`TaskModel` (metres).

    Parameters
    ----------
    data : dict
        As produced by :func:`task_to_dict` (e.g. ``json.load`` of a ``task.json``).
    source : str, optional
        File name used in error messages.

    Returns
    -------
    TaskModel

    Raises
    ------
    InputFormatError
        Wrong or missing schema, missing or mistyped fields, unknown units, kinds or state
        ids, a quaternion that is not unit length, frames out of order. The message names
        ``source`` and the field (e.g. ``states[2].fig25``).
    """
    rd = JsonReader(source or "task")
    d = rd.obj(data, "top level")
    schema = d.get("schema")
    if schema != SCHEMA:
        raise rd.fail("schema", f"expected {SCHEMA!r}, got {schema!r}")
    units = rd.string(rd.get(d, "units", "top level"), "units", tuple(UNITS))
    k = UNITS[units]
    frame = rd.string(rd.get(d, "frame", "top level"), "frame", ("environment",))
    models = rd.obj(rd.get(d, "models", "top level"), "models")
    refs = [
        model_from_dict(rd, rd.get(models, r, "models"), f"models.{r}")
        for r in ("grasped", "environment")
    ]
    states: list[State] = []
    ids: set[str] = set()
    for i, sd_ in enumerate(rd.lst(rd.get(d, "states", "top level"), "states")):
        prev_last = states[-1].frames[1] if states else -1
        states.append(_read_state(rd, sd_, f"states[{i}]", k, ids, prev_last))
        ids.add(states[-1].id)
    tl = rd.lst(rd.get(d, "transitions", "top level"), "transitions")
    if len(tl) != max(len(states) - 1, 0):
        raise rd.fail(
            "transitions",
            f"expected {max(len(states) - 1, 0)} (one between each pair of consecutive "
            f"states), got {len(tl)}",
        )
    transitions = [
        _read_transition(rd, td_, f"transitions[{i}]", k, states[i], states[i + 1])
        for i, td_ in enumerate(tl)
    ]
    rejected = [
        _read_rejected(rd, rj_, f"rejected[{i}]", ids)
        for i, rj_ in enumerate(rd.lst(d.get("rejected", []), "rejected"))
    ]
    n_frames = rd.integer(d.get("n_frames", states[-1].frames[1] + 1 if states else 0), "n_frames")
    if states and states[-1].frames[1] >= n_frames:
        raise rd.fail(
            "n_frames", f"{n_frames} but the last state ends at frame {states[-1].frames[1]}"
        )
    extra = d.get("extra", {})
    task = TaskModel(
        units=units,
        grasped=refs[0],
        environment=refs[1],
        states=tuple(states),
        transitions=tuple(transitions),
        rejected=tuple(rejected),
        n_frames=n_frames,
        frame=frame,
        source=rd.string(d.get("source", ""), "source"),
        threshold=rd.number(d.get("threshold", 0.0), "threshold") * k,
        extra=dict(rd.obj(extra, "extra")),
    )
    if "graph" in d:
        check_graph(task, d["graph"], source=source)
    return task


def _read_state(rd: JsonReader, sd_: Any, w: str, k: float, ids: set[str], prev_last: int) -> State:
    """Read one state ``w`` (lengths times ``k`` to metres); ``ids`` are the earlier ones."""
    sd = rd.obj(sd_, w)
    sid = rd.string(rd.get(sd, "id", w), f"{w}.id")
    if not sid or sid in ids:
        raise rd.fail(f"{w}.id", f"empty or duplicate state id {sid!r}")
    fr = rd.lst(rd.get(sd, "frames", w), f"{w}.frames", 2)
    f0, f1 = rd.integer(fr[0], f"{w}.frames[0]"), rd.integer(fr[1], f"{w}.frames[1]")
    if not 0 <= f0 <= f1 or f0 <= prev_last:
        raise rd.fail(f"{w}.frames", f"frames [{f0}, {f1}] out of order")
    tv = rd.vector(sd.get("times", [0.0, 0.0]), f"{w}.times", 2)
    fig = rd.lst(rd.get(sd, "fig25", w), f"{w}.fig25", 8)
    fig25 = tuple(rd.integer(x, f"{w}.fig25[{j}]") for j, x in enumerate(fig))
    if any(not 0 <= v <= 3 for v in fig25):
        raise rd.fail(f"{w}.fig25", f"entries must be in 0..3, got {list(fig25)}")
    six = _read_six(rd, sd.get("six", {}), f"{w}.six")
    elements = [
        element_from_dict(rd, ed_, f"{w}.elements[{j}]", k)
        for j, ed_ in enumerate(rd.lst(rd.get(sd, "elements", w), f"{w}.elements"))
    ]
    singular = rd.boolean(rd.get(sd, "singular", w), f"{w}.singular")
    if singular != any(e.singular for e in elements):
        raise rd.fail(f"{w}.singular", f"{singular} disagrees with the elements' normals")
    pd = rd.obj(rd.get(sd, "pose", w), f"{w}.pose")
    pos = rd.vector(rd.get(pd, "position", f"{w}.pose"), f"{w}.pose.position", 3) * k
    quat = rd.vector(rd.get(pd, "quaternion", f"{w}.pose"), f"{w}.pose.quaternion", 4)
    if abs(float(np.linalg.norm(quat)) - 1.0) > tol.json_quaternion_norm:
        raise rd.fail(f"{w}.pose.quaternion", f"not a unit quaternion: {quat.tolist()}")
    pf = sd.get("pose_frame")
    same_as = sd.get("same_as")
    if same_as is not None and rd.string(same_as, f"{w}.same_as") not in ids | {sid}:
        raise rd.fail(f"{w}.same_as", f"unknown earlier state {same_as!r}")
    return State(
        id=sid,
        frames=(f0, f1),
        times=(float(tv[0]), float(tv[1])),
        singular=singular,
        fig25=cast("tuple[int, int, int, int, int, int, int, int]", fig25),
        six=six,
        elements=tuple(elements),
        X_EG=pose_from_position_quaternion(pos, quat),
        pose_frame=None if pf is None else rd.integer(pf, f"{w}.pose_frame"),
        pose_converged=rd.boolean(sd.get("pose_converged", True), f"{w}.pose_converged"),
        same_as=same_as,
    )


def _read_six(rd: JsonReader, v: Any, w: str) -> dict[str, tuple[int, int, int, int, int, int]]:
    """Read a state's ``six`` numbers per space (6 non-negative ints summing to 3)."""
    six_d = rd.obj(v, w)
    six: dict[str, tuple[int, int, int, int, int, int]] = {}
    for sp in SPACES:
        if sp in six_d:
            vals = rd.lst(six_d[sp], f"{w}.{sp}", 6)
            tup = tuple(rd.integer(x, f"{w}.{sp}[{j}]") for j, x in enumerate(vals))
            if sum(tup) != 3 or min(tup) < 0:
                raise rd.fail(
                    f"{w}.{sp}",
                    f"must be 6 non-negative ints summing to 3, got {list(tup)}",
                )
            six[sp] = cast("tuple[int, int, int, int, int, int]", tup)
    return six


def element_from_dict(rd: JsonReader, ed_: Any, we: str, k: float) -> Element:
    """Read the contact element ``we`` (its point times ``k``, to metres; unit normals)."""
    ed = rd.obj(ed_, we)
    normals_l = rd.lst(rd.get(ed, "normals", we), f"{we}.normals")
    if not normals_l:
        raise rd.fail(f"{we}.normals", "expected at least one normal")
    normals = np.array([rd.vector(n, f"{we}.normals[{m}]", 3) for m, n in enumerate(normals_l)])
    if np.any(np.abs(np.linalg.norm(normals, axis=1) - 1.0) > tol.json_unit_norm):
        raise rd.fail(f"{we}.normals", "normals must be unit vectors")
    return Element(
        kind=rd.string(rd.get(ed, "kind", we), f"{we}.kind", KINDS),
        grasped=rd.feature(ed.get("grasped", ["v", 0]), f"{we}.grasped"),
        environment=rd.feature(ed.get("environment", ["v", 0]), f"{we}.environment"),
        point=rd.vector(rd.get(ed, "point", we), f"{we}.point", 3) * k,
        normals=normals,
    )


def _read_transition(
    rd: JsonReader, td_: Any, w: str, k: float, before: State, after: State
) -> Transition:
    """Read the transition ``w`` between the consecutive states ``before`` and ``after``."""
    td = rd.obj(td_, w)
    a = rd.string(rd.get(td, "from", w), f"{w}.from")
    b = rd.string(rd.get(td, "to", w), f"{w}.to")
    if (a, b) != (before.id, after.id):
        raise rd.fail(w, f"expected {before.id} -> {after.id}, got {a} -> {b}")
    dd = rd.obj(rd.get(td, "dof_transitions", w), f"{w}.dof_transitions")
    dof_t = {sp: _read_pairs(rd, dd.get(sp, []), f"{w}.dof_transitions.{sp}") for sp in SPACES}
    choice: dict[str, str] = {}
    alternatives: dict[str, tuple[tuple[tuple[str, str], ...], ...]] = {}
    dec = rd.obj(td.get("decomposition", {}), f"{w}.decomposition")
    for sp in SPACES:
        if sp not in dec:
            continue
        ws = f"{w}.decomposition.{sp}"
        ds = rd.obj(dec[sp], ws)
        choice[sp] = rd.string(ds.get("choice", "unique"), f"{ws}.choice")
        alternatives[sp] = tuple(
            _read_pairs(rd, alt, f"{ws}.alternatives[{j}]")
            for j, alt in enumerate(rd.lst(ds.get("alternatives", []), f"{ws}.alternatives"))
        )
    subs = [
        _read_subskill(rd, ud_, f"{w}.subskills[{j}]", k)
        for j, ud_ in enumerate(rd.lst(rd.get(td, "subskills", w), f"{w}.subskills"))
    ]
    return Transition(
        from_id=a,
        to_id=b,
        frame=rd.integer(td.get("frame", after.frames[0]), f"{w}.frame"),
        dof_transitions=dof_t,
        subskills=tuple(subs),
        critical=rd.boolean(rd.get(td, "critical", w), f"{w}.critical"),
        choice=choice,
        alternatives=alternatives,
        direct=rd.boolean(td.get("direct", True), f"{w}.direct"),
    )


def _read_subskill(rd: JsonReader, ud_: Any, wu: str, k: float) -> SubSkill:
    """Read one sub-skill ``wu`` (its axis point times ``k`` to metres)."""
    ud = rd.obj(ud_, wu)
    typ = ud.get("type")
    rows = rd.lst(ud.get("subspace", []), f"{wu}.subspace")
    return SubSkill(
        kind=SubSkillKind(rd.string(rd.get(ud, "kind", wu), f"{wu}.kind", SUBSKILL_KINDS)),
        space=rd.string(rd.get(ud, "space", wu), f"{wu}.space", SPACES),
        type=None if typ is None else rd.string(typ, f"{wu}.type", ("I", "II")),
        direction=rd.vector(ud.get("direction", [0, 0, 0]), f"{wu}.direction", 3),
        point=(None if ud.get("point") is None else rd.vector(ud["point"], f"{wu}.point", 3) * k),
        source=rd.string(ud.get("source", "none"), f"{wu}.source"),
        subspace=np.array(
            [rd.vector(row, f"{wu}.subspace[{r}]", 3) for r, row in enumerate(rows)],
            dtype=np.float64,
        ).reshape(-1, 3),
    )


def _read_rejected(rd: JsonReader, rj_: Any, w: str, ids: set[str]) -> Rejected:
    """Read one rejected run ``w``; ``ids`` are the task's state ids."""
    rj = rd.obj(rj_, w)
    fr = rd.lst(rd.get(rj, "frames", w), f"{w}.frames", 2)
    return Rejected(
        frames=(rd.integer(fr[0], f"{w}.frames[0]"), rd.integer(fr[1], f"{w}.frames[1]")),
        elements=tuple(
            rd.string(x, f"{w}.elements") for x in rd.lst(rj.get("elements", []), f"{w}.elements")
        ),
        replaced_by=tuple(
            rd.string(x, f"{w}.replaced_by", tuple(ids))
            for x in rd.lst(rj.get("replaced_by", []), f"{w}.replaced_by")
        ),
        reason=rd.string(rj.get("reason", ""), f"{w}.reason"),
    )


def _read_pairs(rd: JsonReader, v: Any, where: str) -> tuple[tuple[str, str], ...]:
    """Read a list of unit DOF transitions ``[["M", "D"], ...]``."""
    out: list[tuple[str, str]] = []
    for j, pr in enumerate(rd.lst(v, where)):
        wp = f"{where}[{j}]"
        pl = rd.lst(pr, wp, 2)
        out.append((rd.string(pl[0], wp, DOF_KINDS), rd.string(pl[1], wp, DOF_KINDS)))
    return tuple(out)


def model_from_dict(rd: JsonReader, v: Any, where: str) -> ModelRef:
    """Read the model reference ``where`` (a 64-hex-digit ``sha256`` or null)."""
    m = rd.obj(v, where)
    path = rd.string(rd.get(m, "path", where), f"{where}.path")
    h = m.get("sha256")
    if h is not None:
        h = rd.string(h, f"{where}.sha256")
        if len(h) != 64 or any(c not in "0123456789abcdef" for c in h):
            raise rd.fail(f"{where}.sha256", "expected 64 lowercase hex digits")
    return ModelRef(path=path, sha256=h, name=rd.string(m.get("name", ""), f"{where}.name"))


# --------------------------------------------------------------------------------------------
# The state graph: each distinct contact state once, with its visits
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GraphState:
    """A distinct contact state of the task (the same contact elements), with its visits.

    Attributes
    ----------
    id : str
        Id of its first visit in ``TaskModel.states``.
    states : tuple of str
        Ids of every visit, in time order.
    visits : tuple of (int, int)
        Frame range ``(first, last)`` of every visit, inclusive.
    """

    id: str
    states: tuple[str, ...]
    visits: tuple[tuple[int, int], ...]


@dataclass(frozen=True)
class GraphTransition:
    """Transitions between two distinct states, counted.

    Attributes
    ----------
    from_id, to_id : str
        Ids of the distinct states (``GraphState.id``).
    count : int
        How often the demonstration makes it.
    frames : tuple of int
        First frame of the ``to`` state at each occurrence.
    critical : bool
        True if some occurrence is critical.
    direct : bool
        True if every occurrence passes the direct-transition test.
    """

    from_id: str
    to_id: str
    count: int
    frames: tuple[int, ...]
    critical: bool
    direct: bool


@dataclass(frozen=True)
class StateGraph:
    """The task's distinct contact states and the transitions between them."""

    states: tuple[GraphState, ...]
    transitions: tuple[GraphTransition, ...]


def _element_set(s: State) -> frozenset[tuple[str, Feature, Feature]]:
    return frozenset((e.kind, e.grasped, e.environment) for e in s.elements)


_Visit = tuple[str, tuple[int, int], frozenset[tuple[str, Feature, Feature]]]
_Change = tuple[str, str, int, bool, bool]


def _visits(states: Sequence[State]) -> list[_Visit]:
    """``(id, frames, element keys)`` of each state (a table's states are not made)."""
    if isinstance(states, StateTable):
        keys = [frozenset((e.kind, e.grasped, e.environment) for e in kd.elements)
                for kd in states.kinds]  # fmt: skip
        rows = zip(states.ids, states.frames.tolist(), states.kind.tolist(), strict=True)
        return [(sid, (a, b), keys[kk]) for sid, (a, b), kk in rows]
    return [(s.id, s.frames, _element_set(s)) for s in states]


def _changes(transitions: Sequence[Transition]) -> list[_Change]:
    """``(from, to, frame, critical, direct)`` of each transition (a table's not made)."""
    if isinstance(transitions, TransitionTable):
        ids, kinds = transitions.ids, transitions.kinds
        rows = zip(transitions.which.tolist(), transitions.frames.tolist(), strict=True)
        return [(ids[i], ids[i + 1], f, kinds[w].critical, kinds[w].direct)
                for i, (w, f) in enumerate(rows)]  # fmt: skip
    return [(t.from_id, t.to_id, t.frame, t.critical, t.direct) for t in transitions]


def state_graph(task: TaskModel) -> StateGraph:
    """Return the graph of distinct contact states (same elements) and their transitions.

    A demonstration that repeats an assembly visits each distinct state several times; the
    graph lists it once with the frame ranges of its visits, and each transition between
    distinct states once with its count, in order of first occurrence.
    """
    node_of: dict[frozenset[tuple[str, Feature, Feature]], str] = {}
    visits: dict[str, list[_Visit]] = {}
    by_state: dict[str, str] = {}
    for v in _visits(task.states):
        nid = by_state[v[0]] = node_of.setdefault(v[2], v[0])
        visits.setdefault(nid, []).append(v)
    edges: dict[tuple[str, str], list[_Change]] = {}
    for t in _changes(task.transitions):
        edges.setdefault((by_state[t[0]], by_state[t[1]]), []).append(t)
    return StateGraph(
        states=tuple(
            GraphState(nid, tuple(v[0] for v in vs), tuple(v[1] for v in vs))
            for nid, vs in visits.items()
        ),
        transitions=tuple(
            GraphTransition(
                a, b, len(ts), tuple(t[2] for t in ts),
                any(t[3] for t in ts), all(t[4] for t in ts),
            )
            for (a, b), ts in edges.items()
        ),
    )  # fmt: skip


def graph_to_dict(graph: StateGraph) -> dict[str, Any]:
    """Return the JSON form of a state graph (the ``graph`` of ``task.json``)."""
    return {
        "states": [
            {"id": g.id, "states": list(g.states),
             "visits": [[int(a), int(b)] for a, b in g.visits]}
            for g in graph.states
        ],
        "transitions": [
            {"from": e.from_id, "to": e.to_id, "count": e.count,
             "frames": [int(f) for f in e.frames], "critical": e.critical, "direct": e.direct}
            for e in graph.transitions
        ],
    }  # fmt: skip


def check_graph(task: TaskModel, data: Any, *, source: str = "") -> StateGraph:
    """Check the ``graph`` of a ``task.json`` against its states and transitions.

    Raises
    ------
    InputFormatError
        If ``data`` is not the graph the states and transitions give.
    """
    graph = state_graph(task)
    if data != graph_to_dict(graph):
        raise InputFormatError(
            f"{source or 'task'}: graph: does not match the states and transitions "
            "(each distinct contact state once with its visits, transitions counted)"
        )
    return graph
