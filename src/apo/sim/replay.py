"""Replay a task model in MuJoCo: plan, execute with the compliant hand, judge by contacts.

:func:`replay` is what ``apo replay`` runs (``docs/sim.md``): it builds the scene from the
task's two models, perturbs the start pose of the grasped object and moves the environment
by an offset the plan does not know, executes the skill program of :func:`apo.motion.plan`
(or, with ``playback=True``, follows the observed poses by position control), and judges
the outcome with apo's own contact analysis: :class:`apo.contact.ContactFinder` on the
simulated pose of the grasped object in the (moved) environment's frame.

Success means the final contact state has the same elements as the task's final state
(kind, grasped feature, environment feature), compared exactly by feature ids (both come
from the same model files). The states visited are the task states whose element sets the
simulated poses match, in order.
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

__all__ = ["SAMPLE_PERIOD", "ReplayResult", "Visit", "random_motion", "replay"]

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


def state_ids(finder: Any, task: TaskModel) -> dict[frozenset[tuple[str, Any, Any]], str]:
    """Element sets of the task's states, by the ids of ``finder``'s models.

    Each state is known by its elements as recorded in the task and as ``finder`` finds them
    at the state's pose: the models loaded for the replay may number their features
    differently from the ones the task was analysed with (a model file re-triangulated or
    re-ordered); the second key is the honest mapping then.
    """
    out: dict[frozenset[tuple[str, Any, Any]], str] = {}
    found = finder.find_batch(np.stack([s.X_EG for s in task.states]))
    for s, f in zip(task.states, found, strict=True):
        out.setdefault(_key(f.elements), s.id)
    for s in task.states:
        out.setdefault(_key(s.elements), s.id)
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

    Returns
    -------
    ReplayResult
    """
    from apo.contact import ContactFinder

    rng = np.random.default_rng(seed)
    dec = decompositions or {
        "grasped": convex_pieces(grasped),
        "environment": convex_pieces(environment),
    }
    lo, hi = environment.vertices.min(axis=0), environment.vertices.max(axis=0)
    X_start0 = task.states[0].X_EG
    X_pert = random_motion(rng, perturb[0], perturb[1], X_start0[:3, :3] @ grasped.vertices.mean(0)
                           + X_start0[:3, 3])  # fmt: skip
    X_WE = random_motion(rng, environment_offset[0], environment_offset[1], 0.5 * (lo + hi))
    X_WG0 = X_pert @ X_start0
    scene = build_scene(
        grasped, environment, X_WG=X_WG0, X_WE=X_WE, clearance=clearance, params=params,
        decompositions=dec,
    )  # fmt: skip
    hand = Hand(scene, gains)
    X_EW = np.linalg.inv(X_WE)
    rec_t: list[float] = []
    rec_X: list[FloatArray] = []
    every = max(1, round(SAMPLE_PERIOD / scene.params.timestep))
    counter = [0]

    def sample(h: Hand) -> None:
        counter[0] += 1
        if counter[0] % every == 0:
            rec_t.append(h.time)
            rec_X.append(X_EW @ h.pose())
            if video is not None:
                video.capture(scene)

    wall = time.perf_counter()
    if playback:
        times, poses = frames if frames is not None else _state_poses(task)
        runs = run_playback(hand, times, poses, scene.com_G, sample)
        mode = "playback"
    else:
        if program is None:
            from apo.motion import plan

            program = plan(task)
        runs = run_program(hand, program, sample)
        mode = "skills"
    wall = time.perf_counter() - wall
    if not rec_t or hand.time > rec_t[-1]:
        rec_t.append(hand.time)
        rec_X.append(X_EW @ hand.pose())
    T, X = np.asarray(rec_t), np.stack(rec_X)
    threshold = max(task.threshold, 3.0 * clearance)
    finder = ContactFinder(grasped, environment, threshold=threshold)
    ids = state_ids(finder, task)
    visits, final_key = _visits(finder, ids, T, X)
    final_id = ids.get(final_key)
    goal = task.states[-1].id
    success = final_id == goal
    failed = [r for r in runs if not r.ok]
    why = (
        ""
        if not failed
        else f"; primitive {failed[0].index} ({failed[0].kind}) {failed[0].outcome}"
    )
    verdict = (
        f"{'SUCCESS' if success else 'FAILURE'}: final contact state "
        f"{final_id or 'not in the task'} ({len(final_key)} elements), task's final state {goal}"
        f"{why}"
    )
    return ReplayResult(
        success=success,
        mode=mode,
        final_X_EG=X[-1],
        final_state=final_id,
        states_reached=_reached(visits),
        visits=visits,
        task_states=[s.id for s in task.states],
        max_force=hand.max_force,
        max_penetration=hand.max_penetration,
        primitives=runs,
        sim_time=hand.time,
        wall_time=wall,
        times=T,
        X_EG=X,
        verdict=verdict,
        settings={
            "perturb": [perturb[0], perturb[1]],
            "environment_offset": [environment_offset[0], environment_offset[1]],
            "X_WE": X_WE,
            "clearance": clearance,
            "seed": seed,
            "threshold": threshold,
            "contact": scene.params,
            "gains": hand.gains,
            "pieces": {k: (v.method, len(v.pieces), v.tolerance) for k, v in dec.items()},
        },
    )


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
