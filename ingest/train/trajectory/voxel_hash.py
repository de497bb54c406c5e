"""Nearest neighbours in a hash of voxels (compiled, numba): the odometry's map search.

The odometry's local map changes every 100 ms chunk (points join, old ones
leave), and rebuilding a k-d tree of its ~120k points each time would be the
largest cost of the trajectory pass. A voxel hash builds in one linear pass
(KISS-ICP's idea): the points are bucketed by their `cell_m` cube, the buckets
laid out contiguously (a counting sort), and an open-addressing table maps a
cube's packed key to its bucket.

A search visits the cubes around the query's own in shells of growing
Chebyshev radius r, skipping cubes whose box lies farther than the best
distance found so far. After shell r every point within r * cell_m of the
query, plus its distance to the nearest face of its own cube, has been seen,
so the search stops as soon as its answer lies that close: the result is
exact, the same neighbours a k-d tree returns within the radius (up to ties),
not an approximation. Most queries of a registered scan end after the own
cube or the first shell.

Kernels are compiled on first use and cached on disk (`cache=True`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from calibration.types import F64, I64

_EMPTY = -1
_OFFSET = 1 << 20  # cube coordinates are stored offset by this: 21 bits per axis, +-1e6 cubes
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


@njit(cache=True, nogil=True, inline="always")
def _key(ix: int, iy: int, iz: int) -> int:  # pragma: no cover
    return ((ix + _OFFSET) << 42) | ((iy + _OFFSET) << 21) | (iz + _OFFSET)


@njit(cache=True, nogil=True, inline="always")
def _slot(key: int, shift: int) -> int:  # pragma: no cover
    return np.int64(  # type: ignore[return-value]
        (np.uint64(key) * _GOLDEN) >> np.uint64(shift)
    )


@njit(cache=True, nogil=True)
def _cube_keys(xyz, cell_m):  # type: ignore[no-untyped-def]  # pragma: no cover
    keys = np.empty(xyz.shape[0], np.int64)
    for i in range(xyz.shape[0]):
        keys[i] = _key(
            math.floor(xyz[i, 0] / cell_m),
            math.floor(xyz[i, 1] / cell_m),
            math.floor(xyz[i, 2] / cell_m),
        )
    return keys


@njit(cache=True, nogil=True)
def _bucket_of(keys, bits):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Each key's bucket (numbered as first seen) in a table of 2^bits slots; -1 rows when it fills up."""
    size = 1 << bits
    shift = 64 - bits
    table_key = np.full(size, _EMPTY, np.int64)
    table_bucket = np.zeros(size, np.int64)
    bucket_of = np.empty(keys.shape[0], np.int64)
    n_buckets = 0
    last_key, last_bucket = _EMPTY, -1
    for i in range(keys.shape[0]):
        key = keys[i]
        if key != last_key:  # neighbours in a scan mostly share a cube
            s = _slot(key, shift)
            while table_key[s] != key and table_key[s] != _EMPTY:
                s = (s + 1) & (size - 1)
            if table_key[s] == _EMPTY:
                if 2 * (n_buckets + 1) > size:
                    return table_key, table_bucket, bucket_of[:0], -1
                table_key[s] = key
                table_bucket[s] = n_buckets
                n_buckets += 1
            last_key, last_bucket = key, table_bucket[s]
        bucket_of[i] = last_bucket
    return table_key, table_bucket, bucket_of, n_buckets


