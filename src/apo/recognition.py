"""Recognition of a demonstration: poses -> contact states -> task model (paper section 4.3).

The pipeline of :func:`recognize` (``docs/recognition.md`` has the details and the cost
model):

1. contact elements at every frame (``apo.contact.ContactFinder``, run once per distinct
   set of near feature pairs, :func:`near_signatures`);
2. the distinct observed contact states are the candidate states; their cost at every
   frame (correction residual of the claimed contacts, evidence of observed contacts left
   out) needs only feature distances (:func:`element_distances`);
3. a first segmentation without the direct-transition test shortlists the states worth
   analysing; the rest is noise, recorded as rejected;
4. each shortlisted state is analysed once: representative pose by pose correction
   (:func:`correct_poses`, paper 4.3.1), DOF there (``apo.dof``), the direct-transition test
   between pairs (``apo.transitions``), and bridging states where two consecutive states
   cannot follow each other directly;
5. segmentation with repair: a Viterbi pass over feasible sequences only;
6. every frame's pose corrected under its chosen state (residuals before and after,
   converged flag);
7. runs of frames with the same state become the task's states (letters A, B, ...) with a
   representative pose from a converged frame, and the transitions between them carry their
   DOF transitions, sub-skills and critical marks.

Everything is in metres, in the environment frame; poses ``X_EG`` are 4x4 matrices of the
grasped object G in the environment frame E.
"""

from __future__ import annotations

import enum
import importlib
import itertools
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from apo.contact import ContactElement, ContactState
from apo.errors import InputFormatError
from apo.geometry import (
    Polyhedron,
    closest_point_on_segment,
    point_face_distance,
    segment_segment_closest,
)
from apo.task import (
    Element,
    ModelRef,
    Rejected,
    State,
    SubSkill,
    TaskModel,
    Transition,
    state_letters,
)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]
StateKey = frozenset[tuple[str, tuple[str, int], tuple[str, int]]]
Progress = Callable[[int, int], None]
Six = tuple[int, int, int, int, int, int]

__all__ = [
    "THRESHOLD_FRACTION",
    "CandidateState",
    "Recognition",
    "SegmentationCosts",
    "check_sequence",
    "correct_poses",
    "default_threshold",
    "element_distances",
    "near_signatures",
    "recognize",
    "recognize_frames",
    "viterbi",
    "viterbi_uniform",
]

#: Frames per batch handed to the contact finder (and per progress update).
_CHUNK = 512

THRESHOLD_FRACTION = 0.035
"""Default contact threshold of recognition, as a fraction of the smaller model's ``scale``.

Observed poses carry vision noise of millimetres; the contact finder's own default (a
fraction of a millimetre for a 10 cm part) suits exact poses, not observations. 3.5 % of the
bounding diagonal is 4.1 mm for the first author's 118 mm peg, the order of the paper's
threshold for its stereo data.
"""


def default_threshold(grasped: Polyhedron, environment: Polyhedron) -> float:
    """Return the default contact threshold for observed poses (metres).

    ``THRESHOLD_FRACTION`` times the smaller of the two models' bounding diagonals.
    """
    return THRESHOLD_FRACTION * min(grasped.scale, environment.scale)


@dataclass(frozen=True)
class SegmentationCosts:
    """Weights of the segmentation cost (``docs/recognition.md``), dimensionless.

    Distances are measured in units of the contact threshold ``theta``.

    Attributes
    ----------
    claim : float
        Times ``(max_i d_i / theta)^2`` over the claimed elements, ``d_i`` their distances
        at the observed pose: the residual the pose correction has to remove.
    miss : float
        Per observed element the state leaves out, times ``(1 - d / theta)^2``: strong
        evidence when the features were nearly touching, none at the threshold.
    switch : float
        Per state change.
    fail : float
        Per frame assigned to a state whose pose correction converged at no frame.
    jump : float
        Per transition that fails the direct-transition test; taken only when every
        feasible sequence explains the frames worse by more than this (it is then reported
        with ``direct = False``).
    window : int
        Two candidates whose observed frames are never within ``window`` frames of each
        other are not tested for a direct transition (treated as not direct); this keeps
        the number of tests near linear in the number of candidates.
    reach : float
        A bridging candidate (a state between two observed ones, observed at no frame) is
        kept only if its elements are within ``reach * theta`` at the observed pose it is
        corrected from, and the correction moves no vertex more than twice that distance
        plus ``theta`` (it did not converge to a distant solution).
    """

    claim: float = 1.0
    miss: float = 4.0
    switch: float = 1.5
    fail: float = 6.0
    jump: float = 25.0
    window: int = 10
    reach: float = 3.0


@dataclass(frozen=True)
class CandidateState:
    """A distinct observed contact state, analysed once.

    Attributes
    ----------
    key : frozenset
        ``ContactState.key`` (element kinds and feature ids).
    state : ContactState
        The contact state at the representative pose (or as observed, if no frame converged).
    dof : Any
        ``apo.dof.DofResult`` of ``state``.
    frame : int
        Representative frame (best converged correction; else the first observed frame).
    X_EG : ndarray, shape (4, 4)
        Corrected pose at ``frame`` (metres).
    converged : bool
        True if the correction converged at ``frame``.
    n_observed : int
        Number of frames at which it was observed.
    """

    key: StateKey
    state: ContactState
    dof: Any
    frame: int
    X_EG: FloatArray
    converged: bool
    n_observed: int


