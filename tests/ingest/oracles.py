"""The numpy references of compiled kernels, kept beside the tests that use them as oracles.

Each is the plain formula of a compiled pass in the package (named in its
docstring); the tests compare the two bit for bit or to float tolerance.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from calibration.types import F32, I64, Bool
from ingest.raster.edges import valid_gt
from ingest.raster.geometry import ViewPoints
from ingest.raster.lod import SPHERE_CELLS
from ingest.raster.params import EMPTY_KEY
from ingest.raster.visibility import _keys


def zbuffer_erode(pts: ViewPoints, H: int, W: int) -> tuple[I64, I64]:
    """`ingest.raster.visibility.zbuffer` in numpy alone (same keys, bit for bit).

    Points are grouped by footprint half-widths (ku, kv); each group's own
    buffer is eroded (cv2.erode on the keys viewed as float64, which orders
    positive keys the same) by its ellipse: one erode per group.
    """
    P = H * W
    own = np.full(P, EMPTY_KEY, np.int64)
    splat = np.full(P, EMPTY_KEY, np.int64)
    if len(pts.pix) == 0:
        return own, splat
    key = _keys(pts)
    K = int(max(pts.ku.max(), pts.kv.max())) + 1
    cls = pts.ku * K + pts.kv
    order = np.argsort(cls, kind="stable")
    bounds = np.r_[0, np.cumsum(np.bincount(cls, minlength=K * K))]
    layer = np.empty(P, np.int64)
    for c in np.flatnonzero(np.diff(bounds)):
        sel = order[bounds[c] : bounds[c + 1]]
        pix = pts.pix[sel]
        layer.fill(EMPTY_KEY)
        np.minimum.at(layer, pix, key[sel])
        np.minimum(own, layer, out=own)
        ku, kv = divmod(int(c), K)
        if ku == 0 and kv == 0:
            np.minimum(splat, layer, out=splat)
            continue
        # erode only the window holding this group's points (plus the kernel)
        rows = pix // W
        cols = pix - rows * W
        r0, r1 = max(0, int(rows.min()) - kv), min(H, int(rows.max()) + kv + 1)
        c0, c1 = max(0, int(cols.min()) - ku), min(W, int(cols.max()) + ku + 1)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * ku + 1, 2 * kv + 1))
        win = layer.view(np.float64).reshape(H, W)[r0:r1, c0:c1]
        eroded = cv2.erode(win, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
        target = splat.reshape(H, W)[r0:r1, c0:c1]
        np.minimum(target, eroded.view(np.int64), out=target)
    return own, splat


def edge_steps_numpy(gt: np.ndarray[Any, Any], step_abs: float = 0.05, step_rel: float = 0.03) -> Bool:
    """`ingest.raster.edges.edge_band`'s discontinuities (H, W) in numpy: the reference of its compiled pass
    (`_steps`)."""
    ok = valid_gt(gt)
    kernel = np.ones((3, 3), np.uint8)
    g = np.where(ok, gt, np.float32(0.0)).astype(np.float32, copy=False)
    hi = cv2.dilate(g, kernel)  # largest valid value around (0: none)
    np.copyto(g, np.float32(np.inf), where=~ok)
    lo = cv2.erode(g, kernel)  # smallest valid value around (inf: none, so hi - lo = -inf: no step)
    threshold = lo * np.float32(step_rel)
    np.maximum(threshold, np.float32(step_abs), out=threshold)
    out: Bool = hi - lo > threshold
    return out


def sphere_cells_numpy(xyz: F32, cells: tuple[int, int] = SPHERE_CELLS) -> tuple[I64, I64]:
    """`ingest.raster.point_kernels.sphere_cells` in numpy: each point's cell and the points per cell (the reference)."""
    n_u, n_az = cells
    r = np.sqrt(np.einsum("ij,ij->i", xyz, xyz))
    with np.errstate(invalid="ignore"):  # NaN casts to int32's minimum: clipped into cell 0
        cu = np.clip(((xyz[:, 2] / np.maximum(r, 1e-12) + 1.0) * (n_u / 2.0)).astype(np.int32), 0, n_u - 1)
        az = np.arctan2(xyz[:, 1].astype(np.float64), xyz[:, 0].astype(np.float64)).astype(np.float32)
        ca = np.clip(((az + math.pi) * (n_az / (2.0 * math.pi))).astype(np.int32), 0, n_az - 1)
    cell: I64 = cu.astype(np.int64) * n_az + ca
    counts: I64 = np.bincount(cell, minlength=n_u * n_az)
    return cell, counts
