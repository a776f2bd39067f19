"""A small scripted scene for tests, benchmarks and demos of the perception front end.

A T-shaped peg (50 mm wide, 40 mm tall) is carried above a U-shaped slot (60 mm wide), lowered
and inserted; a camera looks down at it from about 0.33 m. Everything is in metres. (The
recognition examples live in :mod:`apo.synthetic`; this module only needs poses.)
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from apo.perception.frames import Camera
from apo.perception.render import Triangles, pose_looking_at
from apo.spatial import invert_pose, pose_from_position_quaternion

__all__ = ["example_camera", "insertion_trajectory", "peg_and_slot"]

FloatArray = npt.NDArray[np.float64]


def _prism(
    outline: list[tuple[float, float]], caps: list[tuple[int, int, int]], thickness: float
) -> Triangles:
    """Return the closed mesh of an xz-plane outline extruded along y (metres).

    The outline (``(x, z)`` points, triangulated by ``caps``) is extruded over
    ``[-thickness/2, thickness/2]``; the triangles are oriented outwards.
    """
    n = len(outline)
    uv = np.asarray(outline, dtype=np.float64)
    h = thickness / 2
    V = np.vstack(
        [np.column_stack((uv[:, 0], np.full(n, -h), uv[:, 1])),
         np.column_stack((uv[:, 0], np.full(n, h), uv[:, 1]))]
    )  # fmt: skip
    T = [list(c) for c in caps] + [[c[0] + n, c[2] + n, c[1] + n] for c in caps]
    for i in range(n):
        j = (i + 1) % n
        T += [[i, j + n, j], [i, i + n, j + n]]
    tri = np.asarray(T, dtype=np.int64)
    a, b, c = V[tri[:, 0]], V[tri[:, 1]], V[tri[:, 2]]
    if np.einsum("ij,ij->i", a, np.cross(b, c)).sum() < 0:  # make the normals point out
        tri = tri[:, ::-1].copy()
    return V, tri


def peg_and_slot() -> tuple[Triangles, Triangles]:
    """Return the T-peg (grasped) and U-slot (environment) meshes, metres.

    Both are closed, consistently oriented prisms (valid for
    :func:`apo.geometry.polyhedron_from_triangles`), z up. The peg's frame is at the bottom
    centre of its stem (16 mm wide along x, 30 mm tall) under a 50 x 10 mm head; it is 19 mm
    thick along y. The slot's frame is at the bottom centre of its 60 x 40 mm footprint: a
    15 mm base and two 20 mm walls 25 mm high leaving a 20 mm gap along x (2 mm clearance
    each side of the stem); 40 mm thick along y.
    """
    s, b, h, t = 0.008, 0.025, 0.030, 0.010
    peg = _prism(
        [(-s, 0.0), (s, 0.0), (s, h), (b, h), (b, h + t), (-b, h + t), (-b, h), (-s, h)],
        [(0, 1, 2), (0, 2, 7), (5, 6, 7), (5, 7, 2), (5, 2, 3), (5, 3, 4)],
        0.019,
    )
    w, g, d, H = 0.030, 0.010, 0.015, 0.040
    slot = _prism(
        [(-w, 0.0), (w, 0.0), (w, H), (g, H), (g, d), (-g, d), (-g, H), (-w, H)],
        [(0, 1, 4), (0, 4, 5), (1, 2, 3), (1, 3, 4), (0, 5, 6), (0, 6, 7)],
        0.040,
    )
    return peg, slot


def insertion_trajectory(n: int, *, duration: float = 3.0) -> tuple[FloatArray, FloatArray]:
    """Return ``(times, X_EG)`` of a carry-approach-insert motion of the peg (metres).

    The peg starts 80 mm up and 60 mm to the side, turned 30 deg about z and tilted 10 deg,
    reaches the slot's axis 60 mm up, square, by 60 % of the time, then descends to rest on
    the slot's floor (stem bottom at z = 15 mm).
    """
    from scipy.spatial.transform import Rotation

    t = np.linspace(0.0, duration, n)
    s = t / duration
    X = np.empty((n, 4, 4))
    for k, sk in enumerate(s):
        a = min(sk / 0.6, 1.0)
        a = 0.5 - 0.5 * np.cos(np.pi * a)  # smooth
        b = 0.0 if sk <= 0.6 else (sk - 0.6) / 0.4
        b = 0.5 - 0.5 * np.cos(np.pi * b)
        p = np.array([0.060 * (1 - a), 0.0, 0.080 - 0.020 * a - 0.045 * b])
        rot = Rotation.from_euler("zx", [30.0 * (1 - a), 10.0 * (1 - a)], degrees=True)
        x, y, z, w = rot.as_quat()
        X[k] = pose_from_position_quaternion(p, [w, x, y, z])
    return t, X


def example_camera(width: int = 640, height: int = 480) -> tuple[Camera, FloatArray]:
    """Return the camera (``fx = fy = 525 * width / 640``, depth in 0.1 mm units) and ``X_CE``.

    The camera is 0.33 m from the slot, looking down at 50 deg from 30 deg to the side (so
    that faces of both objects constrain every direction); ``camera.X_WC`` is its pose
    in the environment (world) frame.
    """
    f = 525.0 * width / 640.0
    X_EC = pose_looking_at([0.12, -0.19, 0.25], [0.0, 0.0, 0.03])
    cam = Camera(f, f, (width - 1) / 2, (height - 1) / 2, width, height, 1e-4, X_EC)
    return cam, invert_pose(X_EC)
