"""Compiled (numba) helpers of the camera-model contract, imported on first use.

`finish_projection` turns a model's raw (u, v, valid) into the contract's
(uv, valid) in one pass: valid only where the model says so and every input
coordinate and output pixel is finite, NaN elsewhere. In numpy that took
about eight passes over the points (finiteness of five arrays, the mask, the
stacking, the NaN fill), more than the Double Sphere formula itself.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from calibration.types import F64, Bool


@njit(cache=True, nogil=True)
def _finish(u, v, valid, x, y, z, uv, ok):  # type: ignore[no-untyped-def]  # pragma: no cover
    for i in range(u.shape[0]):
        good = (
            valid[i]
            and math.isfinite(u[i])
            and math.isfinite(v[i])
            and math.isfinite(x[i])
            and math.isfinite(y[i])
            and math.isfinite(z[i])
        )
        ok[i] = good
        if good:
            uv[i, 0] = u[i]
            uv[i, 1] = v[i]
        else:
            uv[i, 0] = np.nan
            uv[i, 1] = np.nan


def finish_projection(u: F64, v: F64, valid: Bool, x: F64, y: F64, z: F64) -> tuple[F64, Bool]:
    """(uv (N, 2), valid (N,)) from flat model outputs and inputs; NaN where not valid."""
    n = len(x)
    uv = np.empty((n, 2), np.float64)
    ok = np.empty(n, np.bool_)
    _finish(
        np.broadcast_to(np.asarray(u, np.float64), (n,)),
        np.broadcast_to(np.asarray(v, np.float64), (n,)),
        np.broadcast_to(np.asarray(valid, np.bool_), (n,)),
        x, y, z, uv, ok,
    )  # fmt: skip
    return uv, ok
