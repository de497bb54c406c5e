"""Inspect bags: per-topic timing, stereo pairing, LiDAR coverage and a suggested rig mapping.

Public API:

- `inspect_bags(paths, salvage=False, rig=None, progress=None) -> BagReport`:
  reads every message once (through `ingest.bags.reader.open_bags`) and returns
  frozen dataclasses, nothing printed.
- `header_stamp_ns(raw, ros_version) -> int`: the `std_msgs/Header` stamp of
  any message whose first field is a header, read from the first 12 bytes
  (ROS 2 CDR: 4-byte encapsulation, int32 sec, uint32 nanosec; ROS 1: uint32
  seq, uint32 sec, uint32 nsec), so images are never decoded.

What is measured (all times from header stamps unless said otherwise):

- Per topic (`TopicStats`): count; rate = 1 / median interval between
  successive distinct stamps (Hz); gaps = intervals longer than `GAP_FACTOR`
  times that median (count, largest in ms); duplicated stamps (a stamp seen
  before on the topic) and out-of-order stamps (earlier than the previous
  message's, in log-time order); log time minus stamp (median, min, max, ms;
  positive = the message was recorded after its stamp).
- Stereo (`StereoReport`): upper/lower frames paired by ingest's rule
  (`ingest.train.sync.pair_stereo`: nearest by stamp, each frame once) within
  half the upper camera's median period; signed dt = lower - upper.
- LiDAR (`LidarCoverage`): per sweep the point count, the fraction of (0,0,0)
  no-return points, the spread of per-point stamps (ms), and the fraction of
  1x1 degree azimuth/elevation cells over 360 x [-7, 52] deg (the Mid-360's
  field of view, sensor frame) hit by its non-zero points; medians over sweeps.
- `TopicMapping`: image topics named upper/top/left or lower/bottom/right
  become cam0 (upper) and cam1 (lower); LiDARs (PointCloud2, Livox CustomMsg)
  and IMUs are paired by the livox_ros_driver2 multi_topic names
  `lidar_<ip>`/`imu_<ip>`; a LiDAR whose IMU's mean specific force (the
  reaction to gravity) points along +z is named `lidar_top` (upright), along
  -z `lidar_bottom` (mounted upside down); otherwise LiDARs are named by IP.
- With a rig: its camera, LiDAR and IMU topics missing from the bags or of
  the wrong message type (`RigProblem`).
"""

from __future__ import annotations

import dataclasses
import re
from array import array
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calibration.rig import Rig
from ingest.bags.decode import ImuSample, RosVersion, Sweep, decode, header_stamp_ns
from ingest.bags.reader import BagSet, RawMessage, open_bags
from ingest.bags.rostypes import COMPRESSED_IMAGE_TYPE, IMAGE_TYPE, IMU_TYPE, LIVOX_PACKAGES, POINTCLOUD2_TYPE
from ingest.bags.rostypes import typestore as sensorbox_typestore
from ingest.errors import BagError, MessageDecodeError
from ingest.train.sync import median_period_ns, pair_stereo, pair_tolerance_ns

__all__ = [
    "BagReport",
    "LidarCoverage",
    "MappedSensor",
    "RigProblem",
    "StereoReport",
    "TopicMapping",
    "TopicStats",
    "header_stamp_ns",
    "inspect_bags",
]

IMAGE_TYPES = frozenset({IMAGE_TYPE, COMPRESSED_IMAGE_TYPE})
LIDAR_TYPES = frozenset({POINTCLOUD2_TYPE, *(f"{pkg}/msg/CustomMsg" for pkg in LIVOX_PACKAGES)})
IMU_TYPES = frozenset({IMU_TYPE})
GAP_FACTOR = 1.5
"""An interval longer than this many median periods counts as a gap."""
EL_RANGE_DEG = (-7.0, 52.0)
"""Elevation band of the coverage grid: the Mid-360's vertical field of view (deg)."""
CELL_DEG = 1.0
"""Side of a coverage cell in azimuth and elevation (deg)."""
N_AZ = round(360 / CELL_DEG)
N_EL = round((EL_RANGE_DEG[1] - EL_RANGE_DEG[0]) / CELL_DEG)
GRAVITY_SAMPLES = 400
"""IMU messages per topic decoded to find the gravity direction (the rest only give stamps)."""
UPRIGHT_COS = 0.7
"""|z| of the mean unit specific force above which a LiDAR counts as upright or upside down."""

