"""Dense ground truth: every sweep of a window, placed with the trajectory, rendered like a laser scan.

The points of all sweeps within +-`window_ns` of the frame time are moved
into cam0 at the frame time with the recording's trajectory
(`ingest.train.trajectory.odometry.RigTrajectory.to_frame`), then rendered with the
benchmark renderer's visibility machinery (`ingest.raster.view.render_view`:
footprint splats, a z-buffer on range, the two-sided occlusion test, same-
surface averaging and values moved onto pixel-centre rays). Accumulated
points the camera cannot see never become ground truth: they lose the
z-buffer or the occlusion test; GT within `occlusion_margin_rad` behind a
nearer point is dropped (`behind_near`: background the LiDARs saw past a
pole or a tree from their other positions over the window, where the
foreground's own points are too sparse to close its silhouette). A surface
pixel gets a value only from a point inside it or a planar fill from its
neighbours' points (never the raw splat range: `RenderParams.raw_fallback`
off).

Depth (fisheye range) and disparity (cam0's rectified equirect, DESIGN.md's
formula and stability mask) come from the same points: the equirect is not
rendered a second time. It shares cam0's centre, so it sees what cam0 sees;
each equirect ray takes the least-squares plane around its nearest fisheye
GT pixel and meets it (`rect_ranges`). That is exact on planes, as the
snapped values are, and costs about 80 ms at full resolution against about
450 ms for a second render of the 3.4 M-pixel window.

Moving objects: a point is kept unless the rays of two of the window's
slice times saw through it, both before the first or after the last slice
time that hit its spot (`ingest.train.gt.free_space`): a mover's earlier
positions are free space once it has left, so its stale points are removed
and counted, and GT within a margin sized from each mover's width around
them is dropped (`mover_margins`, `near_movers`). The ingest tests each block of
points once for every sample (`ingest.train.gt.block_planes`); without those
bits a sample runs the test itself (`free_space_filter`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from calibration.camera import CameraModel
from calibration.spherical import Equirectangular
from calibration.stereo import disparity_and_stability
from calibration.types import F32, F64, I64, Bool
from ingest.dataset.sparse import SparseImage
from ingest.raster.edges import STEP_ABS_M, STEP_REL, edge_band
from ingest.raster.kernels import nearest_range, snap_planar
from ingest.raster.lod import point_index
from ingest.raster.params import RenderParams
from ingest.raster.scan import Scan
from ingest.raster.view import Rendering, pixel_rays, render_view
from ingest.raster.z_order import z_order
from ingest.rows import rows
from ingest.train.gt.block_planes import FreeSpaceSettings
from ingest.train.gt.dense_rect import ResampleParams, cam0_window, rect_lookup, rect_ranges
from ingest.train.gt.free_space import RayTest
from ingest.train.gt.free_space import free_space_filter as free_space_mask
from ingest.train.gt.groundtruth import px_per_rad
from ingest.train.trajectory.planes import Normals, plane_normals

VIEW_MARGIN_PX = 16  # dense GT draws the points this near cam0's image too (they may occlude rays inside it)


@dataclass(frozen=True)
class DenseParams:
    """Dense-GT settings (metres, nanoseconds, degrees)."""

    window_ns: int = 500_000_000  # +- around the frame time
    render: RenderParams = field(
        default_factory=lambda: RenderParams(
            points_per_px=None,
            frustum_culling=False,
            raw_fallback=False,
            fill_passes=0,
            fit_gradient=False,
            colour=False,
        )
    )
    plane_neighbours: int = 10
    plane_max_flatness: float = 0.02
    plane_block_ns: int = 1_000_000_000  # the ingest fits planes once per point, among this long a block
    plane_min_cos: float = 0.2
    surfel_px: int = 1  # each planar point also gives values on the rays of pixels this close
    outline_px: int = 7  # ... inside the points' outline: gaps up to this wide closed
    front_px: int = 11  # ... and no square this wide around it holds only points a range step behind the
    # value (`front_range`): wider than one surface's gaps between points (7 dropped 1.6x the good GT: ground)
    edge_px: int = 1  # GT pixels this close to a range step or to empty sky are dropped
    occlusion_margin_rad: float = 0.01  # ... and those 0.57 deg from a nearer point (`behind_near`)
    free_space: bool = True  # remove points the frame's own sweeps saw through (movers)
    free_cell_deg: float = 1.0  # angular cell of the free-space test (around each LiDAR)
    mover_margin_rad: float = (
        0.035  # GT this close (2 deg) to a removed point's direction is dropped, at most:
    )
    mover_margin_rel: float = 0.25  # ... this fraction of its mover's angular width (`mover_margins`),
    mover_margin_min_rad: float = 0.005  # ... at least this
    mover_link_m: float = 0.5  # removed points this close belong to one mover
    free_voxel_m: float = 0.05  # points are tested a voxel at a time
    free_slice_ns: int = 50_000_000  # one LiDAR's points over this long share one origin
    free_reference_ns: int = 0  # only slices this near the frame time test the others (0: every slice)
    free_margin_m: float = 0.1  # a ray must pass a point by this much (plus 3 % of range) to clear it
    free_pass_m: float = 0.03  # ... and pass within this of it, or within its beam's footprint:
    free_footprint_rad: float = 0.0035  # ... this x range (the Mid-360's 0.2 deg divergence)
    free_min_cos: float = 0.1  # ... meeting its plane no more grazing than this (cosine to the normal)
    free_min_slices: int = 2  # a point is removed once this many slice times saw through it
    resample_flat_m: float = 0.01  # cam0 GT pixels giving an equirect ray its plane must lie on it
    resample_flat_rel: float = 0.01  # ... within this much plus this fraction of the range (the render's tau)
    resample_max_change: float = 0.05  # ... and the plane may move the range by at most this fraction
    stability_max_rel_error: float = 0.5
    stability_disp_error_px: float = 0.5


@dataclass(frozen=True)
class DenseGt:
    """One sample's dense GT."""

    range_img: SparseImage  # fisheye range (m) along pixel rays
    disp_img: SparseImage  # equirect disparity (px of the full sphere)
    unstable: int  # equirect pixels with range but failing the stability mask


