"""Rectified stereo pairs -> depth, by OpenCV's semi-global block matching (SGBM).

The layout of a stereo folder ``STEREO/`` (``docs/perception.md``)::

    stereo.json          {"fx", "fy", "cx", "cy", "baseline", "width", "height"[, "pose",
                          "num_disparities", "block_size"]}
    left/000000.png      8-bit colour (or grey), rectified; the reference view
    right/000000.png     8-bit colour (or grey), rectified, same size
    timestamps.txt       optional: one time in seconds per frame
    background/left.png  optional, with background/right.png: the scene without the objects

``fx, fy, cx, cy`` are the rectified left camera's intrinsics (pixels), ``baseline`` the
distance between the two optical centres (metres, the right camera at ``+x``), ``pose`` the
left camera in the world frame (``[x, y, z, qw, qx, qy, qz]``, metres). Depth is
``z = fx * baseline / disparity``; the colour image of a frame is the left image, so colour
and depth are registered, as with the paper's multi-baseline stereo camera.

OpenCV is optional (``pip install apo[perception]``); it is imported when depth is computed.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from apo.errors import ApoError, InputFormatError
from apo.perception.camera import DEFAULT_FPS, Camera, camera_from_json, read_calibration
from apo.perception.layout import check_numbering, frame_indices, read_times
from apo.typing import FloatArray

__all__ = ["StereoFrames", "depth_from_disparity", "disparity_sgbm", "open_stereo"]


def _cv2() -> Any:
    try:
        import cv2
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ApoError(
            f"stereo needs OpenCV, which could not be imported ({exc}); install it with "
            "`pip install apo[perception]`"
        ) from None
    return cv2


def disparity_sgbm(
    left: npt.ArrayLike,
    right: npt.ArrayLike,
    *,
    num_disparities: int = 128,
    block_size: int = 5,
) -> npt.NDArray[np.float32]:
    """Disparity (pixels) of a rectified pair by OpenCV SGBM, left image as reference.

    Parameters
    ----------
    left, right : ndarray of uint8, shape (H, W, 3) or (H, W)
        Rectified images (RGB or grey).
    num_disparities : int, optional
        Disparity search range, a positive multiple of 16.
    block_size : int, optional
        Odd matching block size, pixels.

    Returns
    -------
    ndarray of float32, shape (H, W)
        Disparity in pixels, 0 where there is no reliable match.
    """
    cv2 = _cv2()
    if num_disparities <= 0 or num_disparities % 16:
        raise ValueError(
            f"num_disparities must be a positive multiple of 16, got {num_disparities}"
        )
    L = np.asarray(left, dtype=np.uint8)
    R = np.asarray(right, dtype=np.uint8)
    if L.ndim == 3:
        L = cv2.cvtColor(L, cv2.COLOR_RGB2GRAY)
    if R.ndim == 3:
        R = cv2.cvtColor(R, cv2.COLOR_RGB2GRAY)
    if L.shape != R.shape:
        raise ValueError(f"left image {L.shape} and right image {R.shape} differ in size")
    channels = 1
    sgbm = cv2.StereoSGBM_create(
        minDisparity=0,
        numDisparities=num_disparities,
        blockSize=block_size,
        P1=8 * channels * block_size**2,
        P2=32 * channels * block_size**2,
        disp12MaxDiff=1,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    disp = sgbm.compute(L, R).astype(np.float32) / 16.0
    disp[disp <= 0] = 0.0
    return np.asarray(disp, dtype=np.float32)


def depth_from_disparity(
    disparity: npt.ArrayLike, fx: float, baseline: float
) -> npt.NDArray[np.float32]:
    """Depth ``z = fx * baseline / disparity`` (metres), 0 where the disparity is not positive.

    Parameters
    ----------
    disparity : ndarray, shape (H, W)
        Pixels.
    fx : float
        Focal length, pixels.
    baseline : float
        Metres.
    """
    d = np.asarray(disparity, dtype=np.float32)
    with np.errstate(divide="ignore"):
        z = np.where(d > 0, np.float32(fx * baseline) / np.maximum(d, 1e-6), 0.0)
    return z.astype(np.float32)


class StereoFrames:
    """A stereo folder read as registered colour + depth frames (a ``FrameSource``)."""

    def __init__(
        self,
        root: Path,
        camera: Camera,
        baseline: float,
        count: int,
        times: FloatArray,
        *,
        num_disparities: int,
        block_size: int,
    ) -> None:
        self.root = root
        self._camera = camera
        self.baseline = baseline
        self._count = count
        self._times = times
        self.num_disparities = num_disparities
        self.block_size = block_size

    @property
    def camera(self) -> Camera:
        """The rectified left camera."""
        return self._camera

    @property
    def times(self) -> FloatArray:
        """Frame times, seconds."""
        return self._times

    def __len__(self) -> int:
        """Return the number of frames."""
        return self._count

    def _image(self, path: Path) -> npt.NDArray[np.uint8]:
        from PIL import Image

        if not path.is_file():
            raise InputFormatError(f"{path}: file not found")
        with Image.open(path) as im:
            if im.mode not in ("RGB", "RGBA", "L"):
                raise InputFormatError(f"{path}: expected an 8-bit RGB or grey PNG, got {im.mode}")
            arr = np.array(im.convert("RGB"), dtype=np.uint8)
        if arr.shape[:2] != (self._camera.height, self._camera.width):
            raise InputFormatError(
                f"{path}: image is {arr.shape[1]}x{arr.shape[0]}, stereo.json says "
                f"{self._camera.width}x{self._camera.height}"
            )
        return arr

    def rgb(self, index: int) -> npt.NDArray[np.uint8]:
        """Return the left image of frame ``index``."""
        return self._image(self.root / "left" / f"{index:06d}.png")

    def _depth(self, left: Path, right: Path) -> npt.NDArray[np.float32]:
        disp = disparity_sgbm(
            self._image(left),
            self._image(right),
            num_disparities=self.num_disparities,
            block_size=self.block_size,
        )
        return depth_from_disparity(disp, self._camera.fx, self.baseline)

    def depth(self, index: int) -> npt.NDArray[np.float32]:
        """Depth of frame ``index`` (metres, 0 = none), from SGBM disparity."""
        name = f"{index:06d}.png"
        return self._depth(self.root / "left" / name, self.root / "right" / name)

    def background(
        self,
    ) -> tuple[npt.NDArray[np.uint8] | None, npt.NDArray[np.float32] | None]:
        """Left image and depth of ``background/``, or ``(None, None)``."""
        left = self.root / "background" / "left.png"
        right = self.root / "background" / "right.png"
        if not (left.exists() and right.exists()):
            return None, None
        return self._image(left), self._depth(left, right)


def open_stereo(path: str | Path, *, fps: float = DEFAULT_FPS) -> StereoFrames:
    """Open a stereo folder (see the module notes), validating its layout.

    Raises
    ------
    InputFormatError
        Missing or bad ``stereo.json``, missing or unpaired images.
    """
    root = Path(path)
    cal_path = root / "stereo.json"
    data = read_calibration(cal_path, "stereo")
    if not isinstance(data, dict):
        raise InputFormatError(f"{cal_path}: expected a JSON object")
    extra = {k: data.pop(k) for k in ("baseline", "num_disparities", "block_size") if k in data}
    if "baseline" not in extra:
        raise InputFormatError(f"{cal_path}: missing key baseline (metres)")
    b = extra["baseline"]
    if isinstance(b, bool) or not isinstance(b, int | float) or not math.isfinite(b) or b <= 0:
        raise InputFormatError(f"{cal_path}: baseline must be a positive number, got {b!r}")
    camera = camera_from_json({**data, "depth_scale": 1.0}, cal_path)
    nd = extra.get("num_disparities", 128)
    bs = extra.get("block_size", 5)
    if not isinstance(nd, int) or nd <= 0 or nd % 16:
        raise InputFormatError(f"{cal_path}: num_disparities must be a multiple of 16, got {nd!r}")
    if not isinstance(bs, int) or bs < 1 or bs % 2 == 0:
        raise InputFormatError(f"{cal_path}: block_size must be a positive odd integer, got {bs!r}")
    left = frame_indices(root / "left")
    right = frame_indices(root / "right")
    check_numbering(root, "left", left)
    check_numbering(root, "right", right)
    if len(left) != len(right):
        raise InputFormatError(
            f"{root}: left/ has {len(left)} frames, right/ has {len(right)}; they must pair"
        )
    ts = root / "timestamps.txt"
    times = read_times(ts, len(left)) if ts.exists() else np.arange(len(left)) / fps
    return StereoFrames(
        root,
        camera,
        float(b),
        len(left),
        np.asarray(times, dtype=np.float64),
        num_disparities=nd,
        block_size=bs,
    )