_UPPER_WORDS = frozenset({"upper", "top", "up", "left"})
_LOWER_WORDS = frozenset({"lower", "bottom", "down", "low", "right"})
_NOT_COLOUR_WORDS = frozenset({"depth", "disparity", "confidence", "mask", "normals", "seg"})
_LIVOX_IP = re.compile(r"(?:^|/)(lidar|imu)_(\d{1,3})_(\d{1,3})_(\d{1,3})_(\d{1,3})$")

Progress = Callable[[int, int], None]
"""Called with (messages read, messages in total)."""


# ---------------------------------------------------------------- report types


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
    the extremes of non-zero points over all sweeps.
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

    @property
    def duration_s(self) -> float:
        """Log-time span of the bags in seconds (0 for an empty bag)."""
        if self.start_log_ns is None or self.end_log_ns is None:
            return 0.0
        return (self.end_log_ns - self.start_log_ns) / 1e9

    def topic(self, name: str) -> TopicStats:
        """The stats of one topic; `BagError` listing the bag's topics when absent."""
        for t in self.topics:
            if t.topic == name:
                return t
        have = ", ".join(t.topic for t in self.topics) or "none"
        raise BagError(f"topic {name!r} is not in {', '.join(map(str, self.paths))}; its topics are: {have}")


# ---------------------------------------------------------------- header stamps


@cache
def _has_header(msgtype: str, ros_version: RosVersion) -> bool:
    """True when SensorBox's typestore knows `msgtype` and its first field is a Header."""
    store = sensorbox_typestore(ros_version)
    if msgtype not in store.fielddefs:
        return False
    fields = store.fielddefs[msgtype][1]
    return bool(fields) and fields[0][1][1] == "std_msgs/msg/Header"


# ---------------------------------------------------------------- accumulators


@dataclass
class _TopicAcc:
    """Raw per-topic observations while reading (arrival = log-time order)."""

    msgtype: str
    stamped: bool
    count: int = 0
    stamps: array[int] = field(default_factory=lambda: array("q"))
    logs: array[int] = field(default_factory=lambda: array("q"))
    first_log: int | None = None
    last_log: int | None = None
    undecodable: int = 0
    error: str | None = None

    def fail(self, err: Exception) -> None:
        self.undecodable += 1
        if self.error is None:
            self.error = str(err)


@dataclass
class _SweepAcc:
    """Per-sweep LiDAR observations."""

    points: list[int] = field(default_factory=list)
    zeros: list[int] = field(default_factory=list)
    durations_ms: list[float] = field(default_factory=list)
    coverage: list[float] = field(default_factory=list)
    el_min: float = np.inf
    el_max: float = -np.inf
    undecodable: int = 0


@dataclass
class _ImuAcc:
    """Sum of unit specific-force vectors of the first `GRAVITY_SAMPLES` messages."""

    total: np.ndarray[Any, np.dtype[np.float64]] = field(default_factory=lambda: np.zeros(3))
    n: int = 0


# ---------------------------------------------------------------- per-message work