def snap_to_pixel_rays(
    model: CameraModel, pts: F64, normals: Normals, radius_px: int, min_cos: float, close_px: int = 7,
    front_px: int = 11,
) -> F64:  # fmt: skip
    """Points moved onto pixel-centre rays along their own local planes (all in the model's frame).

    Each point with a planar neighbourhood gives one point on the ray of every
    pixel centre within `radius_px` of its projection (the ray meets the
    point's plane there), as long as that spot lies within the point's own
    neighbourhood in the image (a surfel of `radius_px` pixels) and the pixel
    holds a point or lies in a gap between points that a `close_px` square
    closes (so a surfel never reaches past the outline of the points, into
    the sky beside a silhouette), and no `front_px` square around the pixel
    holds only points behind the value by more than a range step (5 cm /
    3 %, `ingest.raster.edges`'s): so a surfel never reaches past the
    outline of the points at its own range or nearer either, onto the
    background beside a pole's or a trunk's silhouette (`front_range`). Rays grazing
    the plane (|n . ray| < `min_cos`) give nothing; non-planar points, and
    planar ones whose own ray grazes their plane, stay as they are (a
    surface seen edge-on still holds its pixels: a nearer surface's surfels
    do not spread over its silhouette onto them, where the edge band then
    drops them). Values on pixel-centre rays need no range gradient in the
    renderer: they are exact on planes.
    """
    uv, ok = model.project(pts)
    ok &= np.isfinite(uv).all(axis=1)
    pix = np.floor(np.nan_to_num(uv) + 0.5).astype(np.int64)
    ok &= (pix[:, 0] >= 0) & (pix[:, 0] < model.width) & (pix[:, 1] >= 0) & (pix[:, 1] < model.height)
    # pixels a surfel may fill: those holding a point, and the gaps closed between them (never beyond
    # the outline of the points, so a silhouette against the sky does not grow)
    occupied = np.zeros((model.height, model.width), np.uint8)
    occupied[pix[ok, 1], pix[ok, 0]] = 1
    reach = 2 * radius_px + 1
    near = cv2.dilate(occupied, np.ones((reach, reach), np.uint8))
    closed = cv2.morphologyEx(occupied, cv2.MORPH_CLOSE, np.ones((close_px, close_px), np.uint8))
    range_ok = np.linalg.norm(pts[ok], axis=1).astype(np.float32)
    nearest_m = nearest_range(pix[ok, 1], pix[ok, 0], range_ok, model.height, model.width)
    front_m = np.where((closed > 0) & (near > 0), front_range(nearest_m, front_px), np.float32(np.inf))
    # a plane seen edge-on stays as its points: snapped it would give no value and leave its pixels
    # empty, for a nearer surface's surfels to spread over its silhouette into
    range_m = np.maximum(np.linalg.norm(pts, axis=1), 1e-12)
    facing = np.abs(np.einsum("ij,ij->i", normals.normal, pts)) >= min_cos * range_m
    snap = ok & normals.planar & facing
    idx = np.flatnonzero(snap)
    rays, ray_ok = pixel_rays(model)
    snapped = snap_planar(
        rows(pts, idx), rows(normals.normal, idx), pix[:, 0][idx], pix[:, 1][idx], front_m, rays, ray_ok,
        radius_px, min_cos, STEP_ABS_M, STEP_REL,
    )  # fmt: skip
    return np.concatenate([rows(pts, ~snap), snapped])


