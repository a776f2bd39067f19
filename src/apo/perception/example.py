"""Scripted scenes for tests, benchmarks and demos of the perception front end (metres).

Two scenes:

- :func:`peg_and_slot`, :func:`insertion_trajectory`, :func:`example_camera`: a small T-peg
  (50 mm wide, 40 mm tall) carried above a U-shaped slot (60 mm wide), lowered and inserted;
  a camera looks down at it from about 0.33 m. Only poses: the benchmark's scene.
- :func:`render_builtin`: the built-in example of ``apo demo``
  (:func:`apo.synthetic.peg_in_hole_2d`, the paper's Fig. 21 insertion with states A-H of
  Fig. 25) rendered into a frames folder from its true poses, with :func:`builtin_camera`.
  Tracking these frames and recognising the tracked poses must give the task recognised from
  the true poses (``tests/test_perception_track.py``, ``apo demo --from-frames``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from apo.perception.frames import Camera
from apo.perception.render import DepthNoise, Triangles, pose_looking_at, render_demonstration
from apo.spatial import invert_pose, pose_from_position_quaternion
from apo.typing import FloatArray

if TYPE_CHECKING:
    from apo.geometry import Polyhedron
    from apo.synthetic import SyntheticDemo

__all__ = [
    "RenderedDemo",
    "builtin_camera",
    "example_camera",
    "insertion_trajectory",
    "peg_and_slot",
    "polyhedron_triangles",
    "render_builtin",
    "render_synthetic",
    "synthetic_camera",
]


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


BUILTIN_UP = (0.0, 1.0, 0.0)
"""Up direction of the built-in example's frames (:func:`apo.synthetic.peg_in_hole_2d`: y up)."""


def builtin_camera(width: int = 640, height: int = 480) -> tuple[Camera, FloatArray]:
    """Return the camera of the built-in example (``fx = fy = 525 * width / 640``) and ``X_CE``.

    :func:`apo.synthetic.peg_in_hole_2d` moves the peg in the environment's xy-plane, y up,
    over a 140 mm block. The camera is 0.42 m from the block's slot, in front of that plane
    (+z), above it and to the right, so that faces of both objects constrain every direction
    and the slot is seen from the front; depth in 0.1 mm units; ``camera.X_WC`` is its pose
    in the environment (world) frame.
    """
    f = 525.0 * width / 640.0
    target = np.array([0.0, 0.10, 0.0])
    view = np.array([0.30, 0.45, 0.85])
    eye = target + 0.42 * view / np.linalg.norm(view)
    X_EC = pose_looking_at(eye, target, up=BUILTIN_UP)
    cam = Camera(f, f, (width - 1) / 2, (height - 1) / 2, width, height, 1e-4, X_EC)
    return cam, invert_pose(X_EC)


def polyhedron_triangles(poly: Polyhedron) -> Triangles:
    """Return ``(vertices, triangles)`` of a polyhedron's face triangulation (its own units)."""
    tri = np.concatenate([np.asarray(t, dtype=np.int64) for t in poly.face_triangles])
    return np.asarray(poly.vertices, dtype=np.float64), tri


@dataclass(frozen=True)
class RenderedDemo:
    """The built-in example rendered into a frames folder (see :func:`render_builtin`).

    Attributes
    ----------
    frames : Path
        The frames folder (``docs/perception.md`` layout).
    demo : SyntheticDemo
        The scripted demonstration and its ground truth (``X_EG_true``, ``times``, metres).
    grasped, environment : (vertices, triangles)
        The two models, metres, own frames (what the tracker registers).
    camera : Camera
        The camera (``camera.X_WC`` is its pose in the environment frame).
    X_CE : ndarray, shape (4, 4)
        True pose of the environment in the camera frame, metres.
    X_CG0 : ndarray, shape (4, 4)
        True pose of the grasped object in the camera frame at the first frame, metres.
    """

    frames: Path
    demo: SyntheticDemo
    grasped: Triangles
    environment: Triangles
    camera: Camera
    X_CE: FloatArray
    X_CG0: FloatArray


SYNTHETIC_UP: dict[str, tuple[float, float, float]] = {"peg_in_hole_2d": BUILTIN_UP}
"""Up direction of the :mod:`apo.synthetic` demonstrations that are not z-up (``apo.shapes``)."""


