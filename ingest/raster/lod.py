"""Level of detail for dense scans: voxel buckets in stratified order, and per-view point selection.

A view must touch only the points it needs: those inside its frustum, at a
density matching its pixels. `build_index` sorts a scan once into voxel
buckets (`voxel_m` cubes in the scan frame), in a random order inside each
bucket, so any prefix of a bucket is a uniform subsample of it. `select` then
keeps the voxels whose bounding sphere reaches the image and takes from each a
prefix sized so the image receives about `points_per_px` points per pixel.

Density needs the scanner's angular sampling: `angular_spacing` counts points
per solid angle around the scanner in equal-area (cos polar x azimuth) cells;
a point's metric spacing on its surface is then its cell's angular spacing
times its range from its scanner, and seen from a camera at range r_c it
spans spacing * r_scan / r_c radians (surface tilt ignored).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from calibration.camera import CameraModel
from calibration.types import F32, F64, I64, U8, Bool
from ingest.errors import ScanError
from ingest.raster.point_kernels import sphere_cells
from ingest.raster.scan import Scan

VOXEL_M = 0.25
POINT_SPACING_SMOOTH = 5  # `point_index`: counts averaged over 5 x 5 cells (no bucket mean)
SPHERE_CELLS = (256, 512)  # equal-area cells in cos(polar) x azimuth: 0.5 deg at the equator
RANK_BITS = 24
RANK_SEED = 0x5CA9
NEAR_VOXEL_RAD = 0.12  # voxels wider than this (angular radius) are culled by their corners too
VERY_NEAR_VOXEL_RAD = 0.5  # ... and wider than this are always kept, uncut
_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)


@dataclass(frozen=True, eq=False)
class ScanIndex:
    """A scan sorted into LOD voxel buckets (all arrays in bucket order, scan frame)."""

    name: str
    T_world_scan: F64
    xyz: F32  # (N, 3)
    rgb: U8  # (N, 3)
    masked: Bool | None  # (N,)
    mask_xyz: F32  # (M, 3) mask cloud (unsorted, small)
    mask_spacing_rad: F32  # (M,)
    voxel_start: I64  # (V + 1,) bucket v holds points voxel_start[v]:voxel_start[v+1]
    voxel_centre: F32  # (V, 3) cube centres
    voxel_spacing_rad: F32  # (V,) the scanner's mean angular spacing over the bucket
    voxel_m: float

    @property
    def n_points(self) -> int:
        return len(self.xyz)

    @property
    def n_voxels(self) -> int:
        return len(self.voxel_centre)

    def point_spacing_rad(self) -> F32:
        """Each point's bucket's angular spacing (N,); a point index's own, without a copy."""
        if self.n_voxels == self.n_points:  # one point per bucket (`point_index`)
            return self.voxel_spacing_rad
        out: F32 = np.repeat(self.voxel_spacing_rad, np.diff(self.voxel_start))
        return out


def angular_spacing(xyz: F32, cells: tuple[int, int] = SPHERE_CELLS, smooth: int = 1) -> F32:
    """Angular spacing (rad) of the scanner's sampling at each point, from points per steradian.

    Cells at the edge of what the scanner saw (sky line, tripod shadow) are
    partly empty and report a wider spacing, which only makes splats larger.
    `smooth` > 1 averages the counts over that many cells square first
    (occupied cells only), for points that get no other averaging. The cells
    are counted in one compiled pass (`point_kernels.sphere_cells`: 21 against
    37 ms in numpy for 1 M points, whose float32 arctan2 alone took 16).
    """
    n_u, n_az = cells
    cell = np.empty(len(xyz), np.int64)
    counts = np.zeros(n_u * n_az, np.int64)
    sphere_cells(np.ascontiguousarray(xyz, np.float32), n_u, n_az, cell, counts)
    return cell_spacing(cell, counts, cells, smooth)


