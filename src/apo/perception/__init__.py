"""Perception: recorded depth (or stereo) frames -> segmentation -> robust ICP -> poses.

The front end of apo (paper section 4.2). Modules, in the order of the data flow:

- :mod:`apo.perception.frames`: the camera model and the frames folder layout.
- :mod:`apo.perception.stereo`: rectified stereo pairs -> depth (OpenCV SGBM).
- :mod:`apo.perception.segment`: background subtraction, colour model, occupancy histogram.
- :mod:`apo.perception.register`: robust ICP (Open3D), global initialisation, confidence.
- :mod:`apo.perception.track`: the whole pipeline, :func:`track_frames`.
- :mod:`apo.perception.render`: synthetic frames of posed meshes, for tests and demos.

Open3D and OpenCV are optional (``pip install apo[perception]``); they are imported only by
the functions that need them.
"""

from apo.perception.frames import Camera, open_frames

__all__ = ["Camera", "open_frames"]
