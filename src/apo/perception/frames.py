"""Recorded frames on disk: the camera model, the folder layout, reading, writing, validation.

The layout (``docs/perception.md``) of a frames folder ``FRAMES/``::

    camera.json            {"fx", "fy", "cx", "cy", "width", "height", "depth_scale"[, "pose"]}
    rgb/000000.png         8-bit colour, width x height (RGB or RGBA; alpha ignored)
    depth/000000.png       16-bit single channel; metres = value * depth_scale; 0 = no measurement
    rgb/000001.png ...     frames numbered from 000000 without gaps, six digits
    background/rgb.png     optional: the scene without the two objects
    background/depth.png   optional: its depth (same encoding as depth/)
    timestamps.txt         optional: one time in seconds per frame, increasing

Pixel ``(row v, column u)`` has its centre at image coordinates ``(u, v)``; the camera frame
``C`` has ``x`` right, ``y`` down and ``z`` forward (OpenCV), and a depth value is the ``z``
coordinate of the surface point, not the distance along the ray. ``pose`` is the camera in the
world frame ``X_WC`` as ``[x, y, z, qw, qx, qy, qz]`` (metres).

PNG files are read and written with Pillow (a dependency of matplotlib), so frames work
without the optional OpenCV.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from apo.errors import InputFormatError
from apo.spatial import pose_from_xyz_quat, position_quaternion_from_pose
from apo.typing import FloatArray

__all__ = [
    "DEFAULT_FPS",
    "Camera",
    "FrameSource",
    "Frames",
    "open_frames",
    "read_camera",
    "write_background",
    "write_camera",
    "write_frame",
    "write_timestamps",
]

DEFAULT_FPS = 30.0
"""Frame rate assumed when a frames folder has no ``timestamps.txt`` (t = index / 30 s)."""

_FRAME_NAME = re.compile(r"^(\d{6})\.png$")
_CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height", "depth_scale")


@dataclass(frozen=True)
class Camera:
    """A calibrated pinhole depth camera (no distortion: frames are rectified).

    Attributes
    ----------
    fx, fy : float
        Focal lengths, pixels.
    cx, cy : float
        Principal point, pixels (pixel centres at integer coordinates).
    width, height : int
        Image size, pixels.
    depth_scale : float
        Metres per unit of the 16-bit depth images (0.001: millimetres).
    X_WC : ndarray, shape (4, 4), or None
        Pose of the camera frame ``C`` in the world frame ``W`` (metres), if known.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    depth_scale: float = 0.001
    X_WC: FloatArray | None = field(default=None, compare=False)

    def backproject(self, depth: npt.ArrayLike, mask: npt.ArrayLike | None = None) -> FloatArray:
        """Return the 3-D points (camera frame, metres) of the valid pixels of a depth image.

        Parameters
        ----------
        depth : ndarray, shape (height, width)
            Depth in metres, 0 (or NaN) where there is no measurement.
        mask : ndarray of bool, shape (height, width), optional
            Pixels to keep (in addition to valid depth).

        Returns
        -------
        points_C : ndarray, shape (N, 3)
            Points in the camera frame, metres, in row-major pixel order.
        """
        d = np.asarray(depth, dtype=np.float64)
        keep = np.isfinite(d) & (d > 0)
        if mask is not None:
            keep &= np.asarray(mask, dtype=bool)
        v, u = np.nonzero(keep)
        z = d[v, u]
        return np.column_stack(((u - self.cx) * z / self.fx, (v - self.cy) * z / self.fy, z))

    def project(self, points_C: npt.ArrayLike) -> FloatArray:
        """Return the image coordinates ``(u, v)`` (pixels) of points in the camera frame."""
        P = np.asarray(points_C, dtype=np.float64)
        return np.column_stack(
            (self.fx * P[:, 0] / P[:, 2] + self.cx, self.fy * P[:, 1] / P[:, 2] + self.cy)
        )

    def scaled(self, factor: float) -> Camera:
        """Return the camera for images resized by ``factor`` (e.g. 0.5 for half size)."""
        return Camera(
            self.fx * factor,
            self.fy * factor,
            (self.cx + 0.5) * factor - 0.5,
            (self.cy + 0.5) * factor - 0.5,
            round(self.width * factor),
            round(self.height * factor),
            self.depth_scale,
            self.X_WC,
        )

    def crop(self, u0: int, v0: int, width: int, height: int) -> Camera:
        """Return the camera of the image window with top-left pixel ``(u0, v0)``."""
        return Camera(
            self.fx,
            self.fy,
            self.cx - u0,
            self.cy - v0,
            width,
            height,
            self.depth_scale,
            self.X_WC,
        )

    def subsampled(self, step: int) -> Camera:
        """Return the camera of the image ``image[::step, ::step]`` (every step-th pixel)."""
        if step < 1:
            raise ValueError(f"step must be a positive integer, got {step}")
        return Camera(
            self.fx / step,
            self.fy / step,
            self.cx / step,
            self.cy / step,
            -(-self.width // step),
            -(-self.height // step),
            self.depth_scale,
            self.X_WC,
        )

    def to_json(self) -> dict[str, Any]:
        """Return the ``camera.json`` dictionary (``pose`` as ``[x, y, z, qw, qx, qy, qz]``)."""
        out: dict[str, Any] = {
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "width": self.width,
            "height": self.height,
            "depth_scale": self.depth_scale,
        }
        if self.X_WC is not None:
            p, q = position_quaternion_from_pose(self.X_WC)
            out["pose"] = [*map(float, p), *map(float, q)]
        return out


def camera_from_json(data: Any, source: str | Path) -> Camera:
    """Return the camera of a ``camera.json`` dictionary; errors name ``source``.

    Raises
    ------
    InputFormatError
        A key is missing or has a value of the wrong type or range.
    """
    if not isinstance(data, dict):
        raise InputFormatError(f"{source}: expected a JSON object, got {type(data).__name__}")
    missing = [k for k in _CAMERA_KEYS if k not in data]
    if missing:
        raise InputFormatError(
            f"{source}: missing key(s) {', '.join(missing)}; "
            f"expected {', '.join(_CAMERA_KEYS)} and optional pose"
        )
    unknown = sorted(set(data) - {*_CAMERA_KEYS, "pose"})
    if unknown:
        raise InputFormatError(f"{source}: unknown key(s) {', '.join(unknown)}")
    values: dict[str, float] = {}
    for key in _CAMERA_KEYS:
        v = data[key]
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise InputFormatError(f"{source}: {key} must be a finite number, got {v!r}")
        values[key] = float(v)
    for key in ("width", "height"):
        if not values[key].is_integer() or values[key] < 1:
            raise InputFormatError(f"{source}: {key} must be a positive integer, got {data[key]!r}")
    for key in ("fx", "fy", "depth_scale"):
        if values[key] <= 0:
            raise InputFormatError(f"{source}: {key} must be positive, got {data[key]!r}")
    X_WC = None
    if "pose" in data and data["pose"] is not None:
        pose = data["pose"]
        if (
            not isinstance(pose, list)
            or len(pose) != 7
            or not all(isinstance(x, int | float) and not isinstance(x, bool) for x in pose)
        ):
            raise InputFormatError(
                f"{source}: pose must be 7 numbers [x, y, z, qw, qx, qy, qz], got {pose!r}"
            )
        try:
            X_WC = pose_from_xyz_quat(pose)
        except ValueError as exc:
            raise InputFormatError(f"{source}: pose: {exc}") from None
    return Camera(
        values["fx"],
        values["fy"],
        values["cx"],
        values["cy"],
        int(values["width"]),
        int(values["height"]),
        values["depth_scale"],
        X_WC,
    )


def read_camera(path: str | Path) -> Camera:
    """Read a ``camera.json`` file.

    Raises
    ------
    InputFormatError
        Missing or unreadable file, invalid JSON, missing or bad keys.
    """
    p = Path(path)
    if not p.is_file():
        raise InputFormatError(f"{p}: camera calibration file not found")
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputFormatError(f"{p}: not valid JSON: {exc}") from None
    return camera_from_json(data, p)


def write_camera(path: str | Path, camera: Camera) -> None:
    """Write ``camera.json``."""
    Path(path).write_text(json.dumps(camera.to_json(), indent=2) + "\n", encoding="utf-8")


class FrameSource(Protocol):
    """A recorded sequence of registered colour and depth frames (what tracking reads)."""

    @property
    def camera(self) -> Camera:
        """The colour and depth camera (shared: the images are registered)."""
        ...

    @property
    def times(self) -> FloatArray:
        """Time of each frame, seconds, shape (N,)."""
        ...

    def __len__(self) -> int:
        """Return the number of frames."""
        ...

    def rgb(self, index: int) -> npt.NDArray[np.uint8]:
        """Colour image of a frame, shape (height, width, 3)."""
        ...

    def depth(self, index: int) -> npt.NDArray[np.float32]:
        """Depth image of a frame, metres, 0 where there is no measurement."""
        ...

    def background(self) -> tuple[npt.NDArray[np.uint8] | None, npt.NDArray[np.float32] | None]:
        """Colour and depth of the scene without the objects, each None when not recorded."""
        ...


def _read_png(path: Path, *, kind: str, camera: Camera) -> npt.NDArray[Any]:
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise InputFormatError(f"{path}: file not found")
    try:
        with Image.open(path) as im:
            mode = im.mode
            arr = np.array(im)
    except (UnidentifiedImageError, OSError) as exc:
        raise InputFormatError(f"{path}: not a readable PNG image ({exc})") from None
    if kind == "depth":
        if arr.ndim != 2 or mode not in ("I;16", "I;16B", "I;16L", "I"):
            raise InputFormatError(
                f"{path}: depth must be a 16-bit single-channel PNG, got mode {mode} "
                f"with shape {arr.shape}"
            )
        if arr.dtype != np.uint16:
            if arr.min(initial=0) < 0 or arr.max(initial=0) > 65535:
                raise InputFormatError(f"{path}: depth values outside 0..65535")
            arr = arr.astype(np.uint16)
    else:
        if mode == "RGBA":
            arr = arr[:, :, :3]
        elif mode != "RGB":
            raise InputFormatError(f"{path}: colour must be an 8-bit RGB(A) PNG, got mode {mode}")
    if arr.shape[:2] != (camera.height, camera.width):
        raise InputFormatError(
            f"{path}: image is {arr.shape[1]}x{arr.shape[0]}, camera.json says "
            f"{camera.width}x{camera.height}"
        )
    return arr


def _frame_indices(folder: Path) -> list[int]:
    if not folder.is_dir():
        raise InputFormatError(f"{folder}: folder not found (expected {folder.name}/NNNNNN.png)")
    indices = []
    for entry in folder.iterdir():
        m = _FRAME_NAME.match(entry.name)
        if m:
            indices.append(int(m.group(1)))
        elif entry.suffix.lower() == ".png":
            raise InputFormatError(
                f"{entry}: frame files must be named with six digits, e.g. 000000.png"
            )
    return sorted(indices)


def _read_times(path: Path, n: int) -> FloatArray:
    times: list[float] = []
    for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        try:
            times.append(float(s))
        except ValueError:
            raise InputFormatError(
                f"{path}:{lineno}: expected one time in seconds, got {s!r}"
            ) from None
    t = np.asarray(times, dtype=np.float64)
    if len(t) != n:
        raise InputFormatError(f"{path}: {len(t)} times for {n} frames; expected one per frame")
    if not np.all(np.isfinite(t)):
        raise InputFormatError(f"{path}: times must be finite")
    bad = np.nonzero(np.diff(t) <= 0)[0]
    if len(bad):
        raise InputFormatError(f"{path}: times must increase; frame {bad[0] + 1} does not")
    return t


class Frames:
    """A frames folder (``rgb/``, ``depth/``, ``camera.json``, ...), read lazily.

    Use :func:`open_frames`, which validates the layout.

    Attributes
    ----------
    root : Path
        The folder.
    camera : Camera
        Its calibration.
    times : ndarray, shape (N,)
        Seconds, from ``timestamps.txt`` or ``index / DEFAULT_FPS``.
    """

    def __init__(self, root: Path, camera: Camera, count: int, times: FloatArray) -> None:
        self.root = root
        self._camera = camera
        self._count = count
        self._times = times

    @property
    def camera(self) -> Camera:
        """The calibration of ``camera.json``."""
        return self._camera

    @property
    def times(self) -> FloatArray:
        """Frame times, seconds, shape (N,)."""
        return self._times

    def __len__(self) -> int:
        """Return the number of frames."""
        return self._count

    def _check(self, index: int) -> None:
        if not 0 <= index < self._count:
            raise IndexError(f"frame {index} out of range 0..{self._count - 1}")

    def rgb(self, index: int) -> npt.NDArray[np.uint8]:
        """Colour image of frame ``index``, uint8, shape (height, width, 3)."""
        self._check(index)
        path = self.root / "rgb" / f"{index:06d}.png"
        return np.asarray(_read_png(path, kind="rgb", camera=self._camera), dtype=np.uint8)

    def depth(self, index: int) -> npt.NDArray[np.float32]:
        """Depth of frame ``index``, float32 metres, 0 where there is no measurement."""
        self._check(index)
        path = self.root / "depth" / f"{index:06d}.png"
        raw = _read_png(path, kind="depth", camera=self._camera)
        return (raw * np.float32(self._camera.depth_scale)).astype(np.float32)

    def background(
        self,
    ) -> tuple[npt.NDArray[np.uint8] | None, npt.NDArray[np.float32] | None]:
        """Colour and depth of ``background/``, each None when absent."""
        rgb_path = self.root / "background" / "rgb.png"
        depth_path = self.root / "background" / "depth.png"
        rgb = (
            np.asarray(_read_png(rgb_path, kind="rgb", camera=self._camera), dtype=np.uint8)
            if rgb_path.exists()
            else None
        )
        depth = (
            (
                _read_png(depth_path, kind="depth", camera=self._camera)
                * np.float32(self._camera.depth_scale)
            ).astype(np.float32)
            if depth_path.exists()
            else None
        )
        return rgb, depth


def open_frames(path: str | Path, *, fps: float = DEFAULT_FPS) -> FrameSource:
    """Open a recorded sequence: a frames folder, or a stereo folder (``stereo.json``).

    Parameters
    ----------
    path : str or Path
        A frames folder (``camera.json``, ``rgb/``, ``depth/``; see the module notes) or a
        stereo folder (``stereo.json``, ``left/``, ``right/``; see :mod:`apo.perception.stereo`).
    fps : float, optional
        Frame rate used for the times when there is no ``timestamps.txt``.

    Returns
    -------
    FrameSource
        Frames read lazily; every image is checked against the calibration when read.

    Raises
    ------
    InputFormatError
        The layout is not the documented one; the message names the file and the problem.
    """
    root = Path(path)
    if not root.is_dir():
        raise InputFormatError(f"{root}: frames folder not found")
    if (root / "stereo.json").is_file() and not (root / "camera.json").is_file():
        from apo.perception.stereo import open_stereo

        return open_stereo(root, fps=fps)
    camera = read_camera(root / "camera.json")
    rgb = _frame_indices(root / "rgb")
    depth = _frame_indices(root / "depth")
    if not rgb:
        raise InputFormatError(f"{root / 'rgb'}: no frames (expected rgb/000000.png, ...)")
    _check_numbering(root, "rgb", rgb)
    _check_numbering(root, "depth", depth)
    if len(rgb) != len(depth):
        shorter, longer = ("rgb", "depth") if len(rgb) < len(depth) else ("depth", "rgb")
        first = min(len(rgb), len(depth))
        raise InputFormatError(
            f"{root / shorter / f'{first:06d}.png'}: missing "
            f"({longer}/{first:06d}.png exists): rgb/ has {len(rgb)} frames, depth/ {len(depth)}"
        )
    n = len(rgb)
    ts = root / "timestamps.txt"
    if ts.exists():
        times = _read_times(ts, n)
    else:
        if fps <= 0:
            raise InputFormatError(f"fps must be positive, got {fps}")
        times = np.arange(n, dtype=np.float64) / fps
    return Frames(root, camera, n, times)


def _check_numbering(root: Path, name: str, indices: Sequence[int]) -> None:
    if not indices:
        raise InputFormatError(f"{root / name}: no frames (expected {name}/000000.png, ...)")
    for expected, got in enumerate(indices):
        if got != expected:
            raise InputFormatError(
                f"{root / name / f'{expected:06d}.png'}: missing; frames must be numbered "
                f"from 000000 without gaps"
            )


def _depth_to_png(depth: npt.ArrayLike, camera: Camera) -> npt.NDArray[np.uint16]:
    d = np.asarray(depth, dtype=np.float64)
    units = np.where(np.isfinite(d) & (d > 0), np.round(d / camera.depth_scale), 0.0)
    if units.max(initial=0.0) > 65535:
        raise InputFormatError(
            f"depth up to {d[np.isfinite(d)].max():.3f} m does not fit 16 bits with "
            f"depth_scale {camera.depth_scale}"
        )
    return units.astype(np.uint16)


def _write_png(path: Path, image: npt.NDArray[Any]) -> None:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path, compress_level=1)


def write_frame(
    root: str | Path,
    index: int,
    rgb: npt.ArrayLike,
    depth: npt.ArrayLike,
    camera: Camera,
) -> None:
    """Write ``rgb/NNNNNN.png`` and ``depth/NNNNNN.png`` of one frame.

    Parameters
    ----------
    root : str or Path
        The frames folder.
    index : int
        Frame number (six digits in the file name).
    rgb : ndarray of uint8, shape (height, width, 3)
        Colour image.
    depth : ndarray, shape (height, width)
        Depth in metres, 0 or NaN where there is no measurement; stored in units of
        ``camera.depth_scale``.
    camera : Camera
        The calibration (for the depth scale and the image size).
    """
    r = Path(root)
    rgb_arr = np.asarray(rgb, dtype=np.uint8)
    if rgb_arr.shape != (camera.height, camera.width, 3):
        raise ValueError(
            f"rgb has shape {rgb_arr.shape}, expected {(camera.height, camera.width, 3)}"
        )
    _write_png(r / "rgb" / f"{index:06d}.png", rgb_arr)
    _write_png(r / "depth" / f"{index:06d}.png", _depth_to_png(depth, camera))


def write_background(
    root: str | Path, rgb: npt.ArrayLike, depth: npt.ArrayLike, camera: Camera
) -> None:
    """Write ``background/rgb.png`` and ``background/depth.png`` (depth in metres)."""
    r = Path(root)
    _write_png(r / "background" / "rgb.png", np.asarray(rgb, dtype=np.uint8))
    _write_png(r / "background" / "depth.png", _depth_to_png(depth, camera))


def write_timestamps(root: str | Path, times: npt.ArrayLike) -> None:
    """Write ``timestamps.txt`` (one time in seconds per line)."""
    t = np.asarray(times, dtype=np.float64)
    Path(root, "timestamps.txt").write_text("".join(f"{x:.6f}\n" for x in t), encoding="utf-8")
