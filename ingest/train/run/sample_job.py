"""What a worker gets and gives back for one sample: the rig's geometry (built once), the sample's points,
gyro readings and images (`SampleJob`) with the run's settings (`SampleParams`), and what became of it
(`SampleResult`). All picklable: a process pool or a Dask cluster carries them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from calibration.errors import CalibrationError
from calibration.rectify import StereoRectification, rectify_rig
from calibration.rig import Rig
from calibration.spherical import Equirectangular
from calibration.types import F64, I64, U64
from calibration.warp import build_maps, check_height_full, default_height_full
from ingest.dataset.meta import AlignmentMeta, SampleMeta
from ingest.raster.view import pixel_rays
from ingest.rows import rows
from ingest.train.gt.dense import DenseParams, warm_up
from ingest.train.gt.groundtruth import GtParams, px_per_rad
from ingest.train.trajectory.rig_trajectory import RigTrajectory

MAX_ALIGN_PIXEL_DEG = 2.0
"""Images whose pixel at the centre spans more than this are too coarse for the LiDAR points' alignment:
the tool's own 48x30 px emulated capture (3.75 deg pixels) of a right rig had every sample 9-16 deg
"off" and both LiDARs' poses and the stereo pose called wrong."""


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

    @property
    def too_coarse_to_align(self) -> bool:
        """Whether cam0's pixel spans more than `MAX_ALIGN_PIXEL_DEG` at its centre: too coarse for the
        LiDAR points' alignment on its images, which then is not run."""
        return bool(np.degrees(1.0 / self.px_per_rad) > MAX_ALIGN_PIXEL_DEG)

    def coarse_line(self) -> str:
        """One warning line when the images are too coarse to align the LiDAR points on ('' otherwise)."""
        if not self.too_coarse_to_align:
            return ""
        model = self.rig.upper.model
        return (
            f"cam0's images ({model.width}x{model.height} px, {np.degrees(1.0 / self.px_per_rad):.1f} deg a "
            f"pixel) are too coarse to lay the LiDAR points on (over {MAX_ALIGN_PIXEL_DEG:g} deg a pixel): "
            "the pose, clock and stereo checks were not run"
        )

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
        """Dense GT's per-camera caches and compiled kernels, built now (`ingest.train.gt.dense.warm_up`)."""
        warm_up(self.rig.upper.model, self.equirect, self.rect.R_cam0_rect, self.rect.baseline_m, params)


@dataclass(frozen=True)
class LidarPoints:
    """Raw points of one LiDAR around a frame time: sensor frame (m), absolute stamps, Livox tags."""

    name: str
    xyz_m: np.ndarray[Any, Any]
    stamps_ns: I64
    tag: np.ndarray[Any, Any] | None
    normal_world: np.ndarray[Any, Any] | None = None  # dense GT: (N, 3) float16, NaN: none (`block_planes`)
    clear_bits: U64 | None = None  # dense GT: (N, words), slices that saw through / hit each (`block_planes`)
    reflectivity: np.ndarray[Any, Any] | None = None  # (N,) as the driver stored it (`ingest.train.gt.align`)

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
    # sparse GT: the free-space test of the window's own slices (`DenseParams`' ray rule and agreeing slices),
    # so that a point the other sweeps saw through (rain, dust, a stray echo, a mover's earlier place) is
    # removed, not drawn in front of the surface behind it
    sparse_free_space: bool = True
    sparse_free_slice_ns: int = 10_000_000  # ... its slices: a 50 ms window holds five of each LiDAR
    align_lower: bool = True  # also lay the points onto the lower image (the stereo pose's check)
    lower_every: int = 3  # ... of every n-th sample of a run that writes them (`calib refine`: of all)
    lower_check_points: int = 4_000  # the other samples' quick lower alignment: points of all LiDARs ...
    lower_check_width_px: int = 480  # ... on the lower image resized to at most this width
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
    repeated: tuple[str, ...] = ()  # "upper", "lower": the cameras whose frame repeats the one before it

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
