"""Free-space consistency of accumulated sweeps: what the frame's own sweeps saw through is removed.

A mover's earlier positions are empty once it has left: a LiDAR slice near
the frame time (a reference) sees past the spot, so points there from
other slices are stale. Each reference's points give the nearest return per
cell of direction from its origin; a point of another slice nearer than its
cell's nearest return (by a margin) sat in space the reference saw empty.

The test runs per voxel (its first point stands for it), and only on the
voxels a caller asks about: a reference's own points still come from every
direction, as its map of nearest returns needs them. Directions are binned
on the faces of a cube around the origin (no trigonometry per test, which
dominated the test's cost): a cell is at most the requested angle wide, at
the faces' centres, and about a third of it in the corners.

`free_space_bits` says which references saw through each point (one bit
each, so that the stream pass can test a block once for every sample that
will hold it: `ingest.train.block_planes`); `free_space_filter` is the
test of one sample's own references.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from calibration.types import F64, I64, U64, Bool
from ingest.rows import rows
from ingest.train.voxel_hash import voxel_groups

FREE_MARGIN_REL = 0.03  # a ray must pass a point by margin_m + 3 % of its range to clear it


@njit(cache=True, nogil=True)
def _cell(dx, dy, dz, n):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Cube-map cell (face, row, col flattened) of a direction and its length."""
    ax, ay, az = abs(dx), abs(dy), abs(dz)
    if ax >= ay and ax >= az:
        face, m, u, v = (0 if dx > 0 else 1), ax, dy, dz
    elif ay >= az:
        face, m, u, v = (2 if dy > 0 else 3), ay, dx, dz
    else:
        face, m, u, v = (4 if dz > 0 else 5), az, dx, dy
    m = max(m, 1e-12)
    iu = min(int((u / m + 1.0) * 0.5 * n), n - 1)
    iv = min(int((v / m + 1.0) * 0.5 * n), n - 1)
    return (face * n + iv) * n + iu, math.sqrt(dx * dx + dy * dy + dz * dz)


@njit(cache=True, nogil=True, error_model="numpy")
def _cells(x, y, z, ox, oy, oz, n, cell, range2):  # type: ignore[no-untyped-def]  # pragma: no cover
    """`_cell` of every (x, y, z) - origin, squared ranges, in a loop without branches.

    Selects instead of `_cell`'s if/elif and no early exit: the compiler
    pipelines (and vectorises) it, twice as fast as testing voxel by voxel.
    The same comparisons and divisions as `_cell`, so the same cells.
    """
    for t in range(x.shape[0]):
        dx, dy, dz = x[t] - ox, y[t] - oy, z[t] - oz
        ax, ay, az = abs(dx), abs(dy), abs(dz)
        on_x = (ax >= ay) & (ax >= az)
        on_y = (not on_x) & (ay >= az)
        on_z = not (on_x or on_y)
        m = max(ax if on_x else (ay if on_y else az), 1e-12)
        u = dy if on_x else dx
        v = dy if on_z else dz
        along = dx if on_x else (dy if on_y else dz)
        face = (0 if on_x else (2 if on_y else 4)) + (0 if along > 0 else 1)
        iu = min(int((u / m + 1.0) * 0.5 * n), n - 1)
        iv = min(int((v / m + 1.0) * 0.5 * n), n - 1)
        cell[t] = (face * n + iv) * n + iu
        range2[t] = dx * dx + dy * dy + dz * dz


