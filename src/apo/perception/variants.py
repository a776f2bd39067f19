"""Randomised recording conditions for perception tests and benchmarks.

A :class:`Variant` fixes what a recording of an :mod:`apo.synthetic` demonstration varies in
the world: the camera model (intrinsics of common RGB-D cameras, :data:`CAMERAS`), its
distance (0.3 to 1.0 m) and elevation (20 to 70 deg above the table) and azimuth, the table
(grey, white, textured), the depth noise ``sigma(z) = c z^2`` (``c`` 1 to 6 mm per square
metre), random dropouts, a hand and forearm holding the grasped part, and whether background
frames were recorded. :func:`random_variant` draws one from a seed; :func:`render_variant`
renders it (:func:`apo.perception.render.render_demonstration`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from apo.perception.camera import Camera
from apo.perception.example import SYNTHETIC_UP, RenderedDemo, polyhedron_triangles
from apo.perception.render import (
    TABLE_COLOURS,
    WHITE,
    DepthNoise,
    pose_looking_at,
    render_demonstration,
)
from apo.spatial import invert_pose
from apo.typing import FloatArray

__all__ = [
    "CAMERAS",
    "DEMOS",
    "PART_COLOURS",
    "Variant",
    "random_variant",
    "render_variant",
    "variant_camera",
]


CAMERAS: dict[str, tuple[float, float, float, float, int, int]] = {
    "kinect_v1": (525.0, 525.0, 319.5, 239.5, 640, 480),
    "realsense_d435": (383.0, 383.0, 320.5, 237.8, 640, 480),
    "realsense_d415": (594.0, 594.0, 318.0, 241.0, 640, 480),
    "azure_kinect_nfov": (504.2, 504.3, 321.5, 329.0, 640, 576),
    "orbbec_astra": (570.3, 570.3, 319.5, 239.5, 640, 480),
}
"""Depth-camera intrinsics ``(fx, fy, cx, cy, width, height)`` (typical factory values)."""

PART_COLOURS: dict[str, tuple[float, float, float]] = {
    "white": WHITE,
    "blue": (0.20, 0.35, 0.75),
}
"""Albedo of the parts by :attr:`Variant.parts` (besides "table": the table's colour)."""

DEMOS = ("peg_in_hole_2d", "square_peg_in_hole")
"""The demonstrations variants are drawn from: a T-peg into a U-slot, a square peg."""


@dataclass(frozen=True)
class Variant:
    """One set of recording conditions (lengths in metres, angles in degrees).

    Attributes
    ----------
    demo : str
        Name of the :mod:`apo.synthetic` demonstration (:data:`DEMOS`).
    camera : str
        Key of :data:`CAMERAS`.
    distance : float
        Camera to the centre of the scene, metres.
    elevation : float
        Viewing direction above the table plane, degrees.
    azimuth : float
        Around the up axis from the scene's front, degrees.
    table : {"grey", "white", "textured"}
    noise : float
        ``c`` of ``sigma(z) = c z^2``, metres per square metre (1e-3 to 6e-3).
    dropout : float
        Share of pixels without depth besides the edges'.
    hand : bool
        A hand and forearm hold the grasped part.
    background : bool
        Background frames are recorded.
    background_frames : int
        How many (depth frames of the empty scene, combined by the tracker).
    n_frames : int
    seed : int
        Seed of the sensor noise.
    parts : {"white", "table", "blue"}
        Colour of the two parts (:data:`PART_COLOURS`; "table": the table's own colour).
    """

    demo: str
    camera: str
    distance: float
    elevation: float
    azimuth: float
    table: str
    noise: float
    dropout: float
    hand: bool
    background: bool
    n_frames: int = 120
    seed: int = 0
    background_frames: int = 5
    parts: str = "white"

    def label(self) -> str:
        """Short description for tables."""
        return (
            f"{self.demo} {self.camera} {self.distance:.2f}m {self.elevation:.0f}deg "
            f"{self.table} c={self.noise * 1e3:.1f} drop={self.dropout:.2f}"
            f"{' hand+arm' if self.hand else ''}{' bg' if self.background else ''}"
            f" parts={self.parts}"
        )


def random_variant(seed: int, *, demo: str | None = None, n_frames: int = 120) -> Variant:
    """Draw recording conditions from a seed (uniform over the documented ranges)."""
    rng = np.random.default_rng(seed)
    return Variant(
        demo=demo or DEMOS[int(rng.integers(len(DEMOS)))],
        camera=sorted(CAMERAS)[int(rng.integers(len(CAMERAS)))],
        distance=float(rng.uniform(0.3, 1.0)),
        elevation=float(rng.uniform(20.0, 70.0)),
        azimuth=float(rng.uniform(-60.0, 60.0)),
        table=("grey", "white", "textured")[int(rng.integers(3))],
        noise=float(rng.uniform(1e-3, 6e-3)),
        dropout=float(rng.uniform(0.0, 0.05)),
        hand=bool(rng.random() < 0.5),
        background=bool(rng.random() < 0.5),
        n_frames=n_frames,
        seed=seed,
        parts=("white", "table", "blue")[int(rng.integers(3))],  # drawn last: seeds keep
    )


def _demo(v: Variant):  # type: ignore[no-untyped-def]
    from apo import synthetic

    if v.demo not in DEMOS:
        raise ValueError(f"unknown demo {v.demo!r}; expected one of {', '.join(DEMOS)}")
    return getattr(synthetic, v.demo)(v.n_frames)


def variant_camera(v: Variant, demo: object) -> tuple[Camera, FloatArray]:
    """Return the camera of a variant and ``X_CE`` (the camera looks at the scene's centre).

    The centre is that of the bounding box of the environment and the grasped object over
    its true poses; the front of the scene is ``-y`` for z-up demonstrations, ``+z`` for
    y-up ones; depth in 0.1 mm units.
    """
    from apo.perception.render import _frame_with_z_up

    name = str(getattr(demo, "name", ""))
    up = SYNTHETIC_UP.get(name, (0.0, 0.0, 1.0))
    G = polyhedron_triangles(demo.grasped)  # type: ignore[attr-defined]
    E = polyhedron_triangles(demo.environment)  # type: ignore[attr-defined]
    X = np.asarray(demo.X_EG_true, dtype=np.float64)  # type: ignore[attr-defined]
    moved = np.einsum("nij,kj->nki", X[:, :3, :3], G[0]) + X[:, None, :3, 3]
    pts = np.vstack([E[0], moved.reshape(-1, 3)])
    centre = (pts.min(0) + pts.max(0)) / 2
    _, b, u = _frame_with_z_up(up)
    front = -b  # -y for z-up scenes, +z for y-up ones
    side = np.cross(u, front)
    az, el = np.radians(v.azimuth), np.radians(v.elevation)
    horizontal = np.cos(az) * front + np.sin(az) * side
    view = np.cos(el) * horizontal + np.sin(el) * u
    X_EC = pose_looking_at(centre + v.distance * view, centre, up=up)
    fx, fy, cx, cy, w, h = CAMERAS[v.camera]
    cam = Camera(fx, fy, cx, cy, w, h, 1e-4, X_EC)
    return cam, invert_pose(X_EC)


def render_variant(v: Variant, out_dir: str | Path) -> RenderedDemo:
    """Render a variant's demonstration into a frames folder; returns it with the truth."""
    demo = _demo(v)
    G = polyhedron_triangles(demo.grasped)
    E = polyhedron_triangles(demo.environment)
    cam, X_CE = variant_camera(v, demo)
    noise = DepthNoise(sigma_1m=v.noise, dropout=v.dropout)
    out = render_demonstration(
        G, E, X_CE, demo.X_EG_true, demo.times, cam, out_dir,
        units="m", noise=noise, seed=v.seed, hand=v.hand, arm=v.hand,
        background=v.background, table_colour=v.table, background_frames=v.background_frames,
        up=SYNTHETIC_UP.get(demo.name, (0.0, 0.0, 1.0)),
        part_colour=TABLE_COLOURS[v.table] if v.parts == "table" else PART_COLOURS[v.parts],
    )  # fmt: skip
    return RenderedDemo(out, demo, G, E, cam, X_CE, X_CE @ demo.X_EG_true[0])
