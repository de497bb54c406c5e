"""What the emulator does to a stream on purpose (malformed datagrams of each kind the driver
rejects) and its exact record of it, which a test compares with the driver's counters."""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

from sensorbox.livox import packets

MALFORMED_KINDS = ("short", "length", "version", "data_type", "dot_num", "crc32", "oversized")
"""Injected in this order; each is the driver's reject reason of the same name."""


@dataclass
class EmulatorCounters:
    """What the emulator did, for exact comparison with the driver's counters."""

    packets_sent: int = 0  # point datagrams sent, duplicates included, malformed ones not
    points_sent: int = 0  # points in distinct point packets sent
    dropped: list[int] = field(default_factory=list)  # stream index of every point packet lost on purpose
    duplicated: int = 0
    reordered: int = 0
    malformed: int = 0
    malformed_by_kind: dict[str, int] = field(default_factory=dict)
    imu_sent: int = 0
    point_datagrams: int = 0  # every datagram that left the point port (malformed, duplicates included)
    imu_datagrams: int = 0  # every datagram that left the IMU port
    sweeps: int = 0  # sweeps fully streamed
    pushes: int = 0
    discovery_replies: int = 0
    commands: list[bytes] = field(default_factory=list)  # every datagram received on the command port


def malformed_datagram(raw: bytes, kind: str) -> bytes:
    """A point datagram broken the way `kind` (one of MALFORMED_KINDS) says."""
    b = bytearray(raw)
    if kind == "short":
        return bytes(b[:20])
    if kind == "length":
        struct.pack_into("<H", b, 1, len(b) + 1)
    elif kind == "version":
        b[0] = 1
    elif kind == "data_type":
        b[10] = 9
    elif kind == "dot_num":
        b = b[: -packets.POINT_DTYPES[b[10]].itemsize]
        struct.pack_into("<H", b, 1, len(b))
    elif kind == "crc32":
        b[-1] ^= 0xFF
    elif kind == "oversized":
        return bytes(b) * 3
    return bytes(b)
