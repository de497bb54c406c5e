"""Free-space consistency of accumulated sweeps: what the frame's own sweeps saw through is removed.

A mover's earlier positions are empty once it has left: a LiDAR slice near
the frame time (a reference) sees past the spot, so points there from
other slices are stale. Every point of a reference is the end of a ray from
its LiDAR at the point's own time; a point of another slice is seen through
when one of those rays passed it within the beam's footprint (or a few
centimetres) and returned beyond it by a margin (`RayTest`). Where the point
has a plane, the ray must cross that plane beside the point, not skim along
it: a ray grazing a static surface (the ground far ahead, a wall seen
edge-on) passes a point on it closely and returns from farther along the
same surface, and a ray passing just past a static edge returns from
behind it, so a single ray says little. A reference that also returned
from within the tolerance of the point (a ray ending there, or a point in
its voxel) hit its surface: rays of it passing beside the point are no
evidence (a 12 mm cable or a table leg is passed within 3 cm by rays
that miss it, while others of the same slice hit it). A point is removed
only when the rays of several slice times agree (`free_space_filter`'s
`min_slices`, `FreeSpaceSettings.min_slices`), and only slice times before
the first or after the last that hit it count (`stale_slices`): a mover's
earlier position is hit while the mover is there and crossed by the rays
of the slices after it left, a thin static object is hit throughout the
window and passed closely in between.

The test runs per voxel (its first point stands for it), and only on the
voxels a caller asks about: a reference's own points still come from every
direction. A reference's rays are grouped by direction on the faces of a
cube around its origin (no trigonometry per test), and a point looks only
at the cells its tolerance reaches.

`free_space_bits` says which references saw through each point and which
hit it (one bit each, so that the stream pass can test a block once for
every sample that will hold it: `ingest.train.gt.block_planes`);
`free_space_filter` is the test of one sample's own references.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from calibration.types import F64, I64, U64, Bool
from ingest.rows import rows
from ingest.train.trajectory.voxel_hash import voxel_groups

FREE_MARGIN_REL = 0.03  # a ray must pass a point by margin_m + 3 % of its range to clear it


@dataclass(frozen=True)
class RayTest:
    """When a LiDAR ray saw through a point (metres, radians, degrees).

    The ray must pass the point within `pass_m` or its beam's footprint
    (`footprint_rad` x range: the Mid-360's 0.2 deg divergence), meet the
    point's plane (where it has one) at an angle whose cosine to the normal
    is at least `min_cos`, and return at least `margin_m` + `margin_rel` x
    range beyond it. Rays are grouped by direction in `cell_deg` cells and
    points tested a `voxel_m` voxel at a time.
    """

    cell_deg: float = 1.0
    voxel_m: float = 0.05
    margin_m: float = 0.1
    margin_rel: float = FREE_MARGIN_REL
    pass_m: float = 0.03
    footprint_rad: float = 0.0035
    min_cos: float = 0.1


@njit(cache=True, nogil=True)
def _face_tangents(dx, dy, dz):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Cube face of a direction and its two tangents on it (each in -1..1)."""
    ax, ay, az = abs(dx), abs(dy), abs(dz)
    if ax >= ay and ax >= az:
        face, m, u, v = (0 if dx > 0 else 1), ax, dy, dz
    elif ay >= az:
        face, m, u, v = (2 if dy > 0 else 3), ay, dx, dz
    else:
        face, m, u, v = (4 if dz > 0 else 5), az, dx, dy
    m = max(m, 1e-12)
    return face, u / m, v / m


@njit(cache=True, nogil=True)
def _cell(dx, dy, dz, n):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Cube-map cell (face, row, col flattened) of a direction and its length."""
    face, u, v = _face_tangents(dx, dy, dz)
    iu = min(int((u + 1.0) * 0.5 * n), n - 1)
    iv = min(int((v + 1.0) * 0.5 * n), n - 1)
    return (face * n + iv) * n + iu, math.sqrt(dx * dx + dy * dy + dz * dz)


@njit(cache=True, nogil=True)
def _rays_by_cell(pts, own, a, b, ox, oy, oz, ray_origin, n, count):  # type: ignore[no-untyped-def]  # pragma: no cover
    """A reference's rays grouped by the cube-map cell of their return seen from (ox, oy, oz).

    Returns each cell's first ray (`count`, reused: 6 n^2 + 1 entries), the
    rays in cell order as origin (3), unit direction (3) and length (m)
    columns, and the largest distance from (ox, oy, oz) to a ray's origin.
    """
    m = b - a
    cell = np.empty(m, np.int64)
    count[:] = 0
    spread = 0.0
    for j in range(a, b):
        i = own[j]
        c, _ = _cell(pts[i, 0] - ox, pts[i, 1] - oy, pts[i, 2] - oz, n)
        cell[j - a] = c
        count[c + 1] += 1
        ex, ey, ez = ray_origin[i, 0] - ox, ray_origin[i, 1] - oy, ray_origin[i, 2] - oz
        spread = max(spread, math.sqrt(ex * ex + ey * ey + ez * ez))
    for c in range(1, count.shape[0]):
        count[c] += count[c - 1]
    ray = np.empty((m, 7))
    fill = count[:-1].copy()
    for j in range(a, b):
        i = own[j]
        q = fill[cell[j - a]]
        fill[cell[j - a]] += 1
        dx, dy, dz = pts[i, 0] - ray_origin[i, 0], pts[i, 1] - ray_origin[i, 1], pts[i, 2] - ray_origin[i, 2]
        length = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
        ray[q, 0], ray[q, 1], ray[q, 2] = ray_origin[i, 0], ray_origin[i, 1], ray_origin[i, 2]
        ray[q, 3], ray[q, 4], ray[q, 5], ray[q, 6] = dx / length, dy / length, dz / length, length
    return count, ray, spread


@njit(cache=True, nogil=True)
def _sees_through(ray, q, px, py, pz, nx, ny, nz, tol, margin_m, margin_rel, min_cos):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Whether ray `q` passed within `tol` of the point (px, py, pz) and went on beyond it by the margin.

    With a normal (nx, ny, nz; NaN: none) the ray must meet the point's plane
    at most `tol` from the point, at an angle whose cosine to the normal is
    at least `min_cos`, and return beyond that crossing by `margin_m` +
    `margin_rel` x its distance: a ray grazing a surface beside the point
    crosses its plane far from it and counts for nothing. Without one, the
    ray's closest approach to the point counts.
    """
    wx, wy, wz = px - ray[q, 0], py - ray[q, 1], pz - ray[q, 2]
    dx, dy, dz, length = ray[q, 3], ray[q, 4], ray[q, 5], ray[q, 6]
    along = wx * dx + wy * dy + wz * dz
    if along <= 0.0:
        return False
    if nx == nx:
        cos = nx * dx + ny * dy + nz * dz
        if abs(cos) < min_cos:
            return False
        along = (nx * wx + ny * wy + nz * wz) / cos
        if along <= 0.0:
            return False
    if length <= along + margin_m + margin_rel * along:
        return False
    ex, ey, ez = wx - along * dx, wy - along * dy, wz - along * dz
    return ex * ex + ey * ey + ez * ez <= tol * tol


@njit(cache=True, nogil=True)
def _returns_near(ray, q, px, py, pz, tol):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Whether ray `q` ended within `tol` of the point (px, py, pz): its reference hit the point's surface."""
    ex = ray[q, 0] + ray[q, 3] * ray[q, 6] - px
    ey = ray[q, 1] + ray[q, 4] * ray[q, 6] - py
    ez = ray[q, 2] + ray[q, 5] * ray[q, 6] - pz
    return ex * ex + ey * ey + ez * ez <= tol * tol


@njit(cache=True, nogil=True)
def _clearing(  # type: ignore[no-untyped-def]  # pragma: no cover
    pts, voxel, rep, candidate, own, own_start, origins, ray_origin, normal, ref_bit, n,
    margin_m, margin_rel, pass_m, footprint_rad, min_cos, bits, hits,
):  # fmt: skip
    """Set bit `ref_bit[r]` of `hits[v]` for every voxel v reference r hit (a point of r in it, or, for a
    candidate, a ray of r ending within the tolerance of its representative), else of `bits[v]` for every
    candidate voxel v that a ray of reference r saw through."""
    count = np.zeros(6 * n * n + 1, np.int64)
    tested = np.flatnonzero(candidate)
    for r in range(origins.shape[0]):
        a, b = own_start[r], own_start[r + 1]
        if a == b:
            continue
        word, bit = ref_bit[r] >> 6, np.uint64(1) << np.uint64(ref_bit[r] & 63)
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        for j in range(a, b):
            hits[voxel[own[j]], word] |= bit
        start, ray, spread = _rays_by_cell(pts, own, a, b, ox, oy, oz, ray_origin, n, count)
        for t in range(tested.shape[0]):
            v = tested[t]
            if hits[v, word] & bit:  # hit by this reference's time (its voxel, or a ray ending near it)
                continue
            i = rep[v]
            px, py, pz = pts[i, 0], pts[i, 1], pts[i, 2]
            dx, dy, dz = px - ox, py - oy, pz - oz
            rng = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-9)
            face, u, w = _face_tangents(dx, dy, dz)
            nx, ny, nz = normal[i, 0], normal[i, 1], normal[i, 2]
            tol = max(pass_m, footprint_rad * rng)
            # the cells a passing ray's return can lie in: the tolerance and the origins' spread as an
            # angle, in cells (a cell's angle shrinks to a third towards a face's corners)
            k = min(int((tol + spread) / rng * (1.0 + u * u + w * w) * 0.5 * n) + 1, n)
            iu = min(int((u + 1.0) * 0.5 * n), n - 1)
            iw = min(int((w + 1.0) * 0.5 * n), n - 1)
            cleared = hit = False
            for jw in range(max(iw - k, 0), min(iw + k, n - 1) + 1):
                for ju in range(max(iu - k, 0), min(iu + k, n - 1) + 1):
                    c = (face * n + jw) * n + ju
                    for q in range(start[c], start[c + 1]):
                        if _returns_near(ray, q, px, py, pz, tol):
                            hit = True
                            break
                        if not cleared:
                            cleared = _sees_through(
                                ray, q, px, py, pz, nx, ny, nz, tol, margin_m, margin_rel, min_cos
                            )
                    if hit:
                        break
                if hit:
                    break
            if hit:  # the reference hit the point's surface too: a ray passing beside it is no evidence
                hits[v, word] |= bit
                bits[v, word] &= ~bit
            elif cleared:
                bits[v, word] |= bit
    return bits


