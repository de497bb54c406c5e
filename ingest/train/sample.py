"""The per-sample function: one stereo pair + LiDAR points -> WideDepth files on disk.

`process_sample` is pure apart from writing its own files, takes only
picklable inputs and is what the local process pool or a Dask cluster runs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from calibration.errors import CalibrationError
from calibration.rectify import StereoRectification, rectify_rig
from calibration.rig import Rig
from calibration.spherical import Equirectangular
from calibration.types import F64, I64, U64
from calibration.warp import build_maps, check_height_full, check_source, default_height_full, remap_spans
from ingest.dataset.identity import frame_digest
from ingest.dataset.layout import SampleFiles, write_sample
from ingest.dataset.meta import AlignmentMeta, GtMeta, MotionMeta, PointMeta, SampleMeta
from ingest.dataset.sparse import SparseImage
from ingest.raster.view import pixel_rays
from ingest.rows import rows
from ingest.runtime.background import Background
from ingest.train.align import ImageLevels, align_points
from ingest.train.block_planes import cleared_for
from ingest.train.clouds import (
    REFERENCE_RANGE_M,
    FilterCounts,
    compensate,
    estimate_velocity,
    filter_points,
    integrate_gyro,
)
from ingest.train.dense import (
    DenseParams,
    dense_ground_truth,
    free_space_filter,
    free_space_settings,
    may_matter,
    warm_up,
)
from ingest.train.groundtruth import (
    GtParams,
    equirect_disparity,
    fisheye_range,
    in_view,
    occlusion_filter,
    px_per_rad,
    splat_to_pixels,
    surface_normals,
)
from ingest.train.planes import Normals
from ingest.train.rig_trajectory import RigTrajectory
from ingest.train.sync import IMU_MARGIN_NS

INTERPOLATION = {"linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC, "nearest": cv2.INTER_NEAREST}
VELOCITY_SIGMAS = 4.0  # an estimated velocity counts when its norm exceeds this many standard errors


@dataclass(frozen=True)
class Geometry:
    """Rig-derived geometry shared by every sample (built once)."""

    rig: Rig
    rect: StereoRectification
    equirect: Equirectangular  # full sphere in cam0's rectified frame
    px_per_rad: float
    fisheye_valid_px: int  # pixels of cam0 with a valid ray: the denominator of GT density

    @classmethod
    def from_rig(cls, rig: Rig, height_full: int | None = None) -> Geometry:
        model = rig.upper.model
        h = check_height_full(default_height_full(model) if height_full is None else height_full)
        valid = int(pixel_rays(model)[1].sum())  # cached: dense GT's warm-up and renderer reuse the rays
        if valid == 0:  # GT density's denominator
            where = rig.source or rig.name
            raise CalibrationError(
                f"{where}: camera {rig.upper.name} maps none of its {model.width}x{model.height} pixels to a "
                "ray; expected a camera model that sees"
            )
        return cls(rig, rectify_rig(rig), Equirectangular(h), px_per_rad(model), valid)

    def warm_maps(self) -> None:
        """Load or build both cameras' equirect remap maps into calibration.warp's cache now.

        Called in the main process before the worker pool forks, the maps
        are loaded once (from the on-disk cache, `calibration.warp.map_cache_dir`;
        built and stored there the first time, ~3.5 s of CPU for the reference
        rig, the two maps in two threads) and shared copy-on-write by every
        worker instead of being loaded or built in each one's first sample.
        """
        from concurrent.futures import ThreadPoolExecutor

        jobs = [(self.rig.upper.model, self.rect.R_cam0_rect), (self.rig.lower.model, self.rect.R_cam1_rect)]
        with ThreadPoolExecutor(2) as pool:  # numpy releases the GIL in the array work
            list(pool.map(lambda job: build_maps(job[0], self.equirect, job[1]), jobs))

    def warm_dense(self, params: DenseParams) -> None:
        """Dense GT's per-camera caches and compiled kernels, built now (`ingest.train.dense.warm_up`)."""
        warm_up(self.rig.upper.model, self.equirect, self.rect.R_cam0_rect, self.rect.baseline_m, params)


