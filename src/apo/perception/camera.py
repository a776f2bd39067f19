"""The camera of a recorded sequence: pinhole model, ``camera.json``, the frame-source protocol.

Shared by the frames folder (:mod:`apo.perception.frames`) and the stereo folder
(:mod:`apo.perception.stereo`); it imports neither of them, so the two never import each
other's internals.

Pixel ``(row v, column u)`` has its centre at image coordinates ``(u, v)``; the camera frame
``C`` has ``x`` right, ``y`` down and ``z`` forward (OpenCV), and a depth value is the ``z``
coordinate of the surface point, not the distance along the ray. ``pose`` is the camera in the
world frame ``X_WC`` as ``[x, y, z, qw, qx, qy, qz]`` (metres).
"""

from __future__ import annotations

import json
import math
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
    "camera_from_json",
    "read_camera",
    "write_camera",
]

DEFAULT_FPS = 30.0
"""Frame rate assumed when a sequence has no ``timestamps.txt`` (t = index / 30 s)."""

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
    return camera_from_json(read_calibration(p, "camera"), p)


def read_calibration(path: Path, what: str) -> Any:
    """Return the parsed JSON of a calibration file (``what``: "camera", "stereo").

    Raises
    ------
    InputFormatError
        The file is missing or is not valid JSON (the message names the file).
    """
    from apo.io.jsonfile import read_json

    return read_json(path, what=f"{what} calibration file")


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
