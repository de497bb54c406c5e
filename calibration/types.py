"""Array type aliases for every package (calibration, ingest, sensorbox); shapes are in each docstring."""

from __future__ import annotations

from typing import Any, TypeAlias

import numpy as np
import numpy.typing as npt

F64: TypeAlias = npt.NDArray[np.float64]
"""float64 array; the shape is given in each docstring."""

Bool: TypeAlias = npt.NDArray[np.bool_]
"""Boolean mask array."""

ArrayLike: TypeAlias = npt.ArrayLike

F32: TypeAlias = np.ndarray[Any, np.dtype[np.float32]]
"""float32 array (point clouds, depth and disparity images)."""

I64: TypeAlias = np.ndarray[Any, np.dtype[np.int64]]
"""int64 array (stamps in ns, indices)."""

U8: TypeAlias = np.ndarray[Any, np.dtype[np.uint8]]
"""uint8 array (images, packed bytes)."""

U64: TypeAlias = np.ndarray[Any, np.dtype[np.uint64]]
"""uint64 array (bit sets)."""

Structured: TypeAlias = np.ndarray[Any, np.dtype[np.void]]
"""Structured (record) array, e.g. decoded point or packet fields."""