@dataclass(frozen=True)
class LidarPoints:
    """Raw points of one LiDAR around a frame time: sensor frame (m), absolute stamps, Livox tags."""

    name: str
    xyz_m: np.ndarray[Any, Any]
    stamps_ns: I64
    tag: np.ndarray[Any, Any] | None
    normal_world: np.ndarray[Any, Any] | None = None  # dense GT: (N, 3) float16, NaN: none (`block_planes`)
    clear_bits: U64 | None = None  # dense GT: (N, words), the slices that saw through each (`block_planes`)
    reflectivity: np.ndarray[Any, Any] | None = None  # (N,) as the driver stored it (`ingest.train.align`)

    def within(self, t0_ns: int, t1_ns: int) -> LidarPoints:
        """The points stamped in [t0_ns, t1_ns], in their order."""
        keep = (self.stamps_ns >= t0_ns) & (self.stamps_ns <= t1_ns)
        tag = None if self.tag is None else self.tag[keep]
        normal = None if self.normal_world is None else rows(self.normal_world, keep)
        bits = None if self.clear_bits is None else rows(self.clear_bits, keep)
        refl = None if self.reflectivity is None else self.reflectivity[keep]
        return LidarPoints(self.name, rows(self.xyz_m, keep), self.stamps_ns[keep], tag, normal, bits, refl)


@dataclass(frozen=True)
class ImuWindow:
    """Gyro readings (rad/s, IMU frame) around a frame time, and the IMU's pose in cam0."""

    stamps_ns: I64
    gyro_rad_s: F64
    R_cam0_imu: F64

    def within(self, t0_ns: int, t1_ns: int) -> ImuWindow:
        """The readings stamped in [t0_ns, t1_ns]."""
        keep = (self.stamps_ns >= t0_ns) & (self.stamps_ns <= t1_ns)
        return ImuWindow(self.stamps_ns[keep], self.gyro_rad_s[keep], self.R_cam0_imu)


@dataclass(frozen=True)
class SampleParams:
    """Per-run settings every sample needs (all plain values)."""

    min_range_m: float = 0.3
    min_motion_px: float = 0.25
    motion: Literal["full", "rotation", "off"] = (
        "full"  # what compensation may use (ablations: rotation, off)
    )
    estimate_velocity: bool = True  # constant-velocity translation from the sweep's self-consistency
    window_ns: int = 50_000_000  # +- LiDAR window around the frame time (set from IngestConfig)
    exr: bool = False
    png_level: int = 1
    interpolation: Literal["linear", "cubic", "nearest"] = "linear"  # equirect warps of the images
    overlap_images: bool = True  # warps in a helper thread beside the point work (off: inline)
    gt: GtParams = field(default_factory=GtParams)
    method: Literal["sparse", "dense"] = "sparse"  # the run's GT method (--gt auto is decided before)
    decision: str = "asked"  # why `method` (written to every sample's meta)
    gap_fallback: bool = False  # dense: a frame in a trajectory gap gets sparse GT (--gt auto), not skipped
    dense: DenseParams = field(default_factory=DenseParams)
    align_lower: bool = False  # also lay the points onto the lower image (`calib refine`'s stereo check)
    alignment_only: bool = False  # `calib refine`'s rounds: the alignments only (no GT, warps or files)


@dataclass(frozen=True)
class SampleJob:
    """Everything `process_sample` needs for one sample."""

    out: Path
    sid: str
    source: str
    upper_stamp_ns: int
    lower_stamp_ns: int
    upper_bgr: np.ndarray[Any, Any]  # BGR, or BGRA as a bgra8 bag records it (warped and written as is)
    lower_bgr: np.ndarray[Any, Any]
    lidars: tuple[LidarPoints, ...]
    imu: ImuWindow | None
    velocity_cam0_mps: F64 | None
    geometry: Geometry
    params: SampleParams
    trajectory: RigTrajectory | None = None  # the recording's (dense GT)
    thin_lidars: tuple[str, ...] = ()  # LiDARs with far fewer points than their rate (lidar_rate)
    thin_lidars_sparse: tuple[str, ...] = ()  # the same over sparse GT's window (`sparse_window`)
    settings: dict[str, Any] = field(default_factory=dict)  # the dataset's settings, for the meta
    upper_shift_ns: int = 0  # the rig's camera clock offsets: stamp + shift = exposure on the LiDAR clock
    lower_shift_ns: int = 0

    @property
    def exposure_ns(self) -> int:
        """The sample's time: the upper camera's mid-exposure on the LiDAR clock (ns)."""
        return self.upper_stamp_ns + self.upper_shift_ns

    @property
    def stereo_dt_ms(self) -> float:
        """Lower minus upper camera exposure time (ms)."""
        return (self.lower_stamp_ns + self.lower_shift_ns - self.exposure_ns) / 1e6

    def timing(self) -> dict[str, Any]:
        """The SampleMeta fields that say when the sample is: stamps as recorded, the exposure used."""
        return {
            "stamp_ns": self.upper_stamp_ns, "lower_stamp_ns": self.lower_stamp_ns,
            "stereo_dt_ms": self.stereo_dt_ms, "exposure_ns": self.exposure_ns,
            "clock_offset_ms": self.upper_shift_ns / 1e6,
        }  # fmt: skip


