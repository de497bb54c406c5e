"""The driver's UDP sockets: a large receive buffer, and the kernel's arrival time (SO_TIMESTAMPNS)
and drop count (SO_RXQ_OVFL) read from each datagram's ancillary data (Linux).

Data and command sockets own their port (no SO_REUSEADDR): a second driver on
the same ports is a clear error instead of a second reader silently taking a
share of each LiDAR's datagrams. Only the broadcast discovery socket shares
its port."""

from __future__ import annotations

import contextlib
import errno
import socket
import struct
import sys
import time

from sensorbox.errors import DriverError

_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35) if sys.platform.startswith("linux") else None


MSG_TRUNC = int(getattr(socket, "MSG_TRUNC", 0))


_SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40) if sys.platform.startswith("linux") else None


ANC_SIZE = 96  # room for both control messages


def arrival_ns(ancillary: list[tuple[int, int, bytes]]) -> int:
    """The kernel's receive time of a datagram (SO_TIMESTAMPNS), else the host clock now (ns)."""
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(data) >= 16:
            sec, nsec = struct.unpack_from("qq", data)
            return int(sec * 1_000_000_000 + nsec)
    return time.time_ns()


def kernel_drops_so_far(ancillary: list[tuple[int, int, bytes]]) -> int:
    """Datagrams the kernel dropped on this socket so far (SO_RXQ_OVFL; sent only once nonzero)."""
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == _SO_RXQ_OVFL and len(data) >= 4:
            return int(struct.unpack_from("I", data)[0])
    return 0


def udp_socket(ip: str, port: int, *, rcvbuf: int = 0, broadcast: bool = False) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        if broadcast:  # discovery shares its port with whatever else listens for the broadcast
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        for option in (_SO_TIMESTAMPNS, _SO_RXQ_OVFL):  # arrival times; kernel drop counts
            if option is not None:
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, option, 1)
        if rcvbuf:
            force = getattr(socket, "SO_RCVBUFFORCE", None)
            try:
                if force is None:
                    raise PermissionError
                sock.setsockopt(socket.SOL_SOCKET, force, rcvbuf)  # beyond rmem_max when privileged
            except PermissionError:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        sock.bind((ip, port))
    except OSError as err:
        sock.close()
        hint = (
            " (another driver - sensorbox launch or capture - is using it?)"
            if err.errno == errno.EADDRINUSE
            else ""
        )
        raise DriverError(f"cannot bind UDP {ip}:{port}: {err.strerror or err}{hint}") from err
    return sock