@dataclass(frozen=True)
class Recognition:
    """Result of :func:`recognize_frames`: the task model and per-frame diagnostics.

    Attributes
    ----------
    task : TaskModel
    state_of_frame : list of str
        Task state id of every frame.
    observed : ndarray of int, shape (N,)
        Index into ``keys`` of the state observed at each frame.
    assigned : ndarray of int, shape (N,)
        Index into ``keys`` of the state chosen at each frame.
    residual_before, residual_after : ndarray, shape (N,)
        Largest contact distance (metres) of the observed contacts before and after the
        pose correction of each frame.
    converged : ndarray of bool, shape (N,)
        True where the correction converged.
    repaired : ndarray of bool, shape (N,)
        True where the chosen state differs from the observed one.
    candidates : list of CandidateState or None
        The analysed candidates (None: observed noise, not analysed), aligned with ``keys``.
    keys : list of frozenset
        Contact-state keys of the observed states, then of the bridging states.
    feasible : ndarray of bool, shape (K, K)
        Direct-transition test between candidates (diagonal True; False where untested).
    times : ndarray, shape (N,)
    emission : ndarray, shape (N, K)
        Cost of each candidate at each frame (``docs/recognition.md``).
    timings : dict
        Seconds spent in each stage.
    """

    task: TaskModel
    state_of_frame: list[str]
    observed: IntArray
    assigned: IntArray
    residual_before: FloatArray
    residual_after: FloatArray
    converged: BoolArray
    repaired: BoolArray
    candidates: list[CandidateState | None]
    keys: list[StateKey]
    feasible: BoolArray
    times: FloatArray
    emission: FloatArray
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def flags(self) -> list[list[str]]:
        """Per-frame flags: ``"correction_failed"``, ``"repaired"``."""
        out: list[list[str]] = []
        for c, r in zip(self.converged, self.repaired, strict=True):
            f = [] if c else ["correction_failed"]
            if r:
                f.append("repaired")
            out.append(f)
        return out


# --------------------------------------------------------------------------------------------
# Input validation
# --------------------------------------------------------------------------------------------


def check_sequence(
    times: npt.ArrayLike, X_EG_seq: npt.ArrayLike, *, source: str = "demonstration"
) -> tuple[FloatArray, FloatArray]:
    """Validate a pose sequence; return ``(times, X_EG_seq)`` as float arrays.

    Raises
    ------
    InputFormatError
        Empty sequence, wrong shapes, non-finite values, non-rigid poses, or times that go
        backwards; the message names ``source`` and the frame.
    """
    X = np.asarray(X_EG_seq, dtype=np.float64)
    if X.ndim != 3 or X.shape[1:] != (4, 4):
        raise InputFormatError(f"{source}: expected poses of shape (N, 4, 4), got {X.shape}")
    n = X.shape[0]
    if n == 0:
        raise InputFormatError(f"{source}: empty sequence (no frames)")
    t = np.arange(n, dtype=np.float64) if times is None else np.asarray(times, dtype=np.float64)
    if t.shape != (n,):
        raise InputFormatError(f"{source}: expected {n} time stamps, got shape {t.shape}")
    bad = ~np.isfinite(X).all(axis=(1, 2))
    if bad.any():
        raise InputFormatError(f"{source}: frame {int(np.argmax(bad))}: pose is not finite")
    if not np.isfinite(t).all():
        raise InputFormatError(
            f"{source}: frame {int(np.argmax(~np.isfinite(t)))}: time is not finite"
        )
    back = np.diff(t) < 0
    if back.any():
        raise InputFormatError(f"{source}: frame {int(np.argmax(back)) + 1}: time goes backwards")
    R = X[:, :3, :3]
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    nonrigid = (err > 1e-4) | (det < 0) | np.any(np.abs(X[:, 3] - [0, 0, 0, 1]) > 1e-9, axis=1)
    if nonrigid.any():
        raise InputFormatError(
            f"{source}: frame {int(np.argmax(nonrigid))}: not a rigid pose (rotation not "
            "orthonormal or last row not 0 0 0 1)"
        )
    return t, X


#: Poses that never bring G within this many model sizes of E suggest wrong units.
FAR_FACTOR = 50.0


def _check_scale(grasped: Polyhedron, environment: Polyhedron, X: FloatArray, source: str) -> None:
    """Raise if G is never near E: the poses or the models are in the wrong units."""
    centre_g = 0.5 * (grasped.vertices.min(axis=0) + grasped.vertices.max(axis=0))
    lo, hi = environment.vertices.min(axis=0), environment.vertices.max(axis=0)
    c = np.einsum("nij,j->ni", X[:, :3, :3], centre_g) + X[:, :3, 3]
    gap = np.linalg.norm(np.maximum(0.0, np.maximum(lo - c, c - hi)), axis=1)
    size = max(grasped.scale, environment.scale)
    if float(gap.min()) > FAR_FACTOR * size:
        raise InputFormatError(
            f"{source}: the grasped object is never near the environment (closest "
            f"{gap.min():.4g} m for models of {size:.4g} m): are the poses and the models in "
            "the same units (--units)?"
        )


# --------------------------------------------------------------------------------------------
# Distances of contact elements over a sequence of poses
# --------------------------------------------------------------------------------------------


def element_distances(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG_seq: npt.ArrayLike,
    keys: Sequence[tuple[str, tuple[str, int], tuple[str, int]]],
) -> FloatArray:
    """Distances between the features of each element key at every pose.

    Parameters
    ----------
    grasped, environment : Polyhedron
        Models G and E (metres, own frames).
    X_EG_seq : array_like, shape (N, 4, 4)
        Poses of G in E.
    keys : sequence of (kind, grasped feature, environment feature)
        ``ContactElement.key`` values.

    Returns
    -------
    ndarray, shape (N, len(keys))
        Euclidean distance (metres) between the two closed features: vertex, edge segment,
        face polygon.
    """
    X = np.asarray(X_EG_seq, dtype=np.float64)
    R, p = X[:, :3, :3], X[:, :3, 3]
    out = np.empty((X.shape[0], len(keys)))
    G, E = grasped, environment
    for j, (_kind, (gk, gi), (ek, ei)) in enumerate(keys):

        def g_pts(v: FloatArray) -> FloatArray:
            out_: FloatArray = np.einsum("nij,j->ni", R, v) + p
            return out_

        def e_in_g(v: FloatArray) -> FloatArray:
            out_: FloatArray = np.einsum("nji,nj->ni", R, v[None, :] - p)
            return out_

        if gk == "v" and ek == "f":
            out[:, j] = point_face_distance(E, ei, g_pts(G.vertices[gi]))[0]
        elif gk == "f" and ek == "v":
            out[:, j] = point_face_distance(G, gi, e_in_g(E.vertices[ei]))[0]
        elif gk == "e" and ek == "e":
            a, b = G.edges[gi]
            c, d = E.edges[ei]
            r = segment_segment_closest(
                g_pts(G.vertices[a]), g_pts(G.vertices[b]), E.vertices[c], E.vertices[d]
            )
            out[:, j] = r.distance
        elif gk == "v" and ek == "e":
            c, d = E.edges[ei]
            q = g_pts(G.vertices[gi])
            cl, _ = closest_point_on_segment(q, E.vertices[c], E.vertices[d])
            out[:, j] = np.linalg.norm(q - cl, axis=1)
        elif gk == "e" and ek == "v":
            a, b = G.edges[gi]
            q = e_in_g(E.vertices[ei])
            cl, _ = closest_point_on_segment(q, G.vertices[a], G.vertices[b])
            out[:, j] = np.linalg.norm(q - cl, axis=1)
        elif gk == "v" and ek == "v":
            out[:, j] = np.linalg.norm(g_pts(G.vertices[gi]) - E.vertices[ei], axis=1)
        else:
            raise ValueError(f"unsupported feature pair {(gk, ek)} in element key")
    return out


