"""How the LiDARs' ranges agree on the surfaces they both see: where cam0 sees a point of two LiDARs in
one pixel, both lie on the same surface along that pixel's ray, so their ranges from cam0 should be the
same. A LiDAR whose ranges read a few per cent long (a range scale, a unit or an offset fault) passes
every other check: its points still fall where its pose puts them, only too far out along the ray. The
same pixels' ratios scatter by the two LiDARs' range noise: a LiDAR far noisier than a Mid-360 (or one
whose points land apart from the other's: a time or pose error that varies over the window) scatters them
as no other check sees, since its points still lie around the right surfaces."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from calibration.types import F64, I64, Bool

MIN_PAIRS = 50
"""Pixels holding points of both LiDARs below which a sample says nothing about their agreement."""
MAD_TO_SIGMA = 1.4826
"""A normal distribution's 1-sigma per median absolute deviation."""


def range_ratios(
    pts_cam0: F64, visible: Bool, cols: F64, rows: F64, which: I64, names: Sequence[str], width: int
) -> dict[str, tuple[float, int, float]]:
    """Per LiDAR after the first: the median ratio of its range (m, from cam0) to the first LiDAR's in the
    pixels where cam0 sees a visible point of both (the nearest of each), how many such pixels, and the
    ratios' scatter (the robust 1-sigma of their log, `MAD_TO_SIGMA` times its median absolute deviation:
    a fraction of range, sqrt(2) times each LiDAR's relative range noise when they are alike); none with
    fewer than `MIN_PAIRS` (a LiDAR barely in view, or one LiDAR only).

    `cols` and `rows` are each point's pixel (`ingest.train.gt.groundtruth.in_view`), `which` its LiDAR
    (an index into `names`), `width` the image's width.
    """
    if len(names) < 2:
        return {}
    pixel = rows[visible].astype(np.int64) * width + cols[visible].astype(np.int64)  # NaN off the image
    range_m = np.linalg.norm(pts_cam0[visible], axis=1)
    lidar = which[visible]
    first = _nearest(pixel[lidar == 0], range_m[lidar == 0])
    out = {}
    for k in range(1, len(names)):
        mine = _nearest(pixel[lidar == k], range_m[lidar == k])
        shared, a, b = np.intersect1d(mine[0], first[0], assume_unique=True, return_indices=True)
        if len(shared) >= MIN_PAIRS:
            ratio = mine[1][a] / first[1][b]
            log_ratio = np.log(ratio)
            scatter = MAD_TO_SIGMA * np.median(np.abs(log_ratio - np.median(log_ratio)))
            out[names[k]] = (float(np.median(ratio)), len(shared), float(scatter))
    return out


def _nearest(pixel: I64, range_m: F64) -> tuple[I64, F64]:
    """Each pixel once (sorted), with the nearest of its points' ranges."""
    order = np.lexsort((range_m, pixel))
    pixel, range_m = pixel[order], range_m[order]
    first = np.ones(len(pixel), bool)
    first[1:] = pixel[1:] != pixel[:-1]
    return pixel[first], range_m[first]


PLANE_NEIGHBOURS = 12
"""Points of the other LiDARs a plane is fitted to around each point `plane_scatter` measures."""
PLANE_POINTS = 3_000
"""Points of each LiDAR `plane_scatter` measures at most (evenly spread over its window)."""
MIN_PLANE_POINTS = 200
"""Points on planes of the other LiDARs below which a LiDAR's scatter is not measured."""


def plane_scatter(pts_cam0: F64, which: I64, names: Sequence[str]) -> dict[str, tuple[float, int]]:
    """Per LiDAR of a rig with two or more: the robust 1-sigma (m, `MAD_TO_SIGMA` times the median
    absolute deviation) of its points' distances to the planes the other LiDARs' points give around
    them, and how many points were measured; none under `MIN_PLANE_POINTS`.

    A plane is the PCA plane of the `PLANE_NEIGHBOURS` nearest points of the other LiDARs, kept when flat
    (smallest eigenvalue under 5 % of their sum), local (its spread under a tenth of the range plus 5 cm)
    and near (its nearest point within 2 % of the range plus 5 cm). The plane averages the other LiDARs'
    noise over its points, so the distances scatter by about the LiDAR's own range noise: the range-ratio
    scatter (`range_ratios`) mixes both LiDARs' and says not which. On the fixture room, 5 cm of range noise
    on one LiDAR reads 40 mm for it and 12 mm for the other; both with a Mid-360's 2 cm, 18-22 mm each.
    """
    if len(names) < 2:
        return {}
    out = {}
    for k, name in enumerate(names):
        mine, theirs = pts_cam0[which == k], pts_cam0[which != k]
        if len(mine) < MIN_PLANE_POINTS or len(theirs) < PLANE_NEIGHBOURS:
            continue
        a = mine[np.linspace(0, len(mine) - 1, min(PLANE_POINTS, len(mine))).astype(np.int64)]
        range_m = np.linalg.norm(a, axis=1)
        # an unbalanced tree builds and answers these queries in half the time, with the same answers; a
        # point whose nearest neighbour is too far for a plane near it needs no plane (the cheap query first)
        tree = cKDTree(theirs, balanced_tree=False, compact_nodes=False)
        near = tree.query(a, 1)[0] < 0.02 * range_m + 0.05
        a, range_m = a[near], range_m[near]
        j = tree.query(a, PLANE_NEIGHBOURS)[1]
        nb = theirs[j]
        centre = nb.mean(axis=1)
        offsets = nb - centre[:, None]
        eigenvalues, eigenvectors = np.linalg.eigh(
            np.einsum("nki,nkj->nij", offsets, offsets) / PLANE_NEIGHBOURS
        )
        ok = eigenvalues[:, 0] <= 0.05 * eigenvalues.sum(axis=1)
        ok &= np.sqrt(np.maximum(eigenvalues[:, 2], 0.0)) < 0.1 * range_m + 0.05
        if ok.sum() < MIN_PLANE_POINTS:
            continue
        d = np.einsum("ij,ij->i", eigenvectors[ok, :, 0], a[ok] - centre[ok])
        out[name] = (float(MAD_TO_SIGMA * np.median(np.abs(d - np.median(d)))), int(ok.sum()))
    return out