@njit(cache=True, nogil=True)
def _layout(xyz, bucket_of, n_buckets):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Counting sort of the points by bucket: (start (B + 1,), order (N,), points in that order (N, 3))."""
    n = xyz.shape[0]
    start = np.zeros(n_buckets + 1, np.int64)
    for i in range(n):
        start[bucket_of[i] + 1] += 1
    for b in range(n_buckets):
        start[b + 1] += start[b]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    xyz_sorted = np.empty((n, 3))
    for i in range(n):
        s = fill[bucket_of[i]]
        fill[bucket_of[i]] += 1
        order[s] = i
        xyz_sorted[s, 0] = xyz[i, 0]
        xyz_sorted[s, 1] = xyz[i, 1]
        xyz_sorted[s, 2] = xyz[i, 2]
    return start, order, xyz_sorted


@njit(cache=True, nogil=True, inline="always")
def _bucket(table_key, table_bucket, shift, key):  # type: ignore[no-untyped-def]  # pragma: no cover
    size = table_key.shape[0]
    s = _slot(key, shift)
    while True:
        k = table_key[s]
        if k == key:
            return table_bucket[s]
        if k == _EMPTY:
            return -1
        s = (s + 1) & (size - 1)


@njit(cache=True, nogil=True, inline="always")
def _axis_d2(v, lo, cell_m):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Squared distance along one axis from v to the interval [lo, lo + cell_m] (0 inside)."""
    d = v - lo
    if d < 0.0:
        return d * d
    if d > cell_m:
        return (d - cell_m) * (d - cell_m)
    return 0.0


@njit(cache=True, nogil=True)
def _shift(table_key):  # type: ignore[no-untyped-def]  # pragma: no cover
    shift = 64
    size = table_key.shape[0]
    while size > 1:
        size >>= 1
        shift -= 1
    return shift


@njit(cache=True, nogil=True)
def _knn(queries, xyz_sorted, order, start, table_key, table_bucket, cell_m, radius_m, best, idx):  # type: ignore[no-untyped-def]  # pragma: no cover
    """The k nearest points within `radius_m` of each query, nearest first (-1: none).

    best (M, k) and idx (M, k) come in holding radius_m^2 and -1 and leave
    holding the squared distances and indices.
    """
    shift = _shift(table_key)
    k = best.shape[1]
    r_max = math.ceil(radius_m / cell_m)
    for i in range(queries.shape[0]):
        qx, qy, qz = queries[i, 0], queries[i, 1], queries[i, 2]
        cx, cy, cz = math.floor(qx / cell_m), math.floor(qy / cell_m), math.floor(qz / cell_m)
        # the query's distance to its own cube's nearest face: shell r reaches every point r cubes plus this
        margin = min(qx - cx * cell_m, qy - cy * cell_m, qz - cz * cell_m)
        margin = max(min(margin, (cx + 1) * cell_m - qx, (cy + 1) * cell_m - qy, (cz + 1) * cell_m - qz), 0.0)
        worst = best[i, k - 1]
        for r in range(r_max + 1):
            for dx in range(-r, r + 1):
                ex = _axis_d2(qx, (cx + dx) * cell_m, cell_m)
                if ex >= worst:
                    continue
                for dy in range(-r, r + 1):
                    ey = ex + _axis_d2(qy, (cy + dy) * cell_m, cell_m)
                    if ey >= worst:
                        continue
                    step = 1 if abs(dx) == r or abs(dy) == r else 2 * r  # inside the shell: its two z faces
                    for dz in range(-r, r + 1, step):
                        if ey + _axis_d2(qz, (cz + dz) * cell_m, cell_m) >= worst:
                            continue
                        b = _bucket(table_key, table_bucket, shift, _key(cx + dx, cy + dy, cz + dz))
                        if b < 0:
                            continue
                        for s in range(start[b], start[b + 1]):
                            d2 = (xyz_sorted[s, 0] - qx) ** 2 + (xyz_sorted[s, 1] - qy) ** 2
                            d2 += (xyz_sorted[s, 2] - qz) ** 2
                            if d2 < worst:  # insert, keeping the row ascending
                                j = k - 1
                                while j > 0 and best[i, j - 1] > d2:
                                    best[i, j] = best[i, j - 1]
                                    idx[i, j] = idx[i, j - 1]
                                    j -= 1
                                best[i, j] = d2
                                idx[i, j] = order[s]
                                worst = best[i, k - 1]
            seen = r * cell_m + margin  # every point this close to the query has been seen
            if idx[i, k - 1] >= 0 and worst <= seen * seen:
                break


def voxel_keys(xyz: F64, voxel_m: float) -> I64:
    """One int64 per point naming its `voxel_m` cube (21 bits per axis: +-100 km at 0.1 m)."""
    out: I64 = _cube_keys(np.ascontiguousarray(xyz, np.float64).reshape(-1, 3), float(voxel_m))
    return out


