"""How each stretch of one LiDAR's window sits among the window's other points: a sweep out of place.

A LiDAR's points over a sample's window, placed in cam0 at the exposure, lie on the scene's surfaces
whatever part of the window they come from; the stretches of its point times (`stretch_of`) each land
among the others' points. A glitched sweep (its points turned, moved or mirrored, or another moment's)
covers a stretch of the window whose points land where the others have none. Its image counterpart is
`ingest.train.gt.align.part_correlations`; the two find different faults (a sweep moved along a flat
floor stays on it; one turned by a few degrees about a horizontal axis still matches the image's texture).
"""

from __future__ import annotations

import numpy as np

from calibration.types import F64, I64

WINDOW_PARTS = 8
"""A LiDAR's window is split into this many equal stretches of point time (12.5 ms of a 100 ms window)."""
MIN_STRETCH_POINTS = 400
"""Points a stretch needs to be measured."""
QUERY_POINTS = 400
"""Points of a stretch looked up (evenly spread over its order), and `TREE_POINTS` of each other stretch
searched, among them `NEIGHBOURS` nearest: enough for a share to +-0.03."""
TREE_POINTS = 4000
NEIGHBOURS = 16
NEAR_M = 0.03
NEAR_RANGE = 0.01
"""A point has a neighbour when another stretch holds one within `NEAR_M` plus `NEAR_RANGE` of its range."""


def stretch_of(stamps_ns: I64, parts: int = WINDOW_PARTS) -> I64:
    """Each point's stretch (0 .. `parts` - 1): equal spans of the points' times, first to last."""
    if len(stamps_ns) == 0:
        return np.zeros(0, np.int64)
    edges = np.linspace(float(stamps_ns.min()), float(stamps_ns.max()) + 1.0, parts + 1)
    out: I64 = np.clip(np.searchsorted(edges, stamps_ns, side="right") - 1, 0, parts - 1).astype(np.int64)
    return out


def evenly_spread(n: int, limit: int) -> I64:
    """At most `limit` indices evenly spread over range(n) (deterministic)."""
    if n <= limit:
        return np.arange(n, dtype=np.int64)
    return np.linspace(0, n - 1, limit).round().astype(np.int64)


def stretch_shares(pts_cam0: F64, stamps_ns: I64) -> list[float | None]:
    """Per stretch of one LiDAR's window (`stretch_of`): the share of its points with a neighbour among
    the other stretches' points (m, in cam0 at the exposure); None for a stretch under
    `MIN_STRETCH_POINTS`.

    One voxel hash (`ingest.train.trajectory.voxel_hash`, exact within its radius) holds every
    stretch's `TREE_POINTS`; a point's `NEIGHBOURS` nearest in it are searched for one of another
    stretch (a point's own stretch crowds its scan line, so its nearest are often its own).
    """
    from ingest.train.trajectory.voxel_hash import VoxelHash  # numba: loaded with the first window

    out: list[float | None] = [None] * WINDOW_PARTS
    finite = np.isfinite(pts_cam0).all(axis=1)
    pts, part = pts_cam0[finite], stretch_of(stamps_ns[finite])
    members = [np.flatnonzero(part == k) for k in range(WINDOW_PARTS)]
    measured = [k for k, idx in enumerate(members) if len(idx) >= MIN_STRETCH_POINTS]
    if len(measured) < 2:
        return out
    held = np.concatenate([members[k][evenly_spread(len(members[k]), TREE_POINTS)] for k in measured])
    label = np.append(part[held], -1)  # -1: no neighbour (the index the hash gives a missing one reads it)
    queries = {k: pts[members[k][evenly_spread(len(members[k]), QUERY_POINTS)]] for k in measured}
    bounds = {k: NEAR_M + NEAR_RANGE * np.linalg.norm(q, axis=1) for k, q in queries.items()}
    index = VoxelHash.build(pts[held], float(max(b.max() for b in bounds.values())))
    for k, q in queries.items():
        bound = bounds[k]
        d, j = index.query(q, NEIGHBOURS, float(bound.max()))
        other = (label[j] != k) & (label[j] >= 0) & (d <= bound[:, None])
        out[k] = round(float(other.any(axis=1).mean()), 4)
    return out
