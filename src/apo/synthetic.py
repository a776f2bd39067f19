"""Scripted demonstrations with known ground truth (pure numpy, seeded noise, no I/O).

Each builder returns a :class:`SyntheticDemo`: two polyhedra, the true pose of the grasped
object G in the environment frame E at every frame (computed analytically, so every scripted
contact holds to ~1e-12 m), the true contact state of every frame, and the expected DOF
numbers, sub-skills and critical transitions written by hand from the paper's rules
(docs/theory.md "Sub-skills"; ``docs/synthetic.md`` gives the reasoning). :func:`add_noise` makes
observed poses from the true ones (Gaussian pose noise, outliers, dropped frames; seeded).

Demonstrations:

- :func:`peg_in_hole_2d` -- the paper's Fig. 21 peg insertion: a T-peg into a U-slot in a
  vertical plane (states A-H of Fig. 25, two of them singular, one seen in a single frame);
- :func:`square_peg_in_hole` -- a square peg set down beside a square pocket, lifted, and
  lowered straight in (a singular state at the rim in one frame);
- :func:`block_on_table_to_corner` -- a block lowered onto the floor of a tray with two
  walls, slid against one wall, then into the corner;
- :func:`block_tipping` -- a block lowered onto one bottom edge and tipped about it until
  its face lands (rotational push-to).

Units: metres, radians, seconds; poses are 4x4 ``X_EG`` (``p_E = X_EG @ p_G``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from apo.contact import ContactFinder, Feature
from apo.geometry import Polyhedron, polyhedron_from_triangles
from apo.shapes import (
    block_with_square_hole,
    box,
    prism,
    t_peg,
    triangles_from_polygons,
    u_block,
)
from apo.spatial import matrix_from_axis_angle
from apo.typing import BoolArray, FloatArray, IntArray

StateKey = frozenset[tuple[str, Feature, Feature]]
SubSkill = tuple[str, str, str | None]
"""``(kind, space, type)``: kind ``"push_to"``, ``"release"`` or ``"slide"``; space
``"translation"`` or ``"rotation"``; type ``"I"``/``"II"`` for a rotational push-to, else None."""

__all__ = [
    "ExpectedTransition",
    "SubSkill",
    "SyntheticDemo",
    "TrueState",
    "add_noise",
    "all_demos",
    "block_on_table_to_corner",
    "block_tipping",
    "corner_tray",
    "peg_in_hole_2d",
    "square_peg_in_hole",
]

PUSH_T: SubSkill = ("push_to", "translation", None)
PUSH_R1: SubSkill = ("push_to", "rotation", "I")
RELEASE_T: SubSkill = ("release", "translation", None)
RELEASE_R: SubSkill = ("release", "rotation", None)
SLIDE_T: SubSkill = ("slide", "translation", None)
SLIDE_R: SubSkill = ("slide", "rotation", None)


# --------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrueState:
    """A true contact state of a scripted demonstration.

    Attributes
    ----------
    name : str
        Short name ("A", "B", ...; the paper's letters for :func:`peg_in_hole_2d`).
    description : str
        What touches what.
    kinds : Mapping[str, int]
        Expected element kinds and counts (``{"VE": 2}``), derived by hand.
    singular : bool
        Expected: some element has more than one separating normal.
    fig25 : tuple of 8 int
        Expected DOF numbers as the paper's Fig. 25 prints them (translation M, D, C,
        rotation M, D, C -- singular variants in a singular state -- translation and rotation
        restraining), derived by hand.
    reason : str
        One line of reasoning for ``kinds`` and ``fig25``.
    key : frozenset
        Element keys (kind, grasped feature, environment feature) that
        :class:`apo.contact.ContactFinder` (default tight threshold) finds at the exact pose
        of the state's middle frame.
    """

    name: str
    description: str
    kinds: Mapping[str, int]
    singular: bool
    fig25: tuple[int, int, int, int, int, int, int, int]
    reason: str
    key: StateKey = field(default_factory=frozenset)


@dataclass(frozen=True)
class ExpectedTransition:
    """Expected sub-skills of one state transition, written by hand from the paper's rules.

    Attributes
    ----------
    source, target : int
        Indices into ``SyntheticDemo.true_states``.
    subskills : tuple of SubSkill
        ``(kind, space, type)`` tuples, translation first; empty when the transition has
        no sub-skill of its own.
    critical : bool
        The transition contains SM -> C or SD -> C (paper 3.5).
    reason : str
        One line of reasoning (the DOF changes and the rule applied).
    """

    source: int
    target: int
    subskills: tuple[SubSkill, ...]
    critical: bool
    reason: str


@dataclass(frozen=True)
class SyntheticDemo:
    """A scripted demonstration with its ground truth.

    Attributes
    ----------
    name : str
        Builder name.
    grasped : Polyhedron
        Grasped object G (model frame G, metres).
    environment : Polyhedron
        Environment object E (model frame E, metres).
    times : ndarray, shape (N,)
        Frame times, seconds, strictly increasing.
    X_EG : ndarray, shape (N, 4, 4)
        Observed poses of G in E, metres (equal to ``X_EG_true`` until :func:`add_noise`).
    X_EG_true : ndarray, shape (N, 4, 4)
        True poses of G in E, metres; every scripted contact holds exactly.
    labels : ndarray of int, shape (N,)
        True state of each frame, an index into ``true_states``.
    true_states : tuple of TrueState
        The distinct true states (a state revisited later keeps its index).
    expected_subskills : tuple of ExpectedTransition
        One per change of ``labels`` between consecutive segments, in order.
    frame_ids : ndarray of int, shape (N,)
        Index of each frame in the noise-free demonstration (dropped frames leave gaps).
    outliers : ndarray of bool, shape (N,)
        Frames whose observed pose is an outlier.
    meta : Mapping[str, Any]
        Units, geometry parameters, phase names per frame, the margin kept from unscripted
        contacts, and the noise applied (``meta["noise"]``, a list of parameter dicts).
    """

    name: str
    grasped: Polyhedron
    environment: Polyhedron
    times: FloatArray
    X_EG: FloatArray
    X_EG_true: FloatArray
    labels: IntArray
    true_states: tuple[TrueState, ...]
    expected_subskills: tuple[ExpectedTransition, ...]
    frame_ids: IntArray
    outliers: BoolArray
    meta: Mapping[str, Any]

    def __len__(self) -> int:
        return int(self.times.shape[0])

    def segments(self) -> list[tuple[int, int, int]]:
        """Return the runs of equal labels as ``(state, start, stop)`` (stop exclusive)."""
        lab = self.labels
        cut = np.flatnonzero(np.diff(lab)) + 1
        starts = np.concatenate([[0], cut]).astype(int).tolist()
        stops = np.concatenate([cut, [len(lab)]]).astype(int).tolist()
        return [(int(lab[a]), a, b) for a, b in zip(starts, stops, strict=True)]

    @property
    def state_sequence(self) -> list[str]:
        """Names of the true states in the order they are visited."""
        return [self.true_states[s].name for s, _, _ in self.segments()]


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Phase:
    name: str
    state: int
    path: Callable[[float], FloatArray]  # u in [0, 1] -> X_EG
    weight: float = 1.0
    frames: int | None = None  # fixed number of frames (short states)


def _pose(R: FloatArray, t: npt.ArrayLike) -> FloatArray:
    X = np.eye(4)
    X[:3, :3] = R
    X[:3, 3] = np.asarray(t, dtype=np.float64)
    return X


def _rz(theta: float) -> FloatArray:
    return matrix_from_axis_angle([0.0, 0.0, 1.0], theta)


def _lerp(a: float, b: float, u: float) -> float:
    return a + (b - a) * u


def _allocate(n_frames: int, phases: Sequence[_Phase], name: str) -> list[int]:
    """Frames per phase: fixed ones as given, the rest by weight, at least 2 each."""
    fixed = sum(p.frames for p in phases if p.frames is not None)
    free = [p for p in phases if p.frames is None]
    rest = n_frames - fixed
    if rest < 2 * len(free):
        raise ValueError(
            f"{name}: n_frames={n_frames} is too small; need at least {fixed + 2 * len(free)}"
        )
    w = np.array([p.weight for p in free], dtype=np.float64)
    share = 2 + np.floor((rest - 2 * len(free)) * w / w.sum()).astype(int)
    # Hand out the rounding remainder to the heaviest phases first.
    for i in np.argsort(-w, kind="stable")[: rest - int(share.sum())]:
        share[i] += 1
    out, k = [], 0
    for p in phases:
        if p.frames is None:
            out.append(int(share[k]))
            k += 1
        else:
            out.append(int(p.frames))
    return out


def _build(
    name: str,
    grasped: Polyhedron,
    environment: Polyhedron,
    states: Sequence[TrueState],
    phases: Sequence[_Phase],
    transitions: Sequence[ExpectedTransition],
    *,
    n_frames: int,
    fps: float,
    margin: float,
    params: Mapping[str, Any],
) -> SyntheticDemo:
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"{name}: fps must be positive, got {fps}")
    counts = _allocate(n_frames, phases, name)
    poses: list[FloatArray] = []
    labels: list[int] = []
    phase_of: list[str] = []
    for p, n in zip(phases, counts, strict=True):
        us = [0.5] if n == 1 else np.linspace(0.0, 1.0, n).tolist()
        for u in us:
            poses.append(p.path(float(u)))
            labels.append(p.state)
            phase_of.append(p.name)
    X = np.stack(poses)
    lab = np.asarray(labels, dtype=np.int64)
    # The key of each state: what the contact finder sees at the exact pose of the middle
    # frame of the state's first segment.
    finder = ContactFinder(grasped, environment)
    keyed = []
    for i, st in enumerate(states):
        frames = np.flatnonzero(lab == i)
        if len(frames) == 0:
            raise AssertionError(f"{name}: state {st.name} has no frame")  # pragma: no cover
        run_end = frames[0]
        while run_end + 1 < len(lab) and lab[run_end + 1] == i:
            run_end += 1
        mid = (frames[0] + run_end) // 2
        keyed.append(replace(st, key=finder.find(X[mid]).key))
    n_seg = int(np.count_nonzero(np.diff(lab))) + 1
    if len(transitions) != n_seg - 1:
        raise AssertionError(  # pragma: no cover - a builder bug
            f"{name}: {len(transitions)} expected transitions for {n_seg} segments"
        )
    meta: dict[str, Any] = {
        "units": {"length": "m", "angle": "rad", "time": "s"},
        "frame": "environment",
        "fps": float(fps),
        "margin": float(margin),
        "phases": tuple(phase_of),
        "params": dict(params),
        "noise": [],
    }
    n = len(lab)
    return SyntheticDemo(
        name=name,
        grasped=grasped,
        environment=environment,
        times=np.arange(n, dtype=np.float64) / fps,
        X_EG=X.copy(),
        X_EG_true=X,
        labels=lab,
        true_states=tuple(keyed),
        expected_subskills=tuple(transitions),
        frame_ids=np.arange(n, dtype=np.int64),
        outliers=np.zeros(n, dtype=bool),
        meta=meta,
    )


def _check_margin(margin: float, name: str, upper: float) -> float:
    margin = float(margin)
    if not (0 < margin < upper):
        raise ValueError(f"{name}: margin must be in (0, {upper:g}) m, got {margin}")
    return margin


# --------------------------------------------------------------------------------------------
# The paper's 2D peg insertion (Fig. 21, Fig. 25)
# --------------------------------------------------------------------------------------------


def peg_in_hole_2d(
    n_frames: int = 60,
    *,
    fps: float = 10.0,
    tilt_deg: float = 25.0,
    margin: float = 0.002,
    scale: float = 1.0,
    depth: float = 0.070,
    thickness: float = 0.035,
) -> SyntheticDemo:
    """T-peg inserted into a U-slot in a vertical plane (paper Fig. 21, states A-H of Fig. 25).

    Geometry (defaults): ``apo.shapes.t_peg()`` (stem 35 x 70 mm, crossbar 70 x 18 mm, 35 mm
    thick) into ``apo.shapes.u_block(slot_depth=0.070)`` (140 x 88 x 35 mm, slot 35 mm
    wide, floor at y = 18 mm); no clearance, as in the first author's models. Motion in the
    xy-plane (y up), rotation about z; the peg is tilted counter-clockwise so that its
    bottom-left edge is lowest. ``scale`` multiplies every length in the plane of the motion
    (and the motion), ``depth`` is the stem's length and the slot's depth before scaling,
    ``thickness`` the extent of both parts along z (not scaled).

    States: A free approach; B the peg's bottom-left edge on the top face right of the slot;
    C that edge on the slot's right rim edge (singular, 2 frames); D pivoted over the rim so
    the corner is in the slot, the rim edge on the peg's bottom face; E the peg's left face
    also on the left rim (wedged across the slot); F upright with both bottom edges on both
    rim edges (singular, 1 frame); G upright in the slot, faces flush with both walls;
    H seated (stem on the floor, crossbar on the block's top faces).

    Parameters
    ----------
    n_frames : int
        Total number of frames (C has 2, F has 1; the rest are shared by weight).
    fps : float
        Frame rate, Hz.
    tilt_deg : float
        Tilt of the peg in A, B, C, degrees (between 10 and 27).
    margin : float
        Smallest gap (metres) kept between features that are not scripted to touch, at every
        frame: approach and leave the contacts no closer than this.
    scale : float
        Size of the scene in the plane of the motion, relative to the paper's (0.8 to 2).
    depth : float
        Stem length = slot depth before scaling, metres (0.045 to 0.080).
    thickness : float
        Thickness of the peg and the block along z, metres (0.01 to 0.1).

    Returns
    -------
    SyntheticDemo
    """
    name = "peg_in_hole_2d"
    margin = _check_margin(margin, name, 0.004)
    for label, v, lo, hi in (("tilt_deg", tilt_deg, 10.0, 27.0), ("scale", scale, 0.8, 2.0),
                             ("depth", depth, 0.045, 0.080),
                             ("thickness", thickness, 0.01, 0.1)):  # fmt: skip
        if not lo <= v <= hi:
            raise ValueError(f"{name}: {label} must be in [{lo:g}, {hi:g}], got {v}")
    k = float(scale)
    G = t_peg(stem_width=0.035 * k, stem_length=depth * k, bar_width=0.070 * k,
              bar_height=0.018 * k, thickness=thickness)  # fmt: skip
    E = u_block(width=0.14 * k, height=0.088 * k, thickness=thickness, slot_width=0.035 * k,
                slot_depth=depth * k)  # fmt: skip
    phases = _peg_2d_phases(math.radians(tilt_deg), margin, k, depth * k)
    return _build(
        name, G, E, _PEG_2D_STATES, phases, _PEG_2D_TRANSITIONS, n_frames=n_frames, fps=fps,
        margin=margin,
        params={"tilt_deg": tilt_deg, "scale": k, "depth": depth, "thickness": thickness,
                "peg": "t_peg()", "block": "u_block(slot_depth=0.070)"},
    )  # fmt: skip


def _crossbar_clearance(theta: float, k: float, depth: float) -> float:
    """Return the height of the T-peg's crossbar over the block's top in state E.

    The crossbar's lower outer corner on the slot's left side, the peg wedged across the
    slot at tilt ``theta`` (radians); ``k`` the scale, ``depth`` the scaled stem length.
    """
    w, overhang = 0.035 * k, 0.0175 * k  # slot = stem width; the crossbar's overhang
    return (depth - w * math.sin(theta)) * math.cos(theta) - overhang * math.sin(theta)


def _peg_2d_phases(th0: float, margin: float, k: float, depth: float) -> list[_Phase]:
    """Return the eight phases of :func:`peg_in_hole_2d` (tilt ``th0`` rad, scene scale ``k``)."""
    s, H, w = 0.0175 * k, 0.088 * k, 0.035 * k  # half slot, top, slot width
    floor = H - depth  # slot floor
    corner_G = np.array([-s, 0.0, 0.0])  # the peg's bottom-left edge (at z = 0)
    rim_R = np.array([s, H])
    th_c = th0 + math.radians(3.0)
    # D ends / E starts at 50 degrees, or less where a short stem would bring the crossbar
    # within the margin of the block's top there
    th1 = math.radians(50.0)
    while _crossbar_clearance(th1, k, depth) < margin:
        th1 -= math.radians(0.25)
    th_e = math.radians(30.0)  # E ends (the bottom-right edge stays >= 2.3 mm off the top)

    def at(theta: float, corner: FloatArray) -> FloatArray:
        """Pose with tilt theta and the bottom-left edge at ``corner`` (x, y)."""
        R = _rz(theta)
        return _pose(R, np.array([corner[0], corner[1], 0.0]) - R @ corner_G)

    def on_rim(theta: float, d: float) -> FloatArray:
        """Bottom face on the right rim, the corner ``d`` before it along the face."""
        return at(theta, rim_R - d * np.array([math.cos(theta), math.sin(theta)]))

    def wedged(theta: float) -> FloatArray:
        # Corner on the circle with diameter rim_L-rim_R (Thales): faces on both rims.
        return at(theta, np.array([-s * math.cos(2 * theta), H - s * math.sin(2 * theta)]))

    x_b0 = 0.045 * k
    return [
        _Phase("approach", 0, lambda u: at(th0, np.array([_lerp(0.065 * k, x_b0, u),
                                                         H + _lerp(0.06 * k, margin, u)])), 3.0),
        _Phase("touch and slide to the rim", 1,
               lambda u: at(th0, np.array([_lerp(x_b0, s + margin, u), H])), 3.0),
        _Phase("edge on the rim edge", 2, lambda u: at(_lerp(th0, th_c, u), rim_R), frames=2),
        _Phase("pivot the corner into the slot", 3,
               lambda u: on_rim(_lerp(th_c, th1, u),
                                _lerp(margin, w * math.cos(_lerp(th_c, th1, u)) - margin, u)),
               2.0),
        _Phase("wedged across the slot, turning upright", 4,
               lambda u: wedged(_lerp(th1, th_e, u)), 2.0),
        _Phase("upright at the rim", 5, lambda u: wedged(0.0), frames=1),
        _Phase("insert", 6,
               lambda u: at(0.0, np.array([-s, _lerp(H - margin, floor + margin, u)])), 3.0),
        _Phase("seated", 7, lambda u: at(0.0, np.array([-s, floor])), 2.0),
    ]  # fmt: skip


_PEG_2D_STATES = (
    TrueState("A", "free", {}, False, (3, 0, 0, 3, 0, 0, 0, 0),
              "nothing touches: every motion maintains, nothing restrains"),
    TrueState("B", "peg's bottom-left edge on the block's top face (right of the slot)",
              {"VE": 2}, False, (2, 1, 0, 2, 1, 0, 1, 1),
              "line contact, normal +y; the edge's ends lie on the top face's front/back "
              "edges with flush faces (VE, one normal): slide x, z, turn about y and the "
              "edge (M), lift (D), tip about x either way (type I)"),
    TrueState("C", "peg's bottom-left edge on the slot's right rim edge", {"VV": 2}, True,
              (3, 0, 0, 3, 0, 0, 2, 2),
              "parallel convex edges with coincident ends: two VV, normals +y and the "
              "peg's bottom normal reversed; singular, nothing regular left (SM = 3); "
              "two normals at two points along z restrain 2 + 2"),
    TrueState("D", "slot's right rim edge on the peg's bottom face, corner in the slot",
              {"EV": 2}, False, (2, 1, 0, 2, 1, 0, 1, 1),
              "line contact again (rim edge on a face, ends flush: EV), normal = the "
              "peg's bottom normal reversed: same numbers as B"),
    TrueState("E", "also the left rim edge on the peg's left face (wedged)", {"EV": 4},
              False, (1, 2, 0, 1, 2, 0, 2, 2),
              "two line contacts with normals in the xy-plane, not opposite: slide z (M), "
              "2 D; in-plane 3 - 2 = 1 rotation kept (about z, with a translation), tip "
              "about x, y either way (type I)"),
    TrueState("F", "upright, both bottom edges on both rim edges", {"VV": 4}, True,
              (3, 0, 0, 3, 0, 0, 2, 3),
              "two parallel-edge contacts, ends coincident: 4 VV with normals {+x, +y} "
              "and {-x, +y}: singular, SM = 3; normals span the xy-plane (r_t = 2), the "
              "4 points spread in x and z give r_a = 5, r_r = 3"),
    TrueState("G", "upright in the slot, stem faces flush with both walls",
              {"VE": 4, "EV": 4}, False, (2, 0, 1, 1, 0, 2, 1, 2),
              "normals +x and -x at four (y, z) points: y, z slide (M), x constrained; "
              "only rotation about x keeps the faces flush (M), about y, z constrained"),
    TrueState("H", "seated: stem on the slot floor, crossbar on the top faces",
              {"VE": 12, "EV": 8}, False, (1, 1, 1, 0, 1, 2, 2, 3),
              "G plus +y contacts: z slides (M), lift (D), x constrained; tipping about x "
              "lifts either way (type I D), about y, z constrained"),
)  # fmt: skip

_PEG_2D_TRANSITIONS = (
    ExpectedTransition(0, 1, (PUSH_T, PUSH_R1), False,
                       "t: M->D (3,0,0)->(2,1,0); r: M->D with d_r1 0->1: push-to, type I"),
    ExpectedTransition(1, 2, (SLIDE_T, SLIDE_R), False,
                       "t, r: M->SM x2 (+ D->SM) with r_t 1->2 and r_r 1->2: slide in both"),
    ExpectedTransition(2, 3, (), False,
                       "SM->M x2 and SM->D: no sub-skill (part of the next motion); "
                       "no SM->C: not critical"),
    ExpectedTransition(3, 4, (PUSH_T, PUSH_R1), False,
                       "t: M->D (2,1,0)->(1,2,0); r: M->D with d_r1 1->2: push-to, type I"),
    ExpectedTransition(4, 5, (SLIDE_R,), False,
                       "M->SM (+ D->SM x2) in both spaces, but only r_r grows (2->3, r_t "
                       "stays 2): rotational slide only"),
    ExpectedTransition(5, 6, (), True,
                       "t: SM->C once (x), SM->M twice; r: SM->C twice (y, z), SM->M "
                       "once: critical, no sub-skill"),
    ExpectedTransition(6, 7, (PUSH_T, PUSH_R1), False,
                       "t: M->D (2,0,1)->(1,1,1); r: M->D (1,0,2)->(0,1,2), d_r1 0->1: "
                       "push-to, type I"),
)  # fmt: skip


# --------------------------------------------------------------------------------------------
# Square peg into a square pocket (3D)
# --------------------------------------------------------------------------------------------


def square_peg_in_hole(
    n_frames: int = 50,
    *,
    fps: float = 10.0,
    yaw_deg: float = 15.0,
    margin: float = 0.002,
    scale: float = 1.0,
    height: float = 0.06,
) -> SyntheticDemo:
    """Square peg set down beside a square pocket, lifted, and lowered straight in.

    Geometry: peg ``box([0.04, 0.04, 0.06])`` (origin at the centre of its bottom face);
    block ``block_with_square_hole(size=(0.16, 0.16, 0.05), hole=0.04, depth=0.03)`` (top at
    z = 50 mm, pocket 40 mm square, floor at z = 20 mm); no clearance. ``scale`` multiplies
    every length (and the motion), ``height`` is the peg's height before scaling.

    States: A free; B the peg's bottom face on the top face beside the pocket (turned by
    ``yaw_deg``, sliding a little); A again (lifted, turned square, moved over the pocket);
    F the peg's bottom edges on the four rim edges (singular, 1 frame); G in the pocket,
    faces flush with the four walls; H seated on the floor.

    Parameters
    ----------
    n_frames : int
        Total number of frames (F has 1).
    fps : float
        Frame rate, Hz.
    yaw_deg : float
        Turn of the peg about z while it is set down, degrees (5 to 30).
    margin : float
        Smallest gap (metres) kept between features not scripted to touch.
    scale : float
        Size of the scene relative to the default (0.6 to 2).
    height : float
        Height of the peg before scaling, metres (0.04 to 0.1).

    Returns
    -------
    SyntheticDemo
    """
    name = "square_peg_in_hole"
    margin = _check_margin(margin, name, 0.005)
    if not 5.0 <= yaw_deg <= 30.0:
        raise ValueError(f"{name}: yaw_deg must be in [5, 30], got {yaw_deg}")
    if not (0.6 <= scale <= 2.0 and 0.04 <= height <= 0.1):
        raise ValueError(f"{name}: need scale in [0.6, 2] and height in [0.04, 0.1] m")
    k = float(scale)
    G = box([0.04 * k, 0.04 * k, height * k], center=[0.0, 0.0, height * k / 2], name="square_peg")
    E = block_with_square_hole(size=(0.16 * k, 0.16 * k, 0.05 * k), hole=0.04 * k, depth=0.03 * k)
    top, floor = 0.05 * k, 0.02 * k
    yaw = math.radians(yaw_deg)

    def at(psi: float, x: float, y: float, z: float) -> FloatArray:
        return _pose(_rz(psi), (x, y, z))

    # Footprint half-extent 20 (cos + sin) <= 24.5 mm for yaw <= 15 deg: at x = 50 mm the
    # peg stays >= 5.5 mm off the rim (x = 20 mm) and the block's edge (x = 80 mm).
    x_b, y_b = 0.05 * k, -0.01 * k

    def lift(u: float) -> FloatArray:
        # Up, over and down: z peaks 40 mm above the top; x, y go to 0, yaw to 0.
        z = top + margin + 0.04 * k * math.sin(math.pi * u)
        return at(_lerp(yaw - math.radians(3.0), 0.0, u), _lerp(x_b, 0.0, u),
                  _lerp(y_b, 0.0, u), z)  # fmt: skip

    phases = [
        _Phase("approach", 0, lambda u: at(yaw, x_b, 0.0, top + _lerp(0.05 * k, margin, u)),
               2.0),
        _Phase("set down and slide", 1,
               lambda u: at(_lerp(yaw, yaw - math.radians(3.0), u), x_b,
                            _lerp(0.0, y_b, u), top), 2.0),
        _Phase("lift over the pocket", 0, lift, 3.0),
        _Phase("at the rim", 2, lambda u: at(0.0, 0.0, 0.0, top), frames=1),
        _Phase("insert", 3, lambda u: at(0.0, 0.0, 0.0, _lerp(top - margin, floor + margin, u)),
               3.0),
        _Phase("seated", 4, lambda u: at(0.0, 0.0, 0.0, floor), 2.0),
    ]  # fmt: skip
    states = [
        TrueState("A", "free", {}, False, (3, 0, 0, 3, 0, 0, 0, 0),
                  "nothing touches"),
        TrueState("B", "peg's bottom face on the block's top face", {"VF": 4}, False,
                  (2, 1, 0, 1, 2, 0, 1, 2),
                  "4 corners on a plane (normal +z): slide x, y and turn about z (M), lift "
                  "(D), tip about x or y either way (type I)"),
        TrueState("F", "peg's bottom edges on the four rim edges", {"VE": 8}, True,
                  (3, 0, 0, 3, 0, 0, 3, 3),
                  "each peg corner sits on a rim corner, which is not convex (a concave "
                  "pocket edge below it): split into its two convex rim-edge wedges, each "
                  "a VE with normals {+z, inward wall normal}: 8 singular VE, SM = 3; "
                  "normals +-x, +-y, +z at the 4 corners: r_t = 3, r_a = 6"),
        TrueState("G", "in the pocket, faces flush with the four walls", {"VF": 8, "EE": 8},
                  False, (1, 0, 2, 0, 0, 3, 2, 3),
                  "bottom corners in the concave wall corners (2 VF each), vertical edges "
                  "crossing the rim edges (EE): z slides (M), x, y constrained, every "
                  "rotation constrained by the opposite walls"),
        TrueState("H", "seated on the pocket floor", {"VF": 12, "EE": 8}, False,
                  (0, 1, 2, 0, 0, 3, 3, 3),
                  "G plus the floor (+z) at the corners (3 VF each): z can only lift (D)"),
    ]  # fmt: skip
    transitions = [
        ExpectedTransition(0, 1, (PUSH_T, PUSH_R1), False,
                           "t: M->D; r: M->D x2 (3,0,0)->(1,2,0), d_r1 0->2: push-to, type I"),
        ExpectedTransition(1, 0, (RELEASE_T, RELEASE_R), False,
                           "t: D->M; r: D->M x2: release in both spaces"),
        ExpectedTransition(0, 2, (SLIDE_T, SLIDE_R), False,
                           "M->SM x3 in both spaces with r_t 0->3 and r_r 0->3: slide in "
                           "both (the rule, although G arrives from free space)"),
        ExpectedTransition(2, 3, (), True,
                           "t: SM->C x2 (x, y), SM->M (z); r: SM->C x3: critical, no "
                           "sub-skill"),
        ExpectedTransition(3, 4, (PUSH_T,), False,
                           "t: M->D (1,0,2)->(0,1,2); r unchanged (0,0,3): translational "
                           "push-to only"),
    ]  # fmt: skip
    return _build(
        name, G, E, states, phases, transitions, n_frames=n_frames, fps=fps, margin=margin,
        params={"yaw_deg": yaw_deg, "scale": k, "height": height,
                "peg": "box([0.04, 0.04, 0.06])",
                "block": "block_with_square_hole(size=(0.16, 0.16, 0.05))"},
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Block onto a table, into a wall, into the corner
# --------------------------------------------------------------------------------------------


def _oriented_loop(V: FloatArray, loop: list[int], normal: Sequence[float]) -> list[int]:
    """``loop`` reversed if needed so that it is counter-clockwise seen along ``normal``."""
    p = V[loop]
    q = np.roll(p, -1, axis=0)
    newell = np.array(
        [
            np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
            np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
            np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1])),
        ]
    )
    return loop if float(newell @ np.asarray(normal)) > 0 else loop[::-1]


def corner_tray(
    *,
    size: float = 0.3,
    floor: float = 0.02,
    wall: float = 0.02,
    height: float = 0.08,
    name: str = "corner_tray",
) -> Polyhedron:
    """Build a floor slab with two walls along its x = 0 and y = 0 sides, meeting in a corner.

    One closed polyhedron: the slab ``[0, size]^2 x [0, floor]`` and the walls
    ``[0, wall] x [0, size]`` and ``[0, size] x [0, wall]`` up to z = ``height`` (metres).
    The usable floor is the face ``z = floor`` over ``[wall, size]^2``; the wall faces are
    ``x = wall`` (normal +x) and ``y = wall`` (normal +y); the concave edges along their feet
    and between them make the corner.

    Returns
    -------
    Polyhedron
        9 faces, 14 vertices, 21 edges (3 concave).
    """
    W, h, t, Hh = size, floor, wall, height
    if not (0 < t < W and 0 < h < Hh):
        raise ValueError("corner_tray: need 0 < wall < size and 0 < floor < height")
    V = np.array(
        [
            [0, 0, 0], [W, 0, 0], [W, W, 0], [0, W, 0],  # 0-3 bottom
            [0, 0, Hh], [W, 0, Hh], [W, t, Hh], [t, t, Hh], [t, W, Hh], [0, W, Hh],  # 4-9
            [W, t, h], [W, W, h], [t, W, h], [t, t, h],  # 10-13 floor corners
        ],
        dtype=np.float64,
    )  # fmt: skip
    faces = [
        ([0, 1, 2, 3], (0, 0, -1)),
        ([0, 3, 9, 4], (-1, 0, 0)),
        ([0, 4, 5, 1], (0, -1, 0)),
        ([1, 5, 6, 10, 11, 2], (1, 0, 0)),
        ([3, 2, 11, 12, 8, 9], (0, 1, 0)),
        ([4, 9, 8, 7, 6, 5], (0, 0, 1)),
        ([13, 12, 8, 7], (1, 0, 0)),
        ([13, 7, 6, 10], (0, 1, 0)),
        ([13, 10, 11, 12], (0, 0, 1)),
    ]
    polys: list[tuple[list[int], list[list[int]]]] = [
        (_oriented_loop(V, loop, n), []) for loop, n in faces
    ]
    return polyhedron_from_triangles(V, triangles_from_polygons(V, polys), name=name)


def block_on_table_to_corner(
    n_frames: int = 40,
    *,
    fps: float = 10.0,
    yaw_deg: float = 20.0,
    margin: float = 0.002,
    size: Sequence[float] = (0.06, 0.04, 0.03),
) -> SyntheticDemo:
    """Block lowered onto a floor, slid against a wall, then along it into the corner.

    Geometry: block ``box([0.06, 0.04, 0.03])`` (origin at the centre of its bottom face);
    environment :func:`corner_tray` (floor at z = 20 mm, walls ``x = 20 mm`` and
    ``y = 20 mm`` up to z = 80 mm, taller than the block).

    States: A free approach (turned by ``yaw_deg``); B on the floor, sliding towards the
    x-wall while turning square; C its -x face flush against the x-wall, sliding along it
    in -y; D in the corner (its -y face also against the y-wall).

    Parameters
    ----------
    n_frames : int
        Total number of frames.
    fps : float
        Frame rate, Hz.
    yaw_deg : float
        Turn of the block about z during the approach, degrees (0 to 45).
    margin : float
        Smallest gap (metres) kept between features not scripted to touch.
    size : sequence of 3 float
        The block's extents along x, y, z, metres (x 0.02 to 0.08, y 0.02 to 0.06, z 0.01
        to 0.05).

    Returns
    -------
    SyntheticDemo
    """
    name = "block_on_table_to_corner"
    margin = _check_margin(margin, name, 0.01)
    if not 0.0 <= yaw_deg <= 45.0:
        raise ValueError(f"{name}: yaw_deg must be in [0, 45], got {yaw_deg}")
    lx, ly, lz = (float(v) for v in size)
    if not (0.02 <= lx <= 0.08 and 0.02 <= ly <= 0.06 and 0.01 <= lz <= 0.05):
        raise ValueError(f"{name}: size {tuple(size)} is outside [0.02-0.08, 0.02-0.06, 0.01-0.05]")
    G = box([lx, ly, lz], center=[0.0, 0.0, lz / 2], name="block")
    E = corner_tray()
    fl, wl, hx, hy = 0.02, 0.02, lx / 2, ly / 2
    yaw = math.radians(yaw_deg)

    def at(psi: float, x: float, y: float, z: float) -> FloatArray:
        return _pose(_rz(psi), (x, y, z))

    x0, y0 = 0.16, 0.17
    x_c, y_c = wl + hx, wl + hy  # against the x-wall / y-wall
    phases = [
        _Phase("approach", 0, lambda u: at(yaw, x0, y0, fl + _lerp(0.05, margin, u)), 2.0),
        _Phase("on the floor, slide to the wall", 1,
               lambda u: at(_lerp(yaw, 0.0, u), _lerp(x0, x_c + margin, u), y0, fl), 3.0),
        _Phase("against the wall, slide to the corner", 2,
               lambda u: at(0.0, x_c, _lerp(y0, y_c + margin, u), fl), 3.0),
        _Phase("in the corner", 3, lambda u: at(0.0, x_c, y_c, fl), 2.0),
    ]  # fmt: skip
    states = [
        TrueState("A", "free", {}, False, (3, 0, 0, 3, 0, 0, 0, 0), "nothing touches"),
        TrueState("B", "bottom face on the floor", {"VF": 4}, False, (2, 1, 0, 1, 2, 0, 1, 2),
                  "4 corners on a plane (+z): slide x, y, turn about z (M), lift (D), tip "
                  "about x, y either way (type I)"),
        TrueState("C", "on the floor, -x face flush against the x-wall", {"VF": 8}, False,
                  (1, 2, 0, 0, 3, 0, 2, 3),
                  "bottom corners on the floor (the two at the wall's foot also on the wall: "
                  "2 VF each), top corners at the wall: normals +z, +x never cancel: slide "
                  "y (M), 2 D; no rotation keeps both planes, all three type I"),
        TrueState("D", "in the corner: floor, x-wall and y-wall", {"VF": 12}, False,
                  (0, 3, 0, 0, 3, 0, 3, 3),
                  "normals +x, +y, +z: nothing maintains, nothing cancels: all detaching "
                  "(the corner vertex touches 3 faces, 12 VF in all)"),
    ]  # fmt: skip
    transitions = [
        ExpectedTransition(0, 1, (PUSH_T, PUSH_R1), False,
                           "t: M->D; r: M->D x2 (3,0,0)->(1,2,0), d_r1 0->2: push-to, type I"),
        ExpectedTransition(1, 2, (PUSH_T, PUSH_R1), False,
                           "t: M->D (2,1,0)->(1,2,0); r: M->D (1,2,0)->(0,3,0), d_r1 2->3: "
                           "push-to, type I"),
        ExpectedTransition(2, 3, (PUSH_T,), False,
                           "t: M->D (1,2,0)->(0,3,0); r unchanged (0,3,0): translational "
                           "push-to only"),
    ]  # fmt: skip
    return _build(
        name, G, E, states, phases, transitions, n_frames=n_frames, fps=fps, margin=margin,
        params={"yaw_deg": yaw_deg, "block": f"box({[lx, ly, lz]})",
                "environment": "corner_tray()"},
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Block tipped about an edge
# --------------------------------------------------------------------------------------------


def _tipping_block(
    footprint: npt.ArrayLike | None, height: float
) -> tuple[Polyhedron, FloatArray, float]:
    """Return the block of :func:`block_tipping` and its tipping edge.

    Returns the block, the midpoint of its tipping edge, and the distance of the nearest
    other bottom vertex from that edge (metres).
    """
    if footprint is None:
        G = box([0.06, 0.04, 0.03], center=[0.0, 0.0, 0.015], name="block")
        return G, np.array([0.03, 0.0, 0.0]), 0.06
    P = np.asarray(footprint, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 2 or len(P) < 3 or not 0.005 <= height <= 0.2:
        raise ValueError("block_tipping: footprint must be (n >= 3, 2), height 5 to 200 mm")
    x_max = float(P[:, 0].max())
    on_edge = P[:, 0] > x_max - 1e-9
    if int(on_edge.sum()) != 2:
        raise ValueError("block_tipping: the footprint's side of largest x must be one edge")
    G = prism(P, height, name="prism")
    edge = np.array([x_max, float(P[on_edge, 1].mean()), 0.0])
    return G, edge, float((x_max - P[~on_edge, 0]).min())


def block_tipping(
    n_frames: int = 30,
    *,
    fps: float = 10.0,
    tilt_deg: float = 30.0,
    margin: float = 0.002,
    footprint: npt.ArrayLike | None = None,
    height: float = 0.03,
) -> SyntheticDemo:
    """Block lowered onto one bottom edge and tipped about it until its face lands.

    Geometry: block ``box([0.06, 0.04, 0.03])`` (origin at the centre of its bottom face),
    table ``box([0.4, 0.4, 0.05])`` with its top face at z = 0. The block is turned by
    ``tilt_deg`` about y so that its bottom edge at x = +30 mm (along y) is lowest.

    States: A free approach; B resting on that edge, tipped down about it; C the bottom face
    on the table (rotational push-to).

    Parameters
    ----------
    n_frames : int
        Total number of frames.
    fps : float
        Frame rate, Hz.
    tilt_deg : float
        Initial tilt about the edge, degrees (10 to 60).
    margin : float
        Smallest gap (metres) kept between features not scripted to touch.
    footprint : array_like, shape (n, 2), optional
        The block is then a prism (:func:`apo.shapes.prism`) of this convex polygon (metres,
        in its bottom plane), ``height`` tall; it tips about its side of largest x, which
        must be an edge parallel to y (two vertices share the largest x). Default: the
        60 x 40 mm box, 30 mm tall.
    height : float
        Height of the prism (with ``footprint``), metres.

    Returns
    -------
    SyntheticDemo
    """
    name = "block_tipping"
    margin = _check_margin(margin, name, 0.01)
    if not 10.0 <= tilt_deg <= 60.0:
        raise ValueError(f"{name}: tilt_deg must be in [10, 60], got {tilt_deg}")
    G, edge_G, near = _tipping_block(footprint, height)
    n_bottom = 4 if footprint is None else len(np.asarray(footprint))
    E = box([0.4, 0.4, 0.05], center=[0.0, 0.0, -0.025], name="table")
    phi0 = math.radians(tilt_deg)
    # Smallest tilt in B: the nearest other bottom vertex stays >= 1.5 margin up.
    phi_min = math.asin(min(1.0, 1.5 * margin / near))
    p_edge = np.array([0.02, 0.01, 0.0])

    def at(phi: float, z: float) -> FloatArray:
        R = matrix_from_axis_angle([0.0, 1.0, 0.0], phi)
        return _pose(R, p_edge + np.array([0.0, 0.0, z]) - R @ edge_G)

    phases = [
        _Phase("approach", 0, lambda u: at(phi0, _lerp(0.04, margin, u)), 2.0),
        _Phase("on the edge, tip", 1, lambda u: at(_lerp(phi0, phi_min, u), 0.0), 3.0),
        _Phase("face landed", 2, lambda u: at(0.0, 0.0), 2.0),
    ]
    states = [
        TrueState("A", "free", {}, False, (3, 0, 0, 3, 0, 0, 0, 0), "nothing touches"),
        TrueState("B", "bottom edge on the table", {"VF": 2}, False, (2, 1, 0, 2, 1, 0, 1, 1),
                  "two VF on a line along y, normal +z: slide x, y, turn about z and about "
                  "the edge (M), lift (D), tip about x either way (type I)"),
        TrueState("C", "bottom face on the table", {"VF": n_bottom},
                  False, (2, 1, 0, 1, 2, 0, 1, 2),
                  "the bottom corners on the plane: turning about the edge (y) now lifts "
                  "either way"),
    ]  # fmt: skip
    transitions = [
        ExpectedTransition(0, 1, (PUSH_T, PUSH_R1), False,
                           "t: M->D (3,0,0)->(2,1,0); r: M->D, d_r1 0->1: push-to, type I"),
        ExpectedTransition(1, 2, (PUSH_R1,), False,
                           "t unchanged (2,1,0); r: M->D (2,1,0)->(1,2,0), d_r1 1->2: "
                           "rotational push-to, type I"),
    ]  # fmt: skip
    return _build(
        name, G, E, states, phases, transitions, n_frames=n_frames, fps=fps, margin=margin,
        params={"tilt_deg": tilt_deg, "block": G.name, "height": height,
                "footprint": None if footprint is None else np.asarray(footprint).tolist(),
                "table": "box([0.4, 0.4, 0.05])"},
    )  # fmt: skip


def all_demos() -> dict[str, SyntheticDemo]:
    """Every scripted demonstration with its default parameters, by name."""
    return {
        d.name: d
        for d in (peg_in_hole_2d(), square_peg_in_hole(), block_on_table_to_corner(),
                  block_tipping())
    }  # fmt: skip


# --------------------------------------------------------------------------------------------
# Noise
# --------------------------------------------------------------------------------------------


def _rotvec_matrices(rv: FloatArray) -> FloatArray:
    """Rotation matrices (n, 3, 3) of rotation vectors (n, 3) (rad)."""
    th = np.linalg.norm(rv, axis=1)
    safe = np.where(th > 0, th, 1.0)
    k = rv / safe[:, None]
    K = np.zeros((len(rv), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    out: FloatArray = np.eye(3) + s * K + (1.0 - c) * (K @ K)
    return out


def _unit_vectors(rng: np.random.Generator, n: int) -> FloatArray:
    v = rng.normal(size=(n, 3))
    out: FloatArray = v / np.linalg.norm(v, axis=1)[:, None]
    return out


def _drift(rng: np.random.Generator, times: FloatArray, tau: float) -> FloatArray:
    """Unit-variance Ornstein-Uhlenbeck process (n, 3) at ``times`` (s), time constant tau."""
    n = len(times)
    out = np.zeros((n, 3))
    if n == 0:
        return out
    out[0] = rng.normal(size=3)
    dt = np.diff(np.asarray(times, dtype=np.float64))
    a = np.exp(-np.maximum(dt, 0.0) / max(tau, 1e-9))
    for i in range(1, n):
        out[i] = a[i - 1] * out[i - 1] + math.sqrt(1.0 - a[i - 1] ** 2) * rng.normal(size=3)
    return out


def add_noise(
    demo: SyntheticDemo,
    *,
    sigma_mm: float,
    sigma_deg: float,
    outlier_rate: float = 0.0,
    drop_rate: float = 0.0,
    seed: int | np.random.Generator | None = 0,
    outlier_mm: float = 20.0,
    outlier_deg: float = 15.0,
    drift_mm: float = 0.0,
    drift_deg: float = 0.0,
    drift_time: float = 2.0,
) -> SyntheticDemo:
    """Observed poses with pose noise, drift, outliers and dropped frames; the truth stays.

    Parameters
    ----------
    demo : SyntheticDemo
        A demonstration (clean or already noisy: the noise is added to ``demo.X_EG``).
    sigma_mm : float
        Standard deviation of the position noise per axis, millimetres (of the centroid of
        G's vertices, in the environment frame).
    sigma_deg : float
        Standard deviation of the rotation noise per axis (rotation vector about G's vertex
        centroid, environment axes), degrees.
    outlier_rate : float
        Probability that a frame's observed pose is an outlier: instead of the Gaussian
        noise, a random rotation of ``outlier_deg * U(0.5, 1.5)`` degrees about a random
        axis and a random shift of ``outlier_mm * U(0.5, 1.5)`` millimetres.
    drop_rate : float
        Probability that a frame is dropped (removed with its truth). A segment of a state
        never loses its last frame, so the true state sequence and ``expected_subskills``
        stay valid.
    seed : int or numpy.random.Generator, optional
        Seed of ``numpy.random.default_rng`` (or a generator); the same seed gives the same
        result.
    outlier_mm, outlier_deg : float
        Typical size of an outlier's error, millimetres and degrees.
    drift_mm, drift_deg : float
        Standard deviation per axis of a temporally correlated error (a slow drift, as a
        tracker's bias wanders), millimetres and degrees: a Gaussian process with an
        exponential correlation of time constant ``drift_time`` seconds (an
        Ornstein-Uhlenbeck process, stationary from the first frame), added to the white
        noise.
    drift_time : float
        Correlation time of the drift, seconds.

    Returns
    -------
    SyntheticDemo
        A new demonstration; ``meta["noise"]`` lists the noise applied so far.

    Raises
    ------
    ValueError
        Negative sigmas or sizes, or rates outside [0, 1].
    """
    for label, v in (("sigma_mm", sigma_mm), ("sigma_deg", sigma_deg),
                     ("outlier_mm", outlier_mm), ("outlier_deg", outlier_deg),
                     ("drift_mm", drift_mm), ("drift_deg", drift_deg),
                     ("drift_time", drift_time)):  # fmt: skip
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{label} must be a non-negative number, got {v}")
    for label, v in (("outlier_rate", outlier_rate), ("drop_rate", drop_rate)):
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"{label} must be in [0, 1], got {v}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    n = len(demo)
    X = demo.X_EG.copy()
    cg = demo.grasped.vertices.mean(axis=0)
    dp = rng.normal(scale=sigma_mm * 1e-3, size=(n, 3))
    rv = rng.normal(scale=math.radians(sigma_deg), size=(n, 3))
    if drift_mm > 0 or drift_deg > 0:
        dp += _drift(rng, demo.times, drift_time) * (drift_mm * 1e-3)
        rv += _drift(rng, demo.times, drift_time) * math.radians(drift_deg)
    out = rng.random(n) < outlier_rate
    k = int(out.sum())
    if k:
        rv[out] = _unit_vectors(rng, k) * (
            math.radians(outlier_deg) * rng.uniform(0.5, 1.5, size=k)[:, None]
        )
        dp[out] = (
            _unit_vectors(rng, k) * (outlier_mm * 1e-3 * rng.uniform(0.5, 1.5, size=k))[:, None]
        )
    dR = _rotvec_matrices(rv)
    R, t = X[:, :3, :3], X[:, :3, 3]
    c = np.einsum("nij,j->ni", R, cg) + t
    R_new = dR @ R
    X[:, :3, :3] = R_new
    X[:, :3, 3] = c + dp - np.einsum("nij,j->ni", R_new, cg)
    drop = rng.random(n) < drop_rate
    for _state, a, b in demo.segments():
        if drop[a:b].all():
            drop[(a + b - 1) // 2] = False
    keep = ~drop
    noise = {
        "sigma_mm": float(sigma_mm),
        "sigma_deg": float(sigma_deg),
        "outlier_rate": float(outlier_rate),
        "drop_rate": float(drop_rate),
        "outlier_mm": float(outlier_mm),
        "outlier_deg": float(outlier_deg),
        "drift_mm": float(drift_mm),
        "drift_deg": float(drift_deg),
        "drift_time": float(drift_time),
        "seed": seed if isinstance(seed, int) or seed is None else "generator",
        "about": "vertex centroid of the grasped object, environment axes",
        "n_outliers": int((out & keep).sum()),
        "n_dropped": int(drop.sum()),
    }
    meta = dict(demo.meta)
    meta["noise"] = [*demo.meta.get("noise", []), noise]
    meta["phases"] = tuple(np.asarray(demo.meta["phases"], dtype=object)[keep].tolist())
    return replace(
        demo,
        times=demo.times[keep].copy(),
        X_EG=X[keep],
        X_EG_true=demo.X_EG_true[keep].copy(),
        labels=demo.labels[keep].copy(),
        frame_ids=demo.frame_ids[keep].copy(),
        outliers=(demo.outliers | out)[keep],
        meta=meta,
    )


# --------------------------------------------------------------------------------------------
# Randomised variants
# --------------------------------------------------------------------------------------------

#: The scripted demonstrations :func:`random_variant` draws from, with the ranges of their
#: parameters: frame count (speed), approach angle (tilt or yaw, degrees), stand-off margin.
#: ``"prism_tipping"`` is :func:`block_tipping` with a random prism for the block.
VARIANTS: dict[str, tuple[Any, tuple[int, int], str, tuple[float, float]]] = {
    "peg_in_hole_2d": (peg_in_hole_2d, (40, 120), "tilt_deg", (12.0, 27.0)),
    "square_peg_in_hole": (square_peg_in_hole, (35, 110), "yaw_deg", (6.0, 30.0)),
    "block_on_table_to_corner": (block_on_table_to_corner, (30, 90), "yaw_deg", (8.0, 40.0)),
    "block_tipping": (block_tipping, (22, 70), "tilt_deg", (15.0, 50.0)),
    "prism_tipping": (block_tipping, (22, 70), "tilt_deg", (15.0, 50.0)),
}


def random_footprint(rng: np.random.Generator) -> FloatArray:
    """Return a random convex polygon (n, 2), 3 to 7 vertices, metres, for :func:`block_tipping`.

    Its vertices lie on an ellipse (semi-axes 25-70 mm along x, 12-35 mm along y) centred
    at the origin: two at the ends of the ellipse's y-axis (the tipping edge, on x = 0)
    and 1 to 5 at random angles on its other half, at least 14 mm from that edge.
    """
    rx, ry = rng.uniform(0.025, 0.07), rng.uniform(0.012, 0.035)
    ang = np.sort(rng.uniform(math.radians(125.0), math.radians(235.0), int(rng.integers(1, 6))))
    # keep neighbouring vertices apart (>= 8 degrees) so that no edge is tiny
    ang = ang[np.concatenate([[True], np.diff(ang) > math.radians(8.0)])]
    pts = [(0.0, -ry), (0.0, ry)] + [(rx * math.cos(t), ry * math.sin(t)) for t in ang]
    out: FloatArray = np.array(pts, dtype=np.float64)
    return out


def _shape_params(key: str, rng: np.random.Generator) -> dict[str, Any]:
    """Random sizes and proportions of the parts of one of :data:`VARIANTS`."""
    if key == "peg_in_hole_2d":
        return {"scale": float(rng.uniform(0.8, 1.6)), "depth": float(rng.uniform(0.05, 0.08)),
                "thickness": float(rng.uniform(0.015, 0.06))}  # fmt: skip
    if key == "square_peg_in_hole":
        return {"scale": float(rng.uniform(0.7, 1.8)), "height": float(rng.uniform(0.045, 0.1))}
    if key == "block_on_table_to_corner":
        size = (rng.uniform(0.03, 0.08), rng.uniform(0.02, 0.06), rng.uniform(0.012, 0.05))
        return {"size": tuple(float(v) for v in size)}
    if key == "prism_tipping":
        return {"footprint": random_footprint(rng), "height": float(rng.uniform(0.015, 0.08))}
    return {}


def random_variant(
    seed: int | np.random.Generator | None = 0, *, name: str | None = None
) -> SyntheticDemo:
    """Return a randomised variant of a scripted demonstration (for tests not to be tuned).

    Draws (from ``seed``) one of :data:`VARIANTS` (or ``name``), its frame count (the speed
    of the motion), frame rate (10 to 60 frames/s), approach angle (tilt or yaw), stand-off
    margin (1 to 4 mm), the sizes and proportions of its parts (:func:`_shape_params`: the
    T-peg's scale, stem length and thickness; the square peg's scale and height; the
    block's three sides; for ``"prism_tipping"`` a random convex prism,
    :func:`random_footprint`), and a random rigid placement of the whole scene (the
    environment turned about a random axis and moved: the approach direction in the
    environment's frame changes; contacts and the expected states do not).

    Returns
    -------
    SyntheticDemo
        ``meta["variant"]`` records the parameters drawn.
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    key = name or str(rng.choice(sorted(VARIANTS)))
    if key not in VARIANTS:
        raise ValueError(f"unknown demonstration {key!r}; expected one of {sorted(VARIANTS)}")
    build, (lo, hi), angle_name, (alo, ahi) = VARIANTS[key]
    params: dict[str, Any] = {
        "n_frames": int(rng.integers(lo, hi + 1)),
        "fps": float(rng.uniform(10.0, 60.0)),
        angle_name: float(rng.uniform(alo, ahi)),
        "margin": float(rng.uniform(0.001, 0.004)),
    }
    shape = _shape_params(key, rng)
    if "footprint" in shape:  # the tilt must leave room to tip down to phi_min (block_tipping)
        near = float(-shape["footprint"][2:, 0].max())
        least = math.degrees(math.asin(min(1.0, 1.5 * params["margin"] / near))) + 8.0
        params[angle_name] = max(params[angle_name], least)
    demo: SyntheticDemo = build(**params, **shape)
    axis = _unit_vectors(rng, 1)
    T = np.eye(4)
    T[:3, :3] = _rotvec_matrices(axis * rng.uniform(0.0, math.pi))[0]
    T[:3, 3] = rng.uniform(-0.2, 0.2, size=3)
    record = {"name": key, **params, **{k: np.asarray(v).tolist() for k, v in shape.items()}}
    return placed(demo, T, meta={"variant": {**record, "placement": T.tolist()}})


def placed(
    demo: SyntheticDemo, X_NE: npt.ArrayLike, *, meta: Mapping[str, Any] | None = None
) -> SyntheticDemo:
    """Return the demonstration with the environment placed at ``X_NE`` in a new frame N.

    Every pose becomes ``X_NE @ X_EG``; the environment's vertices are moved with it
    (``apo.geometry.transformed``), so feature ids, contact states and expected sub-skills
    are unchanged.
    """
    from apo.geometry import transformed

    T = np.asarray(X_NE, dtype=np.float64)
    return replace(
        demo,
        environment=transformed(demo.environment, T),
        X_EG=np.einsum("ij,njk->nik", T, demo.X_EG),
        X_EG_true=np.einsum("ij,njk->nik", T, demo.X_EG_true),
        meta={**demo.meta, **(meta or {})},
    )