def _near_faces(poly: Polyhedron, P: FloatArray, threshold: float) -> BoolArray:
    """(m, V, F) mask: point ``P[i, v]`` within ``threshold`` of face f of ``poly``."""
    m, nv = P.shape[:2]
    flat = P.reshape(-1, 3)
    heights = flat @ poly.face_normals.T - poly.face_offsets  # (m * V, F)
    out = np.zeros((m * nv, len(poly.faces)), dtype=bool)
    for f in range(len(poly.faces)):
        idx = np.flatnonzero(np.abs(heights[:, f]) <= threshold)
        if len(idx):
            out[idx, f] = point_face_distance(poly, f, flat[idx])[0] <= threshold
    return out.reshape(m, nv, -1)


def near_signatures(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG_seq: npt.ArrayLike,
    threshold: float,
    *,
    chunk: int = 256,
    progress: Progress | None = None,
) -> IntArray:
    """Label frames by the set of feature pairs within ``threshold``, vectorised over frames.

    Two frames get the same label iff the same (vertex of G, face of E), (face of G, vertex
    of E) and (edge of G, edge of E) pairs are within ``threshold``; vertex-edge and
    vertex-vertex proximity is implied by the edge pairs. The contact state found by
    ``apo.contact.ContactFinder`` is determined by these pairs up to the angular tolerances
    of its cone tests, so :func:`recognize_frames` runs the finder once per label.

    Parameters
    ----------
    grasped, environment : Polyhedron
    X_EG_seq : array_like, shape (N, 4, 4)
    threshold : float
        Metres.
    chunk : int
        Frames per vectorised block.
    progress : callable, optional
        Called as ``progress(done, total)`` after each block.

    Returns
    -------
    ndarray of int, shape (N,)
        Labels 0, 1, ... in order of first appearance.
    """
    X = np.asarray(X_EG_seq, dtype=np.float64)
    G, E = grasped, environment
    n = X.shape[0]
    ga, gb = G.vertices[G.edges[:, 0]], G.vertices[G.edges[:, 1]]
    ea, eb = E.vertices[E.edges[:, 0]], E.vertices[E.edges[:, 1]]
    # Bounding spheres of E's edges, for pruning the edge pairs.
    e_mid, e_rad = 0.5 * (ea + eb), 0.5 * np.linalg.norm(eb - ea, axis=1)
    g_mid0, g_rad = 0.5 * (ga + gb), 0.5 * np.linalg.norm(gb - ga, axis=1)
    rows: list[npt.NDArray[np.bool_]] = []
    for a in range(0, n, chunk):
        Xc = X[a : a + chunk]
        m = Xc.shape[0]
        R, t = Xc[:, :3, :3], Xc[:, :3, 3]
        PG = np.einsum("nij,vj->nvi", R, G.vertices) + t[:, None, :]  # G's vertices in E
        PE = np.einsum("nji,vnj->nvi", R, E.vertices[:, None, :] - t[None, :, :])
        vf = _near_faces(E, PG, threshold)
        fv = _near_faces(G, PE, threshold)
        g_mid = np.einsum("nij,ej->nei", R, g_mid0) + t[:, None, :]
        gap = np.linalg.norm(g_mid[:, :, None, :] - e_mid[None, None], axis=3)
        cand = gap <= (g_rad[None, :, None] + e_rad[None, None, :] + threshold)
        ee = np.zeros_like(cand)
        fi, gi, ei = np.nonzero(cand)
        if len(fi):
            A0 = np.einsum("kij,kj->ki", R[fi], ga[gi]) + t[fi]
            A1 = np.einsum("kij,kj->ki", R[fi], gb[gi]) + t[fi]
            d = segment_segment_closest(A0, A1, ea[ei], eb[ei]).distance
            ee[fi, gi, ei] = d <= threshold
        rows.append(np.concatenate([vf.reshape(m, -1), fv.reshape(m, -1), ee.reshape(m, -1)], 1))
        if progress is not None:
            progress(a + m, n)
    bits = np.concatenate(rows, axis=0)
    _, first, labels = np.unique(
        np.packbits(bits, axis=1), axis=0, return_index=True, return_inverse=True
    )
    # Relabel in order of first appearance.
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    out: IntArray = rank[labels.ravel()].astype(np.int64)
    return out


# --------------------------------------------------------------------------------------------
# Viterbi over candidate states
# --------------------------------------------------------------------------------------------