@dataclass(frozen=True)
class SampleResult:
    """What happened to one sample: counts for the summary, milliseconds per stage."""

    sid: str
    written: bool
    reason: str
    meta: SampleMeta | None  # None when the sample was skipped
    stage_ms: dict[str, float]  # sequential stages of the calling thread: they add up to its wall time
    overlapped_ms: dict[str, float] = field(default_factory=dict)  # helper-thread work beside them
    undecodable: tuple[tuple[str, int, str], ...] = ()  # (topic, log ns, why) per image that did not decode
    aligned: SampleAlignment | None = None  # `SampleParams.alignment_only`: what it found (reason ALIGNED)


ALIGNED = "aligned only (calib refine)"
"""The reason of a `SampleParams.alignment_only` result: nothing written, its alignments in the result."""


@dataclass(frozen=True)
class SampleAlignment:
    """A sample's LiDAR points laid onto its images, as the meta would record them: per LiDAR topic onto
    the upper image and onto the lower one, and cam0's twist (`SampleMeta.twist_cam0`)."""

    upper: dict[str, AlignmentMeta]
    lower: dict[str, AlignmentMeta]
    twist_cam0: list[float] | None


def _silent(job: SampleJob) -> list[str]:
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


def _points_by_lidar(job: SampleJob) -> WindowPoints:
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


def start_equirects(job: SampleJob) -> Background[Equirects]:
    """Both images warped to cam0's rectified equirect, in a helper thread (see `ingest.runtime.background`).

    The sizes are checked and the output buffers taken here, in the calling
    thread: they are its reused per-thread buffers (`RemapMaps.scratch`, no
    25 MB allocation and fill per image), valid until its next sample. Inline
    instead when `SampleParams.overlap_images` is off.
    """
    geo = job.geometry
    interp = INTERPOLATION[job.params.interpolation]
    work = []
    for image, model, R in (
        (job.upper_bgr, geo.rig.upper.model, geo.rect.R_cam0_rect),
        (job.lower_bgr, geo.rig.lower.model, geo.rect.R_cam1_rect),
    ):
        check_source(image, model)
        maps = build_maps(model, geo.equirect, R)
        out = maps.scratch((geo.equirect.height, geo.equirect.width, *image.shape[2:]), image.dtype, 0.0)
        work.append((image, maps, out))

    def both() -> Equirects:
        for image, maps, out in work:
            remap_spans(image, maps, out, interp)
        return work[0][2], work[1][2]

    return Background(both, name=f"sensorbox-equirects-{job.sid}", inline=not job.params.overlap_images)


def process_sample(job: SampleJob) -> SampleResult:
    """Clouds -> motion compensation -> GT (fisheye range, equirect disparity) -> images -> files.

    The equirect warps run in a helper thread beside the clouds and GT
    stages; stage "images" is what the calling thread spends on them: starting
    them (building the remap maps, once per process) and waiting at the end.
    """
    if job.params.alignment_only:
        return _process_sparse(job, None, 0.0)
    t0 = time.perf_counter()
    images = start_equirects(job)
    try:
        return _process(job, images, (time.perf_counter() - t0) * 1e3)
    finally:
        images.wait()  # never return while the helper still writes into this thread's buffers


