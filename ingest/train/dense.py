"""Dense ground truth: every sweep of a window, placed with the trajectory, rendered like a laser scan.

The points of all sweeps within +-`window_ns` of the frame time are moved
into cam0 at the frame time with the recording's trajectory
(`ingest.train.odometry.RigTrajectory.to_frame`), then rendered with the
benchmark renderer's visibility machinery (`ingest.raster.view.render_view`:
footprint splats, a z-buffer on range, the two-sided occlusion test, same-
surface averaging and values moved onto pixel-centre rays). Accumulated
points the camera cannot see never become ground truth: they lose the
z-buffer or the occlusion test. A surface pixel gets a value only from a
point inside it or a planar fill from its neighbours' points (never the raw
splat range: `RenderParams.raw_fallback` off).

Depth (fisheye range) and disparity (cam0's rectified equirect, DESIGN.md's
formula and stability mask) are rendered from the same points.

Moving objects: a point is kept only where no sweep of the window saw
through it (`free_space_filter`): a mover's earlier positions are free space
once it has left, so its stale points are removed and counted.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from calibration.camera import CameraModel
from calibration.spherical import Equirectangular
from calibration.stereo import depth_to_disparity, disparity_stability_mask
from calibration.types import F64, I64, Bool
from ingest.dataset.sparse import SparseImage
from ingest.raster.edges import edge_band
from ingest.raster.lod import build_index
from ingest.raster.scan import Scan
from ingest.raster.view import Rendering, render_view
from ingest.raster.visibility import RenderParams


@dataclass(frozen=True)
class DenseParams:
    """Dense-GT settings (metres, nanoseconds, degrees)."""

    window_ns: int = 500_000_000  # +- around the frame time
    render: RenderParams = field(
        default_factory=lambda: RenderParams(points_per_px=None, raw_fallback=False, fill_passes=2)
    )
    edge_px: int = 1  # GT pixels this close to a range step or to empty sky are dropped
    free_space: bool = True  # remove points a later or earlier sweep saw through (movers)
    free_cell_deg: float = 0.5  # angular cell of the free-space test (LiDAR frame)
    free_margin_m: float = 0.1  # a ray must pass a point by this much (plus 3 % of range) to clear it
    stability_max_rel_error: float = 0.5
    stability_disp_error_px: float = 0.5


@dataclass(frozen=True)
class DenseGt:
    """One sample's dense GT and what went into it."""

    range_img: SparseImage  # fisheye range (m) along pixel rays
    disp_img: SparseImage  # equirect disparity (px of the full sphere)
    unstable: int  # equirect pixels with range but failing the stability mask
    points: int  # accumulated points rendered
    stats: dict[str, int]


def render_points(model: CameraModel, pts_cam: F64, T_world_cam: F64, params: RenderParams) -> Rendering:
    """Render points given in a frame "world" (here: cam0 at the frame time) into `model` at `T_world_cam`."""
    xyz = np.ascontiguousarray(pts_cam, np.float32)
    scan = Scan("accumulated", np.eye(4), xyz, np.zeros((len(xyz), 3), np.uint8))
    return render_view([build_index(scan)], model, T_world_cam, params)


def away_from_edges(rend: Rendering, edge_px: int) -> Bool:
    """Valid pixels (flat) farther than `edge_px` from a range step or from a pixel without surface.

    A pixel next to a silhouette mixes foreground and background (its
    centre's ray may pass the edge that its point sits on) and a planar fill
    across the silhouette extrapolates the wrong surface; both are removed.
    Range steps are those of `ingest.eval.metrics.edge_band` (5 cm / 3 %).
    """
    valid = rend.range_m > 0
    if edge_px <= 0:
        out: Bool = valid.reshape(-1)
        return out
    size = 2 * edge_px + 1
    kernel = np.ones((size, size), np.uint8)
    empty = (rend.rays & ~rend.surface).astype(np.uint8)
    near_empty = cv2.dilate(empty, kernel) > 0
    keep = valid & ~near_empty & ~edge_band(rend.range_m, edge_px)
    flat: Bool = keep.reshape(-1)
    return flat