def viterbi(emission: FloatArray, transition: FloatArray) -> tuple[IntArray, float]:
    """Minimum-cost state path.

    Parameters
    ----------
    emission : ndarray, shape (N, K)
        Cost of state k at frame t.
    transition : ndarray, shape (K, K)
        Cost of going from state i (row) to state j (column); 0 on the diagonal.

    Returns
    -------
    path : ndarray of int, shape (N,)
    cost : float

    Examples
    --------
    >>> e = np.array([[0.0, 5], [3, 0], [0, 5]])
    >>> tr = np.array([[0.0, 1], [1, 0]])
    >>> viterbi(e, tr)[0].tolist()
    [0, 0, 0]
    """
    n, k = emission.shape
    back = np.empty((n, k), dtype=np.int64)
    acc = emission[0].copy()
    back[0] = np.arange(k)
    for t in range(1, n):
        tot = acc[:, None] + transition
        arg = np.argmin(tot, axis=0)
        back[t] = arg
        acc = tot[arg, np.arange(k)] + emission[t]
    path = np.empty(n, dtype=np.int64)
    path[-1] = int(np.argmin(acc))
    cost = float(acc[path[-1]])
    for t in range(n - 1, 0, -1):
        path[t - 1] = back[t, path[t]]
    return path, cost


def viterbi_uniform(emission: FloatArray, switch: float) -> IntArray:
    """Minimum-cost path when every change costs ``switch``: O(N K) instead of O(N K^2).

    Equivalent to :func:`viterbi` with ``transition = switch`` off the diagonal.
    """
    n, k = emission.shape
    back = np.empty((n, k), dtype=np.int64)
    acc = emission[0].copy()
    back[0] = np.arange(k)
    ar = np.arange(k)
    for t in range(1, n):
        j = int(np.argmin(acc))
        move = acc[j] + switch < acc
        back[t] = np.where(move, j, ar)
        acc = np.where(move, acc[j] + switch, acc) + emission[t]
    path = np.empty(n, dtype=np.int64)
    path[-1] = int(np.argmin(acc))
    for t in range(n - 1, 0, -1):
        path[t - 1] = back[t, path[t]]
    return path


# --------------------------------------------------------------------------------------------
# Adapters to the contact, correction, DOF and transition modules
# --------------------------------------------------------------------------------------------


def _enum_str(x: Any) -> str:
    return str(x.value) if isinstance(x, enum.Enum) else str(x)


#: Pose correction: iterations, and the residual (metres) below which it has converged.
CORRECTION_MAX_ITER = 12
CORRECTION_TOL = 1e-7


def correct_poses(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG_seq: npt.ArrayLike,
    elements: Sequence[ContactElement],
    *,
    max_iter: int = CORRECTION_MAX_ITER,
    tol: float = CORRECTION_TOL,
    threshold: float | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray]:
    """Correct many poses so that the same contact elements hold exactly (paper 4.3.1).

    :class:`apo.correction.ContactConstraints`: Gauss-Newton on the residuals ``f_i`` of
    ``apo.contact.element_residuals``, batched over the poses, each step the SVD
    least-squares twist applied on the left (``docs/correction.md``). A correction that
    turns or moves G implausibly far (``apo.correction``'s limits) counts as failed.

    Parameters
    ----------
    grasped, environment : Polyhedron
    X_EG_seq : array_like, shape (n, 4, 4)
        Observed poses of G in E, metres.
    elements : sequence of ContactElement
        The contact elements to impose (feature ids; EE elements use their normal's sign).
    max_iter : int
    tol : float
        Convergence: ``max_i |f_i| <= tol`` (metres).
    threshold : float, optional
        The contact threshold (metres): a correction that moves a vertex of G by more than
        ``apo.correction.DISPLACEMENT_FACTOR`` thresholds fails.

    Returns
    -------
    X : ndarray, shape (n, 4, 4)
        Corrected poses.
    before, after : ndarray, shape (n,)
        ``max_i |f_i|`` at the observed and the corrected poses, metres.
    converged : ndarray of bool, shape (n,)
        Converged and not flagged as implausible.
    """
    from apo.correction import ContactConstraints

    X = np.array(X_EG_seq, dtype=np.float64)
    n = X.shape[0]
    if not elements:
        z = np.zeros(n)
        return X, z, z.copy(), np.ones(n, dtype=bool)
    res = ContactConstraints(grasped, environment, elements).correct(
        X, max_iter=max_iter, tol=tol, threshold=threshold
    )
    return res.X_EG, res.residual_before, res.residual_after, res.converged & ~res.flagged


def _correct_batch(
    grasped: Polyhedron,
    environment: Polyhedron,
    X: FloatArray,
    states: Sequence[ContactState],
    labels: IntArray,
    threshold: float,
) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray]:
    """Correct every pose ``X[t]`` under ``states[labels[t]]``, batched by state."""
    n = X.shape[0]
    Xc = X.copy()
    before = np.zeros(n)
    after = np.zeros(n)
    conv = np.ones(n, dtype=bool)
    for k in np.unique(labels):
        frames = np.flatnonzero(labels == k)
        elements = states[int(k)].elements
        if not elements:
            continue
        Xk, b, a, c = correct_poses(grasped, environment, X[frames], elements, threshold=threshold)
        Xc[frames], before[frames], after[frames], conv[frames] = Xk, b, a, c
    return Xc, before, after, conv


def _correct_one(
    grasped: Polyhedron,
    environment: Polyhedron,
    X: FloatArray,
    state: ContactState,
    threshold: float,
) -> tuple[FloatArray, float, float, bool]:
    """Correct one pose under ``state``; return X, residual before, after, converged."""
    Xc, b, a, c = correct_poses(grasped, environment, X[None], state.elements, threshold=threshold)
    return Xc[0], float(b[0]), float(a[0]), bool(c[0])


def _dof_of(state: ContactState) -> Any:
    from apo import dof

    points = [dof.ContactPoint(point=e.point, normals=e.normals) for e in state.elements]
    return dof.analyze(points)