def _buckets(keys: I64, bits: int) -> tuple[I64, I64, I64, int]:
    """`_bucket_of` in a table of 2^bits slots, doubled until the distinct keys fill at most half of it."""
    while True:
        table_key, table_bucket, bucket_of, n_buckets = _bucket_of(keys, bits)
        if n_buckets >= 0:
            return table_key, table_bucket, bucket_of, int(n_buckets)
        bits += 1


@njit(cache=True, nogil=True)
def _first_of_bucket(bucket_of, n_buckets):  # type: ignore[no-untyped-def]  # pragma: no cover
    first = np.empty(n_buckets, np.int64)
    for i in range(bucket_of.shape[0] - 1, -1, -1):
        first[bucket_of[i]] = i
    return first


def voxel_groups(xyz: F64, voxel_m: float) -> tuple[I64, I64]:
    """Each point's voxel (N,), numbered by first appearance, and each voxel's first point (V,).

    What `np.unique(keys, return_index=True, return_inverse=True)` gives up to
    the voxels' numbering, in one hashed pass instead of a sort.
    """
    keys = voxel_keys(xyz, voxel_m)
    # a table for up to half as many voxels as points (a small table stays in cache); doubled if short
    _, _, bucket_of, n_buckets = _buckets(keys, max(4, int(np.ceil(np.log2(max(len(keys), 1))))))
    first: I64 = _first_of_bucket(bucket_of, n_buckets)
    voxel: I64 = bucket_of
    return voxel, first


