"""Mid-360 data packets (notes/livox.md): the 36-byte header, points of data types 1/2/3, IMU
samples; built for the emulator, decoded in numpy batches for the driver."""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from functools import cache

import numpy as np

from calibration.types import F64, I64, U8, Structured
from sensorbox.errors import ProtocolError
from sensorbox.livox.protocol import crc32

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


POINT_SIZES = np.zeros(256, np.int64)  # bytes per point of each data type, 0 for unknown types
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
