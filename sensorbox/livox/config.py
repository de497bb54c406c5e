"""What the Mid-360 driver is told (`DriverConfig`, a `LidarEndpoint` per lidar), what it reports
(`DriverStats`, a `LidarStats` per lidar), and the topics it publishes on."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from sensorbox.errors import DriverError
from sensorbox.livox import packets
from sensorbox.livox.protocol import Ports

Extrinsic = tuple[float, float, float, float, float, float]


@dataclass(frozen=True)
class LidarEndpoint:
    """One Mid-360 to configure and listen to."""

    ip: str  # e.g. "192.168.1.12" or "127.0.0.2"
    extrinsic: Extrinsic | None = None  # roll, pitch, yaw deg; x, y, z mm (livox_ros_driver2 convention)
    topic_ip: str | None = None  # IP named in the topics (default `ip`): an emulator on 127.0.0.12 can
    # then publish the rig's /livox/lidar_192_168_1_12


@dataclass(frozen=True)
class DriverConfig:
    """Everything the driver needs; the defaults are livox_ros_driver2's (msg_MID360 launch)."""

    host_ip: str  # the address the driver binds and announces to the lidars
    lidars: tuple[LidarEndpoint, ...]
    msg_format: Literal["custom", "pointcloud2"] = "custom"
    ros_version: Literal[1, 2] = 2
    publish_interval_ns: int = 100_000_000
    multi_topic: bool = True  # /livox/lidar_192_168_1_12 instead of /livox/lidar
    imu: bool = True
    data_type: int = packets.DATA_TYPE_CARTESIAN_HIGH
    ports: Ports = field(default_factory=Ports)
    discovery_address: str = "255.255.255.255"
    command_timeout_s: float = 0.5  # per try
    command_retries: int = 3  # tries after the first
    reorder_slack_ns: int = 2_000_000  # how long past a sweep's end late packets may still join it
    idle_flush_s: float = 0.25  # publish open sweeps of a lidar silent this long
    rcvbuf_bytes: int = 8 << 20
    batch_wait_s: float = 0.02  # after a datagram wakes the point thread, let more arrive: one numpy
    # batch per 20 ms instead of one per packet (bench_livox: 7 % instead of 37 % of a core for two
    # real-time Mid-360s); unsynced stamps still use each datagram's kernel arrival time
    check_crc: bool = True  # verify the data packets' CRC-32 (the SDK does not)

    def validate(self) -> None:
        if not self.lidars:
            raise DriverError("DriverConfig.lidars is empty: name at least one lidar IP")
        ips = [li.ip for li in self.lidars]
        if len(set(ips)) != len(ips):
            raise DriverError(f"DriverConfig.lidars lists an IP twice: {ips}")
        if not self.multi_topic and len(ips) > 1:
            raise DriverError(
                f"multi_topic 0 with {len(ips)} lidars ({', '.join(ips)}) publishes every lidar on "
                "/livox/lidar and every IMU on /livox/imu, one stream no rig can tell apart; set "
                "multi_topic 1 (/livox/lidar_<ip>)"
            )
        if self.host_ip in ips:
            raise DriverError(f"host_ip {self.host_ip} equals a lidar IP (the SDK drops such datagrams)")
        if self.data_type not in packets.POINT_DTYPES:
            raise DriverError(f"data_type {self.data_type}: expected 1 (mm), 2 (10 mm) or 3 (spherical)")
        if not 10_000_000 <= self.publish_interval_ns <= 2_000_000_000:
            raise DriverError(
                f"publish_interval_ns {self.publish_interval_ns}: expected 10 ms..2 s "
                "(publish_freq 0.5..100 Hz)"
            )
        if self.msg_format not in ("custom", "pointcloud2"):
            raise DriverError(f"msg_format {self.msg_format!r}: expected 'custom' or 'pointcloud2'")
        if self.ros_version not in (1, 2):
            raise DriverError(f"ros_version {self.ros_version}: expected 1 or 2")


@dataclass
class LidarStats:
    """Counters of one lidar since `start()`; packets/points count what was kept and published."""

    ip: str
    packets: int = 0  # valid point packets kept (not duplicates, not late)
    points: int = 0  # points in published sweeps
    lost: int = 0  # point packets missing by udp_cnt
    duplicates: int = 0  # dropped repeats of an udp_cnt already seen
    reordered: int = 0  # packets that arrived after a later udp_cnt (kept)
    late: int = 0  # packets whose sweep was already published (dropped)
    malformed: int = 0  # from this lidar's point/IMU ports, dropped
    malformed_by_reason: dict[str, int] = field(default_factory=dict)
    imu_packets: int = 0
    imu_lost: int = 0
    imu_duplicates: int = 0  # IMU datagrams whose udp_cnt was seen already, dropped
    point_datagrams: int = 0  # every datagram taken from this lidar's point port, whatever became of it
    imu_datagrams: int = 0  # every datagram taken from this lidar's IMU port
    sweeps: int = 0  # published
    unsynced: bool | None = None  # True while packets arrive with time_type 0 (host-clock stamps)
    time_type: int | None = None  # of the newest packet
    time_jumps: int = 0  # the packet clock leapt against the arrival clock (> 1 s): framing restarted
    counter_jumps: int = 0  # udp_cnt leapt where no real gap could be: counted here, not as lost (kept)
    imu_counter_jumps: int = 0  # the same on the IMU port
    pushes: int = 0  # 0x0102 status pushes received
    work_state: int | None = None  # key 0x8006 of the newest push

    def unaccounted_point_datagrams(self) -> int:
        """point_datagrams minus every outcome (kept, duplicate, late, malformed): 0 when balanced."""
        malformed = sum(n for r, n in self.malformed_by_reason.items() if r in packets.REJECT_REASONS)
        return self.point_datagrams - (self.packets + self.duplicates + self.late + malformed)

    def unaccounted_imu_datagrams(self) -> int:
        """imu_datagrams minus every outcome (kept, duplicate, malformed): 0 when the books balance."""
        return self.imu_datagrams - (
            self.imu_packets + self.imu_duplicates + self.malformed_by_reason.get("imu", 0)
        )


@dataclass
class DriverStats:
    lidars: dict[str, LidarStats]
    foreign: int = 0  # datagrams from addresses/ports that are no configured lidar's
    foreign_sources: dict[str, int] = field(default_factory=dict)  # "ip:port" -> datagrams
    rcvbuf_bytes: int = 0  # the point socket's kernel buffer (SO_RCVBUF as granted)
    kernel_drops: int = 0  # point datagrams the host kernel dropped (buffer full): part of `lost`


def topic_suffix(ip: str) -> str:
    return ip.replace(".", "_")


def lidar_topic(ip: str, multi_topic: bool) -> str:
    return f"/livox/lidar_{topic_suffix(ip)}" if multi_topic else "/livox/lidar"


def imu_topic(ip: str, multi_topic: bool) -> str:
    return f"/livox/imu_{topic_suffix(ip)}" if multi_topic else "/livox/imu"
