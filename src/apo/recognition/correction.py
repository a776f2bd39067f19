"""Pose correction of observed frames under contact states (paper 4.3.1)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from functools import partial

import numpy as np
import numpy.typing as npt

from apo.constants import tol
from apo.contact import ContactElement, ContactState
from apo.correction import ContactConstraints
from apo.geometry import Polyhedron
from apo.recognition.contacts import distinct_poses
from apo.recognition.types import BoolArray, FloatArray, IntArray
from apo.workers import PARALLEL_MIN_FRAMES, run_parts, shared_zeros, workers_for

Corrected = tuple[FloatArray, FloatArray, FloatArray, BoolArray]
"""Corrected poses (N, 4, 4), residuals before and after (N,), converged flags (N,)."""

__all__ = [
    "CORRECTION_MAX_ITER",
    "CORRECTION_TOL",
    "Corrected",
    "correct_by_label",
    "correct_one",
    "correct_poses",
]


#: Pose correction: iterations, and the residual (metres) below which it has converged.
CORRECTION_MAX_ITER = 12
CORRECTION_TOL = tol.correction_screening  # why it differs from tol.correction: constants


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
    X = np.array(X_EG_seq, dtype=np.float64)
    n = X.shape[0]
    if not elements:
        z = np.zeros(n)
        return X, z, z.copy(), np.ones(n, dtype=bool)
    res = ContactConstraints(grasped, environment, elements).correct(
        X, max_iter=max_iter, tol=tol, threshold=threshold
    )
    return res.X_EG, res.residual_before, res.residual_after, res.converged & ~res.flagged


def correct_by_label(
    grasped: Polyhedron,
    environment: Polyhedron,
    X: FloatArray,
    states: Sequence[ContactState],
    labels: IntArray,
    threshold: float,
    *,
    jobs: int | None = 1,
) -> Corrected:
    """Correct every pose ``X[t]`` under ``states[labels[t]]``, batched by state.

    Frames of one state whose observed poses are equal bit for bit are corrected once (the
    correction of each frame is a function of its pose and the elements alone: the batch
    iterates every frame on its own), as the contact search does
    (:func:`apo.recognition.contacts.distinct_poses`), among ``DEDUPE_FRAMES`` frames at a
    time (a repeat further on is corrected again, to the same pose).

    ``jobs`` (None: auto, :func:`apo.workers.workers_for`): processes the
    states' frames are shared among (:func:`_share`), each process writing its frames into
    arrays shared with the others; the same numbers, a pose's correction not depending on
    the other poses of its batch.
    """
    n = X.shape[0]
    k = workers_for(jobs, _distinct_to_correct(X, states, labels, k_max=jobs))
    shared = k > 1
    Xc = shared_zeros((n, 4, 4), np.float64, shared)
    Xc[...] = X
    before = shared_zeros((n,), np.float64, shared)
    after = shared_zeros((n,), np.float64, shared)
    conv = shared_zeros((n,), np.bool_, shared)
    conv[...] = True
    out = (Xc, before, after, conv)
    pieces = _share(_chunks(states, labels), k)
    correct = partial(_correct_in_blocks, grasped, environment, threshold=threshold)
    run_parts([partial(_correct_pieces, correct, X, states, labels, out, p) for p in pieces])
    return out


Piece = tuple[int, int, int, int]
"""A share of the correction: state label, first of its frames (a ``DEDUPE_FRAMES`` chunk),
and ``(i, m)``: the ``i``-th of ``m`` runs of the chunk's distinct poses."""


def _chunks(states: Sequence[ContactState], labels: IntArray) -> list[tuple[int, int, int]]:
    """(label, start, frames) of each ``DEDUPE_FRAMES`` chunk of a state with elements."""
    out: list[tuple[int, int, int]] = []
    ks, counts = np.unique(labels, return_counts=True)
    for k, count in zip(ks.tolist(), counts.tolist(), strict=True):
        if states[k].elements:
            out += [(k, a, min(DEDUPE_FRAMES, count - a)) for a in range(0, count, DEDUPE_FRAMES)]
    return out