def _sweep_cells(xyz: np.ndarray[Any, Any]) -> tuple[int, np.ndarray[Any, Any]]:
    """(number of 1x1 deg cells hit, elevations in deg) of non-zero, finite points (sensor frame)."""
    x, y, z = (xyz[:, i].astype(np.float64) for i in range(3))
    az = np.degrees(np.arctan2(y, x))
    el = np.degrees(np.arctan2(z, np.hypot(x, y)))
    ia = np.floor((az + 180.0) / CELL_DEG).astype(np.int64) % N_AZ
    ie = np.floor((el - EL_RANGE_DEG[0]) / CELL_DEG).astype(np.int64)
    inside = (ie >= 0) & (ie < N_EL)
    cells = np.unique(ie[inside] * N_AZ + ia[inside])
    return len(cells), el


def _add_sweep(acc: _SweepAcc, sweep: Sweep) -> None:
    """Record one sweep: points, zeros, stamp spread and angular coverage."""
    xyz = sweep.xyz_m
    valid = np.isfinite(xyz).all(axis=1) & (xyz != 0).any(axis=1)
    hit, el = _sweep_cells(xyz[valid])
    acc.points.append(len(xyz))
    acc.zeros.append(int(len(xyz) - np.count_nonzero(valid)))
    stamps = sweep.stamps_ns
    acc.durations_ms.append(float(stamps.max() - stamps.min()) / 1e6 if len(stamps) else 0.0)
    acc.coverage.append(hit / (N_AZ * N_EL))
    if len(el):
        acc.el_min = min(acc.el_min, float(el.min()))
        acc.el_max = max(acc.el_max, float(el.max()))


def _add_imu(acc: _ImuAcc, msg: RawMessage) -> None:
    """Add the unit specific force of one IMU message (unit-agnostic: g or m/s^2)."""
    sample = decode(msg.msgtype, msg.raw, msg.ros_version)
    if not isinstance(sample, ImuSample):
        return
    norm = float(np.linalg.norm(sample.acc))
    if norm > 0 and np.isfinite(norm):
        acc.total += sample.acc / norm
        acc.n += 1


def _read(
    bag: BagSet,
    topics: dict[str, _TopicAcc],
    sweeps: dict[str, _SweepAcc],
    imus: dict[str, _ImuAcc],
    total: int,
    progress: Progress | None,
) -> None:
    """One pass over the messages of `topics`, filling the accumulators."""
    done = 0
    for msg in bag.messages(topics=list(topics)):
        acc = topics[msg.topic]
        acc.count += 1
        acc.first_log = msg.log_ns if acc.first_log is None else acc.first_log
        acc.last_log = msg.log_ns
        if acc.stamped:
            try:
                stamp = header_stamp_ns(msg.raw, msg.ros_version)
            except MessageDecodeError as err:
                acc.fail(err)
            else:
                acc.stamps.append(stamp)
                acc.logs.append(msg.log_ns)
        _measure(msg, sweeps, imus, acc)
        done += 1
        if progress is not None and done % 64 == 0:
            progress(done, total)
    if progress is not None:
        progress(done, max(total, done))


def _measure(msg: RawMessage, sweeps: dict[str, _SweepAcc], imus: dict[str, _ImuAcc], acc: _TopicAcc) -> None:
    """Decode what needs more than the header: LiDAR sweeps, the first IMU samples."""
    try:
        if msg.topic in sweeps:
            sweep = decode(msg.msgtype, msg.raw, msg.ros_version)
            if isinstance(sweep, Sweep):
                _add_sweep(sweeps[msg.topic], sweep)
        elif msg.topic in imus and imus[msg.topic].n < GRAVITY_SAMPLES:
            _add_imu(imus[msg.topic], msg)
    except MessageDecodeError as err:
        if msg.topic in sweeps:
            sweeps[msg.topic].undecodable += 1
        if acc.error is None:
            acc.error = str(err)


# ---------------------------------------------------------------- statistics


def _ms(ns: float) -> float:
    return float(ns) / 1e6