def dense_ground_truth(
    model: CameraModel,
    eq: Equirectangular,
    R_cam0_rect: F64,
    baseline_m: float,
    pts_cam0: F64,
    params: DenseParams,
) -> DenseGt:
    """Fisheye range and equirect disparity of points already placed in cam0 at the frame time."""
    if len(pts_cam0) == 0:
        empty = SparseImage((model.height, model.width), np.zeros(0, np.int64), np.zeros(0, np.float32))
        return DenseGt(
            empty,
            SparseImage((eq.height, eq.width), np.zeros(0, np.int64), np.zeros(0, np.float32)),
            0,
            0,
            {},
        )
    fish = render_points(model, pts_cam0, np.eye(4), params.render)
    T_cam0_rect = np.eye(4)
    T_cam0_rect[:3, :3] = R_cam0_rect
    rect = render_points(eq, pts_cam0, T_cam0_rect, params.render)
    fish_ok = away_from_edges(fish, params.edge_px)
    pix = np.flatnonzero(fish_ok)
    range_img = SparseImage(fish.range_m.shape, pix, fish.range_m.reshape(-1)[pix])
    epix = np.flatnonzero(away_from_edges(rect, params.edge_px))
    r = rect.range_m.reshape(-1)[epix].astype(np.float64)
    rows = (epix // eq.width).astype(np.float64)
    rays, _ = eq.unproject(np.stack([(epix % eq.width).astype(np.float64), rows], axis=1))
    theta = np.arccos(np.clip(-rays[:, 1], -1.0, 1.0))
    disp = depth_to_disparity(r, theta, baseline_m, eq.height_full)
    stable = disparity_stability_mask(
        theta, r, baseline_m, eq.height_full, params.stability_max_rel_error, params.stability_disp_error_px
    )
    disp_img = SparseImage((eq.height, eq.width), epix[stable], disp[stable].astype(np.float32))
    stats = {f"fisheye_{k}": v for k, v in fish.stats.items()}
    return DenseGt(range_img, disp_img, int((~stable).sum()), len(pts_cam0), stats)


def free_space_filter(pts_world: F64, origins_world: F64, sweep_id: I64, params: DenseParams) -> Bool:
    """Keep mask: points no other sweep saw through (a mover's earlier positions are cleared).

    Each sweep's points, seen from their LiDAR's origin (`origins_world`, one
    row per sweep), give the farthest return per `free_cell_deg` cell of
    direction. A point of another sweep whose direction from that origin falls
    in a cell, and which lies nearer than every return of that cell by more
    than `free_margin_m` + 3 % of its range, sat where that sweep saw empty
    space: it is removed. Cells use the nearest return, so the test clears a
    point only where the whole cell was seen beyond it (edges stay).
    """
    keep = np.ones(len(pts_world), bool)
    cells_per_rad = 1.0 / np.radians(params.free_cell_deg)
    n_az = int(np.ceil(2 * np.pi * cells_per_rad))
    n_el = int(np.ceil(np.pi * cells_per_rad))
    for s in np.unique(sweep_id):
        own = sweep_id == s
        d = pts_world[own] - origins_world[s]
        nearest = _nearest_per_cell(d, cells_per_rad, n_az, n_el)
        other = np.flatnonzero(~own & keep)
        q = pts_world[other] - origins_world[s]
        cell, rng = _cells(q, cells_per_rad, n_az, n_el)
        seen = nearest[cell]
        cleared = np.isfinite(seen) & (seen > rng + params.free_margin_m + 0.03 * rng)
        keep[other[cleared]] = False
    return keep


def _cells(d: F64, cells_per_rad: float, n_az: int, n_el: int) -> tuple[I64, F64]:
    rng = np.sqrt(np.einsum("ij,ij->i", d, d))
    az = np.arctan2(d[:, 1], d[:, 0]) + np.pi
    el = np.arccos(np.clip(d[:, 2] / np.maximum(rng, 1e-12), -1.0, 1.0))
    ia = np.minimum((az * cells_per_rad).astype(np.int64), n_az - 1)
    ie = np.minimum((el * cells_per_rad).astype(np.int64), n_el - 1)
    return ie * n_az + ia, rng


def _nearest_per_cell(d: F64, cells_per_rad: float, n_az: int, n_el: int) -> F64:
    cell, rng = _cells(d, cells_per_rad, n_az, n_el)
    out = np.full(n_az * n_el, np.inf)
    np.minimum.at(out, cell, rng)
    out[np.isinf(out)] = np.nan
    return out
