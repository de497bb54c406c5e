"""What `sensorbox inspect` reports about a recording: per topic, stereo pairing, LiDAR coverage,
the suggested rig mapping and the rig's problems."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from ingest.bags.chunks import LostChunk
from ingest.bags.decode import RosVersion
from ingest.errors import BagError
from ingest.train.sync import lidar_clock_spread


@dataclass(frozen=True)
class TopicStats:
    """Timing of one topic. Times in ms, rates in Hz; None where there is nothing to measure.

    `stamped` is False for types without a leading `std_msgs/Header` (or
    unknown to SensorBox): then only `count` and the log-time span are filled.
    `undecodable` counts messages whose header (or, for LiDARs, points) could
    not be read; `error` holds the first such failure, or why the whole topic
    was refused.
    """

    topic: str
    msgtype: str
    count: int
    stamped: bool
    first_stamp_ns: int | None = None
    last_stamp_ns: int | None = None
    rate_hz: float | None = None
    median_period_ms: float | None = None
    max_interval_ms: float | None = None
    gaps: int = 0
    largest_gap_ms: float | None = None
    duplicates: int = 0
    out_of_order: int = 0
    log_offset_median_ms: float | None = None
    log_offset_min_ms: float | None = None
    log_offset_max_ms: float | None = None
    undecodable: int = 0
    error: str | None = None
    lost: int = 0
    """Messages in corrupt chunks skipped by `--salvage` (`BagReport.lost_chunks`), not in `count`."""


@dataclass(frozen=True)
class StereoReport:
    """Pairing of the upper and lower camera by header stamp; dt = lower - upper (ms).

    `source` says how the topics were chosen: "rig", "names" or "first two".
    """

    upper_topic: str
    lower_topic: str
    source: str
    tolerance_ms: float
    pairs: int
    unpaired_upper: int
    unpaired_lower: int
    median_dt_ms: float | None
    median_abs_dt_ms: float | None
    max_abs_dt_ms: float | None


@dataclass(frozen=True)
class LidarCoverage:
    """Sweep statistics of one LiDAR topic (sensor frame; medians over sweeps).

    `coverage` is the fraction of the 1x1 degree cells of 360 deg x
    `EL_RANGE_DEG` hit by one sweep's non-zero points; `zero_fraction` the
    share of all points that are (0, 0, 0) or not finite; `elevation_*_deg`
    the extremes of non-zero points over all sweeps. `time_layout` says where
    the per-point times came from (`Sweep.time_layout`; several joined by
    " | " if they changed; None without a decoded sweep).
    """

    topic: str
    sweeps: int
    points_median: float | None
    zero_fraction: float | None
    duration_ms_median: float | None
    coverage_median: float | None
    elevation_min_deg: float | None
    elevation_max_deg: float | None
    undecodable: int = 0
    time_layout: str | None = None
    first_point_ns: int | None = None  # the earliest and latest point time of all sweeps
    last_point_ns: int | None = None
    late_points: int = 0  # points whose time lies beyond any sweep (Livox offset_time over 3 s): left out
    points_total: int = 0


@dataclass(frozen=True)
class MappedSensor:
    """One entry of a suggested rig mapping; `reason` says why (for humans)."""

    kind: str  # "camera" | "lidar" | "imu"
    name: str
    topic: str
    role: str | None = None
    ip: str | None = None
    rate_hz: float | None = None
    reason: str = ""


@dataclass(frozen=True)
class TopicMapping:
    """A suggested rig topic mapping; `yaml()` renders it in the rig file's format."""

    sensors: tuple[MappedSensor, ...]
    notes: tuple[str, ...] = ()

    def of_kind(self, kind: str) -> tuple[MappedSensor, ...]:
        """The sensors of one kind ("camera", "lidar", "imu"), in mapping order."""
        return tuple(s for s in self.sensors if s.kind == kind)

    def as_dict(self) -> dict[str, dict[str, dict[str, Any]]]:
        """`{cameras: {cam0: {role, topic}}, lidars: {name: {topic, ip}}, imus: {name: {topic, rate_hz}}}`."""
        out: dict[str, dict[str, dict[str, Any]]] = {}
        for kind, key in (("camera", "cameras"), ("lidar", "lidars"), ("imu", "imus")):
            entries = {}
            for s in self.of_kind(kind):
                entry: dict[str, Any] = {"role": s.role} if s.role else {}
                entry["topic"] = s.topic
                if s.ip:
                    entry["ip"] = s.ip
                if kind == "imu" and s.rate_hz is not None:
                    entry["rate_hz"] = round(s.rate_hz, 1)
                entries[s.name] = entry
            if entries:
                out[key] = entries
        return out

    def yaml(self) -> str:
        """The mapping as rig-file YAML (topics only: poses still come from calibration)."""
        body = self.as_dict()
        if not body:
            return "# no camera, LiDAR or IMU topics found\n"
        head = "# topic mapping for a rig file; add camchain, T_cam0_lidar and T_cam0_imu\n"
        return head + yaml.safe_dump(body, default_flow_style=None, sort_keys=False)