def _topic_stats(topic: str, acc: _TopicAcc) -> TopicStats:
    """Rates, gaps, duplicates, order and log offsets from the accumulated stamps."""
    base = TopicStats(
        topic, acc.msgtype, acc.count, acc.stamped, undecodable=acc.undecodable, error=acc.error
    )
    stamps = np.frombuffer(acc.stamps, np.int64) if acc.stamps else np.zeros(0, np.int64)
    if len(stamps) == 0:
        return base
    logs = np.frombuffer(acc.logs, np.int64)
    offsets = logs - stamps
    unique = np.unique(stamps)
    timing: dict[str, Any] = {
        "first_stamp_ns": int(unique[0]),
        "last_stamp_ns": int(unique[-1]),
        "duplicates": int(len(stamps) - len(unique)),
        "out_of_order": int(np.count_nonzero(np.diff(stamps) < 0)),
        "log_offset_median_ms": _ms(float(np.median(offsets))),
        "log_offset_min_ms": _ms(int(offsets.min())),
        "log_offset_max_ms": _ms(int(offsets.max())),
    }
    if len(unique) >= 2:
        intervals = np.diff(unique)
        median = float(np.median(intervals))
        gaps = intervals[intervals > GAP_FACTOR * median]
        timing |= {
            "rate_hz": 1e9 / median,
            "median_period_ms": _ms(median),
            "max_interval_ms": _ms(int(intervals.max())),
            "gaps": len(gaps),
            "largest_gap_ms": _ms(int(gaps.max())) if len(gaps) else None,
        }
    return dataclasses.replace(base, **timing)


def _lidar_coverage(topic: str, acc: _SweepAcc) -> LidarCoverage:
    """Medians over the sweeps of one LiDAR topic."""
    if not acc.points:
        return LidarCoverage(topic, 0, None, None, None, None, None, None, acc.undecodable)
    total = sum(acc.points)
    return LidarCoverage(
        topic=topic,
        sweeps=len(acc.points),
        points_median=float(np.median(acc.points)),
        zero_fraction=sum(acc.zeros) / total if total else None,
        duration_ms_median=float(np.median(acc.durations_ms)),
        coverage_median=float(np.median(acc.coverage)),
        elevation_min_deg=acc.el_min if np.isfinite(acc.el_min) else None,
        elevation_max_deg=acc.el_max if np.isfinite(acc.el_max) else None,
        undecodable=acc.undecodable,
    )


def _stereo(upper: str, lower: str, source: str, topics: dict[str, _TopicAcc]) -> StereoReport:
    """Pair the two camera topics with ingest's rule (`ingest.train.sync.pair_stereo`), half a period."""
    up = np.unique(np.frombuffer(topics[upper].stamps, np.int64))
    low = np.unique(np.frombuffer(topics[lower].stamps, np.int64))
    tolerance_ns = pair_tolerance_ns(median_period_ns(up if len(up) >= 2 else low))
    pairs = pair_stereo(up, low, tolerance_ns)
    iu, il = pairs.upper, pairs.lower
    dt = pairs.dt_ns.astype(np.float64)
    return StereoReport(
        upper_topic=upper,
        lower_topic=lower,
        source=source,
        tolerance_ms=_ms(tolerance_ns),
        pairs=len(iu),
        unpaired_upper=len(up) - len(iu),
        unpaired_lower=len(low) - len(il),
        median_dt_ms=_ms(float(np.median(dt))) if len(dt) else None,
        median_abs_dt_ms=_ms(float(np.median(np.abs(dt)))) if len(dt) else None,
        max_abs_dt_ms=_ms(float(np.abs(dt).max())) if len(dt) else None,
    )


# ---------------------------------------------------------------- mapping


def _words(topic: str) -> set[str]:
    return set(re.split(r"[^a-z0-9]+", topic.lower())) - {""}


def _camera_role(topic: str) -> str | None:
    """'upper' / 'lower' from the words of a topic name, None when unclear."""
    words = _words(topic)
    up, low = bool(words & _UPPER_WORDS), bool(words & _LOWER_WORDS)
    return "upper" if up and not low else "lower" if low and not up else None