def synthetic_camera(
    demo: SyntheticDemo, width: int = 640, height: int = 480
) -> tuple[Camera, FloatArray]:
    """Return a camera that sees a whole :mod:`apo.synthetic` demonstration, and ``X_CE``.

    The camera (``fx = fy = 525 * width / 640``, depth in 0.1 mm units) looks at the centre
    of the bounding box of the environment and of the grasped object over all its true poses,
    just far enough for the box's bounding sphere to fit in the image, from 30 deg above and
    from one of the four diagonals (front right, front left, back right, back left; front is
    ``-y`` for z-up scenes, ``+z`` for y-up ones, :data:`SYNTHETIC_UP`), whichever sees most
    of the grasped object over the demonstration (walls of the environment hide it from some
    sides). On a diagonal, two side faces of a box-like environment are in view: one seen
    nearly edge-on leaves its sideways position to silhouettes (a 2 mm bias measured on a
    400 mm table box seen from 0.3 of the distance to the side).
    """
    from apo.perception.render import _frame_with_z_up, render_scene

    up = SYNTHETIC_UP.get(demo.name, (0.0, 0.0, 1.0))
    G = polyhedron_triangles(demo.grasped)
    E = polyhedron_triangles(demo.environment)
    X = np.asarray(demo.X_EG_true, dtype=np.float64)
    moved = np.einsum("nij,kj->nki", X[:, :3, :3], G[0]) + X[:, None, :3, 3]
    pts = np.vstack([E[0], moved.reshape(-1, 3)])
    lo, hi = pts.min(0), pts.max(0)
    centre, radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2
    a, b, u = _frame_with_z_up(up)
    f = 525.0 * width / 640.0
    distance = 1.1 * radius / np.sin(np.arctan(min(width, height) / 2 / f))
    frames = np.unique(np.linspace(0, len(X) - 1, 8).round().astype(int))
    best: tuple[float, Camera, FloatArray] | None = None
    for side, front in ((1, 1), (-1, 1), (1, -1), (-1, -1)):
        view = 0.60 * side * a - 0.70 * front * b + 0.50 * u
        X_EC = pose_looking_at(centre + distance * view / np.linalg.norm(view), centre, up=up)
        cam = Camera(f, f, (width - 1) / 2, (height - 1) / 2, width, height, 1e-4, X_EC)
        X_CE = invert_pose(X_EC)
        small = cam.subsampled(4)
        seen: list[float] = []
        for k in frames:  # the grasped object's visible share of its own silhouette
            both = render_scene([E, G], [X_CE, X_CE @ X[k]], small).label
            alone = int(np.count_nonzero(render_scene([G], [X_CE @ X[k]], small).label == 0))
            seen.append(int(np.count_nonzero(both == 1)) / max(alone, 1))
        score = float(np.mean(seen))
        if best is None or score > best[0] + 0.02:
            best = (score, cam, X_CE)
    assert best is not None
    return best[1], best[2]


def render_synthetic(
    demo: SyntheticDemo,
    out_dir: str | Path,
    *,
    camera: tuple[Camera, FloatArray] | None = None,
    width: int = 640,
    height: int = 480,
    noise: DepthNoise | float | None = None,
    seed: int | None = 0,
    hand: bool = False,
) -> RenderedDemo:
    """Render a :mod:`apo.synthetic` demonstration's true poses into a frames folder.

    Parameters
    ----------
    demo : SyntheticDemo
        The demonstration (its ``X_EG_true`` and ``times`` are rendered, metres).
    out_dir : str or Path
        Folder to create (or fill).
    camera : (Camera, ndarray of shape (4, 4)), optional
        The camera and ``X_CE``; default :func:`synthetic_camera` at ``width x height``.
    width, height : int, optional
        Image size of the default camera, pixels.
    noise : DepthNoise or float or None, optional
        Sensor model (see :func:`apo.perception.render.render_demonstration`; None: the
        default, 1 mm at 1 m).
    seed : int or None, optional
        Seed of the noise.
    hand : bool, optional
        Add a hand holding the grasped object's upper part.

    Returns
    -------
    RenderedDemo
    """
    G = polyhedron_triangles(demo.grasped)
    E = polyhedron_triangles(demo.environment)
    cam, X_CE = camera if camera is not None else synthetic_camera(demo, width, height)
    out = render_demonstration(
        G, E, X_CE, demo.X_EG_true, demo.times, cam, out_dir,
        units="m", noise=noise, seed=seed, hand=hand,
        up=SYNTHETIC_UP.get(demo.name, (0.0, 0.0, 1.0)),
    )  # fmt: skip
    return RenderedDemo(out, demo, G, E, cam, X_CE, X_CE @ demo.X_EG_true[0])


def render_builtin(
    out_dir: str | Path,
    *,
    width: int = 640,
    height: int = 480,
    n_frames: int = 60,
    noise: DepthNoise | float | None = None,
    seed: int | None = 0,
    hand: bool = False,
) -> RenderedDemo:
    """Render the built-in example's true poses into a frames folder.

    The demonstration is :func:`apo.synthetic.peg_in_hole_2d` (the one ``apo demo``
    recognises), seen by :func:`builtin_camera`, on a table, with a recorded background.

    Parameters
    ----------
    out_dir : str or Path
        Folder to create (or fill).
    width, height : int, optional
        Image size, pixels.
    n_frames : int, optional
        Frames of the demonstration (at its 10 frames/s).
    noise : DepthNoise or float or None, optional
        Sensor model (see :func:`apo.perception.render.render_demonstration`; None: the
        default, 1 mm at 1 m, 0.18 mm at the parts).
    seed : int or None, optional
        Seed of the noise.
    hand : bool, optional
        Add a hand holding the peg's crossbar.

    Returns
    -------
    RenderedDemo
    """
    from apo.synthetic import peg_in_hole_2d

    return render_synthetic(
        peg_in_hole_2d(n_frames),
        out_dir,
        camera=builtin_camera(width, height),
        noise=noise,
        seed=seed,
        hand=hand,
    )
