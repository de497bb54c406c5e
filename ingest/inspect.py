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
  field of view, sensor frame) hit by its non-zero points; medians over sweeps;
  and where the per-point times come from (field, type, unit, base, driver:
  `ingest.bags.point_time`). A sweep whose point times fit no known layout
  counts as undecodable, with the error naming the field and its values.
- `TopicMapping`: image topics named upper/top/left or lower/bottom/right
  become cam0 (upper) and cam1 (lower); LiDARs (PointCloud2, Livox CustomMsg)
  and IMUs are paired by the livox_ros_driver2 multi_topic names
  `lidar_<ip>`/`imu_<ip>`; a LiDAR whose IMU's mean specific force (the
  reaction to gravity) points along +z is named `lidar_top` (upright), along
  -z `lidar_bottom` (mounted upside down); otherwise LiDARs are named by IP.
- Corrupt chunks (a CRC mismatch, data that does not decompress): an error
  naming the bag, the chunk's log-time range and its messages per topic;
  with `salvage` they are skipped, listed (`BagReport.lost_chunks`) and their
  messages counted per topic (`TopicStats.lost`).
- With a rig: its camera, LiDAR and IMU topics missing from the bags or of
  the wrong message type (`RigProblem`).
"""

from __future__ import annotations

import dataclasses
from array import array
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from calibration.rig import Rig
from ingest.bag_report import (
    BagReport,
    LidarCoverage,
    MappedSensor,
    RigProblem,
    StereoReport,
    TopicMapping,
    TopicStats,
)
from ingest.bags.decode import ImuSample, RosVersion, Sweep, decode, header_stamp_ns
from ingest.bags.reader import READAHEAD_THREADS, BagSet, RawMessage, open_bags
from ingest.bags.rostypes import typestore as sensorbox_typestore
from ingest.errors import BagError, MessageDecodeError
from ingest.runtime.executor import usable_cpus
from ingest.topic_map import IMU_TYPES, LIDAR_TYPES, check_rig, stereo_topics, suggest_mapping
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


Progress = Callable[[int, int], None]
"""Called with (messages read, messages in total)."""


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
    time_layouts: dict[str, None] = field(default_factory=dict)  # insertion-ordered set
    first_point_ns: int | None = None
    last_point_ns: int | None = None
    late_points: int = 0


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
    stamps = sweep.stamps_ns if sweep.late is None else sweep.stamps_ns[~sweep.late]
    acc.late_points += len(sweep.stamps_ns) - len(stamps)  # times no sweep has (the decoder's verdict)
    acc.durations_ms.append(float(stamps.max() - stamps.min()) / 1e6 if len(stamps) else 0.0)
    if len(stamps):
        a, b = int(stamps.min()), int(stamps.max())
        acc.first_point_ns = a if acc.first_point_ns is None else min(acc.first_point_ns, a)
        acc.last_point_ns = b if acc.last_point_ns is None else max(acc.last_point_ns, b)
    acc.coverage.append(hit / (N_AZ * N_EL))
    acc.time_layouts[sweep.time_layout] = None
    if len(el):
        acc.el_min = min(acc.el_min, float(el.min()))
        acc.el_max = max(acc.el_max, float(el.max()))


def _add_imu(acc: _ImuAcc, msg: RawMessage) -> None:
    """Add the unit specific force of one IMU message (unit-agnostic: g or m/s^2)."""
    sample = decode(msg.msgtype, msg.data(), msg.ros_version)
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
    for msg in bag.messages(topics=list(topics), readahead=min(READAHEAD_THREADS, usable_cpus())):
        acc = topics[msg.topic]
        acc.count += 1
        acc.first_log = msg.log_ns if acc.first_log is None else acc.first_log
        acc.last_log = msg.log_ns
        if acc.stamped:
            try:
                stamp = header_stamp_ns(msg.data(), msg.ros_version)
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
            sweep = decode(msg.msgtype, msg.data(), msg.ros_version)
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
    layouts = " | ".join(acc.time_layouts)
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
        time_layout=layouts or None,
        first_point_ns=acc.first_point_ns,
        last_point_ns=acc.last_point_ns,
        late_points=acc.late_points,
        points_total=total,
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


def _imu_up_z(imus: dict[str, _ImuAcc]) -> dict[str, float]:
    """z of the normalised mean unit specific force per IMU topic (+1: sensor z points up)."""
    out = {}
    for topic, acc in imus.items():
        norm = float(np.linalg.norm(acc.total))
        if acc.n and norm > 0:
            out[topic] = float(acc.total[2] / norm)
    return out


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
    cameras and `rig_problems` lists its topics the bags lack, carry with
    the wrong type or declare without a message. `progress(done, total)`
    is called while reading.
    Raises `BagError` when a bag cannot be opened or read (`CorruptChunkError`
    at a corrupt chunk unless `salvage`, which skips it and reports it in
    `lost_chunks` and `TopicStats.lost`); a topic whose type cannot be decoded
    safely is reported (`TopicStats.error`), not read.
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
        salvaged, lost_chunks, lost = bag.salvaged, bag.lost_chunks, bag.lost_counts()
        span = bag.log_span_ns()  # topics refused as undecodable count towards the duration too
    for topic, acc in accs.items():
        if topic not in readable:
            acc.count = summary[topic].count  # refused: the bag's own count
    stats = tuple(dataclasses.replace(_topic_stats(t, a), lost=lost.get(t, 0)) for t, a in accs.items())
    types = {t.topic: t.msgtype for t in stats}
    mapping = suggest_mapping(stats, _imu_up_z(imus))
    pair = stereo_topics(rig, mapping, types)
    firsts = [a.first_log for a in accs.values() if a.first_log is not None] + ([span[0]] if span else [])
    lasts = [a.last_log for a in accs.values() if a.last_log is not None] + ([span[1]] if span else [])
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
        rig_problems=check_rig(rig, types, {t.topic: t.count for t in stats}) if rig is not None else None,
        lost_chunks=lost_chunks,
    )
