"""Dense GT of one sample: every point of a wide window placed by the recording's trajectory, movers
removed by free space, rendered; a frame in a trajectory gap gets sparse GT (`--gt auto`) or is skipped.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ingest.dataset.meta import GtMeta, MotionMeta, PointMeta, SampleMeta
from ingest.rows import rows
from ingest.runtime.background import Background
from ingest.train.gt.block_planes import cleared_for
from ingest.train.gt.dense import dense_ground_truth, free_space_filter, free_space_settings, may_matter
from ingest.train.run.sample_job import SampleJob, SampleResult
from ingest.train.run.sample_parts import (
    Equirects,
    alignment_fields,
    finish_sample,
    free_space_slices,
    plane_scatter_field,
    points_by_lidar,
    range_ratio_field,
    silent_lidars,
    trajectory_twist,
)
from ingest.train.run.sample_sparse import process_sparse
from ingest.train.sync import IMU_MARGIN_NS
from ingest.train.trajectory.clouds import REFERENCE_RANGE_M
from ingest.train.trajectory.planes import Normals

GAP_REASON = "frame in a trajectory gap (LiDAR points missing around it)"
GAP_FALLBACK = "auto: frame in a trajectory gap, sparse GT"
"""The decision in the meta of a frame that `--gt auto` gave sparse GT inside a dense run."""


def sparse_window(job: SampleJob) -> SampleJob:
    """`job` as a sparse run streams it: the points within +-`SampleParams.window_ns` of the frame, the
    gyro readings `IMU_MARGIN_NS` beyond and the thin LiDARs over that window, with no trajectory. A
    dense job holds a wider window."""
    tc, w = job.exposure_ns, job.params.window_ns
    imu = None if job.imu is None else job.imu.within(tc - w - IMU_MARGIN_NS, tc + w + IMU_MARGIN_NS)
    return replace(
        job,
        lidars=tuple(lp.within(tc - w, tc + w) for lp in job.lidars),
        imu=imu,
        params=replace(job.params, method="sparse", decision=GAP_FALLBACK, gap_fallback=False),
        trajectory=None,
        thin_lidars=job.thin_lidars_sparse,
    )


def process_dense(job: SampleJob, images: Background[Equirects], start_ms: float) -> SampleResult:
    """Dense GT: every point of the window placed by the trajectory, movers removed, rendered."""
    ms: dict[str, float] = {}
    t0 = time.perf_counter()
    geo, prm, traj = job.geometry, job.params, job.trajectory
    if traj is None:
        return SampleResult(job.sid, False, "dense GT without a trajectory", None, {})
    tc = job.exposure_ns
    if not traj.covers(np.array([tc]))[0]:
        return SampleResult(job.sid, False, "outside the trajectory", None, {})
    span = traj.measured_span(tc)
    if span is None:  # the frame's own pose is a prediction across a LiDAR gap
        return _in_gap(job, images, start_ms)
    cloud = points_by_lidar(job)
    stamps = cloud.stamps_ns
    covered = (stamps >= span[0]) & (stamps <= span[1])  # no point placed across a gap
    if not covered.any():
        return SampleResult(job.sid, False, "outside the trajectory", None, {})
    cloud = cloud.where(covered)
    stamps = cloud.stamps_ns
    turn_rad, shift_m = traj.motion_from(tc, int(stamps.min()), int(stamps.max()))
    placed = traj.to_frame(cloud.pts, stamps, tc)
    normals = None
    if cloud.normal_world is not None:  # the stream pass's block planes, turned into cam0 at the frame time
        R_world_cam0, _ = traj.pose(np.array([tc]))
        normal = cloud.normal_world @ R_world_cam0[0]
        planar = np.isfinite(normal[:, 0])
        normals = Normals(np.where(planar[:, None], normal, 0.0), planar)
    moving = np.zeros((0, 3))
    if prm.dense.free_space:
        test = may_matter(geo.rig.upper.model, placed, prm.dense)
        if cloud.clear_bits is not None:  # the stream pass's blocks were tested: look the sample's slices up
            fs, block_ns = free_space_settings(prm.dense), prm.dense.plane_block_ns
            keep = ~(test & cleared_for(cloud.clear_bits, stamps, tc, fs, block_ns))
        else:
            slicing = (prm.dense.free_slice_ns, prm.dense.free_reference_ns)
            slice_id, refs, ray_origin = free_space_slices(job, traj, stamps, cloud.lidar, *slicing)
            normal = None if normals is None else np.where(normals.planar[:, None], normals.normal, np.nan)
            keep = free_space_filter(
                placed, slice_id, refs, prm.dense, test, ray_origin, normal, max(len(job.lidars), 1)
            )
        moving, placed, cloud = rows(placed, ~keep), rows(placed, keep), cloud.where(keep)
        normals = None if normals is None else Normals(rows(normals.normal, keep), normals.planar[keep])
    t1 = time.perf_counter()
    ms["clouds"] = (t1 - t0) * 1e3
    rect = geo.rect
    dense = dense_ground_truth(
        geo.rig.upper.model, geo.equirect, rect.R_cam0_rect, rect.baseline_m, placed, prm.dense, moving,
        normals,
    )  # fmt: skip
    ms["ground_truth"] = (time.perf_counter() - t1) * 1e3
    alignment = alignment_fields(job, placed, cloud, ms)
    in_window = (traj.stamps_ns >= tc - prm.dense.window_ns) & (traj.stamps_ns <= tc + prm.dense.window_ns)
    residual = traj.residual_m[in_window]
    residual = residual[np.isfinite(residual)]
    meta = SampleMeta(
        **job.timing(), source_bag=job.source, lidar_skew_ms=cloud.skew_ms, **alignment,
        twist_cam0=trajectory_twist(traj, tc),
        motion=MotionMeta(
            applied=True, source="trajectory", max_rotation_deg=float(np.degrees(turn_rad)),
            speed_mps=traj.speed_mps(tc), velocity_cam0_mps=None,
            predicted_motion_px=(turn_rad + shift_m / REFERENCE_RANGE_M) * geo.px_per_rad,
        ),
        points=PointMeta(
            total=cloud.counts.total, zero=cloud.counts.zero, non_finite=cloud.counts.non_finite,
            too_close=cloud.counts.too_close, noise_tag=cloud.counts.noise_tag, kept=int(covered.sum()),
            out_of_view=0, occluded=0,
            silent_lidars=silent_lidars(job), off_trajectory=int(len(covered) - covered.sum()),
            range_ratio=range_ratio_field(job, placed, cloud),
            plane_scatter=plane_scatter_field(job, placed, cloud),
        ),
        gt=GtMeta(
            depth_pixels=dense.range_img.count, disp_pixels=dense.disp_img.count,
            disp_unstable=dense.unstable, density=dense.range_img.count / geo.fisheye_valid_px,
            method="dense", window_ms=prm.dense.window_ns / 1e6, decision=prm.decision,
            accumulated_points=len(placed), removed_moving=len(moving),
            trajectory_residual_mm=float(residual.max() * 1e3) if len(residual) else None,
        ),
    )  # fmt: skip
    return finish_sample(job, images, start_ms, ms, (dense.range_img, dense.disp_img), meta)


def _in_gap(job: SampleJob, images: Background[Equirects], start_ms: float) -> SampleResult:
    """A dense frame in a trajectory gap: sparse GT under `SampleParams.gap_fallback`, else skipped."""
    if not job.params.gap_fallback:
        return SampleResult(job.sid, False, GAP_REASON, None, {})
    sparse = sparse_window(job)
    if not any(len(lp.stamps_ns) for lp in sparse.lidars):  # a sparse run does not plan it either
        return SampleResult(job.sid, False, GAP_REASON, None, {})
    return process_sparse(sparse, images, start_ms)
