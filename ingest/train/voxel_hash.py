"""Nearest neighbours in a hash of voxels (compiled, numba): the odometry's map search.

The odometry's local map changes every 100 ms chunk (points join, old ones
leave), and rebuilding a k-d tree of its ~120k points each time was the
largest cost of the trajectory pass. A voxel hash builds in one linear pass
(KISS-ICP's idea): the points are bucketed by their `cell_m` cube, the buckets
laid out contiguously (a counting sort), and an open-addressing table maps a
cube's packed key to its bucket.

A search visits the cubes around the query's own in shells of growing
Chebyshev radius r, skipping cubes whose box lies farther than the best
distance found so far. After shell r every point within r * cell_m of the
query has been seen (the query lies inside the centre cube), so the search
stops as soon as its answer lies that close: the result is exact, the same
neighbours a k-d tree returns within the radius (up to ties), not an
approximation. Most queries of a registered scan end after the first shell.

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
    return np.int64((np.uint64(key) * _GOLDEN) >> np.uint64(shift))


@njit(cache=True, nogil=True)
def _build(xyz, cell_m, bits):  # type: ignore[no-untyped-def]  # pragma: no cover
    n = xyz.shape[0]
    size = 1 << bits
    shift = 64 - bits
    table_key = np.full(size, _EMPTY, np.int64)
    table_bucket = np.zeros(size, np.int64)
    bucket_of = np.empty(n, np.int64)
    n_buckets = 0
    for i in range(n):
        key = _key(
            int(math.floor(xyz[i, 0] / cell_m)),
            int(math.floor(xyz[i, 1] / cell_m)),
            int(math.floor(xyz[i, 2] / cell_m)),
        )
        s = _slot(key, shift)
        while table_key[s] != key and table_key[s] != _EMPTY:
            s = (s + 1) & (size - 1)
        if table_key[s] == _EMPTY:
            table_key[s] = key
            table_bucket[s] = n_buckets
            n_buckets += 1
        bucket_of[i] = table_bucket[s]
    start = np.zeros(n_buckets + 1, np.int64)
    for i in range(n):
        start[bucket_of[i] + 1] += 1
    for b in range(n_buckets):
        start[b + 1] += start[b]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[bucket_of[i]]] = i
        fill[bucket_of[i]] += 1
    return table_key, table_bucket, start, order


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
def _box_d2(q, lo, cell_m):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Squared distance from point q to the cube with lower corner `lo` (0 inside)."""
    d2 = 0.0
    for a in range(3):
        v = q[a] - lo[a]
        if v < 0.0:
            d2 += v * v
        elif v > cell_m:
            d2 += (v - cell_m) * (v - cell_m)
    return d2


@njit(cache=True, nogil=True)
def _knn(queries, xyz, xyz_sorted, order, start, table_key, table_bucket, cell_m, k, radius_m, seed, out_idx, out_d2):  # type: ignore[no-untyped-def]  # pragma: no cover
    """The k nearest points within `radius_m` of each query, nearest first (-1 / inf: none)."""
    shift = 64
    size = table_key.shape[0]
    while size > 1:
        size >>= 1
        shift -= 1
    r_max = int(math.ceil(radius_m / cell_m))
    lo = np.empty(3)
    for i in range(queries.shape[0]):
        q = queries[i]
        best = out_d2[i]
        idx = out_idx[i]
        best[:] = radius_m * radius_m
        idx[:] = -1
        if k == 1 and seed[i] >= 0:  # a guess bounds the search from the start
            d2 = 0.0
            for a in range(3):
                v = xyz[seed[i], a] - q[a]
                d2 += v * v
            if d2 < best[0]:
                best[0] = d2
                idx[0] = seed[i]
        cx = int(math.floor(q[0] / cell_m))
        cy = int(math.floor(q[1] / cell_m))
        cz = int(math.floor(q[2] / cell_m))
        for r in range(r_max + 1):
            for dx in range(-r, r + 1):
                for dy in range(-r, r + 1):
                    edge = abs(dx) == r or abs(dy) == r
                    step = 1 if edge else max(2 * r, 1)
                    for dz in range(-r, r + 1, step):
                        lo[0] = (cx + dx) * cell_m
                        lo[1] = (cy + dy) * cell_m
                        lo[2] = (cz + dz) * cell_m
                        if _box_d2(q, lo, cell_m) >= best[k - 1]:
                            continue
                        b = _bucket(table_key, table_bucket, shift, _key(cx + dx, cy + dy, cz + dz))
                        if b < 0:
                            continue
                        for s in range(start[b], start[b + 1]):
                            d2 = 0.0
                            for a in range(3):
                                v = xyz_sorted[s, a] - q[a]
                                d2 += v * v
                            if d2 < best[k - 1]:  # insert, keeping best ascending
                                j = k - 1
                                while j > 0 and best[j - 1] > d2:
                                    best[j] = best[j - 1]
                                    idx[j] = idx[j - 1]
                                    j -= 1
                                best[j] = d2
                                idx[j] = order[s]
            seen = r * cell_m
            if idx[k - 1] >= 0 and best[k - 1] <= seen * seen:
                break
        for j in range(k):
            if idx[j] < 0:
                best[j] = np.inf


@njit(cache=True, nogil=True)
def _voxel_keys(xyz, voxel_m, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    for i in range(xyz.shape[0]):
        out[i] = _key(
            int(math.floor(xyz[i, 0] / voxel_m)),
            int(math.floor(xyz[i, 1] / voxel_m)),
            int(math.floor(xyz[i, 2] / voxel_m)),
        )


def voxel_keys(xyz: F64, voxel_m: float) -> I64:
    """One int64 per point naming its `voxel_m` cube (21 bits per axis: +-100 km at 0.1 m)."""
    out = np.empty(len(xyz), np.int64)
    if len(xyz):
        _voxel_keys(np.ascontiguousarray(xyz, np.float64), float(voxel_m), out)
    return out


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
    def build(cls, xyz: F64, cell_m: float) -> VoxelHash:
        """Bucket the points `xyz` (N, 3, metres) by `cell_m` cubes (load factor at most 1/2)."""
        pts = np.ascontiguousarray(xyz, np.float64)
        bits = max(4, int(np.ceil(np.log2(2 * max(len(pts), 1)))))
        table_key, table_bucket, start, order = _build(pts, float(cell_m), bits)
        return cls(pts, float(cell_m), pts[order], order, start, table_key, table_bucket)

    def query(self, queries: F64, k: int, radius_m: float, seed: I64 | None = None) -> tuple[F64, I64]:
        """Distances (M, k, metres, ascending) and indices (M, k) of each query's k nearest within `radius_m`.

        Neighbours closer than `radius_m` only (strictly); missing ones are
        distance inf and index -1, as scipy's cKDTree reports them. With k = 1,
        `seed` (M,) may name a point near each query (-1: none), such as the
        previous iteration's match: the search then skips every cube farther
        than it, and the answer is the same.
        """
        q = np.ascontiguousarray(queries, np.float64).reshape(-1, 3)
        idx = np.empty((len(q), k), np.int64)
        d2 = np.empty((len(q), k))
        hint = np.full(len(q), -1, np.int64) if seed is None or k != 1 else np.asarray(seed, np.int64)
        if len(q) and len(self.xyz) and k > 0:
            _knn(q, self.xyz, self.xyz_sorted, self.order, self.start, self.table_key, self.table_bucket,
                 self.cell_m, k, float(radius_m), hint, idx, d2)  # fmt: skip
        else:
            idx[:], d2[:] = -1, np.inf
        return np.sqrt(d2), idx