def front_range(nearest_m: F32, size_px: int) -> F32:
    """(H, W) float32: per pixel, the farthest of the nearest ranges of the `size_px` squares around it
    that hold a point (-inf where none does).

    `nearest_m` is the nearest point's range per pixel (inf: no point). A
    value at the pixel at most a range step in front of the result has, in
    every square around the pixel that holds points, one within a range step
    of its own range or nearer: the pixel lies inside the outline of the
    points at the value's range or nearer (their closing by these squares;
    a square without points says nothing). A value farther in front has a
    square beside it that holds only farther points: background seen past
    the surface's silhouette, not the surface. The
    squares are wider than the gaps between one surface's points (about
    one point per ten pixels at 1920x1200), so the farther points that the
    LiDARs saw through gaps of a nearer surface rarely fill one alone.
    """
    square = np.ones((size_px, size_px), np.uint8)
    nearest_in_square = cv2.erode(nearest_m, square, borderType=cv2.BORDER_REPLICATE)
    nearest_in_square[np.isinf(nearest_in_square)] = -np.inf  # a square without points says nothing
    front = cv2.dilate(nearest_in_square, square, borderType=cv2.BORDER_REPLICATE)
    out: F32 = front.astype(np.float32, copy=False)
    return out


def render_points(model: CameraModel, pts_cam: F64, T_world_cam: F64, params: RenderParams) -> Rendering:
    """Render points given in a frame "world" (here: cam0 at the frame time) into `model` at `T_world_cam`."""
    xyz = np.ascontiguousarray(pts_cam, np.float32)
    scan = Scan("accumulated", np.eye(4), xyz, np.zeros((len(xyz), 3), np.uint8))
    return render_view([point_index(scan)], model, T_world_cam, params)


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


def mover_margins(moving_pts: F64, params: DenseParams) -> F64:
    """Per removed point (N, 3), the angle (rad) around it whose GT `near_movers` drops.

    Removed points within `mover_link_m` of each other (a chain of them) are
    one mover; its extent is its width, twice the spread of its points
    across their longest axis (the second principal axis; at most their
    largest distance from their centre), seen from the camera at the
    centre's range. A point's margin is `mover_margin_rel` x its mover's
    angular extent, within `mover_margin_min_rad`..`mover_margin_rad`: a
    person or a car that left a trail of removed points gets the full
    margin; a few points cleared beside a static edge, or a row of them
    along a cable, only the least (by its length alone a 3 m cable got 2
    degrees of GT dropped around each point).
    """
    if len(moving_pts) == 0:
        return np.zeros(0)
    cell = params.mover_link_m / 2
    keys = np.floor(moving_pts / cell).astype(np.int64)
    cells, voxel = np.unique(keys, axis=0, return_inverse=True)
    voxel = voxel.reshape(-1)
    pairs = cKDTree(cells * cell).query_pairs(params.mover_link_m, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(cells), len(cells)))
    _, label = connected_components(graph, directed=False)
    mover = label[voxel]
    n = int(mover.max()) + 1
    count = np.bincount(mover, minlength=n).astype(np.float64)
    centre = np.stack([np.bincount(mover, moving_pts[:, k], n) for k in range(3)], 1) / count[:, None]
    off = moving_pts - centre[mover]
    cov = (
        np.stack(
            [np.bincount(mover, off[:, a] * off[:, b], n) for a in range(3) for b in range(3)], 1
        ).reshape(n, 3, 3)
        / count[:, None, None]
    )
    width = 2.0 * np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[:, 1], 0.0))  # across its longest axis
    extent = np.zeros(n)
    np.maximum.at(extent, mover, np.linalg.norm(off, axis=1))
    extent = np.minimum(extent, width)
    angle = extent / np.maximum(np.linalg.norm(centre, axis=1), 1e-9)
    margin = np.clip(params.mover_margin_rel * angle, params.mover_margin_min_rad, params.mover_margin_rad)
    out: F64 = margin[mover]
    return out