def _image_topics(stats: Iterable[TopicStats]) -> list[TopicStats]:
    """Colour image topics (not depth, disparity, ...), sorted by name."""
    return sorted(
        (t for t in stats if t.msgtype in IMAGE_TYPES and not _words(t.topic) & _NOT_COLOUR_WORDS),
        key=lambda t: t.topic,
    )


def _best(candidates: list[TopicStats]) -> TopicStats:
    """Most messages, then raw Image over CompressedImage, then the shortest name."""
    return min(candidates, key=lambda t: (-t.count, t.msgtype != IMAGE_TYPE, len(t.topic), t.topic))


def _guess_cameras(stats: Sequence[TopicStats]) -> tuple[list[MappedSensor], str | None]:
    """(cam0 upper, cam1 lower) from topic names, else the first two image topics; with a note."""
    images = _image_topics(stats)
    by_role = {r: [t for t in images if _camera_role(t.topic) == r] for r in ("upper", "lower")}
    if by_role["upper"] and by_role["lower"]:
        up, low = _best(by_role["upper"]), _best(by_role["lower"])
        why = "topic name says {}"
        return [
            MappedSensor(
                "camera", "cam0", up.topic, role="upper", rate_hz=up.rate_hz, reason=why.format("upper")
            ),
            MappedSensor(
                "camera", "cam1", low.topic, role="lower", rate_hz=low.rate_hz, reason=why.format("lower")
            ),
        ], None
    if len(images) >= 2:
        a, b = images[:2]
        note = f"camera roles guessed from topic order ({a.topic} upper, {b.topic} lower): check them"
        return [
            MappedSensor(
                "camera", "cam0", a.topic, role="upper", rate_hz=a.rate_hz, reason="first image topic"
            ),
            MappedSensor(
                "camera", "cam1", b.topic, role="lower", rate_hz=b.rate_hz, reason="second image topic"
            ),
        ], note
    if images:
        return [MappedSensor("camera", "cam0", images[0].topic, rate_hz=images[0].rate_hz)], (
            "only one image topic: no stereo pair"
        )
    return [], "no image topics"


def _livox_ip(topic: str, kind: str) -> str | None:
    """The dotted IP of a livox_ros_driver2 multi_topic name (`.../lidar_192_168_1_12`)."""
    m = _LIVOX_IP.search(topic)
    if m is None or m.group(1) != kind or any(int(g) > 255 for g in m.groups()[1:]):
        return None
    return ".".join(m.groups()[1:])


def _mount(up_z: float | None) -> str | None:
    """'top' (upright: gravity reaction along +z), 'bottom' (upside down) or None."""
    if up_z is None:
        return None
    return "top" if up_z > UPRIGHT_COS else "bottom" if up_z < -UPRIGHT_COS else None


def _imu_up_z(imus: dict[str, _ImuAcc]) -> dict[str, float]:
    """z of the normalised mean unit specific force per IMU topic (+1: sensor z points up)."""
    out = {}
    for topic, acc in imus.items():
        norm = float(np.linalg.norm(acc.total))
        if acc.n and norm > 0:
            out[topic] = float(acc.total[2] / norm)
    return out