@dataclass(frozen=True)
class RigProblem:
    """A rig sensor whose topic is missing from the bags or carries the wrong type."""

    sensor: str
    topic: str | None
    problem: str


@dataclass(frozen=True)
class BagReport:
    """Everything `inspect_bags` measured; log times in ns (bag receive time)."""

    paths: tuple[Path, ...]
    ros_version: RosVersion
    salvaged: tuple[Path, ...]
    message_count: int
    start_log_ns: int | None
    end_log_ns: int | None
    topics: tuple[TopicStats, ...]
    stereo: StereoReport | None
    lidars: tuple[LidarCoverage, ...]
    mapping: TopicMapping
    rig_problems: tuple[RigProblem, ...] | None = None
    """None when no rig was given; empty when the rig matches the bags."""
    lost_chunks: tuple[LostChunk, ...] = ()
    """Corrupt chunks skipped (`--salvage`; without it a corrupt chunk is an error)."""

    @property
    def duration_s(self) -> float:
        """Log-time span of the bags in seconds (0 for an empty bag)."""
        if self.start_log_ns is None or self.end_log_ns is None:
            return 0.0
        return (self.end_log_ns - self.start_log_ns) / 1e9

    def clock_problems(self) -> list[str]:
        """One line per LiDAR (point times) or IMU (header stamps) whose times miss the upper camera's.

        A sensor on its own clock (a CustomMsg timebase from the sensor's boot,
        IMU stamps of zero): ingest refuses the recording when the rig uses it.
        Also one line when the LiDARs' clocks seem to disagree
        (`ingest.train.sync.lidar_clock_spread`), which ingest warns about.
        """
        if self.stereo is None:
            return []
        cam = next((t for t in self.topics if t.topic == self.stereo.upper_topic), None)
        if cam is None or cam.first_stamp_ns is None or cam.last_stamp_ns is None:
            return []
        c0, c1 = cam.first_stamp_ns, cam.last_stamp_ns
        ranges = [(li.topic, "point times", li.first_point_ns, li.last_point_ns) for li in self.lidars]
        imus = {s.topic for s in self.mapping.of_kind("imu")}
        ranges += [
            (t.topic, "header stamps", t.first_stamp_ns, t.last_stamp_ns)
            for t in self.topics
            if t.topic in imus
        ]
        lines = [
            f"{topic}: {what} {a / 1e9:.3f} s..{b / 1e9:.3f} s do not overlap {cam.topic}'s stamps "
            f"{c0 / 1e9:.3f} s..{c1 / 1e9:.3f} s (the sensor's clock is not the cameras')"
            for topic, what, a, b in ranges
            if a is not None and b is not None and (b < c0 or a > c1)
        ]
        lines += [
            f"{li.topic}: every point's time lies beyond its sweep ({li.late_points:,} points: a Livox "
            "offset_time over 3 s, such as 0xFFFFFFFF); no sensor measures it, and ingest drops them all"
            for li in self.lidars
            if li.points_total and li.late_points == li.points_total
        ]
        lidars = {li.topic for li in self.lidars}
        offsets = {t.topic: t.log_offset_median_ms for t in self.topics if t.topic in lidars}
        spread = lidar_clock_spread({t: ms for t, ms in offsets.items() if ms is not None})
        return lines + ([spread] if spread else [])

    def topic(self, name: str) -> TopicStats:
        """The stats of one topic; `BagError` listing the bag's topics when absent."""
        for t in self.topics:
            if t.topic == name:
                return t
        have = ", ".join(t.topic for t in self.topics) or "none"
        raise BagError(f"topic {name!r} is not in {', '.join(map(str, self.paths))}; its topics are: {have}")
