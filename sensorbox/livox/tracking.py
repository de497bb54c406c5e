"""Per-lidar bookkeeping of the driver: its receive state, udp_cnt unwrapped with lost, duplicate,
reordered and stale packets counted exactly, and native-unit points turned into metres."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from calibration.types import F64, I64
from sensorbox.livox import packets
from sensorbox.livox.config import DriverConfig, Extrinsic, LidarEndpoint, LidarStats, imu_topic, lidar_topic


def extrinsic_rotation(roll_deg: float, pitch_deg: float, yaw_deg: float) -> F64:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (livox_ros_driver2), angles in degrees."""
    r, p, y = np.radians([roll_deg, pitch_deg, yaw_deg])
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array(
        [
            [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
            [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
            [-sp, sr * cp, cr * cp],
        ]
    )


def to_metres(data_type: int, xyz_native: F64, extrinsic: Extrinsic | None = None) -> F64:
    """Native coordinates (..., 3) -> metres, applying p' = R p + t in the native unit first.

    The extrinsic is (roll, pitch, yaw deg; x, y, z mm), R = Rz(yaw) Ry(pitch)
    Rx(roll), t // 10 for data type 2 and t / 1000 for spherical points, as
    livox_ros_driver2 does.
    """
    if extrinsic is not None:
        R = extrinsic_rotation(*extrinsic[:3])
        t_mm = np.asarray(extrinsic[3:], np.float64)
        if data_type == packets.DATA_TYPE_CARTESIAN_LOW:
            t = np.trunc(np.round(t_mm) / 10.0)  # the driver's integer division to 10 mm
        elif data_type == packets.DATA_TYPE_SPHERICAL:
            t = t_mm / 1000.0
        else:
            t = t_mm
        x, y, z = xyz_native[..., 0], xyz_native[..., 1], xyz_native[..., 2]
        xyz_native = np.stack(
            [R[i, 0] * x + R[i, 1] * y + R[i, 2] * z + t[i] for i in range(3)], axis=-1
        )  # component arithmetic: no tall BLAS matmul on the hot path
    out: F64 = xyz_native / packets.UNIT_DIVISOR[data_type]
    return out


class SeqTracker:
    """Unwraps a 16-bit udp_cnt and counts lost, duplicate and reordered packets exactly.

    lost = (highest - lowest + 1) - unique packets seen, so a reordered packet
    first counts as lost and then fills its gap. Counters within `WINDOW` of the
    newest are remembered; an older one cannot be told apart from a duplicate and
    is dropped as stale; a run of `RESET_RUN` stale ones means the lidar restarted
    its counter, and counting restarts (the loss so far is kept).
    """

    WINDOW = 4096
    RESET_RUN = 16

    def __init__(self) -> None:
        self.lowest: int | None = None
        self.highest = 0
        self.seen: set[int] = set()
        self.unique = 0
        self.duplicates = 0
        self.reordered = 0
        self.stale = 0
        self.resets = 0
        self._stale_run = 0
        self._lost_before = 0
        self._offset = 0

    @property
    def lost(self) -> int:
        span = 0 if self.lowest is None else self.highest - self.lowest + 1
        return self._lost_before + span - self.unique

    def add(self, cnt: int) -> int | None:
        """Record one udp_cnt: its unwrapped sequence number when new (keep the packet), else None."""
        if self.lowest is None:
            self.lowest = self.highest = self._offset + cnt
            self.seen = {self.lowest}
            self.unique = 1
            return self.lowest
        d = ((cnt - self.highest + 0x8000) & 0xFFFF) - 0x8000
        seq = self.highest + d
        if d > 0:
            self.highest = seq
            self._stale_run = 0
            self.seen.add(seq)
            self.unique += 1
            if len(self.seen) > 2 * self.WINDOW:
                floor = seq - self.WINDOW
                self.seen = {s for s in self.seen if s > floor}
            return seq
        if seq <= self.highest - self.WINDOW:
            self.stale += 1
            self._stale_run += 1
            if self._stale_run < self.RESET_RUN:
                return None
            self.stale -= 1  # this one starts the new count
            self._lost_before = self.lost
            self.resets += 1
            self.lowest = None
            self._stale_run = 0
            self._offset = (self.highest // 0x10000 + 1) * 0x10000  # keep sequence numbers increasing
            return self.add(cnt)
        if seq in self.seen:
            self.duplicates += 1
            return None
        self.seen.add(seq)
        self.unique += 1
        self.reordered += 1
        self.lowest = min(self.lowest, seq)
        return seq


@dataclass
class Chunk:
    """Consecutive packets of one lidar that fall into one sweep, decoded."""

    seq: I64  # unwrapped udp_cnt of each packet: the lidar's emission order
    stamps_ns: I64  # (packets * dot_num,)
    xyz_m: np.ndarray[Any, np.dtype[np.float32]]  # (n, 3)
    reflectivity: np.ndarray[Any, np.dtype[np.uint8]]
    tag: np.ndarray[Any, np.dtype[np.uint8]]
    line: np.ndarray[Any, np.dtype[np.uint8]]


class LidarState:
    """Per-lidar receive state: sequence trackers, open sweeps, counters."""

    def __init__(self, endpoint: LidarEndpoint, cfg: DriverConfig) -> None:
        self.endpoint = endpoint
        self.ip = endpoint.ip
        self.stats = LidarStats(endpoint.ip)
        self.points_seq = SeqTracker()
        self.imu_seq = SeqTracker()
        self.frames: dict[int, list[Chunk]] = {}
        self.published_key: int | None = None
        self.newest_ns: int | None = None
        self.last_packet_wall = 0.0
        self.lidar_id = int(endpoint.ip.split(".")[0])  # (uint8) inet_addr(ip): the first octet
        self.topic = lidar_topic(endpoint.topic_ip or endpoint.ip, cfg.multi_topic)
        self.imu_topic = imu_topic(endpoint.topic_ip or endpoint.ip, cfg.multi_topic)
        self.cmd_port = cfg.ports.lidar_cmd

    def snapshot(self) -> LidarStats:
        """A copy of the counters with the sequence trackers' counts filled in (call under the lock)."""
        p, i = self.points_seq, self.imu_seq
        return replace(
            self.stats, malformed_by_reason=dict(self.stats.malformed_by_reason), lost=p.lost,
            duplicates=p.duplicates, reordered=p.reordered, stale=p.stale, counter_resets=p.resets,
            imu_lost=i.lost, imu_duplicates=i.duplicates + i.stale,
        )  # fmt: skip

    def malformed(self, reason: str, count: int = 1) -> None:
        self.stats.malformed += count
        by = self.stats.malformed_by_reason
        by[reason] = by.get(reason, 0) + count