def cell_spacing(cell: I64, counts: I64, cells: tuple[int, int], smooth: int) -> F32:
    """Each point's angular spacing (rad) from its cell's count (`angular_spacing`)."""
    n_u, n_az = cells
    per_cell = counts.astype(np.float64)
    if smooth > 1:
        grid = per_cell.reshape(n_u, n_az)
        occupied = (grid > 0).astype(np.float64)
        size = (smooth, smooth)
        mean = cv2.blur(grid, size, borderType=cv2.BORDER_REPLICATE)
        share = cv2.blur(occupied, size, borderType=cv2.BORDER_REPLICATE)
        per_cell = np.where(grid > 0, mean / np.maximum(share, 1e-9), 0.0).reshape(-1)
    cell_sr = 4.0 * math.pi / (n_u * n_az)
    spacing = np.sqrt(cell_sr / np.maximum(per_cell, 1)).astype(np.float32)
    out: F32 = spacing[cell]
    return out


def voxel_box(xyz: F32, inv: np.float32, voxel_m: float, source: str) -> tuple[I64, I64]:
    """The lowest voxel (3,) and voxels per axis (3,) of the points' bounding box.

    Voxel ids and a random rank share one int64 key, so the box may hold at
    most 2^(62 - RANK_BITS) voxels (about 1.6 km a side at 0.25 m). A larger
    box (outliers at 1e30, millimetres read as metres), or voxel ids beyond
    int32 (points far from the origin), is refused naming the coordinates,
    before the per-point int32 cast could overflow. `inv` is 1 / voxel_m in
    float32, the arithmetic of the per-point cells, so the box matches them.
    """
    lo_m, hi_m = xyz.min(axis=0), xyz.max(axis=0)
    if not (np.isfinite(lo_m).all() and np.isfinite(hi_m).all()):
        raise ScanError(
            f"{source}: coordinates that are not finite (NaN/inf); expected finite points in metres"
        )
    lo_v = np.floor(lo_m * inv).astype(np.float64)
    span_v = np.floor(hi_m * inv).astype(np.float64) - lo_v + 1.0
    bits = sum(math.ceil(math.log2(s + 1.0)) for s in span_v)
    int32_cells = max(np.abs(lo_v).max(), np.abs(lo_v + span_v).max()) < 2.0**31
    if bits + RANK_BITS > 62 or not int32_cells:
        far_m = float(max(np.abs(lo_m).max(), np.abs(hi_m).max()))
        box = " x ".join(f"{e:.3g}" for e in (hi_m.astype(np.float64) - lo_m))
        side_m = voxel_m * 2.0 ** ((62 - RANK_BITS) / 3)
        raise ScanError(
            f"{source}: coordinates up to {far_m:.3g} m (bounding box {box} m), more than the renderer's "
            f"index of {voxel_m:g} m voxels holds (about {side_m:.0f} m a side); expected the scan in metres "
            "in its scanner frame (far outliers, another unit or a world frame?)"
        )
    return lo_v.astype(np.int64), span_v.astype(np.int64)


