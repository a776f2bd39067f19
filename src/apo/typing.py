"""Array type aliases used across apo (one definition, imported everywhere).

>>> import numpy as np
>>> from apo.typing import FloatArray
>>> x: FloatArray = np.zeros(3)
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["BoolArray", "FloatArray", "IntArray"]

FloatArray = npt.NDArray[np.float64]
"""Array of float64 (shape and units in each docstring)."""
IntArray = npt.NDArray[np.int64]
"""Array of int64."""
BoolArray = npt.NDArray[np.bool_]
"""Array of booleans."""