def near_movers(model: CameraModel, moving_pts: F64, radius_rad: F64 | float) -> Bool:
    """(H, W) pixels within `radius_rad` (per point, or one for all) of view of any point the
    free-space test removed.

    A removed point is a mover's earlier (or later) position; where the mover
    is at the frame time the LiDAR may not have looked (below its field of
    view, say), and the background accumulated there would show through it.
    Ground truth near a mover's path is therefore dropped.
    """
    mask = np.zeros((model.height, model.width), bool)
    radius = np.broadcast_to(np.asarray(radius_rad, np.float64), (len(moving_pts),))
    if len(moving_pts) == 0:
        return mask
    uv, ok = model.project(moving_pts)
    pix = np.floor(np.nan_to_num(uv) + 0.5).astype(np.int64)
    inside = ok & (pix[:, 0] >= 0) & (pix[:, 0] < model.width) & (pix[:, 1] >= 0) & (pix[:, 1] < model.height)
    radius_px = np.where(radius > 0, np.maximum(1, np.round(radius * px_per_rad(model))), 0).astype(np.int64)
    for r in np.unique(radius_px[inside & (radius_px > 0)]):
        sel = inside & (radius_px == r)
        # a disc of r px around every such pixel, within their bounding box grown by r: a 5x5-mask distance
        # transform (within 1 % of the pixels of a dilation by a disc of that radius, at a third of its cost)
        c0, r0 = max(int(pix[sel, 0].min()) - r, 0), max(int(pix[sel, 1].min()) - r, 0)
        c1, r1 = (
            min(int(pix[sel, 0].max()) + r + 1, model.width),
            min(int(pix[sel, 1].max()) + r + 1, model.height),
        )
        seed = np.ones((r1 - r0, c1 - c0), np.uint8)
        seed[pix[sel, 1] - r0, pix[sel, 0] - c0] = 0
        dist = cv2.distanceTransform(seed, cv2.DIST_L2, cv2.DIST_MASK_5)
        mask[r0:r1, c0:c1] |= dist <= r
    return mask


def _view_gt(
    model: CameraModel, pts: F64, normals: Normals, moving: F64, params: DenseParams
) -> tuple[Rendering, I64]:
    """Render one view from points in its frame; the flat pixels whose value is ground truth."""
    snapped = snap_to_pixel_rays(
        model, pts, normals, params.surfel_px, params.plane_min_cos, params.outline_px, params.front_px
    )
    rend = render_points(model, snapped, np.eye(4), params.render)
    keep = away_from_edges(rend, params.edge_px) & ~near_movers(
        model, moving, mover_margins(moving, params)
    ).reshape(-1)
    radius_px = round(params.occlusion_margin_rad * px_per_rad(model))
    keep &= ~behind_near(model, pts, rend.range_m, radius_px).reshape(-1)
    return rend, np.flatnonzero(keep)


