"""Contacts per frame (paper 4.3.1): the contact state observed at every frame.

The contact finder (``apo.contact.ContactFinder``, at the recognition threshold) is run
batched over all frames, or once per set of near feature pairs (:func:`near_signatures`);
frames are then labelled by their distinct observed states.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np
import numpy.typing as npt

from apo.contact import ContactFinder, ContactState
from apo.contact.search import BlockSets
from apo.geometry import Polyhedron, point_face_distance, segment_segment_closest
from apo.recognition.types import BoolArray, FloatArray, IntArray, Progress, Scene, StateKey
from apo.workers import run_parts, shared_zeros, workers_for

__all__ = [
    "Observations",
    "distinct_poses",
    "group_states",
    "label_frames",
    "near_signatures",
    "observe",
    "observed_states",
]

#: Frames per batch handed to the contact finder (and per progress update).
CHUNK = 512

#: Frames per call of the whole contact search (points, normals, touching pairs) at the
#: first frame of each observed state (:func:`observe`): its working arrays take some 28 KB
#: a frame (a noisy 30,000-frame demonstration shows 454 states: 13 MB at once).
STATES_CHUNK = 64


@dataclass(frozen=True)
class Observations:
    """The distinct contact states observed, and which one each frame shows.

    Attributes
    ----------
    labels : ndarray of int, shape (N,)
        Index into ``keys`` of the state observed at each frame (order of first appearance).
    keys : list of frozenset
        ``ContactState.key`` of each distinct observed state.
    states : list of ContactState
        Each distinct state as found at its first frame.
    """

    labels: IntArray
    keys: list[StateKey]
    states: list[ContactState]


def observe(
    scene: Scene,
    *,
    memoize: bool = False,
    progress: Progress | None = None,
    jobs: int | None = 1,
) -> Observations:
    """Find the contact state at every frame and group the frames by distinct state.

    The frames are labelled by the keys of their states
    (:meth:`apo.contact.ContactFinder.find_labels`: the search without the normals, points
    and touching pairs), and the whole state is found at the first frame of each label
    only: the same observations as :func:`group_states` of :func:`observed_states`, whose
    states of later frames of a label would be dropped. A pose that repeats an earlier
    one bit for bit is searched once (:func:`distinct_poses`). ``jobs``: processes the
    search of the distinct poses is split over (:func:`label_frames`).
    """
    if memoize:
        return group_states(observed_states(scene, memoize=True, progress=progress))
    X, n = scene.X, scene.n
    first, inverse = distinct_poses(X)
    m = len(first)
    Xu = X if m == n else X[first]  # all distinct: ``first`` is every frame, in order

    def tick(done: int, _total: int) -> None:
        if progress is not None:
            progress(n if done >= m else done * n // m, n)

    labels, once = label_frames(scene.finder, Xu, progress=tick, jobs=jobs)
    states = [  # a few at a time: the whole search's working arrays grow with the frames
        s
        for a in range(0, len(once), STATES_CHUNK)
        for s in scene.finder.find_batch(Xu[once[a : a + STATES_CHUNK]])
    ]
    keys = [s.key for s in states]
    if len(set(keys)) < len(keys):  # pragma: no cover - find_labels is find_batch's keys
        return group_states([states[j] for j in labels[inverse].tolist()])
    return Observations(labels[inverse] if m < n else labels, keys, states)


def label_frames(
    finder: ContactFinder,
    X: FloatArray,
    *,
    progress: Progress | None = None,
    jobs: int | None = 1,
) -> tuple[IntArray, IntArray]:
    """``finder.find_labels(X)``, its blocks of frames split over ``jobs`` processes.

    The blocks (:attr:`ContactFinder.block_frames`: the same blocks as one process
    searches) are taken in turn from a counter the processes share: each takes the next
    block not yet taken when it is done with its last, so the processes finish close
    together whatever the blocks cost and however late a child starts (blocks dealt in a
    fixed order left the parent waiting for its child: 10-29 ms on the jittered 2,993
    frames at load 4-5, 0.5-3 ms so). Two processes
    that read the counter at once both search the same block: the same rows, one is kept;
    none is skipped (every value the counter takes was read by the process that wrote the
    next). Each process keys its blocks' ``(frame, code)`` rows
    (:meth:`ContactFinder.element_codes`) by their sets (:meth:`ContactFinder.sets_of`:
    4 bytes a frame and the block's distinct sets, where the rows take 16 bytes an element)
    and hands those back; the blocks' sets in block order are labelled as
    :meth:`ContactFinder.find_labels` labels them, so the labels are the same bit for bit.
    ``jobs``: None for auto (:func:`apo.workers.workers_for`).
    """
    step = finder.block_frames
    n_blocks = -(-len(X) // step)
    k = min(workers_for(jobs, len(X)), n_blocks)
    if k <= 1:
        return finder.find_labels(X, progress=progress)
    counter = shared_zeros((1,), np.int64, True)

    def block(b: int) -> BlockSets:
        return finder.sets_of(X[b * step : (b + 1) * step])

    def taken(report: Progress | None) -> dict[int, BlockSets]:
        out, top = {}, 0
        while (b := int(counter[0])) < n_blocks:
            counter[0] = b + 1
            out[b] = block(b)
            top = max(top, b + 1)
            if report is not None:
                report(min(len(X), top * step), len(X))
        return out

    found: dict[int, BlockSets] = {}
    for part in run_parts([partial(taken, progress if i == 0 else None) for i in range(k)]):
        for b, got in part.items():
            found.setdefault(b, got)
    # a block taken by a child that died without a result: searched here
    ordered = (found[b] if b in found else block(b) for b in range(n_blocks))
    return finder.labels_of_sets(ordered, len(X))


def observed_states(
    scene: Scene, *, memoize: bool = False, progress: Progress | None = None
) -> list[ContactState]:
    """Contact state at every frame of ``scene.X`` (threshold ``scene.theta``).

    A frame whose pose repeats an earlier frame's exactly (the same 16 numbers, bit for bit)
    is not searched again: the contact finder is a function of the pose (the models, the
    threshold and the tolerances being fixed), so it would find the same state; the frame
    gets that state (the same object). A tracker that holds its last pose, or a
    demonstration file repeated, costs one search per distinct pose.
    With ``memoize``, frames are labelled by their near feature pairs (vectorised) and the
    contact finder runs once per label, at the label's first frame.
    """
    X, n = scene.X, scene.n
    first, inverse = distinct_poses(X)
    m = len(first)
    Xu = X if m == n else X[first]  # all distinct: ``first`` is every frame, in order
    if memoize:
        labels = near_signatures(
            scene.grasped, scene.environment, Xu, scene.theta, progress=progress
        )
        _uniq, once, again = np.unique(labels, return_index=True, return_inverse=True)
        found = scene.finder.find_batch(Xu[once])  # one batched search over the labels
        states = [found[int(j)] for j in again.ravel()]
    else:
        states = []
        for a in range(0, m, CHUNK):
            states.extend(scene.finder.find_batch(Xu[a : a + CHUNK]))
            if progress is not None:
                progress(n if a + CHUNK >= m else (a + CHUNK) * n // m, n)
    return states if m == n else [states[j] for j in inverse.tolist()]


def distinct_poses(X: FloatArray) -> tuple[IntArray, IntArray]:
    """Return the first frame of each distinct pose (bit for bit) and each frame's pose.

    Returns ``first`` (indices into ``X``, in order of first appearance) and ``inverse``
    (``X[first[inverse[i]]]`` is ``X[i]`` exactly). Each pose's 16 numbers are hashed
    (:func:`_pose_hashes`, 8 bytes a frame) and the hashes grouped; the grouping is then
    checked on the poses themselves, bit for bit (a collision, never seen, falls back to
    one ``bytes`` key per pose: 200 bytes a frame, 6 MB at 30,000 frames).

    Examples
    --------
    >>> X = np.stack([np.eye(4), 2 * np.eye(4), np.eye(4)])
    >>> [v.tolist() for v in distinct_poses(X)]
    [[0, 1], [0, 1, 0]]
    """
    rows = np.ascontiguousarray(X, dtype=np.float64).reshape(len(X), -1)
    if not len(rows):
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    words = rows.view(np.uint64)
    _u, first, inverse = np.unique(_pose_hashes(words), return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")  # labels in order of first appearance
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    first, inverse = first[order].astype(np.int64), rank[inverse.ravel()].astype(np.int64)
    for a in range(0, len(rows), DISTINCT_BLOCK):
        b = a + DISTINCT_BLOCK
        if not np.array_equal(words[a:b], words[first[inverse[a:b]]]):
            return _distinct_by_bytes(rows)
    return first, inverse


#: Poses hashed (and checked) at a time by :func:`distinct_poses`.
DISTINCT_BLOCK = 4096


def _pose_hashes(words: npt.NDArray[np.uint64]) -> npt.NDArray[np.uint64]:
    """Return a 64-bit hash of each row of ``words`` (the bits of a pose), block by block."""
    mult = _odd_multipliers(words.shape[1])  # fixed: a row's hash is a function of its bits
    out = np.empty(len(words), dtype=np.uint64)
    for a in range(0, len(words), DISTINCT_BLOCK):
        w = words[a : a + DISTINCT_BLOCK]
        out[a : a + DISTINCT_BLOCK] = ((w ^ (w >> np.uint64(29))) * mult).sum(axis=1)
    return out


def _odd_multipliers(k: int) -> npt.NDArray[np.uint64]:
    """``k`` fixed odd 64-bit numbers (splitmix64's sequence; no ``numpy.random`` import)."""
    out, x, mask = [], 0x9E3779B97F4A7C15, (1 << 64) - 1
    for _ in range(k):
        x = (x + 0x9E3779B97F4A7C15) & mask
        z = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & mask
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & mask
        out.append((z ^ (z >> 31)) | 1)
    return np.array(out, dtype=np.uint64)


def _distinct_by_bytes(rows: FloatArray) -> tuple[IntArray, IntArray]:
    """:func:`distinct_poses` by one ``bytes`` key per row (no hash, more memory)."""
    index: dict[bytes, int] = {}
    inverse = np.fromiter(
        (index.setdefault(r, len(index)) for r in map(bytes, rows)), np.int64, len(rows)
    )
    first = np.full(len(index), len(rows), dtype=np.int64)
    np.minimum.at(first, inverse, np.arange(len(rows), dtype=np.int64))
    return first, inverse


def group_states(states: Sequence[ContactState]) -> Observations:
    """Label each state by its key, in order of first appearance."""
    index: dict[StateKey, int] = {}
    labels = np.empty(len(states), dtype=np.int64)
    first: list[ContactState] = []
    known: dict[int, int] = {}  # id(state) -> label: a state repeated is keyed once
    for i, s in enumerate(states):
        k = known.get(id(s))
        if k is None:
            k = known[id(s)] = index.setdefault(s.key, len(index))
            if k == len(first):
                first.append(s)
        labels[i] = k
    return Observations(labels, list(index), first)


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
