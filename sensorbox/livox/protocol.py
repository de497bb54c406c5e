"""The Livox Mid-360 wire protocol (Livox-SDK2, ethernet protocol v1.4): bytes in, bytes out.

Pure functions and dataclasses, no sockets; the driver and the emulator both
build on them. Everything on the wire is little-endian (notes/livox.md section 2):

- Control frames (`SdkPacket`): 24-byte header (sof 0xAA, version 0, length,
  seq, cmd_id, cmd_type, sender_type, 6 reserved, CRC-16/CCITT-FALSE of bytes
  0..17, CRC-32 of the payload or 0 when it is empty) and a payload; the
  set/query/push commands carry a key/value list.
- Data packets (`LivoxLidarEthernetPacket`): 36-byte header (version, length,
  time_interval in 0.1 us, dot_num, udp_cnt, frame_cnt, data_type, time_type,
  12 reserved, CRC-32 of bytes 28..end, u64 timestamp in ns) and `dot_num`
  points of data type 1 (int32 mm), 2 (int16 cm) or 3 (spherical), or one IMU
  sample (data type 0).

Data packets are decoded in batches: datagrams sit in fixed-size slots of one
receive buffer and a structured dtype with the slot as its item size views every
header at once, so validation and point decoding are a few numpy operations per
batch instead of per point (or per packet).
"""

from __future__ import annotations

import ipaddress
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np

from calibration.types import F64, I64, U8, Structured
from sensorbox.errors import ProtocolError

# ----------------------------------------------------------------------------- ports


@dataclass(frozen=True)
class Ports:
    """UDP ports of both ends (Livox-SDK2 define.h); override them so parallel tests do not collide.

    The host sends commands from `host_cmd` to the lidar's `lidar_cmd`; the lidar
    streams points from `lidar_point` to the host's `host_point`, IMU from
    `lidar_imu` to `host_imu` and status pushes from `lidar_push` to `host_push`.
    Discovery uses `discovery` on both ends.
    """

    discovery: int = 56000
    lidar_cmd: int = 56100
    host_cmd: int = 56101
    lidar_push: int = 56200
    host_push: int = 56201
    lidar_point: int = 56300
    host_point: int = 56301
    lidar_imu: int = 56400
    host_imu: int = 56401

    @classmethod
    def block(cls, base: int) -> Ports:
        """Nine consecutive ports starting at `base` (tests: one block per test, none shared)."""
        return cls(*range(base, base + 9))


# ----------------------------------------------------------------------------- CRCs


def _crc16_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC16 = _crc16_table()