def behind_near(model: CameraModel, pts: F64, range_m: F32, radius_px: int) -> Bool:
    """(H, W) pixels whose range lies behind a point within `radius_px` of them by more than a range step.

    `pts` are the window's points in the model's frame, `range_m` the
    rendered ranges (0: none). A step is 5 cm or 3 % of the pixel's range
    (`ingest.raster.edges.edge_band`'s). The window's points were seen from
    the LiDARs' positions over the window, not from the camera: past a thin
    or narrow foreground (a pole, a tree, a cable) they saw background that
    the camera at the frame time sees behind the foreground, where the
    foreground's own points are too sparse (about one per ten pixels at
    1920x1200) for the renderer's two-sided leak test to close its
    silhouette. Such background GT is dropped.
    """
    h, w = model.height, model.width
    out = np.zeros((h, w), bool)
    if radius_px <= 0 or len(pts) == 0:
        return out
    uv, ok = model.project(pts)
    pix = np.floor(np.nan_to_num(uv) + 0.5).astype(np.int64)
    ok &= (pix[:, 0] >= 0) & (pix[:, 0] < w) & (pix[:, 1] >= 0) & (pix[:, 1] < h)
    nearest = nearest_range(pix[ok, 1], pix[ok, 0], np.linalg.norm(pts[ok], axis=1).astype(np.float32), h, w)
    d = np.arange(-radius_px, radius_px + 1)
    disc = (d[:, None] ** 2 + d[None, :] ** 2 <= radius_px**2).astype(np.uint8)
    near = cv2.erode(nearest, disc)  # the nearest point within the disc around each pixel
    valid = range_m > 0
    out[valid] = near[valid] < range_m[valid] - np.maximum(STEP_ABS_M, STEP_REL * range_m[valid])
    return out


def dense_ground_truth(
    model: CameraModel,
    eq: Equirectangular,
    R_cam0_rect: F64,
    baseline_m: float,
    pts_cam0: F64,
    params: DenseParams,
    moving_cam0: F64 | None = None,
    normals: Normals | None = None,
) -> DenseGt:
    """Fisheye range and equirect disparity of points already placed in cam0 at the frame time.

    `moving_cam0` are the points the free-space test removed (see `near_movers`).
    `normals` are the points' local planes in cam0 (the ingest's block planes,
    `ingest.train.gt.block_planes`); without them each point's plane is fitted
    to its `plane_neighbours` nearest neighbours among `pts_cam0`.
    Only what cam0 sees is rendered: points outside its view (plus a margin
    of `VIEW_MARGIN_PX`) cannot occlude rays inside it. The equirect's ranges
    come from cam0's GT over the window of the sphere cam0 covers
    (`cam0_window`, `rect_ranges`), as the sparse GT's disparity comes from
    cam0's visible points too.
    """
    moving = np.zeros((0, 3)) if moving_cam0 is None else moving_cam0
    near = np.flatnonzero(near_view(model, pts_cam0, VIEW_MARGIN_PX))
    if normals is None:
        near = near[z_order(rows(pts_cam0, near))]  # neighbours in memory: the k-NN runs twice as fast
    pts_cam0 = rows(pts_cam0, near)
    if len(pts_cam0) == 0:
        nothing = np.zeros(0, np.int64), np.zeros(0, np.float32)
        return DenseGt(
            SparseImage((model.height, model.width), *nothing),
            SparseImage((eq.height, eq.width), *nothing),
            0,
        )
    if normals is None:
        normals = plane_normals(pts_cam0, params.plane_neighbours, params.plane_max_flatness)
    else:
        normals = Normals(rows(normals.normal, near), normals.planar[near])
    fish, pix = _view_gt(model, pts_cam0, normals, moving, params)
    range_img = SparseImage(fish.range_m.shape, pix, fish.range_m.reshape(-1)[pix])
    win = cam0_window(model, eq, R_cam0_rect)
    resample = ResampleParams(
        params.resample_flat_m, params.resample_flat_rel, params.resample_max_change, params.plane_min_cos
    )
    r_win = rect_ranges(model, win, R_cam0_rect, range_img, resample)
    wpix = np.flatnonzero(r_win > 0)
    r = r_win[wpix].astype(np.float64)
    row, col = np.divmod(wpix, win.width)
    row += win.row_offset - eq.row_offset
    col += win.col_offset - eq.col_offset
    inside = (row >= 0) & (row < eq.height) & (col >= 0) & (col < eq.width)
    row, col, r = row[inside], col[inside], r[inside]
    epix = row * eq.width + col
    theta = eq.theta_of_row(row)  # latitude from up: the rectified equirect's poles lie on its y axis
    disp, stable = disparity_and_stability(
        r, theta, baseline_m, eq.height_full, params.stability_max_rel_error, params.stability_disp_error_px
    )
    disp_img = SparseImage((eq.height, eq.width), epix[stable], disp[stable].astype(np.float32))
    return DenseGt(range_img, disp_img, int((~stable).sum()))


