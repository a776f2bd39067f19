"""Offscreen video of a replay (``apo replay --video FILE``).

MuJoCo renders offscreen through the OpenGL back-end named by the environment variable
``MUJOCO_GL``: ``egl`` (a GPU or Mesa's EGL), ``osmesa`` (software, ``apt install
libosmesa6``) or ``glfw`` (a display). Without a working context :class:`Recorder` raises
:class:`apo.errors.ApoError` at the first frame, naming the setting; only ``--video`` needs
it. ``.gif`` is written with Pillow, ``.mp4`` with OpenCV (extra ``perception``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from apo.errors import ApoError, InputFormatError

__all__ = ["FPS", "Recorder"]

FPS = 25
"""Frames per simulated second."""


class Recorder:
    """Collect frames of a scene at :data:`FPS` and write them to ``path`` on :meth:`close`."""

    def __init__(self, path: Path, *, width: int = 640, height: int = 480) -> None:
        suffix = path.suffix.lower()
        if suffix not in (".gif", ".mp4"):
            raise InputFormatError(f"{path}: --video must end in .gif or .mp4")
        if not path.parent.exists() and str(path.parent):
            raise InputFormatError(f"{path}: folder {path.parent} does not exist")
        self.path = path
        self.size = (width, height)
        self.frames: list[np.ndarray] = []
        self._renderer: Any = None
        self._camera: Any = None
        self._next = 0.0

    def _open(self, scene: Any) -> None:
        import mujoco

        try:
            self._renderer = mujoco.Renderer(scene.model, self.size[1], self.size[0])
        except Exception as exc:
            raise ApoError(
                f"--video: cannot open an OpenGL context for offscreen rendering ({exc}); set "
                "MUJOCO_GL=egl (GPU or Mesa EGL) or MUJOCO_GL=osmesa (software rendering, "
                "libosmesa6), see docs/sim.md"
            ) from None
        cam = mujoco.MjvCamera()
        m = scene.model
        cam.lookat[:] = scene.X_WE[:3, 3] + m.stat.center
        cam.distance = 2.5 * float(m.stat.extent)
        cam.azimuth, cam.elevation = 90.0, -15.0
        self._camera = cam

    def capture(self, scene: Any) -> None:
        """Render the scene if a frame is due (called at every recorded sample)."""
        t = float(scene.data.time)
        if t < self._next:
            return
        if self._renderer is None:
            self._open(scene)
        self._renderer.update_scene(scene.data, self._camera)
        self.frames.append(self._renderer.render().copy())
        self._next = t + 1.0 / FPS

    def close(self) -> None:
        """Write the collected frames."""
        if self._renderer is not None:
            self._renderer.close()
        if not self.frames:
            return
        if self.path.suffix.lower() == ".gif":
            from PIL import Image

            imgs = [Image.fromarray(f) for f in self.frames]
            imgs[0].save(
                self.path, save_all=True, append_images=imgs[1:], duration=1000 // FPS, loop=0
            )
            return
        try:
            import cv2
        except ImportError:
            raise ApoError("--video .mp4 needs OpenCV (pip install 'apo[perception]')") from None
        h, w = self.frames[0].shape[:2]
        fourcc = cv2.VideoWriter_fourcc(*"mp4v")  # type: ignore[attr-defined]
        out = cv2.VideoWriter(str(self.path), fourcc, FPS, (w, h))
        for f in self.frames:
            out.write(f[:, :, ::-1])
        out.release()