@njit(cache=True, nogil=True)
def _first_free(keys, taken, bits, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    size = 1 << bits
    shift = 64 - bits
    table = np.full(size, _EMPTY, np.int64)
    for i in range(taken.shape[0]):
        s = _slot(taken[i], shift)
        while table[s] != taken[i] and table[s] != _EMPTY:
            s = (s + 1) & (size - 1)
        table[s] = taken[i]
    n = 0
    for i in range(keys.shape[0]):
        s = _slot(keys[i], shift)
        while table[s] != keys[i] and table[s] != _EMPTY:
            s = (s + 1) & (size - 1)
        if table[s] == _EMPTY:
            table[s] = keys[i]
            out[n] = i
            n += 1
    return n


def first_free(keys: I64, taken: I64) -> I64:
    """Ascending indices of the first of each distinct key in `keys` that is not among `taken`.

    With voxel keys: one point per voxel (the first in input order), none in a
    voxel already held. A hash set, one linear pass: no sort.
    """
    out = np.empty(len(keys), np.int64)
    bits = max(4, int(np.ceil(np.log2(2 * max(len(keys) + len(taken), 1)))))
    n = _first_free(np.ascontiguousarray(keys, np.int64), np.ascontiguousarray(taken, np.int64), bits, out)
    return out[:n]


@dataclass(frozen=True)
class VoxelHash:
    """Points bucketed by `cell_m` cubes, searchable for their k nearest neighbours within a radius."""

    xyz: F64  # (N, 3) the points, in input order
    cell_m: float
    xyz_sorted: F64  # (N, 3) the points bucket by bucket
    order: I64  # (N,) input index of each sorted point
    start: I64  # (B + 1,) bucket b holds sorted points start[b]:start[b + 1]
    table_key: I64  # open-addressing table: packed cube key per slot (-1: empty) ...
    table_bucket: I64  # ... and its bucket

    @classmethod
    def build(cls, xyz: F64, cell_m: float, buckets_hint: int = 0) -> VoxelHash:
        """Bucket the points `xyz` (N, 3, metres) by `cell_m` cubes.

        The table holds at most half as many cubes as slots; `buckets_hint`
        (such as the count of a previous build) sizes it so that it stays small
        enough for the cache, and it doubles until the cubes fit.
        """
        pts = np.ascontiguousarray(xyz, np.float64)
        keys = _cube_keys(pts, float(cell_m))
        bits = max(4, int(np.ceil(np.log2(2 * max(buckets_hint, 1)))) + 1)
        table_key, table_bucket, bucket_of, n_buckets = _buckets(keys, bits)
        start, order, xyz_sorted = _layout(pts, bucket_of, n_buckets)
        return cls(pts, float(cell_m), xyz_sorted, order, start, table_key, table_bucket)

    @property
    def buckets(self) -> int:
        """Occupied cubes."""
        return len(self.start) - 1

    def query(self, queries: F64, k: int, radius_m: float) -> tuple[F64, I64]:
        """Distances (M, k, metres, ascending) and indices (M, k) of each query's k nearest within `radius_m`.

        Neighbours closer than `radius_m` only (strictly); missing ones are
        distance inf and index -1, as scipy's cKDTree reports them.
        """
        q = np.ascontiguousarray(queries, np.float64).reshape(-1, 3)
        idx = np.full((len(q), k), -1, np.int64)
        d2 = np.full((len(q), k), float(radius_m) ** 2)
        if len(q) and len(self.xyz) and k > 0:
            _knn(q, self.xyz_sorted, self.order, self.start, self.table_key, self.table_bucket,
                 self.cell_m, float(radius_m), d2, idx)  # fmt: skip
        d2[idx < 0] = np.inf
        return np.sqrt(d2), idx


@njit(cache=True, nogil=True)
def _claim(table_key, table_id, keys, live_from, next_id, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Claim the free voxels among `keys` (in order) for ids next_id, next_id + 1, ...

    Returns (claimed, slots newly taken).
    """
    size = table_key.shape[0]
    shift = _shift(table_key)
    n = 0
    used = 0
    for i in range(keys.shape[0]):
        s = _slot(keys[i], shift)
        while table_key[s] != keys[i] and table_key[s] != _EMPTY:
            s = (s + 1) & (size - 1)
        if table_key[s] == _EMPTY:
            table_key[s] = keys[i]
            used += 1
        elif table_id[s] >= live_from:
            continue  # held by a live point
        table_id[s] = next_id + n
        out[n] = i
        n += 1
    return n, used


@njit(cache=True, nogil=True)
def _insert(table_key, table_id, keys, ids):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Insert distinct `keys` with their `ids` into an empty table."""
    size = table_key.shape[0]
    shift = _shift(table_key)
    for i in range(keys.shape[0]):
        s = _slot(keys[i], shift)
        while table_key[s] != _EMPTY:
            s = (s + 1) & (size - 1)
        table_key[s] = keys[i]
        table_id[s] = ids[i]


class VoxelSet:
    """Which voxels the map's live points hold: voxel key -> id of the point (ids count up as points join).

    Points leave by age, the oldest first, so "live" is one threshold on the
    id: an entry whose point has left counts as free and is reused, and the
    table is rebuilt from the live entries only when it fills up. Each chunk
    then costs its own points, not the map's.
    """

    def __init__(self) -> None:
        self.table_key = np.full(16, _EMPTY, np.int64)
        self.table_id = np.zeros(16, np.int64)
        self.used = 0  # slots taken, by live or departed points
        self.next_id = 0

    def claim(self, keys: I64, live_from: int) -> I64:
        """Ascending indices of the first of each of `keys` whose voxel no point with id >= `live_from` holds.

        The claimed get the next ids, in order.
        """
        keys = np.ascontiguousarray(keys, np.int64)
        if 2 * (self.used + len(keys)) > len(self.table_key):
            self._rebuild(live_from, len(keys))
        out = np.empty(len(keys), np.int64)
        n, used = _claim(self.table_key, self.table_id, keys, live_from, self.next_id, out)
        self.used += used
        self.next_id += n
        return out[:n]

    def _rebuild(self, live_from: int, extra: int) -> None:
        live = (self.table_key != _EMPTY) & (self.table_id >= live_from)
        keys, ids = self.table_key[live], self.table_id[live]
        size = 1 << max(4, int(np.ceil(np.log2(4 * (len(keys) + extra)))))
        self.table_key = np.full(size, _EMPTY, np.int64)
        self.table_id = np.zeros(size, np.int64)
        _insert(self.table_key, self.table_id, keys, ids)
        self.used = len(keys)