def _state_at(
    finder: Any, exact: Any, X: FloatArray, key: StateKey, fallback: ContactState
) -> ContactState:
    """Return the contact state of ``key``'s elements re-evaluated at the corrected pose ``X``.

    The elements come from ``finder`` (the recognition threshold), restricted to ``key``;
    the touching pairs from ``exact`` (a tight threshold): at a corrected pose the contacts
    hold exactly, so only pairs that really touch enter Donald's inclusion test, not pairs
    that are merely near.
    """
    found = finder.find(X)
    by_key = {e.key: e for e in found.elements}
    if not key <= set(by_key):
        return fallback
    held = exact.find(X)
    closure = {e.key: e for e in held.elements}
    # every element that holds at the corrected pose: an observed subset of a contact (three
    # of a face's four vertices seen within the threshold) is the whole contact
    chosen = list(closure.values()) if key <= set(closure) else [by_key[k] for k in key]
    elements = tuple(sorted(chosen, key=lambda e: e.key))
    touching = held.touching | {(e.grasped, e.environment) for e in elements}
    return ContactState(elements=elements, touching=frozenset(touching))


def _direct_possible(a: CandidateState, b: CandidateState) -> bool:
    transitions = importlib.import_module("apo.transitions")

    return bool(transitions.direct_transition_possible(a.state, b.state, a.dof, b.dof))