@njit(cache=True, nogil=True)
def _clearing(pts, voxel, rep, candidate, own, own_start, origins, ref_bit, n, margin_m, margin_rel, bits):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Set bit `ref_bit[r]` of `bits[v]` for every candidate voxel v that reference r saw through."""
    hit_by = np.full(rep.shape[0], -1, np.int64)
    nearest = np.empty(6 * n * n, np.float64)
    tested = np.flatnonzero(candidate)
    # the tested voxels' representatives, gathered once: the loop per reference reads them in order
    nt = tested.shape[0]
    x, y, z = np.empty(nt), np.empty(nt), np.empty(nt)
    for t in range(nt):
        i = rep[tested[t]]
        x[t], y[t], z[t] = pts[i, 0], pts[i, 1], pts[i, 2]
    cell, range2 = np.empty(nt, np.int64), np.empty(nt, np.float64)
    for r in range(origins.shape[0]):
        a, b = own_start[r], own_start[r + 1]
        if a == b:
            continue
        word, bit = ref_bit[r] >> 6, np.uint64(1) << np.uint64(ref_bit[r] & 63)
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        nearest[:] = np.inf
        for j in range(a, b):
            i = own[j]
            c, rng = _cell(pts[i, 0] - ox, pts[i, 1] - oy, pts[i, 2] - oz, n)
            if rng < nearest[c]:
                nearest[c] = rng
            hit_by[voxel[i]] = r
        _cells(x, y, z, ox, oy, oz, n, cell, range2)
        for t in range(nt):
            near = nearest[cell[t]]
            if near < np.inf:
                v = tested[t]
                if bits[v, word] & bit or hit_by[v] == r:
                    continue
                rng = math.sqrt(range2[t])
                if near > rng + margin_m + margin_rel * rng:
                    bits[v, word] |= bit
    return bits


def clearing_voxels(
    pts: F64, voxel: I64, rep: I64, candidate: Bool, own: I64, own_start: I64, origins: F64, ref_bit: I64,
    n_bits: int, cell_rad: float, margin_m: float, margin_rel: float = FREE_MARGIN_REL,
) -> U64:  # fmt: skip
    """Per voxel, which references saw through it: bit `ref_bit[r]` of row v (V, ceil(n_bits / 64)).

    `voxel` is each point's voxel, `rep` each voxel's representative point,
    `candidate` the voxels to test (the others get no bit); reference r's
    points are `own[own_start[r]:own_start[r + 1]]`, seen from `origins[r]`.
    Per reference: the nearest return in each cell of direction (cube-map
    cells at most `cell_rad` wide), then every candidate voxel that
    reference did not hit and whose representative lies nearer than its
    cell's nearest return by more than `margin_m` + `margin_rel` x its range
    is cleared. All positions in metres, in one frame. References may share
    a bit (the same time, two LiDARs).
    """
    n = max(1, math.ceil(2.0 / cell_rad))  # cells per face edge: tangents -1..1, 2/n rad at the centre
    bits = np.zeros((len(rep), max(1, -(-n_bits // 64))), np.uint64)
    out: U64 = _clearing(
        pts, voxel, rep, candidate, own, own_start, origins, ref_bit, n, margin_m, margin_rel, bits
    )
    return out


def _stable_order(ids: I64) -> I64:
    """`np.argsort(ids, kind="stable")`; a radix sort when the ids span fewer than 2^15 values (slices do)."""
    if len(ids) and int(ids.max()) - int(ids.min()) < 1 << 15:
        out: I64 = np.argsort((ids - ids.min()).astype(np.int16), kind="stable")
        return out
    return np.argsort(ids, kind="stable")


def free_space_bits(
    pts: F64,
    slice_id: I64,
    references: list[tuple[int, F64, int]],
    n_bits: int,
    cell_deg: float,
    voxel_m: float,
    margin_m: float,
    test: Bool | None = None,
) -> U64:
    """Per point, which reference slices saw through it (a mover's earlier positions are cleared).

    `slice_id` names each point's slice (one LiDAR, a few tens of ms);
    `references` are (slice id, that LiDAR's origin at the slice's time,
    its bit < `n_bits`), all in the same frame as `pts` (metres). A point of
    another slice whose direction from a reference's origin falls in a
    `cell_deg` cell and that lies nearer than the cell's nearest return by
    more than `margin_m` + 3 % of its range sat where the reference saw
    empty space: its row (N, ceil(n_bits / 64)) gets the reference's bit.
    Cells with no return say nothing, and the nearest return (not the
    farthest) makes the test clear a point only where the whole cell was
    seen beyond it, so static edges stay. The test runs per `voxel_m` voxel
    (its first point stands for it; a voxel the reference itself hit is
    occupied), well inside the margin. Only voxels holding a point with
    `test` set are tested (default: all).
    """
    voxel, rep = voxel_groups(pts, voxel_m)
    candidate = np.ones(len(rep), bool)
    if test is not None:
        candidate[:] = False
        candidate[voxel[test]] = True
    order = _stable_order(slice_id)
    sids = np.array([sid for sid, _, _ in references], np.int64)
    lo = np.searchsorted(slice_id[order], sids)
    hi = np.searchsorted(slice_id[order], sids + 1)
    own = np.concatenate([order[a:b] for a, b in zip(lo, hi, strict=True)] + [np.zeros(0, np.int64)])
    own_start = np.r_[0, np.cumsum(hi - lo)].astype(np.int64)
    origins = np.array([o for _, o, _ in references], np.float64).reshape(-1, 3)
    ref_bit = np.array([b for _, _, b in references], np.int64)
    if len(ref_bit) and (ref_bit.min() < 0 or ref_bit.max() >= n_bits):
        raise ValueError(f"reference bits must lie in 0..{n_bits - 1}, got {ref_bit.min()}..{ref_bit.max()}")
    bits = clearing_voxels(
        np.ascontiguousarray(pts, np.float64), voxel, rep.astype(np.int64), candidate, own, own_start,
        origins, ref_bit, n_bits, math.radians(cell_deg), margin_m,
    )  # fmt: skip
    out: U64 = rows(bits, voxel)
    return out


def free_space_filter(
    pts: F64,
    slice_id: I64,
    references: list[tuple[int, F64]],
    cell_deg: float,
    voxel_m: float,
    margin_m: float,
    test: Bool | None = None,
) -> Bool:
    """Keep mask: points that no reference slice saw through (`free_space_bits` with one bit for all).

    `references` are (slice id, that LiDAR's origin at the slice's time): the
    frame's own slices.
    """
    refs = [(sid, origin, 0) for sid, origin in references]
    bits = free_space_bits(pts, slice_id, refs, 1, cell_deg, voxel_m, margin_m, test)
    out: Bool = bits[:, 0] == 0
    return out
