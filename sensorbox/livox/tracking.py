"""Per-lidar bookkeeping of the driver: its receive state, udp_cnt unwrapped with lost, duplicate
and reordered packets and counter jumps counted exactly, and native-unit points turned into metres."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from calibration.types import F64, I64
from sensorbox.livox import packets
from sensorbox.livox.config import DriverConfig, Extrinsic, LidarEndpoint, LidarStats, imu_topic, lidar_topic

POINT_PERIOD_NS = 480_000  # the Mid-360's time between point packets (96 points at 200 kHz)
IMU_PERIOD_NS = 5_000_000  # between IMU packets (200 Hz)
TIME_JUMP_NS = 20_000_000  # slack of the clock comparisons below: network jitter and reordering stay
# far below it, and a spoofed clock within it moves framing by at most this much
RATE_SLACK = 4  # the packet clock may run this much faster than arrivals (emulators beyond real time)


def clock_leapt(d_pkt_ns: int, d_recv_ns: int) -> bool:
    """Whether the packet clock leapt (ahead or back) between two packets that arrived d_recv_ns apart.

    A sender catching up after a stall only moves the arrival clock ahead; it never leaps."""
    return d_pkt_ns > RATE_SLACK * d_recv_ns + TIME_JUMP_NS or d_pkt_ns < -TIME_JUMP_NS


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
    newest are remembered, so a repeat among them is a duplicate.

    With packet times (`dev_ns`, the packet clock, and `wall_ns`, the arrival
    clock) each packet is checked against the newest one: a real gap of d
    packets moves the packet clock by about d periods (`consistent`). Where the
    two disagree, the arrival clock says which one leapt: the packet clock, if
    it leapt against arrivals too (`clock_leapt`: a time jump, `last_leapt`), else
    the counter. A counter leap past `JUMP_SLACK` packets, or back past `WINDOW`
    (a restarted counter), is a jump (`jumps`), not loss: counting continues
    as if the packet followed the newest one, it is kept, `lost` is not
    inflated and nothing after it is dropped. A gap past half the counter range
    is unwrapped by the packet clock. Without times only the leap back is seen;
    with arrival stamps only (unsynced, dev_ns == wall_ns) a leap ahead is one
    past what `RATE_SLACK` times the arrival gap allows.
    """

    WINDOW = 4096
    JUMP_SLACK = 64  # packets: a gap this small is always plausible loss

    def __init__(self, period_ns: int = POINT_PERIOD_NS) -> None:
        self.period_ns = period_ns
        self.lowest: int | None = None
        self.highest = 0
        self.seen: set[int] = set()
        self.unique = 0
        self.duplicates = 0
        self.reordered = 0
        self.jumps = 0
        self.last_leapt = False  # the packet clock of the last packet added leapt (a time jump)
        self._counter = 0  # the lidar's unwrapped counter of the packet at `highest`
        self._shift = 0  # seq = unwrapped counter + shift (moved by each jump)
        self._times: tuple[int, int] | None = None  # (packet clock, arrival) of the packet at `highest`

    @property
    def lost(self) -> int:
        span = 0 if self.lowest is None else self.highest - self.lowest + 1
        return span - self.unique

    def consistent(self, d: int, d_dev_ns: int) -> bool:
        """Whether a counter step of d packets fits a packet-clock step of d_dev_ns (25 % + 20 ms)."""
        return abs(d_dev_ns - d * self.period_ns) <= TIME_JUMP_NS + abs(d) * self.period_ns // 4

    def _leaps(self, d: int, dev_ns: int | None, wall_ns: int | None) -> tuple[int, bool, bool]:
        """(d unwrapped, counter leapt, clock leapt) for a packet d counters after the newest."""
        if dev_ns is None or wall_ns is None or self._times is None:
            return d, d <= -self.WINDOW, False
        d_dev, d_wall = dev_ns - self._times[0], wall_ns - self._times[1]
        if dev_ns == wall_ns:  # unsynced: stamped on arrival, whose gaps say little; only leaps past them
            limit = self.JUMP_SLACK + RATE_SLACK * max(0, d_wall) // self.period_ns
            return d, d <= -self.WINDOW or d > limit, False
        clock = clock_leapt(d_dev, d_wall)
        if d_dev > 0 and not clock:  # a gap past half the counter range: unwrapped by the packet clock
            d += 0x10000 * max(0, round((d_dev // self.period_ns - d) / 0x10000))
        if self.consistent(d, d_dev):
            return d, False, False
        return d, d <= -self.WINDOW or d > self.JUMP_SLACK or (d > 0 and not clock), clock

    def add(self, cnt: int, dev_ns: int | None = None, wall_ns: int | None = None) -> int | None:
        """Record one udp_cnt with the packet's time and arrival time (ns, optional): its sequence
        number when new (keep the packet), else None (a duplicate)."""
        if self.lowest is None:
            self._counter = cnt
            self.lowest = self.highest = cnt + self._shift
            self.seen = {self.lowest}
            self.unique = 1
            self._times = None if dev_ns is None or wall_ns is None else (dev_ns, wall_ns)
            self.last_leapt = False
            return self.lowest
        d, counter_leapt, self.last_leapt = self._leaps(
            ((cnt - self._counter + 0x8000) & 0xFFFF) - 0x8000, dev_ns, wall_ns
        )
        if counter_leapt and (d > 1 or d <= -self.WINDOW):
            self.jumps += 1
            self._shift += self.highest + 1 - (self._counter + d + self._shift)
        seq = self._counter + d + self._shift
        if seq > self.highest:
            self.highest, self._counter = seq, self._counter + d
            self._times = None if dev_ns is None or wall_ns is None else (dev_ns, wall_ns)
            self.seen.add(seq)
            self.unique += 1
            if len(self.seen) > 2 * self.WINDOW:
                floor = seq - self.WINDOW
                self.seen = {s for s in self.seen if s > floor}
            return seq
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
        self.points_seq = SeqTracker(POINT_PERIOD_NS)
        self.imu_seq = SeqTracker(IMU_PERIOD_NS)
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
            duplicates=p.duplicates, reordered=p.reordered, counter_jumps=p.jumps,
            imu_lost=i.lost, imu_duplicates=i.duplicates, imu_counter_jumps=i.jumps,
        )  # fmt: skip

    def malformed(self, reason: str, count: int = 1) -> None:
        self.stats.malformed += count
        by = self.stats.malformed_by_reason
        by[reason] = by.get(reason, 0) + count
