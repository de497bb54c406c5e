"""The settings of an ingest run: `IngestConfig` as the user asked it, checked once (`validate`), and the
rig's sensors found among a recording's topics (`Topics`, `resolve_topics`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from calibration.errors import CalibrationError
from calibration.rig import Camera, Rig
from calibration.warp import height_full_problem
from ingest.errors import BagError, DatasetError
from ingest.raster.params import backend_problem
from ingest.topic_map import check_rig
from ingest.train.sample_job import SampleParams
from ingest.train.sync import DEFAULT_LIDAR_WINDOW_NS


@dataclass(frozen=True)
class IngestConfig:
    """Settings of one ingest run (times in ns)."""

    rig: Path
    out: Path
    workers: int = 2
    every: int = 1
    lidar_window_ns: int = DEFAULT_LIDAR_WINDOW_NS
    stereo_tolerance_ns: int | None = None  # default: half the median camera period
    height_full: int | None = None
    salvage: bool = False
    dask: str | None = None
    # sparse | dense | auto (see ingest.train.trajectory.choose_method); `sensorbox ingest` defaults to auto,
    # the library to sparse (no trajectory pass unless asked)
    gt: str = "sparse"
    max_bad: int = 0  # undecodable messages skipped and counted before the run stops (bad_messages)
    sample: SampleParams = field(default_factory=SampleParams)
    widen_static: bool = True  # --gt auto may widen the default dense window for a rig that stood still
    refine: bool = (
        False  # --refine: the cameras' clock offsets and LiDAR rotations refined from the bags first
    )

    def validate(self) -> None:
        """Values a run cannot start with, named as the CLI options that set them."""
        if self.gt not in ("sparse", "dense", "auto"):
            raise DatasetError(f"--gt {self.gt!r}: expected sparse, dense or auto")
        if not self.sample.dense.window_ns > 0:
            raise DatasetError(f"--gt-window-ms must be > 0, got {self.sample.dense.window_ns / 1e6:g}")
        if self.sample.motion not in ("full", "rotation", "off"):
            raise DatasetError(f"--motion {self.sample.motion!r}: expected full, rotation or off")
        if self.gt == "dense" and self.sample.motion != "full":
            raise DatasetError(
                f"--motion {self.sample.motion} does not apply to --gt dense, which places every point with "
                "the trajectory; it chooses the motion model of sparse GT (--gt sparse or auto)"
            )
        backend = self.sample.dense.render.backend
        if (problem := backend_problem(backend)) is not None:
            raise DatasetError(f"--backend {backend!r}: {problem}")
        if self.max_bad < 0:
            raise DatasetError(f"--max-bad must be >= 0, got {self.max_bad}")
        if self.workers < 1:
            raise DatasetError(f"--workers must be >= 1, got {self.workers}")
        if self.every < 1:
            raise DatasetError(f"--every must be >= 1, got {self.every}")
        if self.height_full is not None and (problem := height_full_problem(self.height_full)) is not None:
            raise DatasetError(problem)
        if not 0 <= self.sample.png_level <= 3:
            raise DatasetError(f"--png-level must be 0..3, got {self.sample.png_level}")
        if self.dask:
            from distributed.comm.addressing import get_address_host_port

            try:
                get_address_host_port(self.dask)
            except ValueError as err:
                raise DatasetError(
                    f"--dask {self.dask!r}: expected a scheduler address tcp://HOST:PORT ({err})"
                ) from err
        if not self.lidar_window_ns > 0:
            raise DatasetError(f"--window-ms must be > 0, got {self.lidar_window_ns / 1e6:g}")
        if self.gt == "auto" and self.sample.dense.window_ns < self.lidar_window_ns:
            raise DatasetError(
                f"--gt auto: --gt-window-ms {self.sample.dense.window_ns / 1e6:g} is narrower than "
                f"--window-ms {self.lidar_window_ns / 1e6:g}; the sparse GT it gives frames in trajectory "
                "gaps reads --window-ms of points from the dense window"
            )
        if not (math.isfinite(self.sample.min_range_m) and self.sample.min_range_m >= 0):
            raise DatasetError(f"--min-range must be >= 0 m, got {self.sample.min_range_m:g}")


@dataclass(frozen=True)
class Topics:
    """The bag topics of the rig's sensors (images may be raw or `/compressed`)."""

    upper: str
    lower: str
    lidars: dict[str, str]  # topic -> rig lidar name
    imu: str | None
    R_cam0_imu: Any
    imu_name: str = ""  # the rig's name of the IMU on `imu`
    imu_rate_hz: float | None = None  # its rate as the rig states it
    upper_shift_ns: int = 0  # the rig's timeshift_cam_imu: header stamp + shift = exposure on the LiDAR clock
    lower_shift_ns: int = 0


def resolve_topics(rig: Rig, bag_topics: dict[str, Any], where: str) -> Topics:
    """The bag topics of `rig`'s sensors among `bag_topics` (topic -> its connection), each image topic
    as named or with `/compressed`; a BagError naming `where` and the missing or mistyped topic otherwise."""

    def find(topic: str | None, what: str) -> str:
        for cand in (topic, f"{topic}/compressed"):
            if cand in bag_topics:
                return cand
        if not bag_topics:
            raise BagError(f"{where}: no messages at all (an empty bag, or cut before its first message)")
        listing = ", ".join(sorted(bag_topics))
        raise BagError(f"{where}: no topic {topic!r} for {what} (from the rig); the bag has: {listing}")

    def camera_topic(camera: Camera, what: str) -> str:
        if camera.topic is None:  # the rig's entry says null and the camchain names no rostopic
            raise CalibrationError(
                f"{rig.source or rig.name}: cameras.{camera.name}.topic: {what} has no topic (null in the "
                "rig file and no rostopic in the camchain); expected the topic of its images in the bag"
            )
        return find(camera.topic, what)

    upper = camera_topic(rig.upper, "the upper camera")
    lower = camera_topic(rig.lower, "the lower camera")
    lidars = {find(li.topic, f"lidar {li.name}"): li.name for li in rig.lidars}
    # every IMU the rig names must be there: a silent fallback skews the motion model
    imu_topics = [find(i.topic, f"imu {i.name}") for i in rig.imus]
    # a topic of another type, or of two (a LiDAR topic that also carries Imu messages), was skipped unsaid
    problems = check_rig(rig, {t: s.msgtype for t, s in bag_topics.items()})
    if problems:
        first = problems[0]
        raise BagError(f"{where}: {first.topic} (the rig's {first.sensor}) {first.problem}")
    imu = rig.imus[0] if rig.imus else None
    return Topics(
        upper, lower, lidars, imu_topics[0] if imu else None, imu.T_cam0_imu[:3, :3] if imu else None,
        imu.name if imu else "", imu.rate_hz if imu else None, rig.upper.timeshift_ns, rig.lower.timeshift_ns,
    )  # fmt: skip