def may_matter(model: CameraModel, pts: F64, params: DenseParams) -> Bool:
    """Points that can affect the GT: near the view (`VIEW_MARGIN_PX`) or a mover's margin from it.

    The free-space test runs only on these; a point farther out is culled
    before rendering, and a removed one there could not reach the view
    through `near_movers`' margin either.
    """
    mover_px = params.mover_margin_rad * px_per_rad(model)
    return near_view(model, pts, VIEW_MARGIN_PX + mover_px + 1.0)


def near_view(model: CameraModel, pts: F64, margin_px: float) -> Bool:
    """Points projecting into the image or within `margin_px` of its border."""
    uv, ok = model.project(pts)
    with np.errstate(invalid="ignore"):
        ok &= (uv[:, 0] >= -margin_px) & (uv[:, 0] <= model.width - 1 + margin_px)
        ok &= (uv[:, 1] >= -margin_px) & (uv[:, 1] <= model.height - 1 + margin_px)
    return ok


def ray_test(params: DenseParams) -> RayTest:
    """The free-space test's ray rule of `params`."""
    return RayTest(
        params.free_cell_deg, params.free_voxel_m, params.free_margin_m, pass_m=params.free_pass_m,
        footprint_rad=params.free_footprint_rad, min_cos=params.free_min_cos,
    )  # fmt: skip


def free_space_settings(params: DenseParams) -> FreeSpaceSettings:
    """The free-space test of `params` as the stream pass's blocks run it (`ingest.train.gt.block_planes`)."""
    return FreeSpaceSettings(
        params.window_ns, params.free_reference_ns, params.free_slice_ns, ray_test(params),
        params.free_min_slices,
    )  # fmt: skip


def free_space_filter(
    pts: F64,
    slice_id: I64,
    references: list[tuple[int, F64]],
    params: DenseParams,
    test: Bool | None = None,
    ray_origin: F64 | None = None,
    normal: F64 | None = None,
    lidars: int = 1,
) -> Bool:
    """`ingest.train.gt.free_space.free_space_filter` with the dense-GT settings of `params`."""
    return free_space_mask(
        pts, slice_id, references, ray_test(params), test, ray_origin, normal, params.free_min_slices, lidars
    )


def warm_up(
    model: CameraModel, eq: Equirectangular, R_cam0_rect: F64, baseline_m: float, params: DenseParams
) -> None:
    """Build this process's per-camera caches and compile (or load) the dense-GT kernels, on a synthetic room.

    Called in the main process before the worker pool forks
    (`Geometry.warm_dense`), so that every worker inherits cam0's pixel rays
    (about 1 s at 1920x1200), its equirect window with the lookup of where
    each window ray lands in cam0 (`rect_lookup`, about 0.6 s) and the
    compiled kernels, instead of building them in its first sample: the
    first run of a checkout compiles the kernels (tens of seconds, then
    stored in numba's on-disk cache), and one process doing that beats
    every worker doing it at once. The scene: a wall 3 m away with a box
    1.5 m away in front of it, seen by two LiDARs; a few points are movers.
    Only the compiled (numba) renderer is warmed: a GPU backend must not be
    initialised before a fork.
    """
    rays, ok = pixel_rays(model)
    rect_lookup(model, cam0_window(model, eq, R_cam0_rect), R_cam0_rect)
    if params.render.backend != "numba":
        return
    step = max(4, model.width // 160)
    grid = rays.reshape(model.height, model.width, 3)[::step, ::step].reshape(-1, 3).astype(np.float64)
    grid = grid[ok.reshape(model.height, model.width)[::step, ::step].reshape(-1)]
    box = (np.abs(grid[:, 0]) < 0.3 * grid[:, 2]) & (np.abs(grid[:, 1]) < 0.3 * grid[:, 2])
    pts = grid * np.where(box, 1.5, 3.0)[:, None]
    half = len(pts) // 2
    slice_id = np.r_[np.zeros(half, np.int64), np.ones(len(pts) - half, np.int64)]
    references = [(0, np.array([0.0, -0.1, 0.0])), (1, np.array([0.0, 0.1, 0.0]))]
    keep = np.ones(len(pts), bool)
    if params.free_space:  # as `ingest.train.run.sample_dense.process_dense` runs it
        keep = free_space_filter(pts, slice_id, references, params, may_matter(model, pts, params))
    dense_ground_truth(model, eq, R_cam0_rect, baseline_m, pts[keep], params, pts[~keep][:100] * 0.9)
