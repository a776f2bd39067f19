"""The recognition pipeline: poses -> contact states -> task model (paper section 4.3).

:func:`recognize_frames` runs the stages of ``docs/recognition.md`` in order:

1. contacts per frame (:mod:`apo.recognition.contacts`);
2. the cost of every observed state at every frame (:mod:`apo.recognition.costs`);
3. a first segmentation without the direct-transition test shortlists the states worth
   analysing (:func:`apo.recognition.decoding.viterbi_uniform`);
4. each needed state is analysed once, with the direct-transition tests and bridging
   states (:mod:`apo.recognition.analysis`);
5. segmentation with repair: a Viterbi pass over feasible sequences only
   (:func:`apo.recognition.decoding.constrained_path`);
6. every frame's pose corrected under its chosen state (:mod:`apo.recognition.correction`);
7. the task: states, transitions, rejected runs (:mod:`apo.recognition.build`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from typing import TypeVar

import numpy as np
import numpy.typing as npt

from apo.contact import ContactElement, ContactFinder
from apo.errors import InputFormatError
from apo.geometry import Polyhedron
from apo.recognition.analysis import Analysis, analyse_needed
from apo.recognition.build import build_states, build_transitions, rejected_runs, state_runs
from apo.recognition.contacts import Observations, observe
from apo.recognition.correction import Corrected, correct_by_label
from apo.recognition.distances import StreamedDistances
from apo.recognition.inputs import check_scale, check_sequence, default_threshold
from apo.recognition.noise import (
    CONTACT_NOISE_RATIO,
    NOISE_THRESHOLD_FACTOR,
    NoiseEstimate,
    contact_noise,
    distance_sigma,
    estimate_noise,
    outlier_frames,
)
from apo.recognition.segmentation import Segmentation, first_pass, segment
from apo.recognition.types import (
    BoolArray,
    FloatArray,
    IntArray,
    Progress,
    Recognition,
    Scene,
    SegmentationCosts,
)
from apo.task import UNITS, ModelRef, Rejected, TaskModel, state_spans

__all__ = ["recognize", "recognize_frames"]

T = TypeVar("T")


def recognize(
    grasped: Polyhedron,
    environment: Polyhedron,
    times: npt.ArrayLike | None,
    X_EG_seq: npt.ArrayLike,
    *,
    threshold: float | None = None,
    progress: Progress | None = None,
    units: str = "mm",
    models: tuple[ModelRef, ModelRef] | None = None,
    source: str = "",
    costs: SegmentationCosts | None = None,
    memoize: bool = False,
    noise: tuple[float, float] | None = None,
    floor_share: float | None = None,
    jobs: int | None = None,
) -> TaskModel:
    """Recognise a demonstration into a :class:`~apo.task.TaskModel`.

    Parameters
    ----------
    grasped, environment : Polyhedron
        Models G (moving) and E (fixed), metres, own frames.
    times : array_like, shape (N,), or None
        Time stamps, seconds (None: frame indices).
    X_EG_seq : array_like, shape (N, 4, 4)
        Observed poses of G in E, metres.
    threshold : float, optional
        Contact distance threshold, metres; default: the larger of
        :func:`default_threshold` (scale-aware) and ``NOISE_THRESHOLD_FACTOR`` standard
        deviations of a vertex distance under the pose noise.
    progress : callable, optional
        Called as ``progress(done, total)`` while contacts are found.
    units : str
        Length unit of the task's JSON form.
    models : (ModelRef, ModelRef), optional
        Model files to record; default: the model names without a hash.
    source : str
        Name of the demonstration (e.g. its file name).
    costs : SegmentationCosts, optional
        Weights of the segmentation (``docs/recognition.md``).
    memoize : bool
        Run the contact finder once per set of near feature pairs (:func:`near_signatures`)
        instead of at every frame. Off by default: the finder's batched search over all
        frames (:meth:`apo.contact.ContactFinder.find_batch`) is now the faster of the two.

    noise : (float, float), optional
        Pose noise per axis: position (metres) and rotation (radians) standard deviations;
        default: estimated from the poses (:func:`apo.recognition.noise.estimate_noise`).
    floor_share : float, optional
        Least threshold, as a share of :func:`default_threshold`, when the threshold follows
        the noise; default ``NOISE_FLOOR_SHARE`` (pose files), ``TRACKED_FLOOR_SHARE`` for poses
        tracked from depth frames (their smooth bias does not show in the noise estimate).
    jobs : int, optional
        Processes the contact search and the correction of the distinct frames are split
        over (forked for those stages, :mod:`apo.workers`); default: auto (the
        available cores, on long demonstrations only); 1: one process. The result is the
        same bit for bit whatever ``jobs``.

    Returns
    -------
    TaskModel

    Raises
    ------
    InputFormatError
        Empty sequence, wrong shapes, NaN or non-rigid poses (the frame is named).

    See Also
    --------
    recognize_frames : the same, with per-frame diagnostics.
    """
    return recognize_frames(
        grasped,
        environment,
        times,
        X_EG_seq,
        threshold=threshold,
        progress=progress,
        units=units,
        models=models,
        source=source,
        costs=costs,
        memoize=memoize,
        noise=noise,
        floor_share=floor_share,
        jobs=jobs,
        keep_costs=False,
    ).task


def recognize_frames(
    grasped: Polyhedron,
    environment: Polyhedron,
    times: npt.ArrayLike | None,
    X_EG_seq: npt.ArrayLike,
    *,
    threshold: float | None = None,
    progress: Progress | None = None,
    units: str = "mm",
    models: tuple[ModelRef, ModelRef] | None = None,
    source: str = "",
    costs: SegmentationCosts | None = None,
    memoize: bool = False,
    noise: tuple[float, float] | None = None,
    floor_share: float | None = None,
    jobs: int | None = None,
    keep_costs: bool = True,
) -> Recognition:
    """Recognise a demonstration; return the task model and per-frame diagnostics.

    Parameters are those of :func:`recognize`, and ``keep_costs``: False leaves
    ``Recognition.costs`` and ``cost_columns`` empty, shapes (N, 0) and (0,) (what
    ``apo analyze`` does: no output reads them), and frees them before the correction
    (8 bytes a frame per analysed candidate; ``docs/recognition.md``, "Session 8: memory").

    Returns
    -------
    Recognition
    """
    name = source or "demonstration"
    t, X = check_sequence(times, X_EG_seq, source=name)  # type: ignore[arg-type]
    check_scale(grasped, environment, X, name)
    est = pose_noise(grasped, X, noise)
    once = partial(
        _recognise_once, grasped, environment, t, X, costs=costs or SegmentationCosts(),
        memoize=memoize, progress=progress, units=units, models=models, source=source,
        floor_share=floor_share, jobs=jobs, keep_costs=keep_costs,
    )  # fmt: skip
    rec = once(threshold, est)
    if threshold is not None or noise is not None:
        return rec
    # A drift hides from the second differences, not from the contacts (docs/recognition.md)
    for _ in range(CONTACT_PASSES):
        t0 = time.perf_counter()
        sc = contact_noise(grasped, environment, X, _chosen_elements(rec))
        est = replace(est, contact=sc)
        if not (
            sc > CONTACT_NOISE_RATIO * est.distance
            and NOISE_THRESHOLD_FACTOR * sc > 1.05 * rec.task.threshold
        ):
            break
        est = replace(est, distance=sc)
        tm = dict(rec.timings)
        rec = once(None, est)
        rec.timings["noise"] = time.perf_counter() - t0
        for k, v in tm.items():
            rec.timings[k] = rec.timings.get(k, 0.0) + v
    task = replace(rec.task, extra={**rec.task.extra, "noise": noise_record(est, units)})
    return replace(rec, task=task, noise=est)


#: With a noise level (estimated or given), the threshold is ``NOISE_THRESHOLD_FACTOR``
#: deviations of a contact distance, but at least this share of :func:`default_threshold`
#: (which stays the threshold when no noise is known). A quarter: on clean poses a real gap
#: of a few millimetres is not a contact (docs/recognition.md, "Threshold").
NOISE_FLOOR_SHARE = 0.25

#: The floor for poses tracked from depth frames (``apo analyze FRAMES``, ``apo demo
#: --from-frames``): the whole default. ICP's error on a far camera is a smooth bias of
#: 1-1.5 mm that moves with the view, not frame-to-frame jitter, so the noise estimate
#: (second differences, contact residuals) sees 0.04-0.3 mm of it and a threshold at a
#: quarter of the default misses real contacts (docs/recognition.md, "Threshold").
TRACKED_FLOOR_SHARE = 1.0

#: Passes of recognition again with the contact residuals' noise (drift), at most.
CONTACT_PASSES = 2


def _chosen_elements(rec: Recognition) -> list[tuple[ContactElement, ...]]:
    """Contact elements of the candidate chosen at each frame (none at outlier frames).

    Where fewer than 10 frames are in contact (the contacts of the demonstration were
    mostly not seen: a drift holding G off the surface), the elements observed at each
    frame instead, noise included: they are what the poses say of the contacts.
    """
    out: list[tuple[ContactElement, ...]] = []
    for c, bad in zip(rec.assigned.tolist(), rec.outliers.tolist(), strict=True):
        cand = rec.candidates[c]
        out.append(() if bad or cand is None else tuple(cand.state.elements))
    if sum(1 for e in out if e) < 10 and rec.observed_states:
        seen = [rec.observed_states[int(k)].elements for k in rec.observed]
        out = [() if bad else tuple(e) for e, bad in zip(seen, rec.outliers.tolist(), strict=True)]
    return out


def _recognise_once(
    grasped: Polyhedron,
    environment: Polyhedron,
    t: FloatArray,
    X: FloatArray,
    threshold: float | None,
    est: NoiseEstimate,
    *,
    costs: SegmentationCosts,
    memoize: bool,
    progress: Progress | None,
    units: str,
    models: tuple[ModelRef, ModelRef] | None,
    source: str,
    floor_share: float | None = None,
    jobs: int | None = None,
    keep_costs: bool = True,
) -> Recognition:
    """One pass of the stages at one threshold and noise level."""
    tm: dict[str, float] = {}
    t0 = time.perf_counter()
    scene = make_scene(grasped, environment, X, threshold, costs, est, floor_share)
    observed = observe(scene, memoize=memoize, progress=progress, jobs=jobs)
    tm["contacts"] = time.perf_counter() - t0
    dists = StreamedDistances(grasped, environment, X, scene.unit, jobs=jobs)
    path0, own, seen = _timed(tm, "segmentation", first_pass, scene, observed, dists)
    an = _timed(tm, "analysis", analyse_needed, scene, observed, own, path0)
    seg = _timed(tm, "segmentation", segment, scene, an, dists, observed, seen)
    del dists, seen, path0, own  # the first pass's results: not needed any more
    path, obs_c = seg.path, seg.observed
    # the rejected runs read the costs: made now, the costs can go before the correction
    named = _timed(tm, "task", rejected_of, scene, an, seg)
    if not keep_costs:
        seg.costs, seg.columns = np.zeros((scene.n, 0)), np.zeros(0, dtype=np.int64)
    chosen = an.states(observed)
    corrected = _timed(
        tm, "correction", partial(correct_by_label, jobs=jobs), grasped, environment, X,
        chosen, path, scene.unit,
    )  # fmt: skip
    t4 = time.perf_counter()
    task = build_task(
        scene, t, path, obs_c, corrected, an, named, units=units, models=models, source=source
    )
    tm["task"] = tm["task"] + time.perf_counter() - t4
    tm["total"] = time.perf_counter() - t0
    task = replace(task, extra={**task.extra, "noise": noise_record(est, units)})
    rec = _result(task, observed, an, seg, corrected, t, X, tm)
    return replace(rec, noise=est, outliers=scene.outliers, observed_states=observed.states)


def pose_noise(
    grasped: Polyhedron, X: FloatArray, noise: tuple[float, float] | None
) -> NoiseEstimate:
    """Return the pose noise: given ``(position m, rotation rad)`` per axis, else estimated."""
    if noise is None:
        return estimate_noise(grasped, X)
    sp, sr = (float(v) for v in noise)
    if not (math.isfinite(sp) and math.isfinite(sr) and sp >= 0 and sr >= 0):
        raise InputFormatError(f"noise must be two non-negative numbers, got {noise}")
    return NoiseEstimate(sp, sr, distance_sigma(grasped, sp, sr), "given")


def noise_record(noise: NoiseEstimate, units: str) -> dict[str, object]:
    """Return the noise as written in ``task.json``'s ``extra.noise`` (lengths in ``units``)."""
    k = 1.0 / UNITS.get(units, 1.0)
    return {
        "position": round(noise.position * k, 6),
        "rotation_deg": round(math.degrees(noise.rotation), 6),
        "distance": round(noise.distance * k, 6),
        "contact": round(noise.contact * k, 6),
        "source": noise.source,
    }


