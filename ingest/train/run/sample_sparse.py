"""Sparse GT of one sample: the frame's own sweeps, motion-compensated to the frame time (gyro rotation,
a constant velocity), splatted into the fisheye and the equirect.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from calibration.types import F64, I64, Bool
from ingest.dataset.meta import GtMeta, MotionMeta, PointMeta, SampleMeta
from ingest.runtime.background import Background
from ingest.train.gt.dense import free_space_filter
from ingest.train.gt.groundtruth import (
    equirect_disparity,
    fisheye_range,
    in_view,
    occlusion_filter,
    splat_to_pixels,
    surface_normals,
)
from ingest.train.run.sample_job import ALIGNED, SampleAlignment, SampleJob, SampleResult
from ingest.train.run.sample_parts import (
    Equirects,
    WindowPoints,
    alignment_fields,
    finish_sample,
    free_space_slices,
    gyro_twist,
    plane_scatter_field,
    points_by_lidar,
    range_ratio_field,
    silent_lidars,
)
from ingest.train.trajectory.clouds import (
    GyroTrack,
    MotionDecision,
    estimate_velocity,
    integrate_gyro,
    motion_decision,
)
from ingest.train.trajectory.planes import Normals
from ingest.train.trajectory.rig_trajectory import RigTrajectory

IMU_SILENT_REASON = "IMU silent over the window (no rotation to compensate with)"
"""A sample whose window holds no reading of the rig's IMU (one that stopped, or a gap in its readings) is
left out: its points would be placed without the rig's turn."""
VELOCITY_SIGMAS = 4.0  # an estimated velocity counts when its norm exceeds this many standard errors


def _compensated(
    job: SampleJob, pts: F64, stamps_ns: I64, gyro: GyroTrack | None
) -> tuple[F64, F64 | None, MotionDecision]:
    """The points (cam0, m) at the frame time when the rig moved enough to matter (`motion_decision`),
    else as measured; the velocity used (m/s in cam0; None: none) and the decision.

    The window's motion is a trajectory (`RigTrajectory.over_window`): the
    gyro's turn, and the job's velocity or one estimated from the turned
    points (used only when significant: a still rig is not "compensated"
    with the fit's noise).
    """
    prm, tc = job.params, job.exposure_ns
    dt_s = (stamps_ns - tc) / 1e9
    turn = gyro if prm.motion != "off" else None
    span = (int(stamps_ns.min()), int(stamps_ns.max())) if len(stamps_ns) else (tc, tc)
    turning = RigTrajectory.over_window(turn, None, tc, span)  # the gyro's turn alone
    velocity, source = job.velocity_cam0_mps, ("imu" if turn is not None else "none")
    if prm.motion != "full":
        velocity = None
    elif velocity is None and prm.estimate_velocity:
        rotated = turning.to_frame(pts, stamps_ns, tc) if turn is not None else pts
        est = estimate_velocity(rotated, dt_s, significance=VELOCITY_SIGMAS)
        if est is not None and np.linalg.norm(est.velocity_cam0_mps) > VELOCITY_SIGMAS * est.weakest_m_s:
            velocity = est.velocity_cam0_mps
    if velocity is not None:
        source += "+velocity"
    angle = turning.motion_from(tc, *span)[0] if turn is not None else 0.0
    motion = motion_decision(dt_s, angle, velocity, job.geometry.px_per_rad, prm.min_motion_px, source=source)
    if motion.applied:  # each point at its own time, in cam0 at the frame time
        pts = RigTrajectory.over_window(turn, velocity, tc, span).to_frame(pts, stamps_ns, tc)
    return pts, velocity, motion


def _not_seen_through(
    job: SampleJob, pts: F64, cloud: WindowPoints, gyro: GyroTrack | None, velocity: F64 | None, moved: bool,
    test: Bool,
) -> Bool:  # fmt: skip
    """Keep mask: the points (cam0 at the frame time) that the window's other slices did not see through
    (`ingest.train.gt.free_space`), tested where `test` (those in the upper camera's view). A rain drop,
    a dust echo the LiDAR did not tag or a mover's earlier place is hit in one slice and passed by the
    rays of the others, which return from the surface behind it; a thin static object is hit throughout
    the window. `moved`: the points were placed by the gyro's turn and `velocity` (`_compensated`), else
    as measured."""
    prm, tc = job.params, job.exposure_ns
    span = (int(cloud.stamps_ns.min()), int(cloud.stamps_ns.max()))
    turn = gyro if moved and prm.motion != "off" else None
    traj = RigTrajectory.over_window(turn, velocity, tc, span)
    slice_id, refs, origin = free_space_slices(
        job, traj, cloud.stamps_ns, cloud.lidar, prm.sparse_free_slice_ns
    )
    return free_space_filter(pts, slice_id, refs, prm.dense, test, origin, None, max(len(job.lidars), 1))


