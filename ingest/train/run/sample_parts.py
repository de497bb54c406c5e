"""The stages sparse and dense GT share for one sample: the window's filtered points of every LiDAR in cam0,
their alignments with the images, cam0's twist for the meta, and the sample's files written once the
equirect warps are done.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np

from calibration.types import F64, I64, U64, Bool
from ingest.dataset.identity import frame_digest
from ingest.dataset.layout import SampleFiles, write_sample
from ingest.dataset.meta import AlignmentMeta, SampleMeta
from ingest.dataset.sparse import SparseImage
from ingest.rows import rows
from ingest.runtime.background import Background
from ingest.train.gt.align import MAX_POINTS, ImageLevels, align_points, part_correlations
from ingest.train.gt.groundtruth import in_view
from ingest.train.gt.lidar_agreement import plane_scatter, range_ratios
from ingest.train.gt.stereo_offset import pair_offset
from ingest.train.gt.window_fit import stretch_shares
from ingest.train.run.frame_check import frame_check
from ingest.train.run.sample_job import SampleJob, SampleResult
from ingest.train.trajectory.clouds import FilterCounts, filter_points
from ingest.train.trajectory.rig_trajectory import RigTrajectory


def silent_lidars(job: SampleJob) -> list[str]:
    """The rig's LiDARs that gave no point in the sample's window (a sensor that stopped)."""
    return [lp.name for lp in job.lidars if len(lp.stamps_ns) == 0]


@dataclass(frozen=True)
class WindowPoints:
    """A job's filtered points of every LiDAR, in cam0 at their own times, and what they carry."""

    pts: F64  # (N, 3) m
    stamps_ns: I64
    lidar: I64  # index into `job.lidars`
    counts: FilterCounts
    skew_ms: dict[str, float]  # per LiDAR: the farthest point time from the frame's
    normal_world: F64 | None  # (N, 3), when every LiDAR's points carry them
    clear_bits: U64 | None  # (N, words), when every LiDAR's points carry them
    reflectivity: F64 | None  # (N,), when every LiDAR's points carry it

    def where(self, keep: np.ndarray[Any, Any]) -> WindowPoints:
        """The points `keep` selects with all they carry (the counts and skews stay the window's)."""
        return replace(
            self, pts=rows(self.pts, keep), stamps_ns=self.stamps_ns[keep], lidar=self.lidar[keep],
            normal_world=None if self.normal_world is None else rows(self.normal_world, keep),
            clear_bits=None if self.clear_bits is None else rows(self.clear_bits, keep),
            reflectivity=None if self.reflectivity is None else self.reflectivity[keep],
        )  # fmt: skip


def points_by_lidar(job: SampleJob) -> WindowPoints:
    """Filtered points of every LiDAR in cam0 (at their own times), their stamps, LiDAR, counts and skews,
    with the block fits' normals, free-space bits and reflectivity where every LiDAR has them."""
    pts, stamps, which, total, skew, normals, bits, refl = [], [], [], FilterCounts(), {}, [], [], []
    for i, lp in enumerate(job.lidars):
        keep, counts = filter_points(lp.xyz_m, lp.tag, job.params.min_range_m)
        T = job.geometry.rig.lidar(lp.name).T_cam0_lidar
        xyz = np.asarray(rows(lp.xyz_m, keep), np.float64)
        pts.append(xyz @ T[:3, :3].T + T[:3, 3])
        stamps.append(lp.stamps_ns[keep])
        which.append(np.full(int(keep.sum()), i, np.int64))
        if lp.normal_world is not None:
            normals.append(np.asarray(rows(lp.normal_world, keep), np.float64))
        if lp.clear_bits is not None:
            bits.append(rows(lp.clear_bits, keep))
        if lp.reflectivity is not None:
            refl.append(np.asarray(lp.reflectivity[keep], np.float64))
        total = total + counts
        dt = (stamps[-1] - job.exposure_ns) / 1e6
        skew[lp.name] = float(np.abs(dt).max()) if len(dt) else 0.0
    every = len(job.lidars)
    return WindowPoints(
        np.concatenate(pts), np.concatenate(stamps), np.concatenate(which), total, skew,
        np.concatenate(normals) if len(normals) == every else None,
        np.concatenate(bits) if len(bits) == every else None,
        np.concatenate(refl) if len(refl) == every else None,
    )  # fmt: skip


Equirects = tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]
"""`equirect_up` and `equirect_down_virt` of one sample (the full-sphere equirect's size, each with its
source image's channels: BGR or BGRA)."""