def crc16_ccitt_false(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, xorout 0 ("123456789" -> 0x29B1)."""
    crc = 0xFFFF
    for b in bytes(data):
        crc = ((crc << 8) & 0xFFFF) ^ _CRC16[(crc >> 8) ^ b]
    return crc


def crc32(data: bytes | bytearray | memoryview) -> int:
    """The standard (zlib, ISO-HDLC) CRC-32 ("123456789" -> 0xCBF43926)."""
    return zlib.crc32(data) & 0xFFFFFFFF


# ----------------------------------------------------------------------------- control frames

SOF = 0xAA
CONTROL_HEADER = struct.Struct("<BBHIHBB6sHI")
CONTROL_HEADER_SIZE = CONTROL_HEADER.size  # 24
MAX_CONTROL_SIZE = 1400

CMD_DISCOVERY = 0x0000
CMD_SET_PARAMS = 0x0100
CMD_QUERY_PARAMS = 0x0101
CMD_PUSH = 0x0102
CMD_REBOOT = 0x0200
REQ, ACK = 0, 1
SENDER_HOST, SENDER_LIDAR = 0, 1

KEY_PCL_DATA_TYPE = 0x0000
KEY_PATTERN_MODE = 0x0001
KEY_LIDAR_IP = 0x0004
KEY_STATE_HOST = 0x0005
KEY_POINT_HOST = 0x0006
KEY_IMU_HOST = 0x0007
KEY_INSTALL_ATTITUDE = 0x0012
KEY_WORK_MODE = 0x001A
KEY_IMU_DATA_EN = 0x001C
KEY_SN = 0x8000
KEY_PRODUCT = 0x8001
KEY_FIRMWARE = 0x8002
KEY_WORK_STATE = 0x8006
KEY_CORE_TEMP = 0x8007
KEY_TIME_OFFSET = 0x800B
KEY_SYNC_TYPE = 0x800C

WORK_MODE_NORMAL = 0x01  # SAMPLING: points and IMU flow
WORK_MODE_IDLE = 0x02  # IDLE / standby
DEV_TYPE_MID360 = 9
DEV_TYPE_MID360S = 35

RET_CODES = {
    0x00: "success",
    0x01: "failure",
    0x02: "not allowed in the current state",
    0x03: "value out of range",
    0x20: "parameter error 0x20",
    0x21: "parameter error 0x21",
    0x22: "parameter error 0x22",
    0x23: "parameter error 0x23",
    0x24: "parameter error 0x24",
}


@dataclass(frozen=True)
class ControlFrame:
    """One control command or its ACK; `seq` is echoed by the ACK (the SDK masks it to 16 bits)."""

    cmd_id: int
    cmd_type: int  # REQ or ACK
    sender_type: int  # SENDER_HOST or SENDER_LIDAR
    seq: int
    payload: bytes = b""


def build_control_frame(frame: ControlFrame) -> bytes:
    """Serialise `frame` with both CRCs (CRC-32 is 0 for an empty payload, as the SDK writes it)."""
    length = CONTROL_HEADER_SIZE + len(frame.payload)
    if length > MAX_CONTROL_SIZE:
        raise ProtocolError(f"control frame of {length} bytes exceeds the {MAX_CONTROL_SIZE}-byte maximum")
    head = struct.pack(
        "<BBHIHBB6s", SOF, 0, length, frame.seq & 0xFFFF, frame.cmd_id, frame.cmd_type, frame.sender_type,
        b"\0" * 6,
    )  # fmt: skip
    payload_crc = crc32(frame.payload) if frame.payload else 0
    return head + struct.pack("<HI", crc16_ccitt_false(head), payload_crc) + frame.payload


def parse_control_frame(raw: bytes | bytearray | memoryview) -> ControlFrame:
    """Check sof, version, length and both CRCs (as the SDK's CheckPreamble does), then split."""
    data = bytes(raw)
    if len(data) < CONTROL_HEADER_SIZE:
        raise ProtocolError(f"control frame of {len(data)} bytes is shorter than its 24-byte header")
    sof, version, length, seq, cmd_id, cmd_type, sender, _rsvd, crc16, crc32_d = CONTROL_HEADER.unpack_from(
        data
    )
    if sof != SOF or version != 0:
        raise ProtocolError(f"control frame starts {sof:#04x} version {version}, expected 0xaa version 0")
    if length != len(data):
        raise ProtocolError(f"control frame length field {length} != datagram size {len(data)}")
    if crc16 != crc16_ccitt_false(data[:18]):
        raise ProtocolError(
            f"control frame header CRC-16 {crc16:#06x} != {crc16_ccitt_false(data[:18]):#06x}"
        )
    payload = data[CONTROL_HEADER_SIZE:]
    want = crc32(payload) if payload else 0
    if crc32_d != want:
        raise ProtocolError(f"control frame payload CRC-32 {crc32_d:#010x} != {want:#010x}")
    return ControlFrame(cmd_id, cmd_type, sender, seq, payload)


# ----------------------------------------------------------------------------- key/value lists

KV = tuple[int, bytes]


def encode_kv_list(items: Sequence[KV]) -> bytes:
    """key_num u16, rsvd u16, then per key: key u16, length u16, value (0x0100 and 0x0102 payloads)."""
    out = [struct.pack("<HH", len(items), 0)]
    for key, value in items:
        out.append(struct.pack("<HH", key, len(value)) + value)
    return b"".join(out)


def _decode_kv(data: bytes, pos: int, count: int) -> list[KV]:
    items = []
    for k in range(count):
        if pos + 4 > len(data):
            raise ProtocolError(f"key/value list ends inside entry {k} of {count} (at byte {pos})")
        key, n = struct.unpack_from("<HH", data, pos)
        if pos + 4 + n > len(data):
            raise ProtocolError(f"key {key:#06x} says {n} bytes but only {len(data) - pos - 4} remain")
        items.append((key, data[pos + 4 : pos + 4 + n]))
        pos += 4 + n
    if pos != len(data):
        raise ProtocolError(f"{len(data) - pos} bytes left after {count} key/value entries")
    return items


def decode_kv_list(payload: bytes) -> list[KV]:
    """Inverse of `encode_kv_list`; raises ProtocolError on a count or length that does not fit."""
    if len(payload) < 4:
        raise ProtocolError(f"key/value payload of {len(payload)} bytes is shorter than its 4-byte head")
    (count,) = struct.unpack_from("<H", payload)
    return _decode_kv(payload, 4, count)


def encode_query(keys: Sequence[int]) -> bytes:
    """0x0101 request: key_num u16, rsvd u16, then the u16 keys."""
    return struct.pack(f"<HH{len(keys)}H", len(keys), 0, *keys)


def decode_query(payload: bytes) -> list[int]:
    if len(payload) < 4:
        raise ProtocolError(f"query payload of {len(payload)} bytes is shorter than its 4-byte head")
    (count,) = struct.unpack_from("<H", payload)
    if len(payload) != 4 + 2 * count:
        raise ProtocolError(f"query of {count} keys needs {4 + 2 * count} bytes, got {len(payload)}")
    return list(struct.unpack_from(f"<{count}H", payload, 4))


def encode_set_ack(ret_code: int, error_key: int = 0) -> bytes:
    """0x0100 ACK: ret_code u8, error_key u16 (the first key that failed)."""
    return struct.pack("<BH", ret_code, error_key)


def decode_set_ack(payload: bytes) -> tuple[int, int]:
    if len(payload) != 3:
        raise ProtocolError(f"set-parameter ACK of {len(payload)} bytes, expected 3 (ret_code, error_key)")
    ret, key = struct.unpack("<BH", payload)
    return ret, key


def encode_query_ack(ret_code: int, items: Sequence[KV]) -> bytes:
    """0x0101 ACK: ret_code u8, key_num u16, then the key/value entries."""
    return struct.pack("<BH", ret_code, len(items)) + encode_kv_list(items)[4:]


def decode_query_ack(payload: bytes) -> tuple[int, list[KV]]:
    if len(payload) < 3:
        raise ProtocolError(f"query ACK of {len(payload)} bytes is shorter than its 3-byte head")
    ret, count = struct.unpack_from("<BH", payload)
    return ret, _decode_kv(payload, 3, count)


def host_address_value(ip: str, host_port: int, lidar_port: int) -> bytes:
    """Keys 0x0005/0x0006/0x0007: host IP u8[4] (dotted order), host port u16, lidar port u16."""
    return ipaddress.IPv4Address(ip).packed + struct.pack("<HH", host_port, lidar_port)


def decode_host_address(value: bytes) -> tuple[str, int, int]:
    if len(value) != 8:
        raise ProtocolError(f"host address value of {len(value)} bytes, expected 8")
    host_port, lidar_port = struct.unpack_from("<HH", value, 4)
    return str(ipaddress.IPv4Address(value[:4])), host_port, lidar_port


def install_attitude_value(extrinsic: tuple[float, float, float, float, float, float]) -> bytes:
    """Key 0x0012: roll, pitch, yaw float32 deg, then x, y, z int32 mm (stored, not applied, by the lidar)."""
    roll, pitch, yaw, x, y, z = extrinsic
    return struct.pack("<3f3i", roll, pitch, yaw, round(x), round(y), round(z))


def u8_value(value: int) -> bytes:
    return struct.pack("<B", value)


@dataclass(frozen=True)
class DeviceInfo:
    """A discovery ACK: what a lidar says about itself (serial, address, command port)."""

    ip: str
    serial: str
    dev_type: int = DEV_TYPE_MID360
    cmd_port: int = 56100
    ret_code: int = 0


DISCOVERY_ACK = struct.Struct("<BB16s4sH")  # 24 bytes


def encode_discovery_ack(info: DeviceInfo) -> bytes:
    """ret_code u8, dev_type u8, sn char[16], lidar_ip u8[4], cmd_port u16."""
    sn = info.serial.encode()[:16].ljust(16, b"\0")
    ip = ipaddress.IPv4Address(info.ip).packed
    return DISCOVERY_ACK.pack(info.ret_code, info.dev_type, sn, ip, info.cmd_port)


def decode_discovery_ack(payload: bytes) -> DeviceInfo:
    if len(payload) != DISCOVERY_ACK.size:
        raise ProtocolError(f"discovery ACK of {len(payload)} bytes, expected {DISCOVERY_ACK.size}")
    ret, dev_type, sn, ip, port = DISCOVERY_ACK.unpack(payload)
    serial = sn.split(b"\0", 1)[0].decode(errors="replace")
    return DeviceInfo(str(ipaddress.IPv4Address(ip)), serial, dev_type, port, ret)


# ----------------------------------------------------------------------------- data packets

DATA_HEADER_SIZE = 36
TIME_INTERVAL_UNIT_NS = 100  # time_interval counts 0.1 us
DATA_TYPE_IMU = 0
DATA_TYPE_CARTESIAN_HIGH = 1
DATA_TYPE_CARTESIAN_LOW = 2
DATA_TYPE_SPHERICAL = 3
TIME_TYPE_NO_SYNC = 0
TIME_TYPE_PTP = 1
TIME_TYPE_GPS = 2
MID360_TIME_INTERVAL = 4750  # 475 us over 96 points: points 4947 ns apart
MID360_DOT_NUM = 96

_HEADER_FIELDS: list[tuple[str, str, int]] = [
    ("version", "u1", 0),
    ("length", "<u2", 1),
    ("time_interval", "<u2", 3),
    ("dot_num", "<u2", 5),
    ("udp_cnt", "<u2", 7),
    ("frame_cnt", "u1", 9),
    ("data_type", "u1", 10),
    ("time_type", "u1", 11),
    ("crc32", "<u4", 24),
    ("timestamp", "<u8", 28),
]


@cache
def header_dtype(itemsize: int = DATA_HEADER_SIZE) -> np.dtype[np.void]:
    """The 36-byte data header as a structured dtype; `itemsize` > 36 views headers of fixed-size slots."""
    return np.dtype(
        {
            "names": [n for n, _, _ in _HEADER_FIELDS],
            "formats": [f for _, f, _ in _HEADER_FIELDS],
            "offsets": [o for _, _, o in _HEADER_FIELDS],
            "itemsize": itemsize,
        }
    )


HEADER_DTYPE = header_dtype()
POINT_DTYPES: dict[int, np.dtype[np.void]] = {
    DATA_TYPE_CARTESIAN_HIGH: np.dtype(
        [("x", "<i4"), ("y", "<i4"), ("z", "<i4"), ("reflectivity", "u1"), ("tag", "u1")]
    ),  # 14 B, mm
    DATA_TYPE_CARTESIAN_LOW: np.dtype(
        [("x", "<i2"), ("y", "<i2"), ("z", "<i2"), ("reflectivity", "u1"), ("tag", "u1")]
    ),  # 8 B, 10 mm
    DATA_TYPE_SPHERICAL: np.dtype(
        [("depth", "<u4"), ("theta", "<u2"), ("phi", "<u2"), ("reflectivity", "u1"), ("tag", "u1")]
    ),  # 10 B: mm, zenith and azimuth in 0.01 deg
}
IMU_DTYPE = np.dtype(
    [
        ("gyro_x", "<f4"),
        ("gyro_y", "<f4"),
        ("gyro_z", "<f4"),
        ("acc_x", "<f4"),
        ("acc_y", "<f4"),
        ("acc_z", "<f4"),
    ]
)  # 24 B: rad/s and g
POINT_SIZES = np.zeros(256, np.int64)
for _t, _dt in POINT_DTYPES.items():
    POINT_SIZES[_t] = _dt.itemsize
UNIT_DIVISOR = {DATA_TYPE_CARTESIAN_HIGH: 1000.0, DATA_TYPE_CARTESIAN_LOW: 100.0, DATA_TYPE_SPHERICAL: 1.0}
"""Native coordinate unit -> metres, as livox_ros_driver2 divides (mm, 10 mm; spherical decodes to m)."""


def build_data_packet(
    data_type: int,
    time_type: int,
    timestamp_ns: int,
    udp_cnt: int,
    body: bytes,
    dot_num: int,
    time_interval: int = MID360_TIME_INTERVAL,
    frame_cnt: int = 0,
) -> bytes:
    """One point or IMU datagram with its CRC-32 over bytes 28..end (timestamp and data)."""
    tail = struct.pack("<Q", timestamp_ns) + body
    head = struct.pack(
        "<BHHHHBBB12s", 0, DATA_HEADER_SIZE + len(body), time_interval, dot_num, udp_cnt & 0xFFFF,
        frame_cnt, data_type, time_type, b"\0" * 12,
    )  # fmt: skip
    return head + struct.pack("<I", crc32(tail)) + tail


def build_point_packets(
    data_type: int,
    time_type: int,
    timestamps_ns: I64,
    udp_cnts: I64,
    points: Structured,
    time_interval: int = MID360_TIME_INTERVAL,
) -> U8:
    """Many equal-size point datagrams at once: `points` (P, dot_num) of `POINT_DTYPES[data_type]`.

    Returns a (P, 36 + dot_num * size) uint8 array, one datagram per row, CRCs filled in.
    """
    n_pk, dot_num = points.shape
    size = DATA_HEADER_SIZE + dot_num * POINT_DTYPES[data_type].itemsize
    out = np.zeros((n_pk, size), np.uint8)
    hdr = out[:, :DATA_HEADER_SIZE].view(HEADER_DTYPE)[:, 0]
    hdr["length"] = size
    hdr["time_interval"] = time_interval
    hdr["dot_num"] = dot_num
    hdr["udp_cnt"] = np.asarray(udp_cnts) & 0xFFFF
    hdr["data_type"] = data_type
    hdr["time_type"] = time_type
    hdr["timestamp"] = timestamps_ns
    out[:, DATA_HEADER_SIZE:] = np.ascontiguousarray(points).view(np.uint8).reshape(n_pk, -1)
    hdr["crc32"] = [zlib.crc32(row) for row in out[:, 28:]]
    return out


def build_imu_packet(time_type: int, timestamp_ns: int, udp_cnt: int, gyro_rad_s: F64, acc_g: F64) -> bytes:
    """One 60-byte IMU datagram: data_type 0, dot_num 1, gyro xyz rad/s then acc xyz g as float32."""
    body = struct.pack("<6f", *(float(v) for v in (*gyro_rad_s, *acc_g)))
    return build_data_packet(
        DATA_TYPE_IMU, time_type, timestamp_ns, udp_cnt, body, dot_num=1, time_interval=0
    )


def quantise_points(data_type: int, xyz_m: F64, reflectivity: U8, tag: U8) -> Structured:
    """Metric points (..., 3) as a lidar would send them in `data_type`; (0,0,0) stays all-zero.

    Cartesian: rounded to mm (1) or 10 mm (2). Spherical (3): depth in mm,
    zenith theta and azimuth phi (0..36000) in 0.01 deg.
    """
    out = np.zeros(xyz_m.shape[:-1], POINT_DTYPES[data_type])
    out["reflectivity"], out["tag"] = reflectivity, tag
    if data_type == DATA_TYPE_SPHERICAL:
        r = np.sqrt(np.einsum("...i,...i->...", xyz_m, xyz_m))
        safe = np.where(r > 0, r, 1.0)
        theta = np.degrees(np.arccos(np.clip(xyz_m[..., 2] / safe, -1.0, 1.0)))
        phi = np.degrees(np.arctan2(xyz_m[..., 1], xyz_m[..., 0])) % 360.0
        out["depth"] = np.rint(r * 1000)
        out["theta"] = np.where(r > 0, np.rint(theta * 100), 0)
        out["phi"] = np.where(r > 0, np.rint(phi * 100) % 36000, 0)
        return out
    scale = 1000.0 if data_type == DATA_TYPE_CARTESIAN_HIGH else 100.0
    info = np.iinfo(out.dtype["x"])
    for k, name in enumerate("xyz"):
        out[name] = np.clip(np.rint(xyz_m[..., k] * scale), info.min, info.max)
    return out


def point_times_ns(pkt_time_ns: I64, time_interval: I64, dot_num: I64, n_points: int) -> I64:
    """Per-point stamps (P, n_points) as livox_ros_driver2 computes them.

    Point i of a packet gets pkt_time + i * (time_interval * 100 // dot_num):
    integer division by dot_num (not dot_num - 1), so 4750 over 96 points gives
    4947 ns steps. `pkt_time_ns` is the packet timestamp when synced, else the
    host's receive time.
    """
    spacing = (np.asarray(time_interval, np.int64) * TIME_INTERVAL_UNIT_NS) // np.asarray(dot_num, np.int64)
    idx = np.arange(n_points, dtype=np.int64)
    out: I64 = np.asarray(pkt_time_ns, np.int64)[:, None] + spacing[:, None] * idx[None, :]
    return out


def native_xyz(data_type: int, points: Structured) -> F64:
    """Coordinates (..., 3) float64 in the data type's native unit (mm, 10 mm; metres for spherical)."""
    if data_type == DATA_TYPE_SPHERICAL:
        r = points["depth"] / 1000.0
        theta = points["theta"] / 100.0 / 180.0 * np.pi
        phi = points["phi"] / 100.0 / 180.0 * np.pi
        st = np.sin(theta)
        return np.stack([r * st * np.cos(phi), r * st * np.sin(phi), r * np.cos(theta)], axis=-1)
    return np.stack([points["x"], points["y"], points["z"]], axis=-1).astype(np.float64)


@dataclass(frozen=True)
class ImuPacket:
    udp_cnt: int
    time_type: int
    timestamp_ns: int
    gyro_rad_s: F64  # (3,)
    acc_g: F64  # (3,)


IMU_PACKET_SIZE = DATA_HEADER_SIZE + IMU_DTYPE.itemsize  # 60


def decode_imu_packet(raw: bytes | bytearray | memoryview, check_crc: bool = True) -> ImuPacket:
    """Validate and decode one 60-byte IMU datagram; raises ProtocolError naming the bad field."""
    if len(raw) != IMU_PACKET_SIZE:
        raise ProtocolError(f"IMU datagram of {len(raw)} bytes, expected {IMU_PACKET_SIZE}")
    h = np.frombuffer(raw, HEADER_DTYPE, count=1)[0]
    if h["version"] != 0 or h["length"] != IMU_PACKET_SIZE:
        raise ProtocolError(f"IMU header version {h['version']} length {h['length']}, expected 0 and 60")
    if h["data_type"] != DATA_TYPE_IMU or h["dot_num"] != 1:
        raise ProtocolError(f"IMU header data_type {h['data_type']} dot_num {h['dot_num']}, expected 0 and 1")
    if check_crc and int(h["crc32"]) != zlib.crc32(raw[28:]):
        raise ProtocolError("IMU datagram CRC-32 mismatch")
    v = np.frombuffer(raw, np.dtype("<f4"), count=6, offset=DATA_HEADER_SIZE).astype(np.float64)
    return ImuPacket(int(h["udp_cnt"]), int(h["time_type"]), int(h["timestamp"]), v[:3], v[3:])


@dataclass(frozen=True)
class PointGroup:
    """Valid point packets of one (data_type, dot_num) from one batch, in arrival order."""

    data_type: int
    rows: I64  # slot index of each packet in the receive buffer
    header: Structured  # (P,) of HEADER_DTYPE fields
    points: Structured  # (P, dot_num) of POINT_DTYPES[data_type]


def _compact(hdr: Structured, rows: I64) -> Structured:
    """Copy the header fields of `rows` out of slot-sized records into 36-byte ones."""
    out = np.empty(len(rows), HEADER_DTYPE)
    for name in HEADER_DTYPE.names or ():
        out[name] = hdr[name][rows]
    return out


REJECT_REASONS = ("short", "oversized", "version", "length", "data_type", "dot_num", "crc32")


def decode_point_batch(
    buf: bytearray, slot: int, sizes: I64, check_crc: bool = True
) -> tuple[list[PointGroup], dict[str, I64]]:
    """Validate and view `len(sizes)` point datagrams that sit in `slot`-byte slots of `buf`.

    A datagram is rejected (and named by the first failing check in
    `REJECT_REASONS`) when it is shorter than the header, filled its slot (so it
    may be truncated), has version != 0, a length field != its size, a data type
    other than 1/2/3, a length != 36 + dot_num * point size, or (with
    `check_crc`) a CRC-32 mismatch. Returns the valid packets grouped by
    (data_type, dot_num) and the rejected slot indices by reason.
    """
    n = len(sizes)
    hdr = np.ndarray((n,), header_dtype(slot), buf, 0)
    sizes = np.asarray(sizes, np.int64)
    checks = {
        "short": sizes < DATA_HEADER_SIZE,
        "oversized": sizes >= slot,
        "version": hdr["version"] != 0,
        "length": hdr["length"] != sizes,
        "data_type": POINT_SIZES[hdr["data_type"]] == 0,
        "dot_num": (hdr["dot_num"] == 0)
        | (DATA_HEADER_SIZE + hdr["dot_num"].astype(np.int64) * POINT_SIZES[hdr["data_type"]] != sizes),
    }
    bad = np.zeros(n, bool)
    rejects: dict[str, I64] = {}
    for reason, failed in checks.items():
        hit = failed & ~bad
        if hit.any():
            rejects[reason] = np.flatnonzero(hit)
        bad |= failed
    if check_crc:
        mv = memoryview(buf)
        ok_rows = np.flatnonzero(~bad).tolist()
        crc_bad = [
            k for k in ok_rows if zlib.crc32(mv[k * slot + 28 : k * slot + int(sizes[k])]) != hdr["crc32"][k]
        ]
        if crc_bad:
            rejects["crc32"] = np.asarray(crc_bad, np.int64)
            bad[crc_bad] = True
    good = np.flatnonzero(~bad)
    groups = []
    if len(good):
        keys = hdr["data_type"][good].astype(np.int64) * 65536 + hdr["dot_num"][good]
        for key in np.unique(keys):
            rows = good[keys == key]
            data_type, dot_num = int(key) // 65536, int(key) % 65536
            pdt = POINT_DTYPES[data_type]
            view = np.ndarray((n, dot_num), pdt, buf, DATA_HEADER_SIZE, (slot, pdt.itemsize))
            groups.append(PointGroup(data_type, rows, _compact(hdr, rows), view[rows]))
    return groups, rejects
