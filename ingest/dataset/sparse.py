"""Sparse ground-truth images: the few pixels that hold a value, and the image they belong to.

LiDAR ground truth covers a few percent of an image (a 2048x4096 equirect
holds ~20k disparities). Keeping it as (flat pixel index, value) pairs lets
the writer build the uint16 PNG without scanning 8M mostly-zero floats.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.types import F32, I64


@dataclass(frozen=True)
class SparseImage:
    """Values (float32, physical units) at flat pixel indices (row * width + col) of a (H, W) image."""

    shape: tuple[int, int]
    pixel: I64
    value: F32

    @classmethod
    def from_dense(cls, image: np.ndarray[Any, Any]) -> SparseImage:
        """The non-zero pixels of a dense image (0 = no value)."""
        flat = np.asarray(image, np.float32).reshape(-1)
        idx = np.flatnonzero(flat)
        return cls((int(image.shape[0]), int(image.shape[1])), idx, flat[idx])

    def dense(self) -> F32:
        """(H, W) float32 image, 0 where there is no value."""
        out = np.zeros(self.shape[0] * self.shape[1], np.float32)
        out[self.pixel] = self.value
        return out.reshape(self.shape)

    @property
    def count(self) -> int:
        """Pixels holding a (non-zero) value."""
        return int(np.count_nonzero(self.value))
