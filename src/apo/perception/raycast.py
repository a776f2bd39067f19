"""A second renderer, independent of :mod:`apo.perception.render`: recordings apo was not made with.

Issue 11's acceptance recordings come from a renderer other than apo's own. This one shares
no code with :mod:`apo.perception.render` (only the look-at of the camera) and models the
sensor differently, so that a tracker tuned, even unknowingly, to the first renderer's
quirks fails here:

- **Geometry** by Open3D's ray casting (``RaycastingScene``), two rays a pixel at
  ``(u -/+ 0.25, v -/+ 0.25)`` (pixel centres at integer coordinates): where the two disagree
  (an edge) the pixel is dropped, takes one of the two depths or their mean (a *flying
  pixel*, as time-of-flight and stereo sensors give), at random.
- **A projector beside the camera** (structured light, ``baseline`` 40-80 mm along the
  camera's x): a surface point the projector does not see has no depth (the shadow band
  beside every raised edge), where apo's renderer drops depth at discontinuities only.
- **Noise in disparity**, ``sigma_z = c z^2`` as the issue describes, but half of it spatially
  correlated (white noise smoothed over about 3 pixels) and the depth stored in **whole
  millimetres** (``depth_scale`` 0.001, as most RGB-D cameras write it); random blob-shaped
  dropouts and dark surfaces returning less.
- **Colour** by Lambert shading under a light from above the camera, an ambient term and a
  sensor gamma, with anti-aliased edges (the mean of the two rays); the table a random
  colour, plain or with wood-like stripes; the parts any colour, the table's included.
- **A hand** (a box over the grasped part's top fifth and a forearm) that moves with the
  part, skin of a random tone.
- **Cameras** with random intrinsics (focal length 380-620 px, principal point off centre by
  up to 12 px) rather than the named models of :data:`apo.perception.variants.CAMERAS`.

The demonstrations are :func:`apo.synthetic.random_variant` of the T-peg into the U-slot and
the square peg into the pocket: random sizes, speeds, approach and placement (the
environment's frame turned arbitrarily; the table is perpendicular to the scene's true up).
Open3D is required (``apo[perception]``).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from apo.perception.camera import Camera, write_camera
from apo.perception.render import pose_looking_at
from apo.typing import FloatArray

if TYPE_CHECKING:
    from apo.synthetic import SyntheticDemo

__all__ = ["Conditions", "IndependentRecording", "random_conditions", "render_independent"]

Mesh = tuple[FloatArray, npt.NDArray[np.int64]]

DEMOS = ("peg_in_hole_2d", "square_peg_in_hole")
"""The :mod:`apo.synthetic` demonstrations drawn (issue 11's two kinds of recording)."""

_UP = {"peg_in_hole_2d": (0.0, 1.0, 0.0), "square_peg_in_hole": (0.0, 0.0, 1.0)}
"""Up in each demonstration's environment frame before its random placement."""


PALM = 0.085
"""Width of a hand across its four fingers, metres."""


@dataclass(frozen=True)
class Conditions:
    """How one recording is made (metres, degrees, colours linear in [0, 1])."""

    demo: str
    demo_seed: int
    camera: Camera
    distance: float
    elevation: float
    azimuth: float
    noise: float
    baseline: float
    table: tuple[float, float, float]
    striped: bool
    parts: tuple[float, float, float]
    hand: bool
    skin: tuple[float, float, float]
    finger: float
    background: bool
    blobs: int
    seed: int

    def label(self) -> str:
        """Short description for tables."""
        return (
            f"{self.demo} f={self.camera.fx:.0f} {self.distance:.2f}m {self.elevation:.0f}deg "
            f"c={self.noise * 1e3:.1f} b={self.baseline * 1e3:.0f}mm"
            f"{' striped' if self.striped else ''}{' hand' if self.hand else ''}"
            f"{' bg' if self.background else ''}"
        )


@dataclass(frozen=True)
class IndependentRecording:
    """A rendered recording and its truth (metres).

    ``grasped`` and ``environment`` are the models in their own frames (what a user gives
    ``apo track``); ``X_CE`` the environment in the camera frame; ``demo`` the scripted
    demonstration with its true poses ``X_EG_true`` and ``times``.
    """

    frames: Path
    demo: SyntheticDemo
    grasped: Mesh
    environment: Mesh
    X_CE: FloatArray
    conditions: Conditions


def random_conditions(seed: int, *, demo: str | None = None) -> Conditions:
    """Draw the conditions of one recording from ``seed`` (uniform over documented ranges)."""
    rng = np.random.default_rng([seed, 11])
    grey = float(rng.uniform(0.3, 0.8))
    tables = [(grey, grey, grey), (0.85, 0.85, 0.82), (0.55, 0.38, 0.22), (0.25, 0.35, 0.3)]
    table = tables[int(rng.integers(len(tables)))]
    part_choices = [(0.9, 0.9, 0.88), table, (0.75, 0.15, 0.1), (0.85, 0.7, 0.15), (0.2, 0.2, 0.22)]
    f = float(rng.uniform(380.0, 620.0))
    return Conditions(
        demo=demo or DEMOS[int(rng.integers(len(DEMOS)))],
        demo_seed=int(rng.integers(1 << 30)),
        camera=Camera(f, f * float(rng.uniform(0.995, 1.005)),
                      319.5 + float(rng.uniform(-12, 12)), 239.5 + float(rng.uniform(-12, 12)),
                      640, 480, depth_scale=0.001),
        distance=float(rng.uniform(0.3, 1.0)), elevation=float(rng.uniform(20.0, 70.0)),
        azimuth=float(rng.uniform(-60.0, 60.0)),
        noise=float(rng.uniform(1e-3, 6e-3)), baseline=float(rng.uniform(0.04, 0.08)),
        table=table, striped=bool(rng.random() < 0.4),
        parts=part_choices[int(rng.integers(len(part_choices)))],
        hand=bool(rng.random() < 0.5),
        skin=_skin(rng), finger=float(rng.uniform(0.010, 0.020)),
        background=bool(rng.random() < 0.5), blobs=int(rng.integers(0, 12)), seed=seed,
    )  # fmt: skip


def _skin(rng: np.random.Generator) -> tuple[float, float, float]:
    """Return a skin tone (linear RGB): red above green above blue, light to dark."""
    r = float(rng.uniform(0.25, 0.9))
    g = r * float(rng.uniform(0.6, 0.8))
    return r, g, g * float(rng.uniform(0.7, 0.9))


def _demo(c: Conditions) -> tuple[SyntheticDemo, FloatArray]:
    """Return the demonstration and the scene's up direction in its (placed) environment frame."""
    from apo import synthetic

    demo = synthetic.random_variant(c.demo_seed, name=c.demo)
    placement = np.asarray(demo.meta["variant"]["placement"], dtype=np.float64)
    up = placement[:3, :3] @ np.asarray(_UP[c.demo], dtype=np.float64)
    return demo, up


def _triangles(poly: Any) -> Mesh:
    """Return a polyhedron's vertices and its faces' triangles."""
    tri = np.concatenate([np.asarray(t, dtype=np.int64) for t in poly.face_triangles])
    return np.asarray(poly.vertices, dtype=np.float64), tri


def _moved(mesh: Mesh, X: FloatArray) -> Mesh:
    return mesh[0] @ X[:3, :3].T + X[:3, 3], mesh[1]


def _table(environment: Mesh, up: FloatArray, size: float = 3.0) -> Mesh:
    """Return a square under the environment, perpendicular to ``up``, normal up."""
    V = environment[0]
    low = float((V @ up).min())
    centre = V.mean(axis=0) - (float(V.mean(axis=0) @ up) - low) * up
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    h = size / 2
    P = np.array(
        [centre + h * (sa * a + sb * b) for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    )
    return P, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)


def _box(lo: FloatArray, hi: FloatArray) -> Mesh:
    import trimesh

    box = trimesh.creation.box(bounds=np.array([lo, hi]))
    return np.asarray(box.vertices, dtype=np.float64), np.asarray(box.faces, dtype=np.int64)


def _hand(grasped: Mesh, up_G: FloatArray, away_G: FloatArray, finger: float) -> list[Mesh]:
    """Return a hand over the grasped part's top fifth and a forearm (grasped frame).

    The hand is a block around the top fifth (at most :data:`PALM` of it along each
    axis, centred: the ends of a wide crossbar stick out), ``finger`` thick on the sides
    (10-20 mm: fingers) and twice that on top (the palm); the forearm rises at 30 degrees from the
    hand's top towards ``away_G`` (horizontal, away from the camera: the person stands
    across the table).
    """
    import trimesh

    V = grasped[0]
    axis = int(np.argmax(np.abs(up_G)))
    sign = float(np.sign(up_G[axis]))
    top = V[:, axis] * sign
    keep = top >= top.max() - 0.2 * (top.max() - top.min())
    lo, hi = V[keep].min(axis=0), V[keep].max(axis=0)
    mid = (lo + hi) / 2  # a hand is at most PALM wide along the part: wider ends stick out
    lo, hi = np.maximum(lo, mid - PALM / 2), np.minimum(hi, mid + PALM / 2)
    lo, hi = lo - finger, hi + finger
    if sign > 0:
        hi[axis] += finger
    else:
        lo[axis] -= finger
    start = (lo + hi) / 2
    start[axis] = hi[axis] if sign > 0 else lo[axis]
    direction = up_G * math.sin(math.radians(30.0)) + away_G * math.cos(math.radians(30.0))
    end = start + 0.35 * direction / np.linalg.norm(direction)
    arm = trimesh.creation.cylinder(radius=0.035, segment=np.array([start, end]))
    return [_box(lo, hi), (np.asarray(arm.vertices, np.float64), np.asarray(arm.faces, np.int64))]


def _hand_directions(
    X_EG: FloatArray, X_EC: FloatArray, up: FloatArray, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray]:
    """Up and a horizontal direction away from the camera (+/- 60 deg), grasped frame."""
    away = X_EC[:3, 2] - (X_EC[:3, 2] @ up) * up
    away /= np.linalg.norm(away)
    side = np.cross(up, away)
    a = math.radians(float(rng.uniform(-60.0, 60.0)))
    horizontal = math.cos(a) * away + math.sin(a) * side
    R = X_EG[:3, :3]
    return R.T @ up, R.T @ horizontal


def _camera(c: Conditions, demo: SyntheticDemo, up: FloatArray) -> FloatArray:
    """``X_EC``: the camera looking at the middle of the demonstration's bounding box."""
    G, E = _triangles(demo.grasped), _triangles(demo.environment)
    X = np.asarray(demo.X_EG_true, dtype=np.float64)
    pts = np.vstack([E[0], *(G[0] @ x[:3, :3].T + x[:3, 3] for x in X[:: max(1, len(X) // 20)])])
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    az, el = math.radians(c.azimuth), math.radians(c.elevation)
    view = math.cos(el) * (math.cos(az) * a + math.sin(az) * b) + math.sin(el) * up
    return pose_looking_at(centre + c.distance * view, centre, up=up)


class _Scene:
    """Open3D ray casting of a list of meshes with one albedo each."""

    def __init__(self, meshes: list[Mesh], albedo: list[tuple[float, float, float]]) -> None:
        import open3d

        o3d: Any = open3d
        self.o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        for V, T in meshes:
            self.scene.add_triangles(
                o3d.core.Tensor(np.ascontiguousarray(V, dtype=np.float32)),
                o3d.core.Tensor(np.ascontiguousarray(T, dtype=np.uint32)),
            )
        self.albedo = np.array([*albedo, (0.0, 0.0, 0.0)], dtype=np.float64)

    def cast(self, origin: FloatArray, directions: FloatArray) -> tuple[FloatArray, ...]:
        """Ray parameter at the hit (inf on a miss), mesh index (-1), unit normal."""
        rays = np.empty((*directions.shape[:-1], 6), dtype=np.float32)
        rays[..., :3] = origin
        rays[..., 3:] = directions
        ans = self.scene.cast_rays(self.o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)
        ids = ans["geometry_ids"].numpy().astype(np.int64)
        ids[~np.isfinite(t)] = -1
        return t, ids, ans["primitive_normals"].numpy().astype(np.float64)


def _ray_directions(c: Camera, X_EC: FloatArray, offset: float) -> FloatArray:
    """Directions (H, W, 3) in the environment frame, camera ``z`` component 1."""
    u, v = np.meshgrid(np.arange(c.width) + offset, np.arange(c.height) + offset)
    d = np.stack([(u - c.cx) / c.fx, (v - c.cy) / c.fy, np.ones_like(u, dtype=np.float64)], -1)
    out: FloatArray = np.asarray(d @ X_EC[:3, :3].T, dtype=np.float64)
    return out


def _shade(
    scene: _Scene, ids: FloatArray, normals: FloatArray, view: FloatArray, light: FloatArray,
    stripes: FloatArray | None,
) -> FloatArray:  # fmt: skip
    """Linear RGB of one ray per pixel: Lambert under ``light`` plus ambient."""
    n = normals * np.sign(-(normals * view).sum(-1, keepdims=True) + 1e-12)
    lam = np.clip((n * light).sum(-1), 0.0, 1.0)[..., None]
    rgb: FloatArray = scene.albedo[ids] * (0.35 + 0.65 * lam)
    if stripes is not None:
        rgb[ids == 0] *= stripes[ids == 0][:, None]
    return rgb


class _Renderer:
    """Renders the frames of one recording (the static meshes cast with the moving ones)."""

    def __init__(self, c: Conditions, X_EC: FloatArray, rng: np.random.Generator) -> None:
        self.c, self.X_EC, self.rng = c, X_EC, rng
        self.origin = X_EC[:3, 3]
        self.dirs = [_ray_directions(c.camera, X_EC, o) for o in (-0.25, 0.25)]
        self.projector = X_EC[:3, 3] + c.baseline * X_EC[:3, 0]
        cam_up = -X_EC[:3, 1]
        self.light = cam_up * 0.8 + X_EC[:3, 2] * -0.6
        self.light /= np.linalg.norm(self.light)

    def frame(self, scene: _Scene, table_stripes: bool) -> tuple[FloatArray, FloatArray]:
        """Depth (metres, 0 = none) and linear RGB of one frame."""
        hits = [scene.cast(self.origin, d) for d in self.dirs]
        (t0, i0, n0), (t1, i1, n1) = hits
        z0, z1 = t0, t1  # the directions' camera z is 1: the ray parameter is the depth
        stripes = [
            self._stripes(t, d) if table_stripes else None
            for t, d in zip((t0, t1), self.dirs, strict=True)
        ]
        rgb = 0.5 * (
            _shade(scene, i0, n0, self.dirs[0], self.light, stripes[0])
            + _shade(scene, i1, n1, self.dirs[1], self.light, stripes[1])
        )
        depth = self._edges(z0, z1)
        depth = self._shadowed(scene, depth)
        depth = self._noisy(depth, dark=scene.albedo[i0].mean(-1) < 0.25)
        return depth, rgb

    def _stripes(self, t: FloatArray, d: FloatArray) -> FloatArray:
        p = self.origin + np.where(np.isfinite(t), t, 0.0)[..., None] * d
        out: FloatArray = 0.85 + 0.15 * np.sin(p @ np.array([97.0, 23.0, 41.0]))
        return out

    def _edges(self, z0: FloatArray, z1: FloatArray) -> FloatArray:
        """Where the two rays disagree: none, one of them, or their mean (flying pixel)."""
        z0 = np.where(np.isfinite(z0), z0, 0.0)
        z1 = np.where(np.isfinite(z1), z1, 0.0)
        edge = np.abs(z0 - z1) > 0.01 * np.maximum(z0, z1)
        pick = self.rng.integers(0, 4, size=z0.shape)
        mixed = np.select([pick == 0, pick == 1, pick == 2], [0.0 * z0, z0, z1], (z0 + z1) / 2)
        return np.where(edge, mixed, (z0 + z1) / 2)

    def _shadowed(self, scene: _Scene, depth: FloatArray) -> FloatArray:
        """Depth dropped where the projector does not light the surface point."""
        centre = _ray_directions(self.c.camera, self.X_EC, 0.0)
        P = self.origin + depth[..., None] * centre
        d = P - self.projector
        length = np.linalg.norm(d, axis=-1)
        ok = depth > 0
        t, _, _ = scene.cast(self.projector, d[ok] / length[ok, None])
        lit = np.zeros_like(ok)
        lit[ok] = t >= length[ok] - max(0.002, 0.004 * float(np.median(length[ok])))
        return np.where(lit, depth, 0.0)

    def _noisy(self, depth: FloatArray, dark: npt.NDArray[np.bool_]) -> FloatArray:
        """Disparity noise (half smoothed over ~3 px), blobs and dark-surface dropouts."""
        from scipy.ndimage import gaussian_filter

        c, cam, rng = self.c, self.c.camera, self.rng
        white = rng.standard_normal(depth.shape)
        smooth = gaussian_filter(rng.standard_normal(depth.shape), 3.0)
        smooth /= smooth.std() + 1e-12
        z = depth + c.noise * depth**2 * (white + smooth) / math.sqrt(2.0)
        drop = (dark & (rng.random(depth.shape) < 0.4)) | (rng.random(depth.shape) < 0.003)
        for _ in range(c.blobs):
            v, u = rng.integers(0, cam.height), rng.integers(0, cam.width)
            r = rng.uniform(2.0, 9.0)
            yy, xx = np.ogrid[: cam.height, : cam.width]
            drop |= (yy - v) ** 2 + (xx - u) ** 2 < r * r
        return np.where(drop | (depth <= 0), 0.0, z)


def _write(
    rgb_path: Path, depth_path: Path, depth: FloatArray, rgb: FloatArray, rng: np.random.Generator,
    depth_scale: float,
) -> None:  # fmt: skip
    """8-bit sRGB with sensor noise, 16-bit depth in whole units of ``depth_scale`` (0: none)."""
    from PIL import Image

    srgb = np.clip(rgb, 0.0, 1.0) ** (1 / 2.2) * 255 + rng.normal(0.0, 2.0, rgb.shape)
    Image.fromarray(np.clip(srgb, 0, 255).astype(np.uint8)).save(rgb_path)
    Image.fromarray(np.round(depth / depth_scale).astype(np.uint16)).save(depth_path)


def render_independent(c: Conditions, out_dir: str | Path) -> IndependentRecording:
    """Render the recording of ``c`` into the frames folder ``out_dir`` (docs/perception.md)."""
    demo, up = _demo(c)
    G, E = _triangles(demo.grasped), _triangles(demo.environment)
    X_EC = _camera(c, demo, up)
    out = Path(out_dir)
    for sub in ("rgb", "depth", *(("background",) if c.background else ())):
        (out / sub).mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([c.seed, 12])
    scale = c.camera.depth_scale
    r = _Renderer(c, X_EC, rng)
    static, albedo = [_table(E, up), E], [c.table, c.parts]
    X = np.asarray(demo.X_EG_true, dtype=np.float64)
    extra = _hand(G, *_hand_directions(X[0], X_EC, up, rng), c.finger) if c.hand else []
    for k, X_EG in enumerate(X):
        moving = [_moved(m, X_EG) for m in [G, *extra]]
        scene = _Scene([*static, *moving], [*albedo, c.parts, *[c.skin] * len(extra)])
        depth, rgb = r.frame(scene, c.striped)
        _write(out / "rgb" / f"{k:06d}.png", out / "depth" / f"{k:06d}.png", depth, rgb, rng, scale)
    if c.background:  # the table alone: the environment is part of the scene to find
        depth, rgb = r.frame(_Scene(static[:1], albedo[:1]), c.striped)
        _write(out / "background" / "rgb.png", out / "background" / "depth.png", depth, rgb, rng,
               scale)  # fmt: skip
    X_CE: FloatArray = np.asarray(np.linalg.inv(X_EC), dtype=np.float64)
    write_camera(out / "camera.json", c.camera)
    (out / "timestamps.txt").write_text("".join(f"{t:.6f}\n" for t in demo.times))
    (out.parent / f"{out.name}.conditions.json").write_text(json.dumps(asdict(c), indent=1) + "\n")
    return IndependentRecording(out, demo, G, E, X_CE, c)