def alignment_fields(
    job: SampleJob, pts_cam0: F64, cloud: WindowPoints, ms: dict[str, float]
) -> dict[str, Any]:
    """The meta's `alignment`, `alignment_lower`, `lower_check`, `window_parts` and `window_fit` of the
    points `pts_cam0` (those of `cloud`, placed in cam0 at the exposure), timed as stage "alignment" in
    `ms`; of an alignment-only job (`calib refine`'s rounds, which combine the alignments alone) the first
    two, the checks of a sample's frames and sweeps left empty."""
    t0 = time.perf_counter()
    checks: dict[str, Any] = {"lower_check": {}, "window_parts": {}, "window_fit": {}}
    if job.geometry.too_coarse_to_align:
        return {"alignment": {}, "alignment_lower": {}, **checks}
    upper = ImageLevels.from_bgr(job.upper_bgr) if cloud.reflectivity is not None else None
    if not job.params.alignment_only:
        checks = {
            "lower_check": _lower_check(job, pts_cam0, _standardised(cloud.reflectivity, cloud.lidar)),
            "window_parts": _window_parts(job, upper, pts_cam0, cloud),
            "window_fit": _window_fit(job, pts_cam0, cloud),
        }
    fields = {
        "alignment": _alignments(job, upper, pts_cam0, cloud.reflectivity, cloud.lidar),
        "alignment_lower": _lower_alignments(job, pts_cam0, cloud.reflectivity, cloud.lidar),
        **checks,
    }
    ms["alignment"] = (time.perf_counter() - t0) * 1e3
    return fields


def _alignments(
    job: SampleJob, upper: ImageLevels | None, pts_cam0: F64, reflectivity: F64 | None, which: I64
) -> dict[str, AlignmentMeta]:
    """Each LiDAR's photometric alignment with the upper image (its `upper` levels), of the points placed
    in cam0 at the exposure (`pts_cam0`, from LiDAR `which`); none without reflectivity."""
    if reflectivity is None or upper is None:
        return {}
    return _aligned(job, upper, job.geometry.rig.upper.model, pts_cam0, reflectivity, which)


def _window_parts(
    job: SampleJob, upper: ImageLevels | None, pts_cam0: F64, cloud: WindowPoints
) -> dict[str, list[float | None]]:
    """Per LiDAR, how each stretch of its window's point times matches the upper image
    (`part_correlations`): a stretch far below the others is a sweep out of place
    (`ingest.train.run.frame_check`); none without reflectivity."""
    if cloud.reflectivity is None or upper is None:
        return {}
    model = job.geometry.rig.upper.model
    out = {}
    for i, lp in enumerate(job.lidars):
        mine = cloud.lidar == i
        pts, refl = rows(pts_cam0, mine), cloud.reflectivity[mine]
        out[lp.name] = part_correlations(model, upper, pts, refl, cloud.stamps_ns[mine])
    return out


def _window_fit(job: SampleJob, pts_cam0: F64, cloud: WindowPoints) -> dict[str, list[float | None]]:
    """Per LiDAR, how each stretch of its window's point times sits among its other stretches' points
    (`stretch_shares`): a stretch far below the others is a sweep out of place
    (`ingest.train.run.frame_check`)."""
    return {
        lp.name: stretch_shares(rows(pts_cam0, cloud.lidar == i), cloud.stamps_ns[cloud.lidar == i])
        for i, lp in enumerate(job.lidars)
    }


def _in_cam1(job: SampleJob, pts_cam0: F64) -> F64:
    """`pts_cam0` moved into cam1 by the camchain's stereo pose."""
    T = job.geometry.rig.lower.T_cam_cam0
    out: F64 = pts_cam0 @ T[:3, :3].T + T[:3, 3]
    return out


def _lower_alignments(
    job: SampleJob, pts_cam0: F64, reflectivity: F64 | None, which: I64
) -> dict[str, AlignmentMeta]:
    """`_alignments` onto the lower image, the points moved into cam1 (`SampleParams.align_lower`; none
    without it); in a run that writes samples, of every `SampleParams.lower_every`-th sample only: the
    stereo pose's check needs a few samples, and each alignment costs as much as the upper one's (about
    110 ms of a 400 ms sample at 960x600)."""
    if reflectivity is None or not job.params.align_lower:
        return {}
    if not job.params.alignment_only and job.sid.isdigit() and int(job.sid) % job.params.lower_every:
        return {}
    levels = ImageLevels.from_bgr(job.lower_bgr)
    return _aligned(job, levels, job.geometry.rig.lower.model, _in_cam1(job, pts_cam0), reflectivity, which)