def _timed(tm: dict[str, float], stage: str, f: Callable[..., T], *args: object) -> T:
    """Call ``f(*args)``, adding its wall time to ``tm[stage]``."""
    t0 = time.perf_counter()
    out = f(*args)
    tm[stage] = tm.get(stage, 0.0) + time.perf_counter() - t0
    return out


def make_scene(
    grasped: Polyhedron,
    environment: Polyhedron,
    X: FloatArray,
    threshold: float | None,
    costs: SegmentationCosts,
    noise: NoiseEstimate | None = None,
    floor_share: float | None = None,
) -> Scene:
    """Make the scene of a recognition: models, poses, the two contact finders, the costs.

    The threshold, when not given, is the larger of ``floor_share`` (default
    ``NOISE_FLOOR_SHARE``) times :func:`default_threshold` and ``NOISE_THRESHOLD_FACTOR``
    standard deviations of a vertex distance under ``noise``; without ``noise``, the default.
    Outlier frames (:func:`~apo.recognition.noise.outlier_frames`) are marked. At
    corrected poses contacts hold exactly: the contact finder's own (tight) default
    threshold tells which feature pairs really touch there.
    """
    base = default_threshold(grasped, environment)
    scale = 0.0
    if threshold is None:
        sd = 0.0 if noise is None else noise.distance
        share = NOISE_FLOOR_SHARE if floor_share is None else floor_share
        floor = base if noise is None else share * base
        threshold = max(floor, NOISE_THRESHOLD_FACTOR * sd)
        scale = max(base, threshold)
    finder = ContactFinder(grasped, environment, threshold=threshold)
    exact = ContactFinder(grasped, environment)
    out = (
        np.zeros(len(X), dtype=bool)
        if noise is None
        else outlier_frames(grasped, X, noise, floor=base)
    )
    return Scene(grasped, environment, X, finder, exact, costs, out, scale)