def _process(job: SampleJob, images: Background[Equirects], start_ms: float) -> SampleResult:
    """`process_sample`'s stages, with its warps under way in `images` (starting them took `start_ms`)."""
    if job.params.method == "dense":
        return _process_dense(job, images, start_ms)
    return _process_sparse(job, images, start_ms)


def _process_sparse(job: SampleJob, images: Background[Equirects] | None, start_ms: float) -> SampleResult:
    """Sparse GT: the frame's own sweeps, motion-compensated to the frame time; without `images` (the
    warps), the points' alignments only (`SampleParams.alignment_only`)."""
    ms: dict[str, float] = {}
    t0 = time.perf_counter()
    geo, prm = job.geometry, job.params
    cloud = _points_by_lidar(job)
    counts, gyro, off_imu = cloud.counts, None, 0
    if job.imu is not None and len(job.imu.stamps_ns) >= 2:
        gyro = integrate_gyro(job.imu.stamps_ns, job.imu.gyro_rad_s, job.imu.R_cam0_imu)
        covered = gyro.covers(cloud.stamps_ns)  # rotations outside the IMU's span are unknown: dropped
        off_imu = int((~covered).sum())  # counted in the meta: the filters' counts add up to the total
        counts = replace(counts, kept=counts.kept - off_imu)
        cloud = cloud.where(covered)
    pts, stamps = cloud.pts, cloud.stamps_ns
    dt_s = (stamps - job.exposure_ns) / 1e9
    use_gyro = gyro is not None and prm.motion != "off"
    rotated = gyro.rotate(stamps, job.exposure_ns, pts) if gyro is not None and use_gyro else None
    velocity, source = job.velocity_cam0_mps, ("imu" if use_gyro else "none")
    if prm.motion != "full":
        velocity = None
    elif velocity is None and prm.estimate_velocity:
        est = estimate_velocity(
            rotated[0] if rotated is not None else pts, dt_s, significance=VELOCITY_SIGMAS
        )
        # use it only when it is significant: a static rig must not be "compensated" with fit noise
        if est is not None and np.linalg.norm(est.velocity_cam0_mps) > VELOCITY_SIGMAS * est.weakest_m_s:
            velocity = est.velocity_cam0_mps
    if velocity is not None:
        source += "+velocity"
    pts, motion = compensate(pts, dt_s, rotated, velocity, geo.px_per_rad, prm.min_motion_px, source=source)
    half = prm.window_ns / 2e9
    if motion.applied and not (len(dt_s) and dt_s.min() <= -half and dt_s.max() >= half):
        # a one-sided window (bag start/end, a LiDAR gap) leaves the velocity poorly determined
        return SampleResult(job.sid, False, "moving, LiDAR window one-sided (bag start/end or gap)", None, {})
    t1 = time.perf_counter()
    ms["clouds"] = (t1 - t0) * 1e3
    if images is None:
        fields = _alignment_fields(job, pts, cloud, ms)
        twist = _gyro_twist(job, velocity if motion.applied else None)
        aligned = SampleAlignment(fields["alignment"], fields["alignment_lower"], twist)
        return SampleResult(job.sid, False, ALIGNED, None, ms, aligned=aligned)
    model = geo.rig.upper.model
    view = in_view(model, pts)
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
        twist_cam0=_gyro_twist(job, velocity if motion.applied else None),
        **_alignment_fields(job, pts, cloud, ms),
        motion=MotionMeta(
            applied=motion.applied, source=motion.source, max_rotation_deg=motion.max_rotation_deg,
            speed_mps=motion.speed_mps, predicted_motion_px=motion.motion_px,
            velocity_cam0_mps=motion.velocity_cam0_mps,
        ),
        points=PointMeta(
            total=counts.total, zero=counts.zero, non_finite=counts.non_finite, too_close=counts.too_close,
            noise_tag=counts.noise_tag, kept=counts.kept, out_of_view=int(len(seen) - seen.sum()),
            occluded=int(seen.sum() - visible.sum()), silent_lidars=_silent(job), off_imu=off_imu,
        ),
        gt=GtMeta(
            depth_pixels=range_img.count, disp_pixels=disp_img.count, disp_unstable=unstable,
            density=range_img.count / geo.fisheye_valid_px, window_ms=prm.window_ns / 1e6,
            decision=prm.decision,
        ),
    )  # fmt: skip
    return _finish(job, images, start_ms, ms, (range_img, disp_img), meta)


