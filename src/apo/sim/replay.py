"""Replay a task model in MuJoCo: plan, execute with the compliant hand, judge by contacts.

:func:`replay` is what ``apo replay`` runs (``docs/sim.md``): it builds the scene from the
task's two models, perturbs the start pose of the grasped object and moves the environment
by an offset the plan does not know, executes the skill program of :func:`apo.motion.plan`
(or, with ``playback=True``, follows the observed poses by position control), and judges
the outcome with apo's own contact analysis: :class:`apo.contact.ContactFinder` on the
simulated pose of the grasped object in the (moved) environment's frame.

Success means the final contact state has the same elements as the task's final state
(kind, grasped feature, environment feature), by feature ids (both come from the same model
files), up to the models' symmetries (:func:`judge`). The states visited are the task
states whose element sets the simulated poses match, in order.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from apo.geometry import Polyhedron
from apo.sim.execute import PrimitiveRun, run_playback, run_program
from apo.sim.hand import Gains, Hand
from apo.sim.pieces import Decomposition, convex_pieces
from apo.sim.scene import DEFAULT_CLEARANCE, ContactParameters, build_scene
from apo.spatial import matrix_from_axis_angle
from apo.task import TaskModel
from apo.typing import FloatArray

__all__ = [
    "SAMPLE_PERIOD",
    "Judgement",
    "ReplayResult",
    "Visit",
    "judge",
    "model_symmetries",
    "random_motion",
    "replay",
    "state_ids",
]

SAMPLE_PERIOD = 0.01
"""Seconds between the recorded poses (trajectory and contact-state sequence)."""


@dataclass(frozen=True)
class Visit:
    """A run of recorded poses with one contact state.

    Attributes
    ----------
    state : str or None
        Id of the task state with the same elements, or None for a state not in the task.
    t_start, t_end : float
        Simulated seconds.
    n_elements : int
    """

    state: str | None
    t_start: float
    t_end: float
    n_elements: int


@dataclass
class ReplayResult:
    """The outcome of one replay (SI units, environment frame).

    Attributes
    ----------
    success : bool
        The final contact state equals the task's final state.
    mode : str
        ``"skills"`` or ``"playback"``.
    final_X_EG : ndarray, shape (4, 4)
        Final pose of the grasped object in the (moved) environment's frame, metres.
    final_state : str or None
        Id of the task state matching the final contact state (None: none does).
    states_reached : list of str
        Task states visited, in order (consecutive repeats merged; unknown states skipped).
    visits : list of Visit
        Every contact state visited, unknown ones included.
    task_states : list of str
        The task's state sequence, for comparison.
    max_force : float
        Largest contact force on the grasped object, newtons.
    max_penetration : float
        Largest penetration of any contact, metres.
    primitives : list of PrimitiveRun
    sim_time, wall_time : float
        Simulated and wall-clock seconds of the execution.
    times : ndarray, shape (K,)
        Recorded times, seconds.
    X_EG : ndarray, shape (K, 4, 4)
        Recorded poses of the grasped object in the environment frame, metres.
    verdict : str
        One line for people.
    settings : dict
        Perturbation, offset, clearance, seed, contact parameters, gains.
    by_symmetry : bool
        The final state matched the task's only through a symmetric twin (:func:`judge`).
    """

    success: bool
    mode: str
    final_X_EG: FloatArray
    final_state: str | None
    states_reached: list[str]
    visits: list[Visit]
    task_states: list[str]
    max_force: float
    max_penetration: float
    primitives: list[PrimitiveRun]
    sim_time: float
    wall_time: float
    times: FloatArray
    X_EG: FloatArray
    verdict: str
    settings: dict[str, Any] = field(default_factory=dict)
    by_symmetry: bool = False


def random_motion(
    rng: np.random.Generator, distance: float, angle: float, center: FloatArray
) -> FloatArray:
    """Return a random rigid motion of a given size.

    It translates by ``distance`` metres and turns by ``angle`` radians about ``center``,
    both in directions uniform on the sphere.
    """
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    a = rng.normal(size=3)
    a /= np.linalg.norm(a)
    X = np.eye(4)
    X[:3, :3] = matrix_from_axis_angle(a, angle)
    X[:3, 3] = center - X[:3, :3] @ center + distance * u
    return X


def _key(elements: Any) -> frozenset[tuple[str, Any, Any]]:
    return frozenset(
        (getattr(e.kind, "value", e.kind), tuple(e.grasped), tuple(e.environment)) for e in elements
    )


_CACHE: dict[tuple[str, str], Any] = {}
"""Symmetries and convex pieces of the models replayed in this process, by content."""


def _cached(kind: str, poly: Polyhedron, make: Any) -> Any:
    """``make(poly)``, remembered by the model's content (many replays of one task)."""
    import hashlib

    h = hashlib.sha1(np.ascontiguousarray(poly.vertices).tobytes())
    for t in poly.face_triangles:
        h.update(np.ascontiguousarray(t).tobytes())
    key = (kind, h.hexdigest())
    if key not in _CACHE:
        if len(_CACHE) > 32:
            _CACHE.clear()
        _CACHE[key] = make(poly)
    return _CACHE[key]


