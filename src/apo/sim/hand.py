"""The compliant hand: a 6-DOF hybrid force/position (Cartesian impedance) controller.

Every step the controller computes a wrench about a *compliance centre* (a point fixed in
the grasped object) and applies it to the hand body (``xfrc_applied``); MuJoCo integrates
the hand and the object it carries, contacts included. Nothing is ever placed kinematically.

Control law (world frame W, twists and wrenches ``[omega; v]`` / ``[torque; force]``)::

    force  = S_t (f_cmd - Df_t v) + (I - S_t) (K_t e_p - D_t v)
    torque = S_r (t_cmd - Df_r w) + (I - S_r) (K_r e_r - D_r w)

with ``S_t``, ``S_r`` the projectors on the force-controlled directions and axes
(``apo.motion.Compliance``), ``e_p`` the position error of the centre, ``e_r`` the rotation
vector from the current to the desired orientation, ``v`` and ``w`` the velocity of the
centre and the angular velocity. Gains in :class:`Gains`.

Sensing: :meth:`Hand.contact_wrench` sums MuJoCo's contact forces on the grasped object's
geoms (``mj_contactForce``), the force/torque a wrist sensor would read less the hand's own
inertia; the largest penetration is the most negative contact distance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from apo.sim.scene import Scene
from apo.typing import FloatArray

__all__ = ["Gains", "Hand"]


@dataclass(frozen=True)
class Gains:
    """Impedance gains of the hand (SI).

    Attributes
    ----------
    k_t, d_t : float
        Translational stiffness (N/m) and damping (N s/m) of position-controlled directions.
    k_r, d_r : float
        Rotational stiffness (N m/rad) and damping (N m s/rad).
    df_t, df_r : float
        Damping of the force-controlled directions (sets the free speed under a force).
    """

    k_t: float = 3000.0
    d_t: float = 120.0
    k_r: float = 30.0
    d_r: float = 0.5
    df_t: float = 250.0
    df_r: float = 0.6


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Cross product of two 3-vectors (``np.cross`` costs ~20x more at this size)."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


class Hand:
    """Controller and sensor of the hand of a :class:`Scene`."""

    def __init__(self, scene: Scene, gains: Gains | None = None) -> None:
        import mujoco

        self.scene = scene
        self.gains = gains or Gains()
        self._mj = mujoco
        self.max_force = 0.0
        self.max_penetration = 0.0
        self._f6 = np.zeros(6)
        self._qd = np.zeros(4)
        self._e3 = np.zeros(3)
        ngeom = int(scene.model.ngeom)  # type: ignore[attr-defined]
        self._grasped = np.zeros(ngeom, dtype=np.bool_)
        self._grasped[list(scene.grasped_geoms)] = True

    # ---------------------------------------------------------------- state
    @property
    def time(self) -> float:
        """Simulated time, seconds."""
        return float(self.scene.data.time)  # type: ignore[attr-defined]

    def pose(self) -> FloatArray:
        """Return the current ``X_WG`` (4x4, metres)."""
        d = self.scene.data
        X = np.empty((4, 4))
        X[:3, :3] = d.xmat[self.scene.hand].reshape(3, 3)  # type: ignore[attr-defined]
        X[:3, 3] = d.xpos[self.scene.hand]  # type: ignore[attr-defined]
        X[3] = (0.0, 0.0, 0.0, 1.0)
        return X

    def velocity(self, point_W: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Angular velocity and velocity of the body point at ``point_W`` (world frame)."""
        d = self.scene.data
        qv = d.qvel  # type: ignore[attr-defined]
        R = d.xmat[self.scene.hand].reshape(3, 3)  # type: ignore[attr-defined]
        w = R @ qv[3:6]
        v = qv[0:3] + _cross(w, point_W - d.xpos[self.scene.hand])  # type: ignore[attr-defined]
        return w, v

    def contact_wrench(self, point_W: FloatArray) -> tuple[FloatArray, FloatArray, float]:
        """Contact force on the grasped object, its torque about ``point_W``, penetration.

        Returns ``(force N, torque N m, largest penetration m)``, world frame. The forces
        are the constraint forces of the contacts in their frames (elliptic cones: the
        first three components are normal and tangential forces, as ``mj_contactForce``
        returns them); every contact of the scene is between the grasped object and the
        environment (the pieces of one body never collide).
        """
        d = self.scene.data
        n = int(d.ncon)  # type: ignore[attr-defined]
        if n == 0:
            return np.zeros(3), np.zeros(3), 0.0
        con = d.contact  # type: ignore[attr-defined]
        adr = con.efc_address[:n]
        live = adr >= 0
        fl = np.zeros((n, 3))
        efc = d.efc_force  # type: ignore[attr-defined]
        fl[live] = efc[adr[live, None] + np.arange(3)]
        frames = con.frame[:n].reshape(n, 3, 3)
        f = np.einsum("nji,nj->ni", frames, fl)  # on geom2, from geom1
        sign = np.where(self._grasped[con.geom1[:n]], -1.0, 1.0)
        f *= sign[:, None]
        F = f.sum(axis=0)
        arm = con.pos[:n] - point_W
        T = np.array([
            arm[:, 1] @ f[:, 2] - arm[:, 2] @ f[:, 1],
            arm[:, 2] @ f[:, 0] - arm[:, 0] @ f[:, 2],
            arm[:, 0] @ f[:, 1] - arm[:, 1] @ f[:, 0],
        ])  # fmt: skip
        pen = max(0.0, -float(con.dist[:n].min()))
        return F, T, pen

    def _rotation_error(self, X_des: FloatArray) -> FloatArray:
        """Rotation vector (world frame) that turns the current orientation into X_des's."""
        mj = self._mj
        mj.mju_mat2Quat(self._qd, np.ascontiguousarray(X_des[:3, :3]).ravel())
        q = self.scene.data.xquat[self.scene.hand]  # type: ignore[attr-defined]
        mj.mju_subQuat(self._e3, self._qd, q)  # local frame of the current orientation
        R = self.scene.data.xmat[self.scene.hand].reshape(3, 3)  # type: ignore[attr-defined]
        out: FloatArray = R @ self._e3
        return out

    # ---------------------------------------------------------------- control
    def step(
        self,
        X_des: FloatArray,
        center_G: FloatArray,
        *,
        S_t: FloatArray | None = None,
        S_r: FloatArray | None = None,
        force: FloatArray | None = None,
        torque: FloatArray | None = None,
        slow: float = 1.0,
    ) -> tuple[FloatArray, FloatArray]:
        """Apply the hybrid control law for one time step and advance the simulation.

        Parameters
        ----------
        X_des : ndarray, shape (4, 4)
            Desired ``X_WG`` (its position-controlled part matters).
        center_G : ndarray, shape (3,)
            Compliance centre in the grasped object's frame, metres.
        S_t, S_r : ndarray, shape (3, 3), optional
            Projectors on the force-controlled directions / axes (none by default).
        force, torque : ndarray, shape (3,), optional
            Commanded force (N) and torque about the centre (N m), world frame.
        slow : float
            Factor on the damping of the force-controlled directions (> 1: slower under
            the same force, for the last millimetres before an expected contact).

        Returns
        -------
        (force, torque) : the sensed contact force and torque about the centre after the step.
        """
        g = self.gains
        d = self.scene.data
        b = self.scene.hand
        R = d.xmat[b].reshape(3, 3)  # type: ignore[attr-defined]
        c = R @ center_G + d.xpos[b]  # type: ignore[attr-defined]
        c_des = X_des[:3, :3] @ center_G + X_des[:3, 3]
        w, v = self.velocity(c)
        F = g.k_t * (c_des - c) - g.d_t * v
        if S_t is not None:
            fc = np.zeros(3) if force is None else force
            F = F + S_t @ (fc - slow * g.df_t * v - F)
        T = g.k_r * self._rotation_error(X_des) - g.d_r * w
        if S_r is not None:
            tc = np.zeros(3) if torque is None else torque
            T = T + S_r @ (tc - g.df_r * w - T)
        com = d.xipos[b]  # type: ignore[attr-defined]
        xfrc = d.xfrc_applied[b]  # type: ignore[attr-defined]
        xfrc[:3] = F
        xfrc[3:] = T + _cross(c - com, F)
        self._mj.mj_step(self.scene.model, d)
        R = d.xmat[b].reshape(3, 3)  # type: ignore[attr-defined]
        Fc, Tc, pen = self.contact_wrench(R @ center_G + d.xpos[b])  # type: ignore[attr-defined]
        self.max_force = max(self.max_force, float(np.linalg.norm(Fc)))
        self.max_penetration = max(self.max_penetration, pen)
        return Fc, Tc