def _alignment_fields(
    job: SampleJob, pts_cam0: F64, cloud: WindowPoints, ms: dict[str, float]
) -> dict[str, Any]:
    """The meta's `alignment` and `alignment_lower` of the points `pts_cam0` (those of `cloud`, placed in
    cam0 at the exposure), timed as stage "alignment" in `ms`."""
    t0 = time.perf_counter()
    fields = {
        "alignment": _alignments(job, pts_cam0, cloud.reflectivity, cloud.lidar),
        "alignment_lower": _lower_alignments(job, pts_cam0, cloud.reflectivity, cloud.lidar),
    }
    ms["alignment"] = (time.perf_counter() - t0) * 1e3
    return fields


def _alignments(
    job: SampleJob, pts_cam0: F64, reflectivity: F64 | None, which: I64
) -> dict[str, AlignmentMeta]:
    """Each LiDAR's photometric alignment with the upper image (`ingest.train.align`), of the points
    placed in cam0 at the exposure (`pts_cam0`, from LiDAR `which`); none without reflectivity."""
    if reflectivity is None:
        return {}
    return _aligned(job, job.upper_bgr, job.geometry.rig.upper.model, pts_cam0, reflectivity, which)


def _lower_alignments(
    job: SampleJob, pts_cam0: F64, reflectivity: F64 | None, which: I64
) -> dict[str, AlignmentMeta]:
    """`_alignments` onto the lower image, the points moved into cam1 by the camchain's stereo pose
    (`SampleParams.align_lower`; none without it)."""
    if reflectivity is None or not job.params.align_lower:
        return {}
    lower = job.geometry.rig.lower
    pts_cam1 = pts_cam0 @ lower.T_cam_cam0[:3, :3].T + lower.T_cam_cam0[:3, 3]
    return _aligned(job, job.lower_bgr, lower.model, pts_cam1, reflectivity, which)


def _aligned(
    job: SampleJob, image: np.ndarray[Any, Any], model: Any, pts: F64, reflectivity: F64, which: I64
) -> dict[str, AlignmentMeta]:
    """Each LiDAR's `align_points` of `pts` (in the camera of `image` and `model`)."""
    levels = ImageLevels.from_bgr(image)
    out = {}
    for i, lp in enumerate(job.lidars):
        mine = which == i
        found = align_points(model, levels, rows(pts, mine), reflectivity[mine])
        if found is not None:
            out[lp.name] = found.to_meta()
    return out


TWIST_STEP_NS = 5_000_000


def _trajectory_twist(traj: RigTrajectory, t_ns: int) -> list[float]:
    """cam0's angular velocity (rad/s) and velocity (m/s), both in cam0, at `t_ns` (central differences
    over +-`TWIST_STEP_NS`)."""
    R, p = traj.pose(np.array([t_ns - TWIST_STEP_NS, t_ns, t_ns + TWIST_STEP_NS], np.int64))
    turn, _ = cv2.Rodrigues(R[0].T @ R[2])
    h_s = 2 * TWIST_STEP_NS / 1e9
    # the turn between the two ends is in the frame at the first; at these rates the difference is 1e-5
    omega = turn.ravel() / h_s
    velocity = R[1].T @ (p[2] - p[0]) / h_s
    return [round(float(v), 6) for v in (*omega, *velocity)]


def _gyro_twist(job: SampleJob, velocity_cam0_mps: F64 | None) -> list[float] | None:
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


def _finish(
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
        settings=job.settings,
    )
    files = SampleFiles(job.upper_bgr, job.lower_bgr, up, down, gt[1], gt[0], meta)
    drops = write_sample(job.out, job.sid, files, job.params.exr, job.params.png_level)
    ms["write"] = (time.perf_counter() - t3) * 1e3
    helper = {"equirect warps": images.ms} if job.params.overlap_images else {}
    return SampleResult(job.sid, True, "", meta.written(job.sid, drops), ms, helper)


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


