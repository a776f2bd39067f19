"""Data passed between the stages of recognition (``docs/recognition.md``).

Everything is in metres, in the environment frame E; poses ``X_EG`` are 4x4 matrices of
the grasped object G in E.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from apo.typing import BoolArray as BoolArray  # re-exported for the recognition stages
from apo.typing import FloatArray as FloatArray
from apo.typing import IntArray as IntArray

if TYPE_CHECKING:
    from apo.contact import ContactFinder, ContactState
    from apo.geometry import Polyhedron
    from apo.recognition.noise import NoiseEstimate
    from apo.task import TaskModel

ElementKey = tuple[str, tuple[str, int], tuple[str, int]]
"""``ContactElement.key``: (kind, grasped feature, environment feature)."""
StateKey = frozenset[ElementKey]
"""``ContactState.key``: the set of its element keys."""
FeaturePair = tuple[tuple[str, int], tuple[str, int]]
Progress = Callable[[int, int], None]
Six = tuple[int, int, int, int, int, int]


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
    same : float
        Added to a change between two states with the same DOF numbers (every one of the
        six per space): such a change has no sub-skill and, under noise, is mostly a
        contact seen with more or fewer elements than it has.
    reach : float
        A bridging candidate (a state between two observed ones, observed at no frame) is
        kept only if its elements are within ``reach * theta`` at the observed pose it is
        corrected from, and the correction moves no vertex more than twice that distance
        plus ``theta`` (it did not converge to a distant solution).
    enclosed : float
        Per frame of the free state where that frame and its neighbours are all observed in
        contact (G seen near E throughout): a free run between two contacts needs G seen
        away from E at some frame, not only contacts at the edge of the threshold.
    """

    claim: float = 1.0
    miss: float = 4.0
    switch: float = 1.5
    fail: float = 6.0
    jump: float = 25.0
    window: int = 10
    reach: float = 3.0
    same: float = 6.0
    enclosed: float = 1.0


@dataclass(frozen=True)
class Scene:
    """What every stage needs: the two models, the observed poses and the thresholds.

    Attributes
    ----------
    grasped, environment : Polyhedron
        Models G (moving) and E (fixed), metres, own frames.
    X : ndarray, shape (N, 4, 4)
        Observed poses of G in E, metres.
    finder : ContactFinder
        Contact finder at the recognition threshold ``theta``.
    exact : ContactFinder
        Contact finder at its own tight default threshold: which pairs really touch at a
        corrected pose.
    costs : SegmentationCosts
    outliers : ndarray of bool, shape (N,)
        Frames whose pose is an outlier (``apo.recognition.noise``): ignored by the
        segmentation (every state explains them equally).
    scale : float
        Unit of the costs' distances and of the correction's and rescue's reach (metres;
        ``unit``); 0: the threshold.
    """

    grasped: Polyhedron
    environment: Polyhedron
    X: FloatArray
    finder: ContactFinder
    exact: ContactFinder
    costs: SegmentationCosts
    outliers: BoolArray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    scale: float = 0.0

    def __post_init__(self) -> None:
        if len(self.outliers) != len(self.X):
            object.__setattr__(self, "outliers", np.zeros(len(self.X), dtype=bool))

    @property
    def theta(self) -> float:
        """The recognition threshold (metres)."""
        return float(self.finder.threshold)

    @property
    def unit(self) -> float:
        """Distance unit of the costs and of the correction's reach (metres).

        The threshold, or the larger ``scale`` when the threshold comes from a small noise
        (``docs/recognition.md``): a threshold near the noise finds the contacts, but a
        distance of a few deviations must still look small to the costs.
        """
        return max(self.theta, float(self.scale))

    @property
    def n(self) -> int:
        """Number of frames."""
        return int(self.X.shape[0])


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
    """Result of :func:`apo.recognition.recognize_frames`: the task and per-frame diagnostics.

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
        Largest contact distance (metres) of the chosen state's contacts before and after
        the pose correction of each frame.
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
    costs : ndarray, shape (N, U)
        Cost of each candidate the segmentation could choose (the analysed ones,
        ``cost_columns``) at each frame (``docs/recognition.md``).
    cost_columns : ndarray of int, shape (U,)
        Index into ``keys`` of each column of ``costs``, ascending.
    timings : dict
        Seconds spent in each stage.
    X_observed : ndarray, shape (N, 4, 4)
        The observed poses of G in E (metres), as given.
    X_corrected : ndarray, shape (N, 4, 4)
        Each frame's pose corrected under its chosen state (metres); the observed pose
        where the correction did not converge.
    noise : NoiseEstimate or None
        The pose noise used (estimated from the poses, or given).
    outliers : ndarray of bool, shape (N,)
        Frames taken as outliers (ignored by the segmentation).
    observed_states : list of ContactState
        Each distinct observed state as found at its first frame (``observed`` indexes it).
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
    costs: FloatArray
    cost_columns: IntArray
    timings: dict[str, float] = field(default_factory=dict)
    X_observed: FloatArray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    X_corrected: FloatArray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    noise: NoiseEstimate | None = None
    outliers: BoolArray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    observed_states: list[ContactState] = field(default_factory=list)

    @property
    def emission(self) -> FloatArray:
        """Cost of each candidate at each frame, shape (N, K), ``inf`` where not analysed.

        Made from ``costs`` on each access (``N x K`` floats: not kept).
        """
        out = np.full((len(self.costs), len(self.keys)), np.inf)
        out[:, self.cost_columns] = self.costs
        return out

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