def _lower_check(job: SampleJob, pts_cam0: F64, reflectivity: F64 | None) -> dict[str, AlignmentMeta]:
    """A quick alignment onto the lower image of every sample (beside `_lower_alignments` of some): every
    LiDAR's points as one cloud, at most `SampleParams.lower_check_points` of them, on the image resized to
    `lower_check_width_px`, about a sixth of the full alignments' cost; keyed by the LiDARs' names joined
    with "+". It finds a lower frame out of place (a degree and more off, where the samples lie within a
    few tenths: `IngestSummary.off_lower`); too coarse for the stereo pose's check."""
    if reflectivity is None or not job.params.align_lower:
        return {}
    image, model = _at_most(job.lower_bgr, job.geometry.rig.lower.model, job.params.lower_check_width_px)
    levels = ImageLevels.from_bgr(image)
    found = align_points(model, levels, _in_cam1(job, pts_cam0), reflectivity, job.params.lower_check_points)
    return {} if found is None else {"+".join(lp.name for lp in job.lidars): found.to_meta()}


def free_space_slices(
    job: SampleJob, traj: RigTrajectory, stamps: I64, which: I64, slice_ns: int, reference_ns: int = 0
) -> tuple[I64, list[tuple[int, F64]], F64]:
    """Slice id per point (LiDAR x `slice_ns`), the frame's own slices with their LiDAR origins (those within
    `reference_ns` of the frame time; 0: all), and each point's ray origin (its LiDAR at the point's time),
    for the free-space test (`ingest.train.gt.free_space`).

    Origins are in cam0 at the frame time, where `traj.to_frame` put the points.
    """
    tc = job.exposure_ns
    k = (stamps - tc) // slice_ns
    n_lidars = max(len(job.lidars), 1)
    slice_id = k * n_lidars + which
    own = slice_id if not reference_ns else slice_id[np.abs(stamps - tc) <= reference_ns]
    origins_lidar = np.array([job.geometry.rig.lidar(lidar.name).T_cam0_lidar[:3, 3] for lidar in job.lidars])
    ray_origin = traj.to_frame(origins_lidar[which], stamps, tc)
    if len(own) == 0:
        return slice_id, [], ray_origin
    # the window spans a few dozen slices: a bincount finds them without sorting every point
    lo = int(own.min())
    sids = lo + np.flatnonzero(np.bincount(own - lo))
    t_mid = tc + (sids // n_lidars) * slice_ns + slice_ns // 2
    origins = traj.to_frame(origins_lidar[sids % n_lidars], t_mid, tc)
    refs = [(int(sid), origin) for sid, origin in zip(sids, origins, strict=True)]
    return slice_id, refs, ray_origin


def _standardised(reflectivity: F64 | None, which: I64) -> F64 | None:
    """Each LiDAR's reflectivity to zero mean and unit spread among its own points, so that the points of
    LiDARs reporting it on other scales (0..255, 0..1) share one gain in an alignment of them all."""
    if reflectivity is None:
        return None
    out = np.zeros(len(reflectivity))
    for k in np.unique(which):
        mine = which == k
        values = reflectivity[mine]
        finite = np.isfinite(values)
        spread = float(np.std(values[finite])) if finite.any() else 0.0
        out[mine] = (values - (float(np.mean(values[finite])) if finite.any() else 0.0)) / (spread or 1.0)
    return out


def _at_most(image: np.ndarray[Any, Any], model: Any, width_px: int) -> tuple[np.ndarray[Any, Any], Any]:
    """`image` and its camera `model` resized to at most `width_px` wide (area-averaged), or as they are."""
    if model.width <= width_px:
        return image, model
    smaller = model.scaled(width_px / model.width)
    return cv2.resize(image, (smaller.width, smaller.height), interpolation=cv2.INTER_AREA), smaller


def _aligned(
    job: SampleJob,
    levels: ImageLevels,
    model: Any,
    pts: F64,
    reflectivity: F64,
    which: I64,
    max_points: int = MAX_POINTS,
) -> dict[str, AlignmentMeta]:
    """Each LiDAR's `align_points` of `pts` (in the camera of `levels` and `model`), of at most
    `max_points` of its points."""
    out = {}
    for i, lp in enumerate(job.lidars):
        mine = which == i
        found = align_points(model, levels, rows(pts, mine), reflectivity[mine], max_points)
        if found is not None:
            out[lp.name] = found.to_meta()
    return out


TWIST_STEP_NS = 5_000_000


def trajectory_twist(traj: RigTrajectory, t_ns: int) -> list[float]:
    """cam0's angular velocity (rad/s) and velocity (m/s), both in cam0, at `t_ns` (central differences
    over +-`TWIST_STEP_NS`)."""
    R, p = traj.pose(np.array([t_ns - TWIST_STEP_NS, t_ns, t_ns + TWIST_STEP_NS], np.int64))
    turn, _ = cv2.Rodrigues(R[0].T @ R[2])
    h_s = 2 * TWIST_STEP_NS / 1e9
    # the turn between the two ends is in the frame at the first; at these rates the difference is 1e-5
    omega = turn.ravel() / h_s
    velocity = R[1].T @ (p[2] - p[0]) / h_s
    return [round(float(v), 6) for v in (*omega, *velocity)]


def gyro_twist(job: SampleJob, velocity_cam0_mps: F64 | None) -> list[float] | None:
    """cam0's angular velocity (rad/s, the gyro's readings within +-`TWIST_STEP_NS` of the exposure,
    averaged, in cam0) and the velocity motion compensation used (m/s, 0 when none); None without
    gyro readings there."""
    if job.imu is None:
        return None
    near = np.abs(job.imu.stamps_ns - job.exposure_ns) <= TWIST_STEP_NS
    if not near.any():
        return None
    omega = job.imu.R_cam0_imu @ job.imu.gyro_rad_s[near].mean(axis=0)
    velocity = np.zeros(3) if velocity_cam0_mps is None else np.asarray(velocity_cam0_mps, np.float64)
    return [round(float(v), 6) for v in (*omega, *velocity)]


def finish_sample(
    job: SampleJob,
    images: Background[Equirects],
    start_ms: float,
    ms: dict[str, float],
    gt: tuple[SparseImage, SparseImage],
    meta: SampleMeta,
) -> SampleResult:
    """Wait for the warps, write the sample's files, and time both."""
    t2 = time.perf_counter()
    up, down = images.result()
    t3 = time.perf_counter()
    ms["images"] = start_ms + (t3 - t2) * 1e3
    meta = replace(
        meta,
        points=replace(meta.points, thin_lidars=list(job.thin_lidars)),
        frames_sha256=frame_digest(job.upper_bgr, job.lower_bgr),
        frame_check=frame_check(job.upper_bgr, job.lower_bgr, job.repeated),
        settings=job.settings,
        stereo_offset=None if (offset := pair_offset(up, down, gt[1])) is None else offset.to_meta(),
        stereo_offset_quadrants=[] if offset is None else offset.quadrants_meta(),
    )
    files = SampleFiles(job.upper_bgr, job.lower_bgr, up, down, gt[1], gt[0], meta)
    drops = write_sample(job.out, job.sid, files, job.params.exr, job.params.png_level)
    ms["write"] = (time.perf_counter() - t3) * 1e3
    helper = {"equirect warps": images.ms} if job.params.overlap_images else {}
    return SampleResult(job.sid, True, "", meta.written(job.sid, drops), ms, helper)


def range_ratio_field(
    job: SampleJob, pts_cam0: F64, cloud: WindowPoints, view: tuple[Bool, F64, F64] | None = None
) -> dict[str, list[float]]:
    """The meta's `points.range_ratio`: per LiDAR after the first, how its ranges agree with the first's
    where cam0 sees a point of both in a pixel (`ingest.train.gt.lidar_agreement.range_ratios`); `view`
    is `in_view` of `pts_cam0` when the caller has it."""
    model = job.geometry.rig.upper.model
    seen, cols, rows_px = in_view(model, pts_cam0) if view is None else view
    names = [lp.name for lp in job.lidars]
    found = range_ratios(pts_cam0, seen, cols, rows_px, cloud.lidar, names, model.width)
    return {name: [round(r, 5), pairs, round(spread, 5)] for name, (r, pairs, spread) in found.items()}


def plane_scatter_field(
    job: SampleJob, pts_cam0: F64, cloud: WindowPoints, seen: Bool | None = None
) -> dict[str, list[float]]:
    """The meta's `points.plane_scatter`: per LiDAR, how far its points in cam0's view scatter about the
    other LiDARs' local planes (`ingest.train.gt.lidar_agreement.plane_scatter`); `seen`: which points
    cam0 sees, when the caller has it."""
    if seen is None:
        seen = in_view(job.geometry.rig.upper.model, pts_cam0)[0]
    names = [lp.name for lp in job.lidars]
    found = plane_scatter(pts_cam0[seen], cloud.lidar[seen], names)
    return {name: [round(sigma_m, 5), n] for name, (sigma_m, n) in found.items()}