def build_index(scan: Scan, voxel_m: float = VOXEL_M) -> ScanIndex:
    """Sort ``scan`` into voxel buckets, randomly ordered inside each (one argsort of N int64 keys).

    The index holds sorted copies of the points and colours; the scan's own
    arrays can be dropped afterwards.
    """
    if not (math.isfinite(voxel_m) and voxel_m > 0.0):
        raise ScanError(f"LOD voxel size must be > 0 m, got {voxel_m!r}")
    xyz = scan.xyz
    if len(xyz) == 0:
        raise ScanError(f"{scan.source or scan.name}: the scan has no points")
    inv = np.float32(1.0 / voxel_m)
    lo, span = voxel_box(xyz, inv, voxel_m, scan.source or scan.name)
    spacing = angular_spacing(xyz)
    # voxel id per point, one axis at a time (int32 cells: a 20M-point scan needs no (N, 3) int64)
    cells = [np.floor(xyz[:, k] * inv).astype(np.int32) for k in range(3)]
    key = cells[0].astype(np.int64) - int(lo[0])
    for k in (1, 2):
        key *= int(span[k])
        key += cells[k] - int(lo[k])
    del cells
    vid = key.copy()
    # a random rank inside each bucket: any prefix is a uniform subsample. (Spatially stratified
    # orders - bit-reversed Morton codes, sub-cell round robin - alias with the scanner's regular
    # grid and leave streaks of empty pixels at grazing angles.)
    key <<= RANK_BITS
    key |= np.random.default_rng(RANK_SEED).integers(0, 1 << RANK_BITS, len(xyz), dtype=np.int64)
    order = np.argsort(key)
    del key
    vid_sorted = vid[order]
    del vid
    starts = np.flatnonzero(np.r_[True, vid_sorted[1:] != vid_sorted[:-1]])
    vids = vid_sorted[starts]
    del vid_sorted
    voxel_start = np.r_[starts, len(order)].astype(np.int64)
    iz = vids % span[2]
    iy = (vids // span[2]) % span[1]
    ix = vids // (span[2] * span[1])
    centre = ((np.stack([ix, iy, iz], axis=1) + lo).astype(np.float64) + 0.5) * voxel_m
    sp_sorted = spacing[order]
    mean_sp = np.add.reduceat(sp_sorted.astype(np.float64), starts) / np.diff(voxel_start)
    mask_sp = angular_spacing(scan.mask_xyz) if len(scan.mask_xyz) else np.zeros(0, np.float32)
    return ScanIndex(
        name=scan.name,
        T_world_scan=scan.T_world_scan,
        xyz=np.ascontiguousarray(xyz[order]),
        rgb=np.ascontiguousarray(scan.rgb[order]),
        masked=None if scan.masked is None else scan.masked[order],
        mask_xyz=scan.mask_xyz,
        mask_spacing_rad=mask_sp,
        voxel_start=voxel_start,
        voxel_centre=centre.astype(np.float32),
        voxel_spacing_rad=mean_sp.astype(np.float32),
        voxel_m=float(voxel_m),
    )


def point_index(scan: Scan) -> ScanIndex:
    """An index without buckets: every point its own voxel, in the scan's order (no sort).

    For views that draw every point (`RenderParams.frustum_culling` off, as
    dense ground truth does, whose cloud was gathered for this one view):
    each point keeps its own angular spacing instead of its bucket's mean.
    """
    if len(scan.xyz) == 0:
        raise ScanError(f"{scan.source or scan.name}: the scan has no points")
    n = len(scan.xyz)
    mask_sp = angular_spacing(scan.mask_xyz) if len(scan.mask_xyz) else np.zeros(0, np.float32)
    return ScanIndex(
        name=scan.name,
        T_world_scan=scan.T_world_scan,
        xyz=scan.xyz,
        rgb=scan.rgb,
        masked=scan.masked,
        mask_xyz=scan.mask_xyz,
        mask_spacing_rad=mask_sp,
        voxel_start=np.arange(n + 1, dtype=np.int64),
        voxel_centre=scan.xyz,
        voxel_spacing_rad=angular_spacing(scan.xyz, smooth=POINT_SPACING_SMOOTH),
        voxel_m=0.0,
    )


@dataclass(frozen=True, eq=False)
class Selection:
    """Points of one scan chosen for a view: indices into the index arrays and their spacing."""

    idx: I64
    spacing_rad: F32  # effective angular spacing at the scanner after thinning
    voxels_kept: int


def select(
    index: ScanIndex,
    model: CameraModel,
    T_cam_scan: F64,
    ppr: tuple[F32, F32, int, float, float],
    points_per_px: float | None,
    coarse_mask: Bool | None = None,
) -> Selection:
    """The points of ``index`` a view of ``model`` at ``T_cam_scan`` needs (``None`` density = all).

    ``ppr`` is the camera's coarse pixels-per-radian maps (along u, along v),
    their stride, maximum and the cap of the level of detail
    (`ingest.raster.geometry.PixelGeometry.coarse`). ``coarse_mask`` (one cell per
    stride x stride pixels, already grown by a cell) drops voxels that land
    only where the view draws nothing.
    """
    ppr_u, ppr_v, stride, ppr_max, ppr_cap = ppr
    R, t = T_cam_scan[:3, :3], T_cam_scan[:3, 3]
    c = index.voxel_centre.astype(np.float64)
    c_cam = np.einsum("ij,nj->ni", R, c) + t
    r_cam = np.sqrt(np.einsum("ij,ij->i", c_cam, c_cam))
    ang = 0.5 * math.sqrt(3.0) * index.voxel_m / np.maximum(r_cam, 1e-9)
    uv, ok = model.project(c_cam)
    margin = ang * ppr_max + 1.0
    with np.errstate(invalid="ignore"):
        inside = (
            ok
            & (uv[:, 0] >= -0.5 - margin)
            & (uv[:, 0] <= model.width - 0.5 + margin)
            & (uv[:, 1] >= -0.5 - margin)
            & (uv[:, 1] <= model.height - 0.5 + margin)
        )
    if coarse_mask is not None:  # small voxels whose centre cell is outside the drawn area
        small = inside & (margin < stride)
        cu = np.clip((np.nan_to_num(uv[:, 0]) + 0.5) // stride, 0, coarse_mask.shape[1] - 1).astype(np.int64)
        cv = np.clip((np.nan_to_num(uv[:, 1]) + 0.5) // stride, 0, coarse_mask.shape[0] - 1).astype(np.int64)
        inside &= ~small | coarse_mask[cv, cu]
    # a near voxel spans many pixels: its centre may miss the image while a corner is in it
    near = ang > NEAR_VOXEL_RAD
    centre_in = inside.copy()
    probe = np.flatnonzero(near & ~inside)
    if probe.size:
        corners = c[probe, None, :] + 0.5 * index.voxel_m * _CORNERS[None, :, :]
        cuv, cok = model.project(np.einsum("ij,nkj->nki", R, corners) + t)
        with np.errstate(invalid="ignore"):
            hit = cok & (cuv[..., 0] >= -1.5) & (cuv[..., 0] <= model.width + 0.5)
            hit &= (cuv[..., 1] >= -1.5) & (cuv[..., 1] <= model.height + 0.5)
        inside[probe] = hit.any(axis=1) | (ang[probe] > VERY_NEAR_VOXEL_RAD)
    keep = np.flatnonzero(inside)
    counts = np.diff(index.voxel_start)[keep]
    sp = index.voxel_spacing_rad[keep].astype(np.float64)
    take = counts
    if points_per_px is not None:
        u = np.where(centre_in[keep], uv[keep, 0], 0.0)
        v = np.where(centre_in[keep], uv[keep, 1], 0.0)
        col = np.clip((u + 0.5) // stride, 0, ppr_u.shape[1] - 1).astype(np.int64)
        row = np.clip((v + 0.5) // stride, 0, ppr_u.shape[0] - 1).astype(np.int64)
        p = np.sqrt(ppr_u[row, col].astype(np.float64) * ppr_v[row, col])
        p = np.minimum(np.where(centre_in[keep], p, ppr_max), ppr_cap)
        r_scan = np.sqrt(np.einsum("ij,ij->i", c[keep], c[keep]))
        sp_px = sp * r_scan / np.maximum(r_cam[keep], 1e-9) * p
        frac = np.minimum(1.0, sp_px * sp_px * points_per_px)
        frac = np.where(ang[keep] > VERY_NEAR_VOXEL_RAD, 1.0, frac)
        take = np.maximum(1, np.ceil(frac * counts)).astype(np.int64)
        sp = sp * np.sqrt(counts / take)
    starts = index.voxel_start[keep]
    total = int(take.sum())
    # indices of the first take[k] points of each kept bucket, without a Python loop
    offs = np.repeat(starts - np.r_[0, np.cumsum(take)[:-1]], take)
    idx = np.arange(total, dtype=np.int64) + offs
    return Selection(idx, np.repeat(sp.astype(np.float32), take), len(keep))


def candidates(
    index: ScanIndex,
    model: CameraModel,
    T_cam_scan: F64,
    ppr: tuple[F32, F32, int, float, float],
    points_per_px: float | None,
    coarse_mask: Bool | None,
    culling: bool,
) -> tuple[I64, F32]:
    """The point indices of ``index`` a view draws and their angular spacing (rad): `select`'s, or with
    ``culling`` off (`RenderParams.frustum_culling`, the naive baseline) every point with its bucket's
    spacing. Every backend starts from these."""
    if culling:
        sel = select(index, model, T_cam_scan, ppr, points_per_px, coarse_mask)
        return sel.idx, sel.spacing_rad
    return np.arange(index.n_points), index.point_spacing_rad()