def _guess_lidars(
    stats: Sequence[TopicStats], up_z: dict[str, float]
) -> tuple[list[MappedSensor], list[MappedSensor], list[str]]:
    """LiDAR and IMU entries, paired by Livox IP and named top/bottom by gravity where possible."""
    lidars = [t for t in stats if t.msgtype in LIDAR_TYPES]
    imu_topics = [t for t in stats if t.msgtype in IMU_TYPES]
    imu_by_ip = {ip: t for t in imu_topics if (ip := _livox_ip(t.topic, "imu")) is not None}
    notes: list[str] = []
    plan = []  # (lidar stats, ip, matching imu stats, mount)
    for t in lidars:
        ip = _livox_ip(t.topic, "lidar")
        imu = imu_by_ip.get(ip) if ip else None
        plan.append((t, ip, imu, _mount(up_z.get(imu.topic)) if imu else None))
    mounts = [m for *_, m in plan]
    use_mount = all(mounts) and len(set(mounts)) == len(mounts)
    if lidars and not use_mount:
        notes.append("LiDAR mounting (top/bottom) not clear from IMU gravity: named by IP or order")
    out_l: list[MappedSensor] = []
    out_i: list[MappedSensor] = []
    paired: set[str] = set()
    for k, (t, ip, imu, mount) in enumerate(plan):
        suffix = mount if use_mount else (ip.split(".")[-1] if ip else str(k))
        why = f"{t.msgtype}"
        if use_mount and imu is not None:
            side = "up" if mount == "top" else "down"
            why += f"; its IMU's z axis points {side} (mean unit specific force z {up_z[imu.topic]:+.2f})"
        out_l.append(MappedSensor("lidar", f"lidar_{suffix}", t.topic, ip=ip, rate_hz=t.rate_hz, reason=why))
        if imu is not None:
            paired.add(imu.topic)
            reason = f"same Livox IP as {t.topic}"
            out_i.append(MappedSensor("imu", f"imu_{suffix}", imu.topic, rate_hz=imu.rate_hz, reason=reason))
    others = [t for t in imu_topics if t.topic not in paired]
    for k, t in enumerate(others):
        name = f"imu{k}" if len(others) > 1 else "imu"
        out_i.append(MappedSensor("imu", name, t.topic, rate_hz=t.rate_hz, reason="no LiDAR with its IP"))
    return out_l, out_i, notes


def suggest_mapping(stats: Sequence[TopicStats], up_z: dict[str, float] | None = None) -> TopicMapping:
    """A rig topic mapping from topic names, types and (optionally) IMU gravity directions.

    `up_z` maps an IMU topic to the z component of its mean unit specific
    force (sensor frame): about +1 upright, -1 upside down.
    """
    cams, cam_note = _guess_cameras(stats)
    lidars, imus, notes = _guess_lidars(stats, up_z or {})
    all_notes = ([cam_note] if cam_note else []) + notes
    return TopicMapping((*cams, *lidars, *imus), tuple(all_notes))


# ---------------------------------------------------------------- rig check


def _resolve_image_topic(topic: str | None, names: dict[str, str]) -> str | None:
    """`topic` if in the bag, else its image_transport `/compressed` variant if that is."""
    if topic is None:
        return None
    if topic in names:
        return topic
    compressed = topic.rstrip("/") + "/compressed"
    return compressed if compressed in names else None


def check_rig(rig: Rig, types: dict[str, str]) -> tuple[RigProblem, ...]:
    """Rig topics missing from the bags (`types`: topic -> msgtype) or of the wrong type."""
    problems: list[RigProblem] = []
    wanted: list[tuple[str, str | None, frozenset[str], str]] = [
        (f"camera {c.name}" + (f" ({c.role})" if c.role else ""), c.topic, IMAGE_TYPES, "an image")
        for c in rig.cameras
    ]
    wanted += [(f"lidar {li.name}", li.topic, LIDAR_TYPES, "a LiDAR") for li in rig.lidars]
    wanted += [(f"imu {i.name}", i.topic, IMU_TYPES, "an IMU") for i in rig.imus]
    for sensor, topic, allowed, what in wanted:
        if topic is None:
            problems.append(RigProblem(sensor, None, "has no topic in the rig file"))
        elif topic not in types:
            alt = _resolve_image_topic(topic, types) if allowed is IMAGE_TYPES else None
            hint = f"; the bag has {alt} (image_transport compressed)" if alt else ""
            problems.append(RigProblem(sensor, topic, f"not in the bag{hint}"))
        elif types[topic] not in allowed:
            expected = " or ".join(sorted(allowed))
            problems.append(
                RigProblem(sensor, topic, f"has type {types[topic]}; expected {what} type ({expected})")
            )
    return tuple(problems)


