"""Points in Z-order (Morton order): neighbours in space become neighbours in memory.

An accumulated cloud arrives sweep by sweep, so a point's spatial
neighbours lie scattered over the whole array, and every per-point pass that
looks at neighbours (a k-d tree's k-NN queries, a z-buffer's scatter into an
image) misses the cache on most of them. Sorted by the Morton code of its
`cell_m` cube, the same cloud is walked region by region: on a dense-GT
sample (134k points, one core) Open3D's k-NN plane fit takes half the time
and the whole GT three quarters, with identical output.

Codes interleave 21 bits per axis (cubes counted from the cloud's minimum
corner; beyond 2^21 cubes an axis saturates, which only coarsens the order).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from calibration.types import F64, I64

_AXIS_BITS = 21
_AXIS_MAX = (1 << _AXIS_BITS) - 1


@njit(cache=True, nogil=True, inline="always")
def _spread(x):  # type: ignore[no-untyped-def]  # pragma: no cover
    """The low 21 bits of x spaced three apart (bit i moves to bit 3i)."""
    x &= 0x1FFFFF
    x = (x | (x << 32)) & 0x1F00000000FFFF
    x = (x | (x << 16)) & 0x1F0000FF0000FF
    x = (x | (x << 8)) & 0x100F00F00F00F00F
    x = (x | (x << 4)) & 0x10C30C30C30C30C3
    x = (x | (x << 2)) & 0x1249249249249249
    return x


@njit(cache=True, nogil=True)
def _codes(xyz, lo, cell_m):  # type: ignore[no-untyped-def]  # pragma: no cover
    out = np.empty(xyz.shape[0], np.int64)
    for i in range(xyz.shape[0]):
        code = 0
        for a in range(3):
            q = math.floor((xyz[i, a] - lo[a]) / cell_m)
            q = min(max(q, 0), _AXIS_MAX)
            code |= _spread(np.int64(q)) << a
        out[i] = code
    return out


def morton_codes(xyz: F64, cell_m: float) -> I64:
    """Morton code (N,) of each point's `cell_m` cube, counted from the points' minimum corner."""
    pts = np.ascontiguousarray(xyz, np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros(0, np.int64)
    out: I64 = _codes(pts, pts.min(axis=0), float(cell_m))
    return out


def z_order(xyz: F64, cell_m: float = 0.01) -> I64:
    """Permutation (N,) that puts the points `xyz` (N, 3, metres) in Z-order of their `cell_m` cubes.

    Stable: points in one cube keep their input order.
    """
    out: I64 = np.argsort(morton_codes(xyz, cell_m), kind="stable")
    return out