def _transition_record(
    a: CandidateState, b: CandidateState, from_id: str, to_id: str, frame: int, direct: bool
) -> Transition:
    transitions = importlib.import_module("apo.transitions")

    tr = transitions.analyze_transition(
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
            kind=_enum_str(s.kind),
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


def _label(key: tuple[str, tuple[str, int], tuple[str, int]]) -> str:
    kind, (gk, gi), (ek, ei) = key
    return f"{kind} {gk}{gi}-{ek}{ei}"


def _bridge_candidates(
    grasped: Polyhedron,
    environment: Polyhedron,
    exact: Any,
    X: FloatArray,
    obs: IntArray,
    candidates: Sequence[CandidateState | None],
    feasible: BoolArray,
    index: Mapping[StateKey, int],
    reach: float,
) -> list[tuple[CandidateState, tuple[int, int], tuple[int, int]]]:
    """Candidate states bridging consecutive observed states that are not directly connected.

    For observed runs ``k1`` then ``k2`` with no direct transition between them, the union
    of their elements (with :func:`_meet_elements`: a corner that touched an edge in one
    and whose edge touched a corner in the other meet at the vertex-vertex contact) is
    imposed on the poses of the two boundary frames by the pose correction. Where it
    converges, the contact state found at the corrected pose (e.g. the vertex-vertex contact
    a sliding corner passes through between two frames) becomes a candidate, observed at no
    frame, provided its residual at the observed pose is at most ``reach`` (metres) and
    the correction moved no vertex of G more than twice that residual plus ``reach / 3``.
    Returns ``(candidate, (last frame of k1, first frame of k2), (k1, k2))`` triples.
    """
    out: list[tuple[CandidateState, tuple[int, int], tuple[int, int]]] = []
    seen: set[tuple[int, int]] = set()
    new_keys: set[StateKey] = set()
    runs = _run_bounds(obs)
    for (_a1, b1), (a2, _b2) in itertools.pairwise(runs):
        k1, k2 = int(obs[b1]), int(obs[a2])
        if feasible[k1, k2] or (k1, k2) in seen:
            continue
        seen.add((k1, k2))
        c1, c2 = candidates[k1], candidates[k2]
        if c1 is None or c2 is None:
            continue
        s1, s2 = c1.state, c2.state
        if not s1.elements or not s2.elements:
            continue
        union = ContactState(
            elements=_meet_elements(grasped, environment, s1.elements, s2.elements),
            touching=s1.touching | s2.touching,
        )
        best: tuple[float, FloatArray, int] | None = None
        for f in (b1, a2):
            Xc, before, _after, ok = _correct_one(grasped, environment, X[f], union, reach / 3.0)
            moved = _max_displacement(grasped, X[f], Xc)
            # Near the observation (residual within reach), and the correction did not
            # wander off to a distant solution of the same equations.
            near = before <= reach and moved <= 2.0 * before + reach / 3.0
            if ok and near and (best is None or before < best[0]):
                best = (before, Xc, f)
        if best is None:
            continue
        found = exact.find(best[1])
        if not found.elements or found.key in index or found.key in new_keys:
            continue
        new_keys.add(found.key)
        cand = CandidateState(found.key, found, _dof_of(found), best[2], best[1].copy(), True, 0)
        out.append((cand, (int(b1), int(a2)), (k1, k2)))
    return out


def _feature_vertices(poly: Polyhedron, feature: tuple[str, int]) -> set[int]:
    """Vertex ids of a feature: itself, an edge's ends, or a face's boundary vertices."""
    kind, i = feature
    if kind == "v":
        return {i}
    if kind == "e":
        return {int(v) for v in poly.edges[i]}
    loops = [poly.faces[i], *poly.face_holes[i]]
    return {int(v) for loop in loops for v in loop}


def _meet_elements(
    grasped: Polyhedron,
    environment: Polyhedron,
    first: Sequence[ContactElement],
    second: Sequence[ContactElement],
) -> tuple[ContactElement, ...]:
    """Elements that hold in a state between ``first`` and ``second`` (union, with meets).

    A vertex of G touching an E feature in one state and a G feature touching an E vertex
    in the other, where the E vertex bounds the first E feature and the G vertex bounds the
    second G feature, meet at the vertex-vertex contact of the two vertices (a corner
    passing over a corner); that VV element replaces the two. The rest is the union.
    """
    from apo.contact import ContactKind

    chosen = {e.key: e for e in (*first, *second)}
    for a, b in itertools.chain(itertools.product(first, second), itertools.product(second, first)):
        if a.grasped[0] != "v" or b.environment[0] != "v":
            continue
        gv, ev = a.grasped[1], b.environment[1]
        if ev in _feature_vertices(environment, a.environment) and gv in _feature_vertices(
            grasped, b.grasped
        ):
            vv = ContactElement(
                ContactKind.VV,
                ("v", gv),
                ("v", ev),
                np.asarray(b.point, dtype=np.float64),
                np.asarray(a.normals, dtype=np.float64),
            )
            chosen.pop(a.key, None)
            chosen.pop(b.key, None)
            chosen[vv.key] = vv
    return tuple(chosen[k] for k in sorted(chosen))


def _max_displacement(poly: Polyhedron, X0: FloatArray, X1: FloatArray) -> float:
    """Largest displacement (metres) of a vertex of ``poly`` between poses X0 and X1."""
    v = poly.vertices
    d = (v @ X1[:3, :3].T + X1[:3, 3]) - (v @ X0[:3, :3].T + X0[:3, 3])
    return float(np.linalg.norm(d, axis=1).max())


def _reachable(feasible: BoolArray) -> BoolArray:
    """Transitive closure of the direct-transition relation (i can reach j), shape (K, K)."""
    r = feasible.copy()
    k = len(r)
    for m in range(k):
        r |= r[:, m : m + 1] & r[m : m + 1, :]
    return r


def _near_pairs(obs: IntArray, k_count: int, window: int) -> BoolArray:
    """Pairs of candidates observed within ``window`` frames of each other, shape (K, K)."""
    n = len(obs)
    near = np.zeros((k_count, k_count), dtype=bool)
    # Candidates present in each window of frames [t, t + window].
    onehot = np.zeros((n + 1, k_count))
    onehot[np.arange(n) + 1, obs] = 1.0
    cum = np.cumsum(onehot, axis=0)
    step = max(1, window // 2)
    for a in range(0, n, step):
        b = min(n, a + window + step + 1)
        present = np.flatnonzero(cum[b] - cum[a] > 0)
        near[np.ix_(present, present)] = True
    return near


def _run_bounds(labels: IntArray) -> list[tuple[int, int]]:
    """(first, last) of each run of equal consecutive values."""
    n = len(labels)
    starts = np.flatnonzero(np.r_[True, labels[1:] != labels[:-1]])
    ends = np.r_[starts[1:] - 1, n - 1]
    return [(int(a), int(b)) for a, b in zip(starts, ends, strict=True)]


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
        Contact distance threshold, metres; default :func:`default_threshold` (scale-aware).
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
) -> Recognition:
    """Recognise a demonstration; return the task model and per-frame diagnostics.

    Parameters are those of :func:`recognize`.

    Returns
    -------
    Recognition
    """
    import time

    from apo.contact import ContactFinder

    w = costs or SegmentationCosts()
    tm: dict[str, float] = {}
    t0 = time.perf_counter()
    t, X = check_sequence(times, X_EG_seq, source=source or "demonstration")  # type: ignore[arg-type]
    n = X.shape[0]
    _check_scale(grasped, environment, X, source or "demonstration")
    if threshold is None:
        threshold = default_threshold(grasped, environment)
    finder = ContactFinder(grasped, environment, threshold=threshold)
    # At corrected poses contacts hold exactly: the contact finder's own (tight) default
    # threshold tells which feature pairs really touch there.
    exact = ContactFinder(grasped, environment)
    theta = float(finder.threshold)

    # 1. Contacts per frame: frames are labelled by their near feature pairs (vectorised),
    # and the contact finder runs once per label, at the label's first frame.
    observed_states: list[ContactState] = []
    if memoize:
        labels = near_signatures(grasped, environment, X, theta, progress=progress)
        _uniq, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
        found = finder.find_batch(X[first])  # one batched search over the labels
        observed_states = [found[int(j)] for j in inverse.ravel()]
    else:
        for a in range(0, n, _CHUNK):
            observed_states.extend(finder.find_batch(X[a : a + _CHUNK]))
            if progress is not None:
                progress(min(a + _CHUNK, n), n)
    tm["contacts"] = time.perf_counter() - t0

    # 2. Candidate states = distinct observed keys; their cost at every frame needs only
    # distances (one vectorised pass per element over all frames).
    t1 = time.perf_counter()
    index: dict[StateKey, int] = {}
    obs = np.empty(n, dtype=np.int64)
    first_state: list[ContactState] = []
    for i, s in enumerate(observed_states):
        k = index.setdefault(s.key, len(index))
        if k == len(first_state):
            first_state.append(s)
        obs[i] = k
    k_obs = len(index)
    dists = _DistanceCache(grasped, environment, X, theta)
    touching = [st.touching for st in first_state]
    keys: list[StateKey] = list(index)
    emission = _emission(dists, keys, touching, obs, w)

    # 3. Shortlist: the states an unconstrained segmentation (switch cost only) uses. Only
    # these are analysed; the rest are observed noise that no cheaper path needs.
    path0 = viterbi_uniform(emission, w.switch)
    shortlist = sorted({int(k) for k in np.unique(path0)})
    tm["segmentation"] = time.perf_counter() - t1

    # 4. One analysis per shortlisted state: representative pose (best of its observed
    # frames whose correction converges), the state at that pose, its DOF.
    t2 = time.perf_counter()
    candidates: list[CandidateState | None] = [None] * k_obs
    feasible = np.eye(k_obs, dtype=bool)
    tested = np.eye(k_obs, dtype=bool)

    def analyse(ks: Iterable[int]) -> None:
        for k in ks:
            if candidates[k] is None:
                candidates[k] = _analyse_candidate(
                    grasped,
                    environment,
                    finder,
                    exact,
                    X,
                    obs,
                    k,
                    keys[k],
                    first_state[k],
                    emission[:, k],
                )
        done = np.array([c is not None for c in candidates])
        labels = np.where(done[obs], obs, path0)
        todo = _near_pairs(labels, k_obs, w.window) & ~tested
        todo &= done[:, None] & done[None, :]
        for i, j in zip(*np.nonzero(todo), strict=True):
            ci, cj = candidates[i], candidates[j]
            assert ci is not None and cj is not None
            feasible[i, j] = _direct_possible(ci, cj)
            tested[i, j] = True

    analyse(shortlist)
    # Where the shortlist path changes state in a way no sequence of shortlisted states
    # can make directly, the states observed around that change are analysed too: a short
    # genuine state (a singular contact held for a few frames) may be the way through.
    extra: set[int] = set()
    reach_sl = _reachable(feasible)
    for (_a1, b1), (a2, _b2) in itertools.pairwise(_run_bounds(path0)):
        if not reach_sl[path0[b1], path0[a2]]:
            lo, hi = max(0, b1 - w.window), min(n, a2 + w.window + 1)
            extra |= {int(k) for k in np.unique(obs[lo:hi])}
    if extra - set(shortlist):
        analyse(sorted(extra - set(shortlist)))
    # Bridges: where consecutive states of the shortlist path cannot follow each other
    # directly, the state where both hold (corrected from the boundary frames) is a
    # candidate too.
    bridges = _bridge_candidates(
        grasped, environment, exact, X, path0, candidates, feasible, index, w.reach * theta
    )
    for bridge, _frames, _pair in bridges:
        index[bridge.key] = len(candidates)
        candidates.append(bridge)
        keys.append(bridge.key)
        touching.append(bridge.state.touching)
    k_count = len(candidates)
    if bridges:
        grown = np.eye(k_count, dtype=bool)
        grown[:k_obs, :k_obs] = feasible
        feasible = grown
        for b, (_cand, (f1, f2), _pair) in enumerate(bridges, start=k_obs):
            lo, hi = max(0, f1 - w.window), min(n, f2 + w.window + 1)
            for j in {int(v) for v in path0[lo:hi]} | set(range(k_obs, k_count)):
                cj = candidates[j]
                if j == b or cj is None:
                    continue
                cb = candidates[b]
                assert cb is not None
                feasible[b, j] = _direct_possible(cb, cj)
                feasible[j, b] = _direct_possible(cj, cb)
    tm["analysis"] = time.perf_counter() - t2

    # 5. Constrained segmentation over the analysed candidates.
    t3 = time.perf_counter()
    for k, maybe in enumerate(candidates):
        if maybe is not None:
            touching[k] = maybe.state.touching
    emission = _emission(dists, keys, touching, obs, w)
    # A bridging state happens between its two boundary frames: there it explains the
    # frame as well as the observed state it joins (it holds that state's contacts too).
    for b, (_cand, (f1, f2), (k1, k2)) in enumerate(bridges, start=k_obs):
        emission[f1, b] = min(emission[f1, b], emission[f1, k1])
        emission[f2, b] = min(emission[f2, b], emission[f2, k2])
    unusable = np.array([c is None for c in candidates])
    failed = np.array([c is not None and not c.converged for c in candidates])
    emission = emission + w.fail * failed[None, :] + np.where(unusable, np.inf, 0.0)[None, :]
    trans = np.where(feasible, w.switch, w.switch + w.jump)
    np.fill_diagonal(trans, 0.0)
    path, _cost = viterbi(emission, trans)
    # Candidates observed with different subsets of one contact are the same state once
    # their poses are corrected (their closures agree): one id for them all.
    canon = np.arange(k_count)
    first_of: dict[StateKey, int] = {}
    for k, maybe in enumerate(candidates):
        if maybe is not None and maybe.converged:
            canon[k] = first_of.setdefault(maybe.state.key, k)
    path = canon[path]
    obs_c = canon[obs]  # the observed state, up to that identification
    tm["segmentation"] += time.perf_counter() - t3

    # Per-frame pose correction under the chosen state (batched by state): residuals
    # before and after, converged flags.
    t5 = time.perf_counter()
    chosen_states = [c.state if c is not None else first_state[k] for k, c in enumerate(candidates)]
    Xc, res_before, res_after, conv = _correct_batch(
        grasped, environment, X, chosen_states, path, theta
    )
    tm["correction"] = time.perf_counter() - t5

    # 6. States, transitions, rejected runs.
    t4 = time.perf_counter()
    runs = _run_bounds(path)
    ids = state_letters(len(runs))
    first_id: dict[int, str] = {}
    states: list[State] = []
    run_cands: list[int] = []
    for (a, b), sid in zip(runs, ids, strict=True):
        k = int(path[a])
        run_cands.append(k)
        cand = analysed_at(candidates, k)
        seg = np.arange(a, b + 1)
        good = seg[(obs_c[seg] == k) & conv[seg]]
        if not len(good):
            good = seg[conv[seg]]
        if len(good):
            f = int(good[np.argmin(res_before[good])])
            Xs, pf, pc = Xc[f], f, True
        else:
            Xs, pf, pc = cand.X_EG, cand.frame, cand.converged
        dof_r = cand.dof
        states.append(
            State(
                id=sid,
                frames=(a, b),
                times=(float(t[a]), float(t[b])),
                singular=bool(dof_r.singular),
                fig25=cast("tuple[int, int, int, int, int, int, int, int]", tuple(dof_r.fig25)),
                six={sp: cast("Six", tuple(dof_r.six(sp))) for sp in ("translation", "rotation")},
                elements=tuple(_element_record(e) for e in cand.state.elements),
                X_EG=np.asarray(Xs, dtype=np.float64).copy(),
                pose_frame=pf,
                pose_converged=pc,
                same_as=first_id.get(k),
            )
        )
        first_id.setdefault(k, sid)
    # A pair of candidates is analysed once however often the demonstration repeats it.
    analysed: dict[tuple[int, int], Transition] = {}
    transitions_out = []
    for i in range(len(runs) - 1):
        pair = (run_cands[i], run_cands[i + 1])
        if pair not in analysed:
            analysed[pair] = _transition_record(
                analysed_at(candidates, pair[0]),
                analysed_at(candidates, pair[1]),
                ids[i],
                ids[i + 1],
                runs[i + 1][0],
                bool(feasible[pair]),
            )
        transitions_out.append(
            replace(analysed[pair], from_id=ids[i], to_id=ids[i + 1], frame=runs[i + 1][0])
        )
    rejected = _rejected_runs(obs_c, path, runs, ids, keys, candidates, feasible, emission, w)
    tm["task"] = time.perf_counter() - t4

    g_ref, e_ref = models or (
        ModelRef(grasped.name, None, grasped.name),
        ModelRef(environment.name, None, environment.name),
    )
    task = TaskModel(
        units=units,
        grasped=g_ref,
        environment=e_ref,
        states=tuple(states),
        transitions=tuple(transitions_out),
        rejected=tuple(rejected),
        n_frames=n,
        source=source,
        threshold=theta,
    )
    state_of_frame = [ids[i] for i, (a, b) in enumerate(runs) for _ in range(a, b + 1)]
    tm["total"] = time.perf_counter() - t0
    return Recognition(
        task=task,
        state_of_frame=state_of_frame,
        observed=obs,
        assigned=path,
        residual_before=res_before,
        residual_after=res_after,
        converged=conv,
        repaired=obs_c != path,
        candidates=candidates,
        keys=keys,
        feasible=feasible,
        times=t,
        emission=emission,
        timings=tm,
    )


def analysed_at(candidates: Sequence[CandidateState | None], k: int) -> CandidateState:
    """Return ``candidates[k]``, which must have been analysed."""
    c = candidates[k]
    if c is None:
        raise RuntimeError(f"candidate {k} was chosen but not analysed")
    return c


class _DistanceCache:
    """Distances (in thresholds) of element keys at every observed pose, computed once."""

    def __init__(
        self, grasped: Polyhedron, environment: Polyhedron, X: FloatArray, theta: float
    ) -> None:
        self.args = (grasped, environment, X)
        self.theta = theta
        self.cache: dict[tuple[str, tuple[str, int], tuple[str, int]], FloatArray] = {}

    def get(self, keys: Sequence[tuple[str, tuple[str, int], tuple[str, int]]]) -> FloatArray:
        missing = [k for k in dict.fromkeys(keys) if k not in self.cache]
        if missing:
            d = element_distances(*self.args, missing) / self.theta
            for j, k in enumerate(missing):
                self.cache[k] = d[:, j]
        n = self.args[2].shape[0]
        if not keys:
            return np.zeros((n, 0))
        return np.stack([self.cache[k] for k in keys], axis=1)


def _emission(
    dists: _DistanceCache,
    keys: Sequence[StateKey],
    touching: Sequence[frozenset[tuple[tuple[str, int], tuple[str, int]]]],
    obs: IntArray,
    w: SegmentationCosts,
) -> FloatArray:
    """Cost of every candidate at every frame (``docs/recognition.md``), shape (N, K)."""
    n = len(obs)
    ukeys = sorted({e for key in keys for e in key})
    emission = np.zeros((n, len(keys)))
    if not ukeys:
        return emission
    upos = {e: u for u, e in enumerate(ukeys)}
    dist = dists.get(ukeys)
    # Claimed elements: the correction residual before correction, max_i |f_i| (paper
    # 4.3.1), of the candidate's elements at the observed pose.
    d2 = dist**2
    member = np.zeros((len(ukeys), len(keys)))
    for k, key in enumerate(keys):
        cols = [upos[e] for e in key]
        member[cols, k] = 1.0
        if cols:
            emission[:, k] = w.claim * d2[:, cols].max(axis=1)
    # Observed elements the candidate leaves out: evidence against it. An element whose
    # feature pair touches in the candidate (e.g. a vertex on an edge when the vertex
    # touches the edge's end vertex) is not left out.
    cover = member.copy()
    by_pair: dict[tuple[tuple[str, int], tuple[str, int]], list[int]] = {}
    for u, (_kind, gf, ef) in enumerate(ukeys):
        by_pair.setdefault((gf, ef), []).append(u)
    for k, pairs in enumerate(touching):
        rows = [u for pair in pairs for u in by_pair.get(pair, ())]
        cover[rows, k] = 1.0
    k_obs = int(obs.max()) + 1
    seen = member[:, :k_obs][:, obs].T  # (n, U): element observed at frame t
    missed = w.miss * seen * np.clip(1.0 - dist, 0.0, 1.0) ** 2
    emission += missed @ (1.0 - cover)
    return emission


def _analyse_candidate(
    grasped: Polyhedron,
    environment: Polyhedron,
    finder: Any,
    exact: Any,
    X: FloatArray,
    obs: IntArray,
    k: int,
    key: StateKey,
    observed: ContactState,
    cost: FloatArray,
    tries: int = 3,
) -> CandidateState:
    """Correct the best observed frames of candidate ``k``; analyse it at the first success."""
    frames = np.flatnonzero(obs == k)
    best = frames[np.argsort(cost[frames], kind="stable")[:tries]]
    Xb, _before, _after, ok = correct_poses(
        grasped, environment, X[best], observed.elements, threshold=float(finder.threshold)
    )
    if ok.any():
        i = int(np.argmax(ok))
        f = int(best[i])
        state = _state_at(finder, exact, Xb[i], key, observed)
        return CandidateState(key, state, _dof_of(state), f, Xb[i].copy(), True, len(frames))
    f = int(best[0])
    return CandidateState(key, observed, _dof_of(observed), f, X[f].copy(), False, len(frames))


def _element_record(e: ContactElement) -> Element:
    return Element(
        kind=e.kind.value,
        grasped=e.grasped,
        environment=e.environment,
        point=np.asarray(e.point, dtype=np.float64),
        normals=np.asarray(e.normals, dtype=np.float64).reshape(-1, 3),
    )


def _rejected_runs(
    obs: IntArray,
    path: IntArray,
    runs: list[tuple[int, int]],
    ids: list[str],
    keys: list[StateKey],
    candidates: Sequence[CandidateState | None],
    feasible: BoolArray,
    emission: FloatArray,
    w: SegmentationCosts,
) -> list[Rejected]:
    """Observed runs the segmentation replaced, with the reason."""
    run_of = np.empty(len(path), dtype=np.int64)
    for r, (a, b) in enumerate(runs):
        run_of[a : b + 1] = r
    out: list[Rejected] = []
    marks = np.where(obs == path, -1, obs)
    for a, b in _run_bounds(marks):
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
                kept = float(emission[a : b + 1, k].sum())
                chosen = float(emission[np.arange(a, b + 1), path[a : b + 1]].sum())
                reasons.append(
                    f"costlier than the neighbouring states ({kept:.2f} + switches "
                    f"{w.switch:g} each vs {chosen:.2f})"
                )
        out.append(
            Rejected(
                frames=(a, b),
                elements=tuple(_label(e) for e in sorted(keys[k])),
                replaced_by=tuple(by),
                reason="; ".join(reasons),
            )
        )
    return out