def _process_dense(job: SampleJob, images: Background[Equirects], start_ms: float) -> SampleResult:
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
    cloud = _points_by_lidar(job)
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
            slice_id, refs, ray_origin = _slices(job, traj, stamps, cloud.lidar)
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
    alignment = _alignment_fields(job, placed, cloud, ms)
    in_window = (traj.stamps_ns >= tc - prm.dense.window_ns) & (traj.stamps_ns <= tc + prm.dense.window_ns)
    residual = traj.residual_m[in_window]
    residual = residual[np.isfinite(residual)]
    meta = SampleMeta(
        **job.timing(), source_bag=job.source, lidar_skew_ms=cloud.skew_ms, **alignment,
        twist_cam0=_trajectory_twist(traj, tc),
        motion=MotionMeta(
            applied=True, source="trajectory", max_rotation_deg=float(np.degrees(turn_rad)),
            speed_mps=traj.speed_mps(tc), velocity_cam0_mps=None,
            predicted_motion_px=(turn_rad + shift_m / REFERENCE_RANGE_M) * geo.px_per_rad,
        ),
        points=PointMeta(
            total=cloud.counts.total, zero=cloud.counts.zero, non_finite=cloud.counts.non_finite,
            too_close=cloud.counts.too_close, noise_tag=cloud.counts.noise_tag, kept=int(covered.sum()),
            out_of_view=0, occluded=0,
            silent_lidars=_silent(job), off_trajectory=int(len(covered) - covered.sum()),
        ),
        gt=GtMeta(
            depth_pixels=dense.range_img.count, disp_pixels=dense.disp_img.count,
            disp_unstable=dense.unstable, density=dense.range_img.count / geo.fisheye_valid_px,
            method="dense", window_ms=prm.dense.window_ns / 1e6, decision=prm.decision,
            accumulated_points=len(placed), removed_moving=len(moving),
            trajectory_residual_mm=float(residual.max() * 1e3) if len(residual) else None,
        ),
    )  # fmt: skip
    return _finish(job, images, start_ms, ms, (dense.range_img, dense.disp_img), meta)


def _in_gap(job: SampleJob, images: Background[Equirects], start_ms: float) -> SampleResult:
    """A dense frame in a trajectory gap: sparse GT under `SampleParams.gap_fallback`, else skipped."""
    if not job.params.gap_fallback:
        return SampleResult(job.sid, False, GAP_REASON, None, {})
    sparse = sparse_window(job)
    if not any(len(lp.stamps_ns) for lp in sparse.lidars):  # a sparse run does not plan it either
        return SampleResult(job.sid, False, GAP_REASON, None, {})
    return _process_sparse(sparse, images, start_ms)


def _slices(
    job: SampleJob, traj: RigTrajectory, stamps: I64, which: I64
) -> tuple[I64, list[tuple[int, F64]], F64]:
    """Slice id per point (LiDAR x `free_slice_ns`), the frame's own slices with their LiDAR origins,
    and each point's ray origin (its LiDAR at the point's time).

    Origins are in cam0 at the frame time, where `traj.to_frame` put the points.
    """
    prm, tc = job.params.dense, job.exposure_ns
    k = (stamps - tc) // prm.free_slice_ns
    n_lidars = max(len(job.lidars), 1)
    slice_id = k * n_lidars + which
    own = slice_id if not prm.free_reference_ns else slice_id[np.abs(stamps - tc) <= prm.free_reference_ns]
    origins_lidar = np.array([job.geometry.rig.lidar(lidar.name).T_cam0_lidar[:3, 3] for lidar in job.lidars])
    ray_origin = traj.to_frame(origins_lidar[which], stamps, tc)
    if len(own) == 0:
        return slice_id, [], ray_origin
    # the window spans a few dozen slices: a bincount finds them without sorting every point
    lo = int(own.min())
    sids = lo + np.flatnonzero(np.bincount(own - lo))
    t_mid = tc + (sids // n_lidars) * prm.free_slice_ns + prm.free_slice_ns // 2
    origins = traj.to_frame(origins_lidar[sids % n_lidars], t_mid, tc)
    refs = [(int(sid), origin) for sid, origin in zip(sids, origins, strict=True)]
    return slice_id, refs, ray_origin
