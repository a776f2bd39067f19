"""The batched search: :class:`ContactFinder` and the ``find_contacts*`` functions.

:func:`find_contacts` finds every contact element between the grasped object G and the
environment object E at one pose; :class:`ContactFinder` caches the per-model data and
searches a whole sequence of poses at once (:meth:`ContactFinder.find_batch`);
:func:`find_contacts_naive` is the plain all-pairs reference.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from apo.constants import tol
from apo.contact._arrays import _EMPTY_I
from apo.contact.candidates import _candidates
from apo.contact.classification import _classify, _elements
from apo.contact.distance_tests import (
    _by_frame,
    _edge_pairs,
    _near_features,
    _NearF,
    _touching,
)
from apo.contact.elements import _KIND_LIST, ContactState
from apo.contact.model_data import _model_data, _ModelData
from apo.contact.separating_normals import _cone_pairs
from apo.contact.thresholds import default_angle_tolerance, default_threshold
from apo.dof import ContactPoint
from apo.geometry import Polyhedron
from apo.spatial import check_pose as _check_pose
from apo.spatial import check_poses as _check_poses
from apo.typing import FloatArray, IntArray

# Models with more (query points x primitives) than this use the k-d trees.
_DENSE_LIMIT = 40_000
# A batch of frames may use this many times more for the dense all-pairs tests.
_BATCH_DENSE_FACTOR = 8
# Frames per batch: about this many vertices and edges of both models over the batch.
_BATCH_PRIMITIVES = 16_384


class ContactFinder:
    """Find contact states of a pair of models at many poses, reusing per-model data.

    Parameters
    ----------
    grasped : Polyhedron
        Grasped object G (model frame G, metres).
    environment : Polyhedron
        Environment object E (model frame E, metres).
    threshold : float, optional
        Contact distance threshold, metres; default :func:`default_threshold`.
    angle_tol : float, optional
        Angular tolerance (rad) of the separating-normal cone intersection and of the
        parallel-edge test; default :func:`default_angle_tolerance`.

    Examples
    --------
    >>> import numpy as np
    >>> from apo.shapes import box
    >>> table = box([1.0, 1.0, 0.1], center=[0.0, 0.0, -0.05])
    >>> cube = box([0.1, 0.1, 0.1], center=[0.0, 0.0, 0.05])
    >>> finder = ContactFinder(cube, table)
    >>> [e.kind.value for e in finder.find(np.eye(4)).elements]
    ['VF', 'VF', 'VF', 'VF']

    A whole sequence at once (much faster per frame than one :meth:`find` per pose):

    >>> X = np.stack([np.eye(4), np.eye(4)])
    >>> X[1, 2, 3] = 0.5  # lifted by 50 cm
    >>> [len(s.elements) for s in finder.find_batch(X)]
    [4, 0]

    Notes
    -----
    :meth:`find` is :meth:`find_batch` of one pose. Small models are searched in blocks of
    frames, each stage one numpy pass over the block: broad phase (bounding boxes), the
    features near each vertex (all pairs pruned by bounding spheres, or k-d trees over
    samples for large models), the edge pairs, the touching pairs, the snapping, the cone
    tests of the common cases (a half-space on either side, edge-vertex, edge-edge,
    vertex-vertex) and the contact points. The rest (nearly parallel lineality, merged rays)
    goes through the scalar code that :meth:`find_naive` uses for every pair.
    """

    def __init__(
        self,
        grasped: Polyhedron,
        environment: Polyhedron,
        *,
        threshold: float | None = None,
        angle_tol: float | None = None,
    ) -> None:
        if threshold is None:
            threshold = default_threshold(grasped, environment)
        threshold = float(threshold)
        if not (math.isfinite(threshold) and threshold > 0):
            raise ValueError(f"threshold must be a positive finite length, got {threshold}")
        if angle_tol is None:
            angle_tol = default_angle_tolerance(grasped, environment, threshold)
        angle_tol = float(angle_tol)
        if not (math.isfinite(angle_tol) and 0 < angle_tol < 0.5):
            raise ValueError(f"angle_tol must be in (0, 0.5) rad, got {angle_tol}")
        self.grasped = grasped
        self.environment = environment
        self.threshold = threshold
        self.angle_tol = angle_tol
        self._g = _model_data(grasped)
        self._e = _model_data(environment)

    def find(self, X_EG: npt.ArrayLike) -> ContactState:
        """Contact state at pose ``X_EG`` (4x4, pose of G in E's frame, metres)."""
        return _find_frames(
            self._g, self._e, self.threshold, self.angle_tol, _check_pose(X_EG)[None], naive=False
        )[0]

    def find_batch(self, X_EG_seq: Iterable[npt.ArrayLike] | npt.ArrayLike) -> list[ContactState]:
        """Contact states at each pose of ``X_EG_seq``, vectorised over the poses.

        Parameters
        ----------
        X_EG_seq : array_like, shape (N, 4, 4), or iterable of array_like, shape (4, 4)
            Poses of G in E's frame, metres.

        Returns
        -------
        list of ContactState
            One per pose, equal to :meth:`find` at that pose (up to rounding of the points
            and normals). Small models are processed in blocks of frames (each stage is one
            numpy pass over the block); large ones a few frames at a time.

        Raises
        ------
        ValueError
            A pose is not a finite 4x4 rigid transform (the message gives its index).
        """
        X = _check_poses(X_EG_seq)
        g, e = self._g, self._e
        step = max(1, _BATCH_PRIMITIVES // (g.nv + e.nv + g.ne))
        out: list[ContactState] = []
        for a in range(0, len(X), step):
            out.extend(
                _find_frames(
                    self._g, self._e, self.threshold, self.angle_tol, X[a : a + step], naive=False
                )
            )
        return out

    def find_naive(self, X_EG: npt.ArrayLike) -> ContactState:
        """Find the state as :meth:`find` does, by an all-pairs search (reference)."""
        return _find_frames(
            self._g, self._e, self.threshold, self.angle_tol, _check_pose(X_EG)[None], naive=True
        )[0]

    def find_labels(
        self,
        X_EG_seq: Iterable[npt.ArrayLike] | npt.ArrayLike,
        *,
        progress: Callable[[int, int], None] | None = None,
    ) -> tuple[IntArray, IntArray]:
        """Label the poses by the keys of their contact states, without building the states.

        Two poses get the same label iff :meth:`find_batch` gives states with the same
        ``key`` (the same element kinds and feature pairs) there. The search is that of
        :meth:`find_batch` up to whether each pair of convex pieces has a separating normal;
        the normals themselves, the contact points, the touching pairs and the element
        objects are left out (what a long demonstration needs only at one frame per state:
        ``find_batch(X[first])``).

        Parameters
        ----------
        X_EG_seq : array_like, shape (N, 4, 4)
            Poses of G in E's frame, metres.
        progress : callable, optional
            Called as ``progress(done, N)`` after each block of frames.

        Returns
        -------
        labels : ndarray of int, shape (N,)
            0, 1, ... in order of first appearance.
        first : ndarray of int, shape (number of labels,)
            The first pose of each label.

        Examples
        --------
        >>> import numpy as np
        >>> from apo.shapes import box
        >>> cube = box([0.1, 0.1, 0.1], center=[0.0, 0.0, 0.05])
        >>> finder = ContactFinder(cube, box([1.0, 1.0, 0.1], center=[0.0, 0.0, -0.05]))
        >>> X = np.stack([np.eye(4)] * 3)
        >>> X[1, 2, 3] = 0.5  # lifted
        >>> [v.tolist() for v in finder.find_labels(X)]
        [[0, 1, 0], [0, 1]]
        """
        X = _check_poses(X_EG_seq)
        return self.labels_of_sets(self._sets(X, progress), len(X))

    @property
    def block_frames(self) -> int:
        """Frames per block of :meth:`find_labels` (about ``_BATCH_PRIMITIVES`` primitives).

        The blocks start at multiples of this: :meth:`element_codes` of a slice of poses
        starting at such a multiple computes the same blocks as :meth:`find_labels` of all.
        """
        g, e = self._g, self._e
        return max(1, _BATCH_PRIMITIVES // (g.nv + e.nv + g.ne))

    def element_codes(
        self,
        X_EG_seq: Iterable[npt.ArrayLike] | npt.ArrayLike,
        *,
        progress: Callable[[int, int], None] | None = None,
    ) -> tuple[IntArray, IntArray]:
        """``(frame, code)`` of every contact element at the poses, block by block.

        What :meth:`find_labels` labels the poses by: rows sorted by frame (an index into
        the poses), then by the element's code (its kind and the two features); the rows of
        a slice of poses starting at a multiple of :attr:`block_frames`, with the frames
        moved by the slice's start, are those of the whole (:meth:`labels_of_codes` of the
        concatenated rows gives :meth:`find_labels`).
        """
        return self._codes(_check_poses(X_EG_seq), progress)

    def _codes(
        self, X: FloatArray, progress: Callable[[int, int], None] | None
    ) -> tuple[IntArray, IntArray]:
        g, e = self._g, self._e
        step = self.block_frames
        frames: list[IntArray] = []
        codes: list[IntArray] = []
        for a in range(0, len(X), step):
            f, c = _element_codes(g, e, self.threshold, self.angle_tol, X[a : a + step])
            frames.append(f + a)
            codes.append(c)
            if progress is not None:
                progress(min(a + step, len(X)), len(X))
        if not frames:
            return _EMPTY_I, _EMPTY_I
        return np.concatenate(frames), np.concatenate(codes)

    def _sets(
        self, X: FloatArray, progress: Callable[[int, int], None] | None
    ) -> Iterator[BlockSets]:
        """:func:`block_sets` of each block of ``X`` in turn (its rows dropped once keyed)."""
        g, e = self._g, self._e
        step = self.block_frames
        for a in range(0, len(X), step):
            Xb = X[a : a + step]
            yield self._keyed(_element_codes(g, e, self.threshold, self.angle_tol, Xb), len(Xb))
            if progress is not None:
                progress(min(a + step, len(X)), len(X))

    def sets_of(self, X_EG_seq: npt.ArrayLike) -> BlockSets:
        """:func:`block_sets` of a slice of poses, keyed as :meth:`find_labels` keys its blocks.

        :meth:`element_codes` of the slice, its codes as :attr:`code_type` (one type for
        every block, so that the keys of different blocks compare). For a slice starting at
        a multiple of :attr:`block_frames`, what :func:`merge_sets` needs of it.
        """
        return self._keyed(self.element_codes(X_EG_seq), int(np.shape(X_EG_seq)[0]))

    def _keyed(self, codes: tuple[IntArray, IntArray], n: int) -> BlockSets:
        return block_sets(*codes, n, self.code_type)

    @property
    def code_type(self) -> type[np.signedinteger[Any]]:
        """The narrowest integer type of every element code of the two models (int32, int64).

        The codes ``(kind * g.n_all + G primitive) * e.n_all + E primitive`` of
        :meth:`element_codes` are below ``kinds * g.n_all * e.n_all``.
        """
        bound = len(_KIND_LIST) * self._g.n_all * self._e.n_all
        return np.int32 if bound <= np.iinfo(np.int32).max else np.int64

    @staticmethod
    def labels_of_codes(frame: IntArray, code: IntArray, n: int) -> tuple[IntArray, IntArray]:
        """Labels of ``n`` poses by their sets of element codes (:meth:`element_codes`' rows).

        Returns each pose's label (0, 1, ... in order of first appearance) and the first
        pose of each label, as :meth:`find_labels`.
        """
        if n == 0:
            return _EMPTY_I, _EMPTY_I
        return _group_sets(frame, code, n)

    @staticmethod
    def labels_of_sets(blocks: Iterable[BlockSets], n: int) -> tuple[IntArray, IntArray]:
        """Labels of ``n`` poses from the :func:`block_sets` of their blocks, in order.

        The same labels and first poses as :meth:`labels_of_codes` of the blocks' rows
        concatenated (:func:`merge_sets`).
        """
        if n == 0:
            return _EMPTY_I, _EMPTY_I
        return merge_sets(blocks, n)

    # ---------------------------------------------------------------------------------------


def _broad_phase(g: _ModelData, e: _ModelData, d: float, X: FloatArray) -> IntArray:
    """Frames whose bounding boxes (G's transformed conservatively) are within ``d``."""
    R_all, t_all = X[:, :3, :3], X[:, :3, 3]
    c = 0.5 * (g.lo + g.hi)
    r = 0.5 * (g.hi - g.lo)
    cE = np.einsum("fij,j->fi", R_all, c) + t_all
    rE = np.einsum("fij,j->fi", np.abs(R_all), r)
    apart = np.any(cE - rE > e.hi + d, axis=1) | np.any(cE + rE < e.lo - d, axis=1)
    return np.flatnonzero(~apart)


def _piece_pairs(
    g: _ModelData, e: _ModelData, gcode: IntArray, ecode: IntArray
) -> tuple[IntArray, IntArray, IntArray]:
    """Work items: every pair of convex pieces of each candidate pair of features.

    Returns G's piece, E's piece and the candidate of each work item.
    """
    gs, gc = g.piece_ranges(gcode)
    es, ec = e.piece_ranges(ecode)
    n = gc * ec
    rep = np.repeat(np.arange(len(n)), n)
    o = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    return gs[rep] + o // ec[rep], es[rep] + o % ec[rep], rep


class _Work(NamedTuple):  # not a dataclass: no methods made at import
    """The candidate pairs of convex pieces of a block of frames (stages up to the cones).

    ``active`` are the frames (indices into the block) that passed the broad phase, ``R``,
    ``t`` and ``VG`` their rotations, translations and G's vertices in E; each work item
    pairs G's piece ``pg`` with E's piece ``pe`` for candidate ``rep`` at frame ``wfr``
    (index into ``active``), with the element kind and refined features of
    :func:`_classify`.
    """

    active: IntArray
    R: FloatArray
    t: FloatArray
    VG: FloatArray
    near_g: _NearF
    near_e: _NearF
    ee: tuple[IntArray, IntArray, IntArray]
    pg: IntArray
    pe: IntArray
    wfr: IntArray
    classified: tuple[IntArray, IntArray, IntArray, IntArray, IntArray]


def _work(
    g: _ModelData,
    e: _ModelData,
    d: float,
    angle_tol: float,
    X: FloatArray,
    *,
    naive: bool,
) -> _Work | None:
    """Broad phase, distance tests, candidate features and their pairs of pieces at ``X``.

    None when no frame of the block passes the broad phase.
    """
    active = np.arange(len(X)) if naive else _broad_phase(g, e, d, X)
    if len(active) == 0:
        return None
    R, t = X[active, :3, :3], X[active, :3, 3]
    limit = _DENSE_LIMIT * (_BATCH_DENSE_FACTOR if len(active) > 1 else 1)
    VG = g.V @ R.transpose(0, 2, 1) + t[:, None, :]  # G's vertices in E
    VE_G = (e.V[None, :, :] - t[:, None, :]) @ R  # E's in G
    near_g = _by_frame(
        _near_features(e, VG.reshape(-1, 3), d, naive=naive, dense_limit=limit), g.nv
    )
    near_e = _by_frame(
        _near_features(g, VE_G.reshape(-1, 3), d, naive=naive, dense_limit=limit), e.nv
    )
    ee = _edge_pairs(g, e, VG, R, t, d, naive=naive, limit=limit)
    fr, gkind, gcode, ekind, ecode = _candidates(g, e, angle_tol, near_g, near_e, ee, R)
    pg, pe, rep = _piece_pairs(g, e, gcode, ecode)
    classified = _classify(g, e, pg, pe, gkind[rep], gcode[rep], ekind[rep], ecode[rep])
    return _Work(active, R, t, VG, near_g, near_e, ee, pg, pe, fr[rep], classified)


def _find_frames(
    g: _ModelData, e: _ModelData, d: float, angle_tol: float, X: FloatArray, *, naive: bool
) -> list[ContactState]:
    """Contact states at poses ``X`` (F, 4, 4); every stage is vectorised over frames.

    Stages (:func:`_work`): broad phase (bounding boxes), distance tests (features near each
    vertex, edge pairs), candidate features, pairs of convex pieces; then the touching
    pairs, separating normals, element classification and contact points.
    """
    n_frames = len(X)
    states = [ContactState((), frozenset())] * n_frames
    w = _work(g, e, d, angle_tol, X, naive=naive)
    if w is None:
        return states
    n_act = len(w.active)
    touching = _touching(g, e, w.near_g, w.near_e, w.ee, n_act)
    count, rays, extra = _cones(g, e, angle_tol, w, naive=naive)
    kind, fa_k, fa_i, fb_k, fb_i = w.classified
    valid = (kind >= 0) & (count > 0)
    per_frame = _elements(
        g,
        e,
        tol.ray_merge_factor * angle_tol,
        (w.wfr, w.R, w.t, w.VG, n_act),
        (kind, fa_k, fa_i, fb_k, fb_i, valid),
        (count, rays, extra),
    )
    for k, f in enumerate(w.active.tolist()):
        states[f] = ContactState(per_frame[k], touching[k])
    return states


#: Pairs of convex pieces whose separating normals are found at once (:func:`_cones`): the
#: vectorised cases take about a kilobyte of working arrays a pair, and a block of frames all
#: in contact has some 6,000 pairs (docs/recognition.md, "Session 9: memory").
CONE_CHUNK = 2048


def _cones(
    g: _ModelData,
    e: _ModelData,
    angle_tol: float,
    w: _Work,
    *,
    naive: bool,
    counts_only: bool = False,
) -> tuple[IntArray, FloatArray, dict[int, FloatArray]]:
    """:func:`_cone_pairs` of the work's pairs, ``CONE_CHUNK`` pairs at a time.

    Each pair's normals are found on their own (the vectorised cases row by row, the others
    one by one), so the chunks give the same counts, rays and extra rays as all at once.
    """
    n = len(w.pg)
    if n <= CONE_CHUNK:
        return _cone_pairs(
            g, e, angle_tol, w.pg, w.pe, w.R[w.wfr], naive=naive, counts_only=counts_only
        )
    count = np.zeros(n, dtype=np.int64)
    rays = np.zeros((n, 2, 3))
    extra: dict[int, FloatArray] = {}
    for a in range(0, n, CONE_CHUNK):
        k = slice(a, a + CONE_CHUNK)
        c, r, more = _cone_pairs(
            g, e, angle_tol, w.pg[k], w.pe[k], w.R[w.wfr[k]], naive=naive, counts_only=counts_only
        )
        count[k], rays[k] = c, r
        extra.update((a + i, v) for i, v in more.items())
    return count, rays, extra


def _element_codes(
    g: _ModelData, e: _ModelData, d: float, angle_tol: float, X: FloatArray
) -> tuple[IntArray, IntArray]:
    """(frame, element code) of every element at poses ``X``, sorted, without duplicates.

    The code ``(kind * g.n_all + G primitive) * e.n_all + E primitive`` stands for the
    element's key; the elements are those of :func:`_find_frames`, found by the same stages
    up to whether each pair of pieces has a separating normal (``count > 0``), without the
    rays themselves, the contact points and the touching pairs.
    """
    w = _work(g, e, d, angle_tol, X, naive=False)
    if w is None:
        return _EMPTY_I, _EMPTY_I
    count, _, _ = _cones(g, e, angle_tol, w, naive=False, counts_only=True)
    kind, fa_k, fa_i, fb_k, fb_i = w.classified
    ok = np.flatnonzero((kind >= 0) & (count > 0))
    code = (kind[ok] * g.n_all + g.offset[fa_k[ok]] + fa_i[ok]) * e.n_all
    code += e.offset[fb_k[ok]] + fb_i[ok]
    frame = w.active[w.wfr[ok]]
    order = np.lexsort((code, frame))
    frame, code = frame[order], code[order]
    new = np.ones(len(code), dtype=bool)
    new[1:] = (frame[1:] != frame[:-1]) | (code[1:] != code[:-1])
    return frame[new], code[new]


def _group_sets(frame: IntArray, code: IntArray, n: int) -> tuple[IntArray, IntArray]:
    """Label ``n`` frames by their sets of codes (rows sorted by frame, then code).

    Returns each frame's label (0, 1, ... in order of first appearance) and the first frame
    of each label. The codes keyed as int32 where they all fit.
    """
    i32 = np.iinfo(np.int32)
    narrow = not len(code) or (int(code.min()) >= i32.min and int(code.max()) <= i32.max)
    return merge_sets([block_sets(frame, code, n, np.int32 if narrow else np.int64)], n)


class BlockSets(NamedTuple):
    """The sets of element codes of a block of frames (:func:`block_sets`).

    ``keys``: each distinct set once, as the bytes of its sorted codes (int64), in order
    of first appearance in the block; ``local``: each frame's index into ``keys`` (int32).
    """

    keys: list[bytes]
    local: npt.NDArray[np.int32]


def block_sets(
    frame: IntArray, code: IntArray, n: int, code_type: type[np.signedinteger[Any]] = np.int64
) -> BlockSets:
    """Key the ``n`` frames of a block by their sets of codes (rows sorted by frame, then code).

    Each frame's codes (a run of the sorted rows) make one bytes key, of the codes as
    ``code_type`` (one type for every block, so that the keys of different blocks compare;
    :attr:`ContactFinder.code_type`): the same grouping as its row of codes padded to the
    widest frame, without an ``(n, width)`` matrix. What a block's rows (16 bytes an
    element, some 20 elements a frame in contact) come down to: 4 bytes a frame and the
    block's distinct sets.
    """
    cnt = np.bincount(frame, minlength=n)
    size = np.dtype(code_type).itemsize
    buf = np.asarray(code).astype(code_type).tobytes()
    ends = (np.cumsum(cnt) * size).tolist()
    index: dict[bytes, int] = {}
    local = np.fromiter(
        (
            index.setdefault(buf[a:b], len(index))
            for a, b in zip([0, *ends[:-1]], ends, strict=True)
        ),
        np.int32,
        count=n,
    )
    return BlockSets(list(index), local)


def merge_sets(blocks: Iterable[BlockSets], n: int) -> tuple[IntArray, IntArray]:
    """Labels of ``n`` frames whose consecutive blocks have the sets ``blocks``, in order.

    Returns each frame's label (0, 1, ... in order of first appearance) and the first frame
    of each label. A block's keys come in order of first appearance within the block, so
    numbering them in block order numbers the sets in order of first appearance overall.
    """
    index: dict[bytes, int] = {}
    labels = np.empty(n, dtype=np.int64)
    a = 0
    for keys, local in blocks:
        glob = np.fromiter((index.setdefault(k, len(index)) for k in keys), np.int64, len(keys))
        labels[a : a + len(local)] = glob[local]
        a += len(local)
    if a != n:
        raise ValueError(f"the blocks' sets cover {a} frames, not {n}")
    first = np.full(len(index), n, dtype=np.int64)
    np.minimum.at(first, labels, np.arange(n, dtype=np.int64))
    return labels, first


def find_contacts(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG: npt.ArrayLike,
    *,
    threshold: float | None = None,
    angle_tol: float | None = None,
) -> ContactState:
    """Contact state between G at pose ``X_EG`` and E (paper 4.3.1).

    Parameters
    ----------
    grasped : Polyhedron
        Grasped object G, model frame G, metres.
    environment : Polyhedron
        Environment object E, model frame E, metres.
    X_EG : array_like, shape (4, 4)
        Pose of G in E's frame (``p_E = X_EG @ p_G``), metres.
    threshold : float, optional
        Two features closer than this (metres) touch. Default :func:`default_threshold`
        (``1e-3`` of the smaller model's bounding diagonal), meant for exact poses; observed
        poses need a few millimetres.
    angle_tol : float, optional
        Angular tolerance (rad) of the normal-cone intersection and of the parallel-edge
        test; default :func:`default_angle_tolerance`.

    Returns
    -------
    ContactState
        Elements sorted by key (points and normals in E, metres) and every touching
        feature pair.

    Raises
    ------
    ValueError
        ``X_EG`` is not a finite 4x4 rigid transform, or a bad threshold or tolerance.

    See Also
    --------
    ContactFinder : the same with per-model data reused over many poses.
    find_contacts_naive : all-pairs reference search.

    Notes
    -----
    Candidates: each vertex of G within ``threshold`` of E's surface, each vertex of E within
    ``threshold`` of G's surface, and each non-parallel pair of edges within ``threshold``
    whose endpoints do not touch the other edge. Each is snapped to the lowest-dimensional
    feature of each object within the threshold; the local solids there are split into
    convex pieces and each pair of touching pieces gives an element whose separating normals
    are the extreme rays of ``T_G* ∩ (-T_E*)`` (``docs/contacts.md``).
    """
    finder = ContactFinder(grasped, environment, threshold=threshold, angle_tol=angle_tol)
    return finder.find(X_EG)


def find_contacts_batch(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG_seq: Iterable[npt.ArrayLike] | npt.ArrayLike,
    *,
    threshold: float | None = None,
    angle_tol: float | None = None,
) -> list[ContactState]:
    """Contact states at each pose of ``X_EG_seq`` (N x 4 x 4 poses of G in E, metres).

    Same parameters and result as :func:`find_contacts`, one state per pose; the per-model
    data (k-d trees, local cones) is computed once and the search is vectorised over the
    poses (:meth:`ContactFinder.find_batch`).
    """
    finder = ContactFinder(grasped, environment, threshold=threshold, angle_tol=angle_tol)
    return finder.find_batch(X_EG_seq)


def find_contacts_naive(
    grasped: Polyhedron,
    environment: Polyhedron,
    X_EG: npt.ArrayLike,
    *,
    threshold: float | None = None,
    angle_tol: float | None = None,
) -> ContactState:
    """Find contacts as :func:`find_contacts` does, by a plain all-pairs search.

    Every vertex is measured against every face polygon of the other model
    (:func:`apo.geometry.point_face_distance`), every edge and vertex, and every edge against
    every edge, with no broad phase, and every pair of convex pieces goes through the scalar
    cone intersection (the fast search solves the common cases vectorised); used to test and
    benchmark the fast search.
    """
    finder = ContactFinder(grasped, environment, threshold=threshold, angle_tol=angle_tol)
    return finder.find_naive(X_EG)


def contact_points(state: ContactState) -> list[ContactPoint]:
    """Return copies of the elements of ``state`` as plain DOF-analysis contact points.

    Every :class:`ContactElement` already is an :class:`apo.dof.ContactPoint` and can be
    given to :func:`apo.dof.analyze` as it is; this returns independent copies without the
    feature ids (frame E, metres).

    Parameters
    ----------
    state : ContactState
        A contact state.

    Returns
    -------
    list of apo.dof.ContactPoint
        One per element, in the state's order, with its point and separating normals.
    """
    return [ContactPoint(el.point.copy(), el.normals.copy()) for el in state.elements]