#: The runs ``(first, last)`` of the chosen path, their ids, the rejected runs.
Named = tuple[list[tuple[int, int]], list[str], list[Rejected]]


def rejected_of(scene: Scene, an: Analysis, seg: Segmentation) -> Named:
    """Return the runs of the chosen path, their ids and the observed runs it replaced.

    Made from the segmentation alone, before the correction: the costs that the rejected
    runs' reasons read (``seg.costs``) can then be freed before the correction's per-frame
    arrays are made; :func:`build_task` names the states with the same runs and ids.
    """
    runs, ids = state_runs(seg.path)
    keys, cands = an.keys, an.candidates
    rejected = rejected_runs(seg.observed, seg.path, runs, ids, keys, cands, an.feasible, seg,
                             scene.costs)  # fmt: skip
    return runs, ids, rejected


def build_task(
    scene: Scene,
    times: FloatArray,
    path: IntArray,
    obs_c: IntArray,
    corrected: Corrected,
    an: Analysis,
    named: Named,
    *,
    units: str,
    models: tuple[ModelRef, ModelRef] | None,
    source: str,
) -> TaskModel:
    """Build the task model: states and transitions of the chosen path, rejected runs.

    ``named`` (:func:`rejected_of`): the path's runs, their ids and the rejected runs.
    """
    runs, ids, rejected = named
    runs, ids, states = build_states(times, path, obs_c, corrected, an.candidates, (runs, ids))
    transitions = build_transitions(runs, ids, path, an.candidates, an.feasible)
    G, E = scene.grasped, scene.environment
    g_ref, e_ref = models or (ModelRef(G.name, None, G.name), ModelRef(E.name, None, E.name))
    return TaskModel(
        units=units,
        grasped=g_ref,
        environment=e_ref,
        states=states,
        transitions=transitions,
        rejected=tuple(rejected),
        n_frames=scene.n,
        source=source,
        threshold=scene.theta,
    )


