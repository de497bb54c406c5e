"""The settings of an ingest run: `IngestConfig` as the user asked it, checked once (`validate`), and the
rig's sensors found among a recording's topics (`Topics`, `resolve_topics`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from calibration.errors import CalibrationError
from calibration.rig import Camera, Rig
from calibration.warp import HEIGHT_FULL_EXPECTED, MIN_HEIGHT_FULL
from ingest.errors import BagError, SettingError
from ingest.raster.params import backend_problem
from ingest.topic_map import check_rig, missing_topic
from ingest.train.run.sample_job import SampleParams
from ingest.train.sync import DEFAULT_LIDAR_WINDOW_NS
from ingest.train.trajectory.segments import MIN_OVERLAP_NS, SETTLE_NS, SegmentParams, min_length_ns


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
    # sparse | dense | auto (see ingest.train.trajectory.estimate.choose_method); `sensorbox ingest`
    # defaults to auto, the library to sparse (no trajectory pass unless asked)
    gt: str = "sparse"
    max_bad: int = 0  # undecodable messages skipped and counted before the run stops (bad_messages)
    sample: SampleParams = field(default_factory=SampleParams)
    widen_static: bool = True  # --gt auto may widen the default dense window for a rig that stood still
    refine: bool = (
        False  # --refine: the cameras' clock offsets and LiDAR rotations refined from the bags first
    )
    # the trajectory pass of a run with workers: segments of a long recording, jobs of the workers, joined
    trajectory_segments: SegmentParams = field(default_factory=SegmentParams)

    def validate(self) -> None:
        """Values a run cannot start with: a `SettingError` naming the field (`sensorbox ingest` names
        its option instead)."""
        sample, dense = self.sample, self.sample.dense
        checks: list[tuple[bool, str, object, str]] = [
            (self.gt in ("sparse", "dense", "auto"), "gt", self.gt, "sparse, dense or auto"),
            (dense.window_ns > 0, "sample.dense.window_ns", dense.window_ns, "> 0"),
            (sample.motion in ("full", "rotation", "off"), "sample.motion", sample.motion,
             "full, rotation or off"),
            (self.gt != "dense" or sample.motion == "full", "sample.motion", sample.motion,
             "full with {gt} 'dense', which places every point with the trajectory ({sample.motion} "
             "chooses the motion model of sparse GT: {gt} sparse or auto)"),
            (self.max_bad >= 0, "max_bad", self.max_bad, ">= 0"),
            (self.workers >= 1, "workers", self.workers, ">= 1"),
            (self.every >= 1, "every", self.every, ">= 1"),
            (0 <= sample.png_level <= 3, "sample.png_level", sample.png_level, "0..3"),
            (self.lidar_window_ns > 0, "lidar_window_ns", self.lidar_window_ns, "> 0"),
            (self.gt != "auto" or dense.window_ns >= self.lidar_window_ns, "sample.dense.window_ns",
             dense.window_ns, "at least {lidar_window_ns} with {gt} 'auto': the sparse GT it gives frames "
             "in trajectory gaps reads {lidar_window_ns} of points from the dense window"),
            (math.isfinite(sample.min_range_m) and sample.min_range_m >= 0, "sample.min_range_m",
             sample.min_range_m, "a finite number >= 0 (m)"),
        ]  # fmt: skip
        for ok, setting, value, expected in checks:
            if not ok:
                raise SettingError(setting, value, expected)
        seg = self.trajectory_segments
        if seg.overlap_ns < MIN_OVERLAP_NS:
            raise SettingError("trajectory_segments.overlap_ns", seg.overlap_ns, f">= {MIN_OVERLAP_NS}")
        if seg.length_ns < min_length_ns(seg.overlap_ns):  # consecutive joins' overlaps apart
            raise SettingError(
                "trajectory_segments.length_ns", seg.length_ns,
                "at least 3 x {trajectory_segments.overlap_ns} - " + f"{SETTLE_NS} (consecutive joins apart)",
            )  # fmt: skip
        if self.height_full is not None and self.height_full < MIN_HEIGHT_FULL:
            raise SettingError("height_full", self.height_full, HEIGHT_FULL_EXPECTED)
        backend = dense.render.backend
        if (problem := backend_problem(backend)) is not None:
            known = problem.startswith("expected ")  # an unknown name; else a known one this machine lacks
            wanted = (
                problem.removeprefix("expected ") if known else f"a renderer this machine runs ({problem})"
            )
            raise SettingError("sample.dense.render.backend", backend, wanted)
        if self.dask:
            from distributed.comm.addressing import get_address_host_port

            try:
                get_address_host_port(self.dask)
            except ValueError as err:
                raise SettingError("dask", self.dask, f"a scheduler address tcp://HOST:PORT ({err})") from err


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
        raise BagError(missing_topic(where, topic, what, bag_topics))

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
    # a topic of another type, or of two (a LiDAR topic that also carries Imu messages), is refused here:
    # its messages would otherwise be skipped without a word
    problems = check_rig(rig, {t: s.msgtype for t, s in bag_topics.items()})
    if problems:
        first = problems[0]
        raise BagError(f"{where}: {first.topic} (the rig's {first.sensor}) {first.problem}")
    imu = rig.imus[0] if rig.imus else None
    return Topics(
        upper, lower, lidars, imu_topics[0] if imu else None, imu.T_cam0_imu[:3, :3] if imu else None,
        imu.name if imu else "", imu.rate_hz if imu else None, rig.upper.timeshift_ns, rig.lower.timeshift_ns,
    )  # fmt: skip
