"""Pose correction of observed frames under contact states (paper 4.3.1)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from apo.constants import tol
from apo.contact import ContactElement, ContactState
from apo.correction import ContactConstraints
from apo.geometry import Polyhedron
from apo.recognition.contacts import distinct_poses
from apo.recognition.types import BoolArray, FloatArray, IntArray

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
) -> Corrected:
    """Correct every pose ``X[t]`` under ``states[labels[t]]``, batched by state.

    Frames of one state whose observed poses are equal bit for bit are corrected once (the
    correction of each frame is a function of its pose and the elements alone: the batch
    iterates every frame on its own), as the contact search does
    (:func:`apo.recognition.contacts.distinct_poses`), among ``DEDUPE_FRAMES`` frames at a
    time (a repeat further on is corrected again, to the same pose).
    """
    n = X.shape[0]
    Xc = X.copy()
    before = np.zeros(n)
    after = np.zeros(n)
    conv = np.ones(n, dtype=bool)
    for k in np.unique(labels):
        elements = states[int(k)].elements
        if not elements:
            continue
        of_k = np.flatnonzero(labels == k)
        for start in range(0, len(of_k), DEDUPE_FRAMES):
            frames = of_k[start : start + DEDUPE_FRAMES]
            first, inverse = distinct_poses(X[frames])
            Xk, b, a, c = _correct_in_blocks(
                grasped, environment, X[frames[first]], elements, threshold
            )
            Xc[frames], before[frames], after[frames], conv[frames] = (
                Xk[inverse],
                b[inverse],
                a[inverse],
                c[inverse],
            )
    return Xc, before, after, conv


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