def _share(chunks: list[tuple[int, int, int]], parts: int) -> list[list[Piece]]:
    """Share the chunks among ``parts`` processes, about equal frames each.

    One process: every chunk whole, in order (as corrected before the work was shared).
    Else a chunk of more than a share's frames is cut into runs of its distinct poses, and
    the pieces, largest first, go to the process with the fewest frames so far.
    """
    if parts <= 1:
        return [[(k, a, 0, 1) for k, a, _n in chunks]]
    target = max(1.0, sum(n for _k, _a, n in chunks) / parts)
    pieces: list[tuple[float, Piece]] = []
    for k, a, n in chunks:
        m = max(1, math.ceil(n / target))
        pieces += [(n / m, (k, a, i, m)) for i in range(m)]
    pieces.sort(key=lambda wp: -wp[0])  # stable: ties keep their order
    load = [0.0] * parts
    out: list[list[Piece]] = [[] for _ in range(parts)]
    for w, piece in pieces:
        j = load.index(min(load))
        out[j].append(piece)
        load[j] += w
    return out


def _distinct_to_correct(
    X: FloatArray, states: Sequence[ContactState], labels: IntArray, *, k_max: int | None
) -> int:
    """Distinct poses (bit for bit) among the frames whose state has elements.

    What the correction costs (exact repeats are corrected once); with ``k_max == 1``
    (one process) nothing is counted: 0.
    """
    if k_max == 1 or not len(states):
        return 0
    with_elements = np.array([bool(s.elements) for s in states], dtype=bool)
    Xs = X[with_elements[labels]]
    if len(Xs) == 0 or (k_max is None and len(Xs) < PARALLEL_MIN_FRAMES):
        return len(Xs)  # too few for auto to fork: no need to look for repeats
    return len(distinct_poses(Xs)[0])


def _correct_pieces(
    correct: Callable[[FloatArray, Sequence[ContactElement]], Corrected],
    X: FloatArray,
    states: Sequence[ContactState],
    labels: IntArray,
    out: Corrected,
    pieces: list[Piece],
) -> None:
    """Correct the frames of ``pieces`` (:data:`Piece`) by ``correct``, writing into ``out``.

    A piece's frames are reduced to their distinct poses; the ``i``-th of ``m`` runs of
    them is corrected, and the frames whose pose is one of those are written.
    """
    Xc, before, after, conv = out
    for k, start, i, m in pieces:
        frames = np.flatnonzero(labels == k)[start : start + DEDUPE_FRAMES]
        first, inverse = distinct_poses(X[frames])
        lo, hi = len(first) * i // m, len(first) * (i + 1) // m
        if hi <= lo:
            continue
        Xk, b, a, c = correct(X[frames[first[lo:hi]]], states[k].elements)
        if m > 1:  # the frames whose pose is one of this run's
            mine = (inverse >= lo) & (inverse < hi)
            frames, inverse = frames[mine], inverse[mine] - lo
        Xc[frames], before[frames], after[frames], conv[frames] = (
            Xk[inverse],
            b[inverse],
            a[inverse],
            c[inverse],
        )


#: Frames of one state searched for exact repeats at a time (:func:`correct_by_label`): the
#: working memory of the search is of this many frames, whatever the demonstration's length.
DEDUPE_FRAMES = 2048


#: Poses corrected in one batch at most: the batch's working arrays (Jacobians, SVDs) are
#: this many times the elements' rows, whatever the length of the demonstration.
CORRECTION_BLOCK = 256


def _correct_in_blocks(
    grasped: Polyhedron,
    environment: Polyhedron,
    X: FloatArray,
    elements: Sequence[ContactElement],
    threshold: float,
) -> Corrected:
    """:func:`correct_poses` over blocks of ``CORRECTION_BLOCK`` poses (each pose on its own)."""
    parts = [
        correct_poses(grasped, environment, X[a : a + CORRECTION_BLOCK], elements,
                      threshold=threshold)
        for a in range(0, len(X), CORRECTION_BLOCK)
    ]  # fmt: skip
    Xk, b, a, c = (np.concatenate(v) for v in zip(*parts, strict=True))
    return Xk, b, a, c


def correct_one(
    grasped: Polyhedron,
    environment: Polyhedron,
    X: FloatArray,
    state: ContactState,
    threshold: float,
) -> tuple[FloatArray, float, float, bool]:
    """Correct one pose under ``state``; return X, residual before, after, converged."""
    Xc, b, a, c = correct_poses(grasped, environment, X[None], state.elements, threshold=threshold)
    return Xc[0], float(b[0]), float(a[0]), bool(c[0])
