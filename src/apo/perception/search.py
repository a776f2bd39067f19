"""Global pose search without an initial guess: many candidates, one batched ICP.

:func:`apo.perception.register.initialise` places a model at many candidate orientations
about the observed points and keeps the most confident result. Running one ICP per
candidate (84 of them, Open3D's k-d tree rebuilt at every call) took 2 to 5 s per object;
here every candidate is advanced at once (:func:`batch_icp`): one k-d tree query for all
candidates' points per iteration (the model's samples indexed once, ``scipy.spatial.cKDTree``)
and one batched 6x6 solve. The search is coarse to fine: all candidates on few points and
the sparse samples, then the best distinct ones on more points, then the few most confident
(scored on the depth image: :func:`apo.perception.register.surface_check`) on all points
and the dense samples.

The ICP is the point-to-plane ICP of :func:`apo.perception.register.register` (observed
points to model samples with the model's exact normals, closest point within a
correspondence distance, a robust kernel: Tukey's biweight by default), in numpy.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from apo.perception.projective import tukey_weights
from apo.typing import FloatArray

if TYPE_CHECKING:
    from concurrent.futures import Executor

    from apo.perception.register import ModelCloud

__all__ = ["batch_icp", "centres", "distinct_poses", "inlier_fraction", "voxel_subsample"]


PARALLEL_QUERY = 4000
"""k-d tree queries of at least this many points run on every core (``workers=-1``: the
same results; measured on 40,000 samples: 20,000 points 83 -> 42 ms wall, CPU unchanged;
1,500 points: no faster, 50 % more CPU). 4,000 since session 6 (10,000 before): the last
stages of a search query 3 candidates x 3,000 points against the environment's 200,000
dense samples (8.5 ms of CPU a query); the two searches of dev variant seed 203 replayed,
load 6.4: 4.15 -> 3.2-3.5 s wall, 1.34-1.56 -> 1.41-1.47 s CPU, the same poses."""


def _workers(Q: FloatArray) -> int:
    """Return the ``workers`` of a k-d tree query of the points ``Q`` (..., 3)."""
    return -1 if Q.size >= 3 * PARALLEL_QUERY else 1


def _weights(r: FloatArray, loss: str, scale: float) -> FloatArray:
    """IRLS weights of residuals ``r`` for the robust kernel (Open3D's definitions)."""
    if loss == "tukey":
        return tukey_weights(r, scale)
    if loss == "huber":
        a = np.abs(r)
        return np.where(a <= scale, 1.0, scale / np.maximum(a, 1e-300))
    if loss == "l2":
        return np.ones_like(r)
    raise ValueError(f"unknown loss {loss!r}; expected 'tukey', 'huber' or 'l2'")


def _rotations(w: FloatArray) -> FloatArray:
    """Rotation matrices (K, 3, 3) of rotation vectors ``w`` (K, 3) (Rodrigues)."""
    theta = np.linalg.norm(w, axis=1)
    k = w / np.maximum(theta, 1e-300)[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(theta)[:, None, None], (1.0 - np.cos(theta))[:, None, None]
    return np.asarray(np.eye(3)[None] + s * K + c * (K @ K), dtype=np.float64)


def _jacobians(Q: FloatArray, n: FloatArray) -> FloatArray:
    """Return ``[Q x n, n]`` (..., 6): ``np.cross``'s numbers, without its axis handling."""
    J = np.empty((*Q.shape[:-1], 6))
    J[..., 0] = Q[..., 1] * n[..., 2] - Q[..., 2] * n[..., 1]
    J[..., 1] = Q[..., 2] * n[..., 0] - Q[..., 0] * n[..., 2]
    J[..., 2] = Q[..., 0] * n[..., 1] - Q[..., 1] * n[..., 0]
    J[..., 3:] = n
    return J


def batch_icp(
    points: npt.ArrayLike,
    model: ModelCloud,
    T: npt.ArrayLike,
    *,
    distance: float,
    scale: float,
    iterations: int = 12,
    dense: bool = False,
    loss: str = "tukey",
    tol: float = 1e-7,
    pool: Executor | None = None,
) -> FloatArray:
    """Advance K point-to-plane ICPs of the same points at once; return the K transforms.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Observed points, camera frame, metres.
    model : ModelCloud
        The model (its sparse samples, or the dense ones with ``dense``).
    T : ndarray, shape (K, 4, 4)
        Transforms from the camera frame into the model frame (``inv(X_CM)``), one per
        candidate.
    distance : float
        Correspondence distance, metres (closest sample within it).
    scale : float
        Scale of the robust kernel, metres.
    iterations : int, optional
        Iterations (fewer when every candidate has converged: steps below ``tol``).
    dense : bool, optional
        Register to the dense samples.
    loss : {"tukey", "huber", "l2"}, optional
        Robust kernel.
    tol : float, optional
        Convergence: largest step (radians + metres) below this.
    pool : Executor, optional
        Half the candidates are advanced on a thread of it meanwhile (the k-d queries and
        numpy's work on the candidates' arrays release the GIL): the same transforms, bit
        for bit (each candidate's ICP is its own: its steps, its convergence).

    Returns
    -------
    ndarray, shape (K, 4, 4)
    """
    P = np.asarray(points, dtype=np.float64)
    out = np.array(T, dtype=np.float64, copy=True).reshape(-1, 4, 4)
    tree = model.tree(dense)  # built here, never by two threads
    kw: dict[str, Any] = {"distance": distance, "scale": scale, "iterations": iterations,
                          "dense": dense, "loss": loss, "tol": tol}  # fmt: skip
    if pool is not None and len(out) >= 2:
        half = (len(out) + 1) // 2
        rest = pool.submit(batch_icp, P, model, out[half:], **kw)
        return np.concatenate([batch_icp(P, model, out[:half], **kw), rest.result()])
    samples = model.dense_points if dense else model.points
    normals = model.dense_normals if dense else model.normals
    active = np.arange(len(out))
    for _ in range(iterations):
        if len(active) == 0 or len(P) < 3:
            break
        Ta = out[active]
        Q = np.einsum("kij,nj->kni", Ta[:, :3, :3], P) + Ta[:, None, :3, 3]
        d, idx = tree.query(Q.reshape(-1, 3), distance_upper_bound=distance, workers=_workers(Q))
        ok = np.isfinite(d).reshape(Q.shape[:2])
        idx = np.minimum(idx, len(samples) - 1).reshape(Q.shape[:2])
        n = normals[idx]
        r = np.einsum("kni,kni->kn", Q - samples[idx], n)
        w = _weights(r, loss, scale) * ok
        J = _jacobians(Q, n)  # d r / d [omega; v]
        Jw = np.transpose(J * w[..., None], (0, 2, 1))
        A = Jw @ J
        b = -(Jw @ r[..., None])[..., 0]
        A += np.eye(6)[None] * (1e-12 + 1e-9 * np.trace(A, axis1=1, axis2=2))[:, None, None]
        x = np.linalg.solve(A, b[..., None])[..., 0]
        x[~np.isfinite(x).all(axis=1)] = 0.0
        step = np.zeros((len(active), 4, 4))
        step[:, :3, :3] = _rotations(x[:, :3])
        step[:, :3, 3] = x[:, 3:]
        step[:, 3, 3] = 1.0
        out[active] = step @ Ta
        moving = np.abs(x).sum(axis=1) > tol
        active = active[moving]
    return out


def inlier_fraction(
    points: npt.ArrayLike, model: ModelCloud, T: npt.ArrayLike, inlier_distance: float
) -> FloatArray:
    """Share of the points within ``inlier_distance`` of the sparse samples, per transform.

    A cheap ranking of candidates (the sparse samples are about ``model.spacing`` * a few
    apart, so the distance allowed to the nearest sample is widened by their spacing).
    """
    P = np.asarray(points, dtype=np.float64)
    Ts = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
    Q = np.einsum("kij,nj->kni", Ts[:, :3, :3], P) + Ts[:, None, :3, 3]
    spacing = model.spacing * float(np.sqrt(len(model.dense_points) / len(model.points)))
    d, idx = model.tree(dense=False).query(
        Q.reshape(-1, 3), distance_upper_bound=4 * spacing, workers=_workers(Q)
    )
    ok = np.isfinite(d).reshape(Q.shape[:2])
    idx = np.minimum(idx, len(model.points) - 1).reshape(Q.shape[:2])
    r = np.abs(np.einsum("kni,kni->kn", Q - model.points[idx], model.normals[idx]))
    return np.asarray((ok & (r <= inlier_distance)).mean(axis=1), dtype=np.float64)


def voxel_subsample(points: npt.ArrayLike, count: int, rng: np.random.Generator) -> FloatArray:
    """At most ``count`` points spread evenly over the cloud (one per voxel, then random).

    The voxel edge is chosen from the cloud's extent so that about ``count`` voxels are
    occupied: dense patches (near the camera, facing it) do not outweigh sparse ones.
    """
    P = np.asarray(points, dtype=np.float64)
    if len(P) <= count:
        return P
    lo, hi = P.min(0), P.max(0)
    edge = float(np.sqrt(np.prod(np.sort(hi - lo)[1:]) / count)) or 1e-3
    for _ in range(8):
        keys = np.floor((P - lo) / edge).astype(np.int64)
        _, first = np.unique(keys, axis=0, return_index=True)
        if len(first) >= count:
            break
        edge *= 0.7
    pick = first if len(first) <= count else rng.choice(first, count, replace=False)
    return np.asarray(P[np.sort(pick)])


def distinct_poses(
    T: npt.ArrayLike,
    model: ModelCloud,
    symmetry_rotations: npt.ArrayLike | None,
    *,
    limit: int,
    angle: float = 0.15,
) -> list[int]:
    """Return the indices of the first ``limit`` transforms (in order) showing distinct poses.

    ``T`` (K, 4, 4) map the camera frame into the model's (``inv(X_CM)``); two show the same
    pose when the model's centroid is within a twentieth of its diameter and the rotations
    are within ``angle`` radians up to a symmetry (many candidates of a search converge to
    the same pose; it is scored once).
    """
    Ts = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
    R = np.transpose(Ts[:, :3, :3], (0, 2, 1))  # rotations of X_CM
    centres = np.einsum("kij,kj->ki", R, model.centroid[None] - Ts[:, :3, 3])
    S = np.eye(3)[None] if symmetry_rotations is None else np.asarray(symmetry_rotations)
    S = S.reshape(-1, 3, 3)
    limit_trace = 1.0 + 2.0 * np.cos(angle)
    kept: list[int] = []
    for k in range(len(Ts)):
        if len(kept) >= limit:
            break
        if kept:
            near = np.linalg.norm(centres[kept] - centres[k], axis=1) < model.diameter / 20
            # trace(R_j^T R_k S) over the twins S: above the limit when within ``angle``
            tr = np.einsum("jab,ac,scb->js", R[kept], R[k], S).max(axis=1)
            if np.any(near & (tr > limit_trace)):
                continue
        kept.append(k)
    return kept


def centres(points: npt.ArrayLike, diameter: float, *, limit: int = 4) -> list[FloatArray]:
    """Return where to search for a model of ``diameter`` in ``points``: one or more centres.

    The points' centroid when they are about the model's size (90 % within 0.6 diameters);
    else the centres of the densest clusters at the model's scale (cells of half a diameter
    holding at least 5 % of the points, each moved to the mean of the points within half a
    diameter, no two within half a diameter), densest first, at most ``limit``.
    """
    P = np.asarray(points, dtype=np.float64)
    c = P.mean(axis=0)
    if len(P) == 0 or np.percentile(np.linalg.norm(P - c, axis=1), 90) <= 0.6 * diameter:
        return [c]
    edge = diameter / 2
    _, inverse, counts = np.unique(
        np.floor(P / edge).astype(np.int64), axis=0, return_inverse=True, return_counts=True
    )
    inverse = inverse.ravel()
    out: list[FloatArray] = []
    for cell in np.argsort(-counts, kind="stable"):
        if counts[cell] < 0.05 * len(P) or len(out) >= limit:
            break
        m = P[inverse == cell].mean(axis=0)
        m = P[np.linalg.norm(P - m, axis=1) <= edge].mean(axis=0)
        if all(np.linalg.norm(m - o) > edge for o in out):
            out.append(m)
    return out or [c]
