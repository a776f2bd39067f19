"""The MuJoCo scene of a replay: the environment, the grasped object and the compliant hand.

Frames: the world frame W of the simulation is the environment frame E *as the plan knows
it*; the environment body is placed at ``X_WE`` (identity, or the unknown offset of
``apo replay --environment-offset``). The hand is a free body whose frame is the grasped
object's model frame G, so its pose is ``X_WG``; the grasped object's convex pieces are
geoms of that body (rigidly held, as through a weld). The hand's inertia (``HAND_MASS``) is
put at the object's centroid; the hand itself has no collision geometry.

Units: metres, kilograms, seconds (the task's units are converted before this module).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from apo.geometry import Polyhedron
from apo.sim.pieces import ConvexPiece, Decomposition, convex_pieces, shrink_piece
from apo.spatial import position_quaternion_from_pose
from apo.typing import FloatArray

__all__ = [
    "DEFAULT_CLEARANCE",
    "HAND_MASS",
    "MIN_CLEARANCE",
    "ContactParameters",
    "Scene",
    "build_scene",
]

HAND_MASS = 1.0
"""Mass of the hand with the object, kg."""
DEFAULT_CLEARANCE = 0.0002
"""Gap per side between the simulated grasped object and its model, metres (0.2 mm)."""
MIN_CLEARANCE = 0.00005
"""Smallest clearance accepted, metres (0.05 mm)."""


@dataclass(frozen=True)
class ContactParameters:
    """MuJoCo contact and integration settings of the replay (``docs/sim.md``).

    Attributes
    ----------
    timestep : float
        Seconds.
    solref : tuple of float
        Every contact's reference dynamics. Negative values are MuJoCo's direct form
        ``(-stiffness, -damping)`` (1/s^2, 1/s; per unit of the contact's effective mass):
        a penetration is corrected as ``a_ref = -stiffness r - damping v``. The default
        ``(-6e5, -1e3)`` (natural frequency 775 rad/s, damping ratio 0.65, i.e. a time
        constant of 1.3 ms) is as stiff as a 1 ms step allows with margin (``docs/sim.md``);
        the positive form ``(timeconst, dampratio)`` cannot go below two steps.
    solimp : tuple of float
        ``(dmin, dmax, width)``: impedance 0.99 rising to 0.999 within 0.1 mm.
    impratio : float
        Ratio of frictional to normal impedance (elliptic cones).
    friction : float
        Sliding friction coefficient (dry plastic/metal on metal).
    torsional : float
        Torsional friction coefficient, metres.
    """

    timestep: float = 0.001
    solref: tuple[float, float] = (0.002, 1.0)
    solimp: tuple[float, float, float] = (0.99, 0.999, 0.0001)
    impratio: float = 10.0
    friction: float = 0.3
    torsional: float = 0.0005


@dataclass
class Scene:
    """A compiled MuJoCo model with what the controller needs to know about it.

    Attributes
    ----------
    model, data : mujoco.MjModel, mujoco.MjData
    hand : int
        Body id of the hand.
    grasped_geoms : frozenset of int
        Geom ids of the grasped object's pieces.
    X_WE : ndarray, shape (4, 4)
        Pose of the environment body in the world (the plan's environment frame).
    com_G : ndarray, shape (3,)
        The hand's centre of mass in the grasped object's frame, metres.
    pieces : dict of str to Decomposition
        The decompositions used (``"grasped"`` before shrinking, ``"environment"``).
    clearance : float
        Metres per side.
    params : ContactParameters
    """

    model: object
    data: object
    hand: int
    grasped_geoms: frozenset[int]
    X_WE: FloatArray
    com_G: FloatArray
    pieces: dict[str, Decomposition]
    clearance: float
    params: ContactParameters = field(default_factory=ContactParameters)


def _fmt(a: npt.ArrayLike) -> str:
    return " ".join(f"{float(x):.12g}" for x in np.ravel(a))


def _mesh_xml(name: str, piece: ConvexPiece) -> str:
    return f'<mesh name="{name}" vertex="{_fmt(piece.vertices)}"/>'


def _xml(
    g_pieces: list[ConvexPiece],
    e_pieces: list[ConvexPiece],
    X_WE: FloatArray,
    X_WG: FloatArray,
    com_G: FloatArray,
    p: ContactParameters,
) -> str:
    meshes = [_mesh_xml(f"g{i}", q) for i, q in enumerate(g_pieces)]
    meshes += [_mesh_xml(f"e{i}", q) for i, q in enumerate(e_pieces)]
    pe, qe = position_quaternion_from_pose(X_WE)
    pg, qg = position_quaternion_from_pose(X_WG)
    contact = (
        f'solref="{_fmt(p.solref)}" solimp="{_fmt(p.solimp)}" '
        f'friction="{p.friction:g} {p.torsional:g} 0.0001" condim="4" margin="0"'
    )
    env = "\n".join(
        f'<geom name="env{i}" type="mesh" mesh="e{i}" contype="0" conaffinity="1" '
        f'{contact} rgba="0.6 0.6 0.65 1"/>'
        for i in range(len(e_pieces))
    )
    grasped = "\n".join(
        f'<geom name="grasped{i}" type="mesh" mesh="g{i}" contype="1" conaffinity="0" '
        f'{contact} rgba="0.85 0.45 0.2 1"/>'
        for i in range(len(g_pieces))
    )
    inertia = HAND_MASS * 2e-3
    return f"""<mujoco model="apo replay">
  <compiler angle="radian" inertiafromgeom="false"/>
  <option timestep="{p.timestep:g}" gravity="0 0 0" cone="elliptic" impratio="{p.impratio:g}"
          integrator="implicitfast"/>
  <visual><global offwidth="1280" offheight="960"/></visual>
  <asset>{"".join(meshes)}</asset>
  <worldbody>
    <light pos="0 0 1" dir="0 0 -1" directional="true"/>
    <body name="environment" pos="{_fmt(pe)}" quat="{_fmt(qe)}">
{env}
    </body>
    <body name="hand" pos="{_fmt(pg)}" quat="{_fmt(qg)}">
      <freejoint name="hand"/>
      <inertial pos="{_fmt(com_G)}" mass="{HAND_MASS:g}" diaginertia="{_fmt([inertia] * 3)}"/>
{grasped}
    </body>
  </worldbody>
</mujoco>
"""


def build_scene(
    grasped: Polyhedron,
    environment: Polyhedron,
    *,
    X_WG: npt.ArrayLike,
    X_WE: npt.ArrayLike | None = None,
    clearance: float = DEFAULT_CLEARANCE,
    params: ContactParameters | None = None,
    decompositions: dict[str, Decomposition] | None = None,
) -> Scene:
    """Build the MuJoCo scene of a replay.

    Parameters
    ----------
    grasped, environment : Polyhedron
        The two models (metres, their own frames).
    X_WG : array_like, shape (4, 4)
        Start pose of the grasped object (and hand) in the world, metres.
    X_WE : array_like, shape (4, 4), optional
        Pose of the environment in the world (identity by default).
    clearance : float
        Metres per side by which the grasped object's surface is moved inwards
        (>= :data:`MIN_CLEARANCE`).
    params : ContactParameters, optional
    decompositions : dict, optional
        Precomputed ``{"grasped": ..., "environment": ...}`` (:func:`convex_pieces`), to
        build many scenes of the same models quickly.

    Returns
    -------
    Scene
    """
    import mujoco

    if not (np.isfinite(clearance) and clearance >= MIN_CLEARANCE - 1e-12):
        raise ValueError(
            f"clearance must be at least {MIN_CLEARANCE * 1e3:g} mm, got {clearance * 1e3:g} mm"
        )
    p = params or ContactParameters()
    dec = decompositions or {
        "grasped": convex_pieces(grasped),
        "environment": convex_pieces(environment),
    }
    g_pieces = [shrink_piece(q, clearance) for q in dec["grasped"].pieces]
    com_G = grasped.vertices.mean(axis=0)
    vols = np.array([q.volume for q in g_pieces])
    cents = np.array([q.vertices.mean(axis=0) for q in g_pieces])
    com_G = (vols @ cents) / vols.sum() if vols.sum() > 0 else com_G
    XE = np.eye(4) if X_WE is None else np.asarray(X_WE, dtype=np.float64)
    XG = np.asarray(X_WG, dtype=np.float64)
    xml = _xml(g_pieces, list(dec["environment"].pieces), XE, XG, com_G, p)
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    hand = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "hand")
    geoms = frozenset(
        mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"grasped{i}")
        for i in range(len(g_pieces))
    )
    return Scene(model, data, hand, geoms, XE, com_G, dec, clearance, p)
