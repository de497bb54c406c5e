"""Per-sample metadata (`meta/<id>.json`): typed here, plain JSON on disk.

The JSON keeps the release layout's nesting (stamps, source bag, per-LiDAR
skew, motion decision, point counts, GT counts and density, uint16 drops); the
dataclasses give every reader the same names and types instead of string keys.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from calibration.files import check_regular_file
from ingest.errors import DatasetError

MAX_META_BYTES = 16 << 20
"""A sample's metadata is a few KiB; a file beyond this is not one (a link to a device is refused before)."""


@dataclass(frozen=True)
class MotionMeta:
    """The motion-compensation decision: applied or not, from what, and why (m/s, deg, px)."""

    applied: bool
    source: str  # "imu", "imu+velocity", "none", ...
    max_rotation_deg: float
    speed_mps: float
    predicted_motion_px: float  # worst-case image motion of an uncompensated point
    velocity_cam0_mps: list[float] | None


@dataclass(frozen=True)
class PointMeta:
    """LiDAR points of the sample's window: what each filter removed and what remained."""

    total: int
    zero: int
    non_finite: int
    too_close: int
    noise_tag: int
    kept: int
    out_of_view: int
    occluded: int
    silent_lidars: list[str] = field(default_factory=list)  # rig LiDARs with no point in the window
    thin_lidars: list[str] = field(
        default_factory=list
    )  # far fewer than their rate: ingest.train.run.lidar_rate
    off_trajectory: int = 0  # dense: points without a registered pose near the frame (a gap, the ends)
    off_imu: int = 0  # sparse: points outside the IMU readings' span (their rotation unknown), left out
    range_ratio: dict[str, list[float]] = field(default_factory=dict)  # sparse: per LiDAR after the first,
    # [median ratio of its range to the first's where cam0 sees both in a pixel, pixels, the ratios' robust
    # 1-sigma scatter] (lidar_agreement)
    plane_scatter: dict[str, list[float]] = field(
        default_factory=dict
    )  # per LiDAR: [robust 1-sigma (m) of its
    # points about the other LiDARs' local planes, points measured] (lidar_agreement.plane_scatter)


@dataclass(frozen=True)
class GtMeta:
    """Ground-truth pixels: fisheye range, equirect disparity, unstable (pole) pixels, density (0..1).

    Once written (`SampleMeta.written`) the counts and the density are the PNGs': a value that did not
    fit uint16 is counted in `SampleMeta.dropped` instead.
    """

    depth_pixels: int
    disp_pixels: int
    disp_unstable: int
    density: float  # GT pixels / valid fisheye pixels
    method: str = "sparse"  # sparse: the frame's own sweeps; dense: all, placed by the trajectory
    window_ms: float = 50.0  # +- LiDAR window around the frame time
    decision: str = ""  # why this method (--gt auto), or "asked" (--gt sparse|dense)
    accumulated_points: int = 0  # dense: points placed into cam0 at the frame time
    removed_moving: int = 0  # dense: points near the view removed because another sweep saw through them
    trajectory_residual_mm: float | None = None  # dense: worst knot RMS point-to-plane residual in it


@dataclass(frozen=True)
class FileMeta:
    """One file a sample wrote, as written: its size and SHA-256 (hex), for a rerun to check it is whole."""

    bytes: int
    sha256: str


@dataclass(frozen=True)
class AlignmentMeta:
    """One LiDAR's photometric alignment with cam0's image (`ingest.train.gt.align`), a quality score that
    needs no truth: the correction that lays its points best onto the image (rotation vector in deg and
    translation in mm, both in cam0), their 1-sigmas (largest axis), `shift_deg` the median angle by
    which the correction moves the points as cam0 sees them (the GT's misalignment), the points used,
    the correlation of image intensity and reflectivity, the information matrix of (rotation rad,
    translation m) that `sensorbox calib refine` combines over samples, the points' median range and
    the angle of one pixel."""

    rotation_deg: list[float]
    translation_mm: list[float]
    sigma_rotation_deg: float
    sigma_translation_mm: float
    shift_deg: float
    points: int
    correlation: float
    information: list[list[float]]
    range_m: float  # the median range of the points used
    pixel_deg: float  # cam0's pixel at its centre: the scale of what the alignment can resolve


@dataclass(frozen=True)
class FrameCheckMeta:
    """A sample's two images on their own (`ingest.train.run.frame_check`): the fraction of each that is
    one flat grey level, whether they are the same pixels, which repeats its camera's frame before it
    to the byte, and each one's colour balance (red against blue)."""

    upper_flat: float
    lower_flat: float
    identical: bool
    repeated: list[str] = field(default_factory=list)  # "upper", "lower": the frame repeats the one before
    upper_red_blue: float | None = None  # log(mean red / mean blue) of the lit pixels; None: not colour
    lower_red_blue: float | None = None