def _stereo_topics(
    rig: Rig | None, mapping: TopicMapping, types: dict[str, str]
) -> tuple[str, str, str] | None:
    """(upper, lower, source) image topics to pair, from the rig, else the suggested mapping."""
    if rig is not None:
        roles = {c.role: _resolve_image_topic(c.topic, types) for c in rig.cameras if c.role}
        up, low = roles.get("upper"), roles.get("lower")
        if up and low and types[up] in IMAGE_TYPES and types[low] in IMAGE_TYPES:
            return up, low, "rig"
    cams = mapping.of_kind("camera")
    if len(cams) >= 2:
        return (
            cams[0].topic,
            cams[1].topic,
            "names" if cams[0].reason.startswith("topic name") else "first two",
        )
    return None


# ---------------------------------------------------------------- entry point


def _readable_topics(bag: BagSet, accs: dict[str, _TopicAcc]) -> dict[str, _TopicAcc]:
    """The topics `BagSet.messages` accepts; refused ones keep their reason in `error`."""
    ok = {}
    for topic, acc in accs.items():
        try:
            bag.messages(topics=[topic])
        except BagError as err:
            acc.error = str(err)
        else:
            ok[topic] = acc
    return ok


def inspect_bags(
    paths: Sequence[str | Path] | str | Path,
    salvage: bool = False,
    rig: Rig | None = None,
    progress: Progress | None = None,
) -> BagReport:
    """Read one or several bags once and report timing, stereo pairing, LiDAR coverage and a mapping.

    `paths` as for `open_bags` (ROS 1 `.bag` files, or ROS 2 `.mcap`/`.db3`
    files and rosbag2 directories); `salvage` reads truncated MCAP files'
    complete chunks. With `rig`, the stereo pair is the rig's upper/lower
    cameras and `rig_problems` lists its topics the bags lack or carry with
    the wrong type. `progress(done, total)` is called while reading.
    Raises `BagError` when a bag cannot be opened or read; a topic whose type
    cannot be decoded safely is reported (`TopicStats.error`), not read.
    """
    path_list = [Path(paths)] if isinstance(paths, str | Path) else [Path(p) for p in paths]
    with open_bags(path_list, salvage=salvage) as bag:
        summary = bag.topics()
        ros: RosVersion = bag.ros_version
        accs = {t: _TopicAcc(s.msgtype, _has_header(s.msgtype, ros)) for t, s in summary.items()}
        readable = _readable_topics(bag, accs)
        sweeps = {t: _SweepAcc() for t, a in readable.items() if a.msgtype in LIDAR_TYPES}
        imus = {t: _ImuAcc() for t, a in readable.items() if a.msgtype in IMU_TYPES}
        total = sum(summary[t].count for t in readable)
        if readable:
            _read(bag, readable, sweeps, imus, total, progress)
        salvaged = bag.salvaged
    for topic, acc in accs.items():
        if topic not in readable:
            acc.count = summary[topic].count  # refused: the bag's own count
    stats = tuple(_topic_stats(t, a) for t, a in accs.items())
    types = {t.topic: t.msgtype for t in stats}
    mapping = suggest_mapping(stats, _imu_up_z(imus))
    pair = _stereo_topics(rig, mapping, types)
    firsts = [a.first_log for a in accs.values() if a.first_log is not None]
    lasts = [a.last_log for a in accs.values() if a.last_log is not None]
    return BagReport(
        paths=tuple(path_list),
        ros_version=ros,
        salvaged=salvaged,
        message_count=sum(a.count for a in accs.values()),
        start_log_ns=min(firsts, default=None),
        end_log_ns=max(lasts, default=None),
        topics=stats,
        stereo=_stereo(*pair, accs) if pair else None,
        lidars=tuple(_lidar_coverage(t, a) for t, a in sweeps.items()),
        mapping=mapping,
        rig_problems=check_rig(rig, types) if rig is not None else None,
    )
