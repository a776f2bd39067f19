"""Recorded frames on disk: the camera model, the folder layout, reading, writing, validation.

The layout (``docs/perception.md``) of a frames folder ``FRAMES/``::

    camera.json            {"fx", "fy", "cx", "cy", "width", "height", "depth_scale"[, "pose"]}
    rgb/000000.png         8-bit colour, width x height (RGB or RGBA; alpha ignored)
    depth/000000.png       16-bit single channel; metres = value * depth_scale; 0 = no measurement
    rgb/000001.png ...     frames numbered from 000000 without gaps, six digits
    background/rgb.png     optional: the scene without the two objects
    background/depth.png   optional: its depth (same encoding as depth/)
    background/depth_000001.png ...  optional: more depth frames of the empty scene
    timestamps.txt         optional: one time in seconds per frame, increasing

Pixel ``(row v, column u)`` has its centre at image coordinates ``(u, v)``; the camera frame
``C`` has ``x`` right, ``y`` down and ``z`` forward (OpenCV), and a depth value is the ``z``
coordinate of the surface point, not the distance along the ray. ``pose`` is the camera in the
world frame ``X_WC`` as ``[x, y, z, qw, qx, qy, qz]`` (metres).

PNG files are read and written with Pillow (a dependency of matplotlib), so frames work
without the optional OpenCV.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from apo.errors import InputFormatError
from apo.perception.camera import (
    DEFAULT_FPS,
    Camera,
    FrameSource,
    camera_from_json,
    read_camera,
    write_camera,
)
from apo.perception.layout import check_numbering, frame_indices, read_times
from apo.perception.stereo import open_stereo
from apo.typing import FloatArray

__all__ = [
    "DEFAULT_FPS",
    "Camera",
    "FrameSource",
    "Frames",
    "camera_from_json",
    "masked_median",
    "open_frames",
    "read_camera",
    "write_background",
    "write_camera",
    "write_frame",
    "write_timestamps",
]


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
        """Colour and depth of ``background/``, each None when absent.

        With several background depth frames (``depth.png``, ``depth_000001.png``, ...) the
        depth is their per-pixel median over the frames that measured it
        (:attr:`background_count` frames): its noise is about ``sqrt(pi / 2n)`` of one frame's.
        """
        rgb_path = self.root / "background" / "rgb.png"
        rgb = (
            np.asarray(_read_png(rgb_path, kind="rgb", camera=self._camera), dtype=np.uint8)
            if rgb_path.exists()
            else None
        )
        paths = self._background_depth_paths()
        if not paths:
            return rgb, None
        scale = np.float32(self._camera.depth_scale)
        depths = [
            (_read_png(p, kind="depth", camera=self._camera) * scale).astype(np.float32)
            for p in paths
        ]
        if len(depths) == 1:
            return rgb, depths[0]
        return rgb, masked_median(np.stack(depths), np.stack(depths) > 0)

    def _background_depth_paths(self) -> list[Path]:
        first = self.root / "background" / "depth.png"
        if not first.exists():
            return []
        paths = [first]
        while (p := self.root / "background" / f"depth_{len(paths):06d}.png").exists():
            paths.append(p)
        return paths

    @property
    def background_count(self) -> int:
        """Number of background depth frames (0 without a background)."""
        return len(self._background_depth_paths())


def masked_median(
    values: npt.NDArray[np.float32], mask: npt.NDArray[np.bool_]
) -> npt.NDArray[np.float32]:
    """Per-pixel median of ``values`` (N, H, W) over the frames where ``mask``; 0 if none.

    The lower median for an even count (a measured value, not an average of two).
    """
    stack = np.sort(np.where(mask, values, np.float32(np.inf)), axis=0)
    count = mask.sum(axis=0)
    idx = np.maximum(count - 1, 0) // 2
    med = np.take_along_axis(stack, idx[None], axis=0)[0]
    return np.where(count > 0, med, 0.0).astype(np.float32)


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
        return open_stereo(root, fps=fps)
    camera = read_camera(root / "camera.json")
    rgb = frame_indices(root / "rgb")
    depth = frame_indices(root / "depth")
    if not rgb:
        raise InputFormatError(f"{root / 'rgb'}: no frames (expected rgb/000000.png, ...)")
    check_numbering(root, "rgb", rgb)
    check_numbering(root, "depth", depth)
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
        times = read_times(ts, n)
    else:
        if fps <= 0:
            raise InputFormatError(f"fps must be positive, got {fps}")
        times = np.arange(n, dtype=np.float64) / fps
    return Frames(root, camera, n, times)


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
    root: str | Path,
    rgb: npt.ArrayLike,
    depth: npt.ArrayLike,
    camera: Camera,
    *more_depths: npt.ArrayLike,
) -> None:
    """Write ``background/rgb.png`` and ``background/depth.png`` (depth in metres).

    ``more_depths`` (further frames of the empty scene) go to ``background/depth_000001.png``
    and on.
    """
    r = Path(root)
    _write_png(r / "background" / "rgb.png", np.asarray(rgb, dtype=np.uint8))
    _write_png(r / "background" / "depth.png", _depth_to_png(depth, camera))
    for k, d in enumerate(more_depths, start=1):
        _write_png(r / "background" / f"depth_{k:06d}.png", _depth_to_png(d, camera))


def write_timestamps(root: str | Path, times: npt.ArrayLike) -> None:
    """Write ``timestamps.txt`` (one time in seconds per line)."""
    t = np.asarray(times, dtype=np.float64)
    Path(root, "timestamps.txt").write_text("".join(f"{x:.6f}\n" for x in t), encoding="utf-8")
