"""Livox discovery: a broadcast 0x0000 REQ on the discovery port, answered by each lidar's ACK."""

from __future__ import annotations

import logging
import time

from sensorbox.errors import DriverError, ProtocolError
from sensorbox.livox import protocol as proto
from sensorbox.livox.config import DriverConfig
from sensorbox.livox.protocol import DeviceInfo
from sensorbox.livox.sockets import udp_socket

log = logging.getLogger(__name__)
REPLY_BYTES = 2048


def discover(cfg: DriverConfig, seq: int, timeout_s: float, until_found: int = 0) -> list[DeviceInfo]:
    """Every lidar that answered within `timeout_s` (the request is resent every second), by IP.

    Datagrams from the host itself (its own broadcast) are dropped, as the SDK
    does; with `until_found` > 0 it returns once that many lidars answered.
    """
    sock = udp_socket("", cfg.ports.discovery, broadcast=True)
    req = proto.build_control_frame(
        proto.ControlFrame(proto.CMD_DISCOVERY, proto.REQ, proto.SENDER_HOST, seq)
    )
    found: dict[str, DeviceInfo] = {}
    try:
        end = time.monotonic() + timeout_s
        next_send = 0.0
        while (now := time.monotonic()) < end and not 0 < until_found <= len(found):
            if now >= next_send:
                try:
                    sock.sendto(req, (cfg.discovery_address, cfg.ports.discovery))
                except OSError as err:
                    raise DriverError(
                        f"discovery: cannot send to {cfg.discovery_address}:{cfg.ports.discovery}: {err}"
                    ) from err
                next_send = now + 1.0
            sock.settimeout(max(0.001, min(end, next_send) - now))
            try:
                raw, (src_ip, _port) = sock.recvfrom(REPLY_BYTES)
            except OSError:  # timeout, or an ICMP error surfacing on the socket
                continue
            if src_ip == cfg.host_ip:
                continue  # our own broadcast (the SDK drops these too)
            try:
                frame = proto.parse_control_frame(raw)
                if frame.cmd_id != proto.CMD_DISCOVERY or frame.cmd_type != proto.ACK:
                    continue
                info = proto.decode_discovery_ack(frame.payload)
            except ProtocolError as err:
                log.debug("discovery: dropped datagram from %s: %s", src_ip, err)
                continue
            if info.ret_code == 0:
                found[info.ip] = info
    finally:
        sock.close()
    return sorted(found.values(), key=lambda d: tuple(int(o) for o in d.ip.split(".")))
