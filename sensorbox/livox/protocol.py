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