@dataclass(frozen=True)
class SampleMeta:
    """One written sample; `id` and `dropped` (values too large for uint16, per image) come with the write."""

    stamp_ns: int  # upper camera header stamp, as recorded in the bag
    lower_stamp_ns: int
    stereo_dt_ms: float  # lower minus upper exposure time
    source_bag: str
    lidar_skew_ms: dict[str, float]  # per LiDAR topic: how far its points spread around the frame time
    motion: MotionMeta
    points: PointMeta
    gt: GtMeta
    id: str = ""
    dropped: dict[str, int] = field(default_factory=dict)
    frames_sha256: str = ""  # the frame's identity: `ingest.dataset.identity.frame_digest` of both images
    files: dict[str, FileMeta] = field(default_factory=dict)  # path in the dataset -> as written
    settings: dict[str, Any] = field(default_factory=dict)  # what made it: dataset.yaml's compared keys
    exposure_ns: int = 0  # the sample's time: the upper camera's mid-exposure on the LiDAR clock
    clock_offset_ms: float = 0.0  # exposure_ns - stamp_ns: the rig's timeshift_cam_imu for the upper camera
    alignment: dict[str, AlignmentMeta] = field(default_factory=dict)  # per LiDAR topic, with reflectivity
    twist_cam0: list[float] | None = None  # cam0's angular (rad/s) and linear (m/s) velocity in cam0
    alignment_lower: dict[str, AlignmentMeta] = field(default_factory=dict)  # onto the lower image, in cam1
    lower_check: dict[str, AlignmentMeta] = field(default_factory=dict)  # every sample's quick alignment
    # onto the lower image: does it lie on the points?
    frame_check: FrameCheckMeta | None = None
    window_parts: dict[str, list[float | None]] = field(default_factory=dict)  # per LiDAR: each stretch of
    # its window's point times matched with the upper image (`ingest.train.gt.align.part_correlations`)
    window_fit: dict[str, list[float | None]] = field(default_factory=dict)  # per LiDAR: each stretch's
    # share of points near the window's other stretches' (`ingest.train.gt.window_fit.stretch_shares`)
    stereo_offset: list[float] | None = None  # the lower rectified image's shift against the upper at the
    # disparity GT's pixels: [across, along the epipolar lines (px), pixels] (`ingest.train.gt.stereo_offset`)
    stereo_offset_quadrants: list[list[float] | None] = field(default_factory=list)  # the same shift in each
    # quadrant of those pixels: upper left, upper right, lower left, lower right, [across, along] or null

    def written(
        self, sid: str, dropped: dict[str, int], files: dict[str, FileMeta] | None = None
    ) -> SampleMeta:
        """The metadata of the files as written: `dropped` (per image, values over uint16, left 0 in the
        PNG) taken off the GT pixel counts and the density (a range over 65.535 m is no GT pixel), and
        `files` (each file's size and SHA-256)."""
        gt = self.gt
        depth_over, disp_over = dropped.get("depth_over_uint16", 0), dropped.get("disp_over_uint16", 0)
        if depth_over or disp_over:
            depth = gt.depth_pixels - depth_over
            density = gt.density * depth / gt.depth_pixels if gt.depth_pixels else gt.density
            gt = replace(gt, depth_pixels=depth, disp_pixels=gt.disp_pixels - disp_over, density=density)
        return replace(self, id=sid, dropped=dict(dropped), gt=gt, files=dict(files or {}))

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1, sort_keys=True) + "\n"

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SampleMeta:
        return cls(
            stamp_ns=int(d["stamp_ns"]), lower_stamp_ns=int(d["lower_stamp_ns"]),
            stereo_dt_ms=float(d["stereo_dt_ms"]), source_bag=str(d["source_bag"]),
            lidar_skew_ms={str(k): float(v) for k, v in d["lidar_skew_ms"].items()},
            motion=MotionMeta(**d["motion"]), points=PointMeta(**d["points"]), gt=GtMeta(**d["gt"]),
            id=str(d.get("id", "")), dropped={str(k): int(v) for k, v in d.get("dropped", {}).items()},
            frames_sha256=str(d.get("frames_sha256", "")),
            files={str(k): FileMeta(int(f["bytes"]), str(f["sha256"])) for k, f in
                   d.get("files", {}).items()},
            settings=dict(d.get("settings", {})),
            exposure_ns=int(d.get("exposure_ns", d["stamp_ns"])),
            clock_offset_ms=float(d.get("clock_offset_ms", 0.0)),
            alignment={str(k): AlignmentMeta(**v) for k, v in d.get("alignment", {}).items()},
            alignment_lower={str(k): AlignmentMeta(**v) for k, v in d.get("alignment_lower", {}).items()},
            lower_check={str(k): AlignmentMeta(**v) for k, v in d.get("lower_check", {}).items()},
            frame_check=None if d.get("frame_check") is None else FrameCheckMeta(**d["frame_check"]),
            twist_cam0=None if d.get("twist_cam0") is None else [float(v) for v in d["twist_cam0"]],
            window_parts={str(k): [None if c is None else float(c) for c in v]
                          for k, v in d.get("window_parts", {}).items()},
            window_fit={str(k): [None if c is None else float(c) for c in v]
                        for k, v in d.get("window_fit", {}).items()},
            stereo_offset=None if d.get("stereo_offset") is None else [float(v) for v in d["stereo_offset"]],
            stereo_offset_quadrants=[None if q is None else [float(v) for v in q]
                                     for q in d.get("stereo_offset_quadrants", [])],
        )  # fmt: skip


def read_meta(out: Path, sid: str) -> SampleMeta:
    """The metadata of written sample `sid` in dataset folder `out`."""
    path = out / "meta" / f"{sid}.json"
    check_regular_file(path, "sample metadata", MAX_META_BYTES, DatasetError)  # a FIFO would block the read
    try:
        return SampleMeta.from_dict(json.loads(path.read_text()))
    except OSError as err:
        raise DatasetError(f"{path}: cannot read: {err.strerror or err}") from err
    except (ValueError, KeyError, TypeError, AttributeError) as err:
        raise DatasetError(f"{path}: not SensorBox sample metadata ({type(err).__name__}: {err})") from err