def clearing_voxels(
    pts: F64, voxel: I64, rep: I64, candidate: Bool, own: I64, own_start: I64, origins: F64, ref_bit: I64,
    n_bits: int, test: RayTest, ray_origin: F64, normal: F64,
) -> U64:  # fmt: skip
    """Per voxel, which references saw through it and which hit it: (V, 2 w), w = ceil(n_bits / 64).

    Bit `ref_bit[r]` of the first w words of row v: reference r saw through
    voxel v; of the last w: reference r hit it (`stale_slices` weighs the
    two). `voxel` is each point's voxel, `rep` each voxel's representative
    point, `candidate` the voxels to test (the others get no saw-through
    bit); reference r's points are `own[own_start[r]:own_start[r + 1]]`,
    each the end of a ray from its `ray_origin` (the LiDAR at the point's
    time), grouped by direction from `origins[r]`. A candidate voxel the
    reference did not hit is seen through when one of its rays saw through
    its representative (`_sees_through`, with `normal`: (N, 3), NaN rows for
    points without a plane). All positions in metres, in one frame.
    References may share a bit (the same time, two LiDARs).
    """
    n = max(1, math.ceil(2.0 / math.radians(test.cell_deg)))  # cells per face edge: 2/n rad at the centre
    words = max(1, -(-n_bits // 64))
    bits = np.zeros((len(rep), words), np.uint64)
    hits = np.zeros((len(rep), words), np.uint64)
    _clearing(
        pts, voxel, rep, candidate, own, own_start, origins, ray_origin, normal, ref_bit, n, test.margin_m,
        test.margin_rel, test.pass_m, test.footprint_rad, test.min_cos, bits, hits,
    )  # fmt: skip
    out: U64 = np.concatenate([bits, hits], axis=1)
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
    ray_test: RayTest,
    test: Bool | None = None,
    ray_origin: F64 | None = None,
    normal: F64 | None = None,
) -> U64:
    """Per point, which reference slices saw through it (a mover's earlier positions are cleared).

    `slice_id` names each point's slice (one LiDAR, a few tens of ms);
    `references` are (slice id, that LiDAR's origin at the slice's time,
    its bit < `n_bits`), all in the same frame as `pts` (metres). Every
    point of a reference is the return of a ray from its `ray_origin` (the
    LiDAR at the point's own time; default: the reference's origin). A point
    of another slice that such a ray passed (within the beam's footprint,
    `RayTest`) and went on beyond, by a margin, sat where the reference saw
    empty space: its row (N, 2 ceil(n_bits / 64)) gets the reference's bit
    in its first half; a point whose voxel the reference hit gets it in the
    second (`clearing_voxels`' layout, weighed by `stale_slices`).
    With `normal` ((N, 3) unit, NaN rows: no plane) the ray must cross the
    point's plane beside it: a ray grazing a static surface past its edge or
    along it clears nothing. The test runs per `ray_test.voxel_m` voxel
    (its first point stands for it; a voxel the reference itself hit is
    occupied). Only voxels holding a point with `test` set are tested
    (default: all).
    """
    voxel, rep = voxel_groups(pts, ray_test.voxel_m)
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
    if ray_origin is None:
        ray_origin = np.zeros((len(pts), 3))
        for r in range(len(references)):
            ray_origin[own[own_start[r] : own_start[r + 1]]] = origins[r]
    if normal is None:
        normal = np.full((len(pts), 3), np.nan)
    bits = clearing_voxels(
        np.ascontiguousarray(pts, np.float64), voxel, rep.astype(np.int64), candidate, own, own_start,
        origins, ref_bit, n_bits, ray_test, np.ascontiguousarray(ray_origin, np.float64),
        np.ascontiguousarray(normal, np.float64),
    )  # fmt: skip
    out: U64 = rows(bits, voxel)
    return out


@njit(cache=True, nogil=True)
def _stale(bits, words):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Per row: the saw-through bits (first `words` words) outside the span of the hit bits (the rest)."""
    out = np.zeros(bits.shape[0], np.int64)
    for i in range(bits.shape[0]):
        first, last = -1, -1
        for b in range(64 * words):
            if bits[i, words + (b >> 6)] >> np.uint64(b & 63) & np.uint64(1):
                if first < 0:
                    first = b
                last = b
        count = 0
        for b in range(64 * words):
            if (b < first or b > last) and bits[i, b >> 6] >> np.uint64(b & 63) & np.uint64(1):
                count += 1
        out[i] = count
    return out


def stale_slices(bits: U64) -> I64:
    """Per row of free-space bits (`clearing_voxels`' layout), the slice times that saw through the point
    before the first or after the last slice time that hit it: how long it has been empty.

    A mover's earlier position is hit while the mover is there and seen
    through once it has left, so the slices seeing through it lie outside
    the span of those hitting it. A thin static object (a cable, a table
    leg, a board's edge) is hit throughout the window, and rays passing
    just beside it, within the test's tolerance, see past it in between:
    those count for nothing. Without any hit every saw-through bit counts.
    """
    words = bits.shape[1] // 2
    out: I64 = _stale(np.ascontiguousarray(bits), words)
    return out


def free_space_filter(
    pts: F64,
    slice_id: I64,
    references: list[tuple[int, F64]],
    ray_test: RayTest,
    test: Bool | None = None,
    ray_origin: F64 | None = None,
    normal: F64 | None = None,
    min_slices: int = 1,
    lidars: int = 1,
) -> Bool:
    """Keep mask: points fewer than `min_slices` slice times saw through (`free_space_bits`).

    `references` are (slice id, that LiDAR's origin at the slice's time): the
    frame's own slices. Slice ids are time x `lidars` + LiDAR: the LiDARs of
    one time share a bit, so agreeing slices are slices of different times.
    """
    times = np.array([sid // lidars for sid, _ in references], np.int64)
    first = int(times.min()) if len(times) else 0
    refs = [(sid, origin, int(k) - first) for (sid, origin), k in zip(references, times, strict=True)]
    n_bits = int(times.max()) - first + 1 if len(times) else 1
    bits = free_space_bits(pts, slice_id, refs, n_bits, ray_test, test, ray_origin, normal)
    out: Bool = stale_slices(bits) < min_slices
    return out
