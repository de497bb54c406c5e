"""Array type aliases shared by the geometry code."""

from __future__ import annotations

from typing import TypeAlias

import numpy as np
import numpy.typing as npt

F64: TypeAlias = npt.NDArray[np.float64]
"""float64 array; the shape is given in each docstring."""

Bool: TypeAlias = npt.NDArray[np.bool_]
"""Boolean mask array."""

ArrayLike: TypeAlias = npt.ArrayLike