def _result(
    task: TaskModel,
    observed: Observations,
    an: Analysis,
    seg: Segmentation,
    corrected: Corrected,
    times: FloatArray,
    X: FloatArray,
    tm: dict[str, float],
) -> Recognition:
    """Gather the per-frame diagnostics."""
    path, obs_c = seg.path, seg.observed
    Xc, res_before, res_after, conv = corrected
    state_of_frame = [s for s, a, b in state_spans(task.states) for _ in range(a, b + 1)]
    return Recognition(
        task=task,
        state_of_frame=state_of_frame,
        observed=observed.labels,
        assigned=path,
        residual_before=res_before,
        residual_after=res_after,
        converged=conv,
        repaired=obs_c != path,
        candidates=an.candidates,
        keys=an.keys,
        feasible=an.feasible,
        times=times,
        costs=seg.costs,
        cost_columns=seg.columns,
        timings=tm,
        X_observed=X,
        X_corrected=_observed_where_failed(Xc, X, conv),
    )


def _observed_where_failed(Xc: FloatArray, X: FloatArray, conv: BoolArray) -> FloatArray:
    """Return the corrected poses, observed where the correction failed (``Xc`` updated).

    In place: the corrections that failed are used nowhere else, and a second per-frame
    array of poses is not made.
    """
    failed = np.flatnonzero(~conv)
    Xc[failed] = X[failed]
    return Xc