def model_symmetries(poly: Polyhedron) -> list[Any]:
    """Rigid symmetries of a model (:func:`apo.symmetry.symmetries`, identity first)."""
    from apo.symmetry import symmetries

    return list(
        _cached(
            "symmetries", poly, lambda p: symmetries(p.vertices, np.concatenate(p.face_triangles))
        )
    )


def state_ids(
    finder: Any,
    task: TaskModel,
    symmetries: tuple[Sequence[Any], Sequence[Any]] | None = None,
) -> dict[frozenset[tuple[str, Any, Any]], str]:
    """Element sets of the task's states, by the ids of ``finder``'s models.

    Each state is known by its elements as recorded in the task and as ``finder`` finds them
    at the state's pose: the models loaded for the replay may number their features
    differently from the ones the task was analysed with (a model file re-triangulated or
    re-ordered); the second key is the honest mapping then. With ``symmetries`` (those of
    the grasped object and of the environment, :func:`model_symmetries`), a state is also
    known by the elements at each of its symmetric twins ``S_E^-1 X_EG S_G``: the same
    contacts with other, symmetric, features (a T-peg turned half a turn about its stem
    touches the other face of the slot with its other face). The exact keys come first: a
    twin never takes the key of another state.
    """
    out: dict[frozenset[tuple[str, Any, Any]], str] = {}
    found = finder.find_batch(np.stack([s.X_EG for s in task.states]))
    for s, f in zip(task.states, found, strict=True):
        out.setdefault(_key(f.elements), s.id)
    for s in task.states:
        out.setdefault(_key(s.elements), s.id)
    if symmetries is None:
        return out
    S_G = np.stack([y.S for y in symmetries[0]] or [np.eye(4)])
    S_E_inv = np.linalg.inv(np.stack([y.S for y in symmetries[1]] or [np.eye(4)]))
    twins = np.einsum("aij,sjk,bkl->sabil", S_E_inv, np.stack([s.X_EG for s in task.states]), S_G)
    shape = twins.shape
    found = finder.find_batch(twins.reshape(-1, 4, 4))
    for k, f in enumerate(found):
        out.setdefault(_key(f.elements), task.states[k // (shape[1] * shape[2])].id)
    return out


def _visits(
    finder: Any, ids: dict[frozenset[Any], str], times: FloatArray, X: FloatArray
) -> tuple[list[Visit], frozenset[Any]]:
    states = finder.find_batch(X)
    visits: list[Visit] = []
    last_key: frozenset[Any] | None = None
    for t, s in zip(times, states, strict=True):
        key = _key(s.elements)
        if visits and key == last_key:
            v = visits[-1]
            visits[-1] = Visit(v.state, v.t_start, float(t), v.n_elements)
        else:
            visits.append(Visit(ids.get(key), float(t), float(t), len(s.elements)))
            last_key = key
    assert last_key is not None
    return visits, last_key


def _reached(visits: Sequence[Visit]) -> list[str]:
    out: list[str] = []
    for v in visits:
        if v.state is not None and (not out or out[-1] != v.state):
            out.append(v.state)
    return out


@dataclass(frozen=True)
class Judgement:
    """Apo's contact analysis of executed poses (:func:`judge`).

    Attributes
    ----------
    success : bool
        The final contact state is the task's final state (up to the models' symmetries).
    final_state : str or None
        Id of the task state the final contact state is (None: none of them).
    by_symmetry : bool
        The final state matched only through a symmetric twin of the task's state.
    visits : list of Visit
    states_reached : list of str
    n_final_elements : int
    threshold : float
        Contact distance threshold used, metres.
    """

    success: bool
    final_state: str | None
    by_symmetry: bool
    visits: list[Visit]
    states_reached: list[str]
    n_final_elements: int
    threshold: float


def judge(
    task: TaskModel,
    grasped: Polyhedron,
    environment: Polyhedron,
    times: FloatArray,
    X_EG: FloatArray,
    *,
    clearance: float = DEFAULT_CLEARANCE,
    symmetric: bool = True,
) -> Judgement:
    """Judge executed poses by apo's own contact analysis (``docs/sim.md``, Verdict).

    Parameters
    ----------
    task : TaskModel
    grasped, environment : Polyhedron
        The models the poses refer to (metres).
    times : ndarray, shape (K,)
        Seconds.
    X_EG : ndarray, shape (K, 4, 4)
        Poses of the grasped object in the environment's frame, metres.
    clearance : float
        Metres per side of the simulated parts: the contact threshold is
        ``max(task threshold, 3 x clearance, scale-aware default)`` (the default of
        recognition, ``apo.contact.default_threshold(observed=True)``).
    symmetric : bool
        Compare contact states up to the models' symmetries (default).
    """
    from apo.contact import ContactFinder, default_threshold

    # the executed poses deviate from the plan by the hand's compliance, not by the vision
    # noise the task's threshold follows (a clean demonstration gives a small one)
    floor = default_threshold(grasped, environment, observed=True)
    threshold = max(task.threshold, 3.0 * clearance, floor)
    finder = ContactFinder(grasped, environment, threshold=threshold)
    exact = state_ids(finder, task)
    syms = (model_symmetries(grasped), model_symmetries(environment)) if symmetric else None
    ids = state_ids(finder, task, syms) if symmetric else exact
    visits, final_key = _visits(finder, ids, times, X_EG)
    final_id = ids.get(final_key)
    return Judgement(
        success=final_id == task.states[-1].id,
        final_state=final_id,
        by_symmetry=final_id is not None and final_key not in exact,
        visits=visits,
        states_reached=_reached(visits),
        n_final_elements=len(final_key),
        threshold=threshold,
    )


def _start(
    task: TaskModel,
    grasped: Polyhedron,
    environment: Polyhedron,
    perturb: tuple[float, float],
    environment_offset: tuple[float, float],
    seed: int,
) -> tuple[FloatArray, FloatArray]:
    """Return the perturbed start pose ``X_WG0`` and the environment's pose ``X_WE``."""
    rng = np.random.default_rng(seed)
    lo, hi = environment.vertices.min(axis=0), environment.vertices.max(axis=0)
    X_start0 = task.states[0].X_EG
    centroid = X_start0[:3, :3] @ grasped.vertices.mean(0) + X_start0[:3, 3]
    X_pert = random_motion(rng, perturb[0], perturb[1], centroid)
    X_WE = random_motion(rng, environment_offset[0], environment_offset[1], 0.5 * (lo + hi))
    return X_pert @ X_start0, X_WE


class _Recorder:
    """Samples the hand's pose (environment frame) every :data:`SAMPLE_PERIOD` seconds."""

    def __init__(self, scene: Any, video: Any = None) -> None:
        self.X_EW = np.linalg.inv(scene.X_WE)
        self.every = max(1, round(SAMPLE_PERIOD / scene.params.timestep))
        self.scene, self.video = scene, video
        self.count = 0
        self.t: list[float] = []
        self.X: list[FloatArray] = []

    def __call__(self, hand: Hand) -> None:
        self.count += 1
        if self.count % self.every == 0:
            self.t.append(hand.time)
            self.X.append(self.X_EW @ hand.pose())
            if self.video is not None:
                self.video.capture(self.scene)

    def finish(self, hand: Hand) -> tuple[FloatArray, FloatArray]:
        """Add the last pose if not sampled; return the times and poses."""
        if not self.t or hand.time > self.t[-1]:
            self.t.append(hand.time)
            self.X.append(self.X_EW @ hand.pose())
        return np.asarray(self.t), np.stack(self.X)


def _execute(
    hand: Hand,
    task: TaskModel,
    program: Any,
    playback: bool,
    frames: tuple[FloatArray, FloatArray] | None,
    sample: Any,
    pace: str = "plan",
) -> tuple[list[PrimitiveRun], str]:
    """Run the skill program (default: ``apo.motion.plan(task)``) or the playback."""
    if playback:
        times, poses = frames if frames is not None else _state_poses(task)
        if pace == "plan":
            times = np.zeros(len(poses))  # no waiting: every move at the plan's speeds
        return run_playback(hand, times, poses, hand.scene.com_G, sample), "playback"
    if program is None:
        from apo.motion import plan

        program = plan(task)
    return run_program(hand, program, sample), "skills"


def _verdict(j: Judgement, goal: str, runs: Sequence[PrimitiveRun]) -> str:
    failed = [r for r in runs if not r.ok]
    why = (
        ""
        if not failed
        else f"; primitive {failed[0].index} ({failed[0].kind}) {failed[0].outcome}"
    )
    twin = " (a symmetric twin)" if j.by_symmetry else ""
    return (
        f"{'SUCCESS' if j.success else 'FAILURE'}: final contact state "
        f"{j.final_state or 'not in the task'}{twin} ({j.n_final_elements} elements), "
        f"task's final state {goal}{why}"
    )


def replay(
    task: TaskModel,
    grasped: Polyhedron,
    environment: Polyhedron,
    *,
    perturb: tuple[float, float] = (0.0, 0.0),
    environment_offset: tuple[float, float] = (0.0, 0.0),
    clearance: float = DEFAULT_CLEARANCE,
    seed: int = 0,
    playback: bool = False,
    program: Any = None,
    decompositions: dict[str, Decomposition] | None = None,
    params: ContactParameters | None = None,
    gains: Gains | None = None,
    frames: tuple[FloatArray, FloatArray] | None = None,
    video: Any = None,
    symmetric: bool = True,
) -> ReplayResult:
    """Execute a task model in MuJoCo and judge the result.

    Parameters
    ----------
    task : TaskModel
        The recognised task (SI, environment frame).
    grasped, environment : Polyhedron
        Its models (metres), the ones its feature ids refer to.
    perturb : (float, float)
        Size of the random rigid motion of the start pose: metres, radians.
    environment_offset : (float, float)
        Size of the random rigid motion of the environment the plan does not know: metres,
        radians (about the centre of the environment's bounding box).
    clearance : float
        Metres per side (:func:`apo.sim.scene.build_scene`).
    seed : int
        Seed of the two random motions.
    playback : bool
        Follow the observed poses (``frames`` if given, else the states' poses at their
        times) by position control instead of executing the skill program.
    program : apo.motion.SkillProgram, optional
        The program to execute (default: ``apo.motion.plan(task)``).
    decompositions : dict, optional
        Precomputed convex pieces ``{"grasped", "environment"}`` (speeds up many replays).
    params, gains : optional
        Contact parameters and hand gains (defaults documented in ``docs/sim.md``).
    frames : (times, X_EG), optional
        Observed per-frame poses for the playback (seconds, (N, 4, 4) metres).
    video : apo.sim.video.Recorder, optional
        Receives the scene at every recorded sample.
    symmetric : bool
        Judge contact states up to the models' symmetries (:func:`judge`).

    Returns
    -------
    ReplayResult
    """
    dec = decompositions or {
        "grasped": _cached("pieces", grasped, convex_pieces),
        "environment": _cached("pieces", environment, convex_pieces),
    }
    X_WG0, X_WE = _start(task, grasped, environment, perturb, environment_offset, seed)
    scene = build_scene(
        grasped, environment, X_WG=X_WG0, X_WE=X_WE, clearance=clearance, params=params,
        decompositions=dec,
    )  # fmt: skip
    hand = Hand(scene, gains)
    rec = _Recorder(scene, video)
    wall = time.perf_counter()
    runs, mode = _execute(hand, task, program, playback, frames, rec)
    wall = time.perf_counter() - wall
    T, X = rec.finish(hand)
    j = judge(task, grasped, environment, T, X, clearance=clearance, symmetric=symmetric)
    return ReplayResult(
        success=j.success, mode=mode, final_X_EG=X[-1], final_state=j.final_state,
        states_reached=j.states_reached, visits=j.visits,
        task_states=[s.id for s in task.states], max_force=hand.max_force,
        max_penetration=hand.max_penetration, primitives=runs, sim_time=hand.time,
        wall_time=wall, times=T, X_EG=X, verdict=_verdict(j, task.states[-1].id, runs),
        by_symmetry=j.by_symmetry,
        settings={
            "perturb": [perturb[0], perturb[1]],
            "environment_offset": [environment_offset[0], environment_offset[1]],
            "X_WE": X_WE, "clearance": clearance, "seed": seed, "threshold": j.threshold,
            "contact": scene.params, "gains": hand.gains, "symmetric": symmetric,
            "pieces": {k: (v.method, len(v.pieces), v.tolerance) for k, v in dec.items()},
        },
    )  # fmt: skip


def _state_poses(task: TaskModel) -> tuple[FloatArray, FloatArray]:
    """Return the times and poses of the task's states (first and last frame of each)."""
    t: list[float] = []
    X: list[FloatArray] = []
    for s in task.states:
        for ti in dict.fromkeys(s.times):
            if not t or ti > t[-1] + 1e-9:
                t.append(float(ti))
                X.append(s.X_EG)
    return np.asarray(t), np.stack(X)


def degrees(x: float) -> float:
    """Radians from degrees (for callers reading ``MM,DEG`` options)."""
    return math.radians(x)