def process_sparse(job: SampleJob, images: Background[Equirects] | None, start_ms: float) -> SampleResult:
    """Sparse GT: the frame's own sweeps, motion-compensated to the frame time; without `images` (the
    warps), the points' alignments only (`SampleParams.alignment_only`)."""
    ms: dict[str, float] = {}
    t0 = time.perf_counter()
    geo, prm = job.geometry, job.params
    cloud = points_by_lidar(job)
    counts, gyro, off_imu = cloud.counts, None, 0
    if job.imu is not None and len(job.imu.stamps_ns) < 2 and prm.motion != "off":
        return SampleResult(job.sid, False, IMU_SILENT_REASON, None, {})
    if job.imu is not None and len(job.imu.stamps_ns) >= 2:
        gyro = integrate_gyro(job.imu.stamps_ns, job.imu.gyro_rad_s, job.imu.R_cam0_imu)
        covered = gyro.covers(cloud.stamps_ns)  # rotations outside the IMU's span are unknown: dropped
        off_imu = int((~covered).sum())  # counted in the meta: the filters' counts add up to the total
        counts = replace(counts, kept=counts.kept - off_imu)
        cloud = cloud.where(covered)
    dt_s = (cloud.stamps_ns - job.exposure_ns) / 1e9
    pts, velocity, motion = _compensated(job, cloud.pts, cloud.stamps_ns, gyro)
    half = prm.window_ns / 2e9
    if motion.applied and not (len(dt_s) and dt_s.min() <= -half and dt_s.max() >= half):
        # a one-sided window (bag start/end, a LiDAR gap) leaves the velocity poorly determined
        return SampleResult(job.sid, False, "moving, LiDAR window one-sided (bag start/end or gap)", None, {})
    t1 = time.perf_counter()
    ms["clouds"] = (t1 - t0) * 1e3
    if images is None:
        fields = alignment_fields(job, pts, cloud, ms)
        twist = gyro_twist(job, velocity if motion.applied else None)
        aligned = SampleAlignment(fields["alignment"], fields["alignment_lower"], twist)
        return SampleResult(job.sid, False, ALIGNED, None, ms, aligned=aligned)
    model = geo.rig.upper.model
    view = in_view(model, pts)
    removed, measured = 0, (pts, cloud)  # the alignments lay every point: as refine's rounds do
    if prm.sparse_free_space and len(pts):
        v_used = velocity if motion.applied else None
        keep = _not_seen_through(job, pts, cloud, gyro, v_used, motion.applied, view[0])
        removed, pts, cloud = int((~keep).sum()), pts[keep], cloud.where(keep)
        view = (view[0][keep], view[1][keep], view[2][keep])
    seen = view[0]
    normals = surface_normals(pts, prm.gt.plane_neighbours, prm.gt.plane_max_flatness, query=seen)
    visible = occlusion_filter(model, pts, prm.gt, view)  # a subset of `seen`
    in_seen = visible[seen]
    kept = Normals(normals.normal[in_seen], normals.planar[in_seen])
    seen_cols_rows = (seen[visible], view[1][visible], view[2][visible])
    splat = splat_to_pixels(model, pts[visible], kept, prm.gt, seen_cols_rows)
    range_img = fisheye_range(model, splat)
    R_rect_cam0 = geo.rect.R_cam0_rect.T
    disp_img, _, unstable = equirect_disparity(
        geo.equirect, R_rect_cam0, pts[visible], kept, geo.rect.baseline_m, prm.gt
    )
    ms["ground_truth"] = (time.perf_counter() - t1) * 1e3
    meta = SampleMeta(
        **job.timing(), source_bag=job.source, lidar_skew_ms=cloud.skew_ms,
        twist_cam0=gyro_twist(job, velocity if motion.applied else None),
        **alignment_fields(job, *measured, ms),
        motion=MotionMeta(
            applied=motion.applied, source=motion.source, max_rotation_deg=motion.max_rotation_deg,
            speed_mps=motion.speed_mps, predicted_motion_px=motion.motion_px,
            velocity_cam0_mps=motion.velocity_cam0_mps,
        ),
        points=PointMeta(
            total=counts.total, zero=counts.zero, non_finite=counts.non_finite, too_close=counts.too_close,
            noise_tag=counts.noise_tag, kept=counts.kept, out_of_view=int(len(seen) - seen.sum()),
            occluded=int(seen.sum() - visible.sum()), silent_lidars=silent_lidars(job), off_imu=off_imu,
            range_ratio=range_ratio_field(job, pts, cloud, view),
            plane_scatter=plane_scatter_field(job, pts, cloud, seen),
        ),
        gt=GtMeta(
            depth_pixels=range_img.count, disp_pixels=disp_img.count, disp_unstable=unstable,
            density=range_img.count / geo.fisheye_valid_px, window_ms=prm.window_ns / 1e6,
            decision=prm.decision, removed_moving=removed,
        ),
    )  # fmt: skip
    return finish_sample(job, images, start_ms, ms, (range_img, disp_img), meta)
