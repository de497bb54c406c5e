"""A Mid-360 on UDP loopback: answers discovery and configuration, streams the simulator's scan.

One `Mid360Emulator` is one device at its own address (127.0.0.x on Linux,
where all of 127/8 is local). Like the real unit (notes/livox.md):

- Discovery: a REQ on the discovery port (broadcast to a wildcard listener, or
  unicast to the device address) is answered by a broadcast ACK from
  device:discovery with ret_code, dev_type 9, serial, IP and command port.
- Commands on the command port: 0x0100 set (keys 0x0000/1/4/5/6/7/0x0012/
  0x001A/0x001C, checked for length and range; ret_code + error_key in the
  ACK), 0x0101 query, anything else is refused; every frame's CRCs are checked
  and bad frames are ignored, as the SDK does. It starts IDLE and streams only
  after the host set the point host (0x0006) and work mode NORMAL (0x001A = 1);
  IMU needs 0x0007 and 0x001C = 1. Status pushes (0x0102) go to the push host
  about once a second.
- Stream: each sweep of the source is cut into its 96-point packets (data type
  1/2/3 as configured, time_interval 4750, free-running udp_cnt, frame_cnt 0,
  CRC-32) plus 60-byte IMU packets; they leave from device:point / device:imu
  when due: device time / `rate` after the stream started (rate 1 = real time).
  time_type 1 stamps packets with the sweep's (synced) time; time_type 0 with
  ns since a notional power-on 5 s before the first sweep.
- Impairments on point packets, drawn from `seed`: loss (never the first or
  the last packet, so a receiver can see every gap), reordering (a packet is
  held back behind the next one), duplication, and extra malformed datagrams
  (cycling through short, bad length, bad version, bad data type, dot_num
  mismatch, bad CRC-32, oversized). `counters` records exactly what was done.
- Flow control (for tests, not in the real unit): with `credit`, a function
  that says how many datagrams the receiver has taken so far on the "point" or
  "imu" stream, the emulator never has more than `window` datagrams of a
  stream in flight. The kernel's receive buffer then never overflows however
  busy the machine is, so a test can demand every datagram; the wall-clock
  schedule (`rate`) still applies on top.
"""

from __future__ import annotations

import contextlib
import itertools
import selectors
import socket
import threading
import time
from collections.abc import Callable
from types import TracebackType

import numpy as np

from calibration.errors import SensorboxError
from calibration.types import F64
from sensorbox.errors import ProtocolError
from sensorbox.livox import packets
from sensorbox.livox import protocol as proto
from sensorbox.livox.protocol import Ports
from sensorbox.sim.impairments import MALFORMED_KINDS, EmulatorCounters, malformed_datagram
from sensorbox.sim.lidar import POINTS_PER_PACKET
from sensorbox.sim.scan_source import ScanSource

POWER_ON_LEAD_NS = 5_000_000_000
_HOST_KEYS = {proto.KEY_STATE_HOST: "push", proto.KEY_POINT_HOST: "point", proto.KEY_IMU_HOST: "imu"}


def _socket(ip: str, port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    try:
        sock.bind((ip, port))
    except OSError as err:
        sock.close()
        raise SensorboxError(f"Mid-360 emulator: cannot bind UDP {ip}:{port}: {err}") from err
    return sock


class Mid360Emulator:
    """One emulated Mid-360 at `ip` streaming `source` (see the module docstring)."""

    def __init__(
        self,
        ip: str,
        source: ScanSource,
        *,
        serial: str = "47MDL9A0010012",
        ports: Ports | None = None,
        data_type: int = packets.DATA_TYPE_CARTESIAN_HIGH,
        time_type: int = packets.TIME_TYPE_PTP,
        loss: float = 0.0,
        reorder: float = 0.0,
        duplicate: float = 0.0,
        malformed: float = 0.0,
        seed: int = 0,
        rate: float = 1.0,
        imu: bool = True,
        fail_keys: frozenset[int] = frozenset(),
        listen_broadcast: bool = True,
        push_period_s: float = 1.0,
        credit: Callable[[str], int] | None = None,
        window: int = 64,
    ) -> None:
        if data_type not in packets.POINT_DTYPES:
            raise SensorboxError(f"Mid-360 emulator: data_type {data_type}, expected 1, 2 or 3")
        if time_type not in (packets.TIME_TYPE_NO_SYNC, packets.TIME_TYPE_PTP, packets.TIME_TYPE_GPS):
            raise SensorboxError(f"Mid-360 emulator: time_type {time_type}, expected 0, 1 or 2")
        if not rate > 0:
            raise SensorboxError(f"Mid-360 emulator: rate must be > 0, got {rate}")
        if window < 1:
            raise SensorboxError(f"Mid-360 emulator: window must be >= 1 datagram, got {window}")
        for name, p in (
            ("loss", loss),
            ("reorder", reorder),
            ("duplicate", duplicate),
            ("malformed", malformed),
        ):
            if not 0.0 <= p <= 1.0:
                raise SensorboxError(f"Mid-360 emulator: {name} probability {p} outside [0, 1]")
        self.ip = ip
        self.source = source
        self.serial = serial
        self.ports = ports or Ports()
        self.time_type = time_type
        self.loss, self.reorder, self.duplicate, self.malformed = loss, reorder, duplicate, malformed
        self.rate = rate
        self.has_imu = imu
        self.fail_keys = fail_keys
        self.listen_broadcast = listen_broadcast
        self.push_period_s = push_period_s
        self.credit = credit
        self.window = window
        self.counters = EmulatorCounters()
        self.params: dict[int, bytes] = {
            proto.KEY_PCL_DATA_TYPE: proto.u8_value(data_type),
            proto.KEY_PATTERN_MODE: proto.u8_value(0),
            proto.KEY_WORK_MODE: proto.u8_value(proto.WORK_MODE_IDLE),
            proto.KEY_IMU_DATA_EN: proto.u8_value(0),
            proto.KEY_SN: serial.encode()[:16].ljust(16, b"\0"),
            proto.KEY_PRODUCT: b"Livox Mid-360 (SensorBox emulator)".ljust(64, b"\0"),
            proto.KEY_FIRMWARE: bytes([10, 11, 6, 0]),
            proto.KEY_WORK_STATE: proto.u8_value(proto.WORK_MODE_IDLE),
        }
        self._rng = np.random.default_rng(seed)
        self._hosts: dict[str, tuple[str, int]] = {}  # "push"/"point"/"imu" -> host (ip, port)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._done = threading.Event()
        self._socks: dict[str, socket.socket] = {}
        self._threads: list[threading.Thread] = []
        self._malformed_kind = itertools.cycle(MALFORMED_KINDS)

    # ------------------------------------------------------------------ state

    @property
    def work_mode(self) -> int:
        return self.params[proto.KEY_WORK_MODE][0]

    @property
    def data_type(self) -> int:
        return self.params[proto.KEY_PCL_DATA_TYPE][0]

    def _streaming(self) -> bool:
        return self.work_mode == proto.WORK_MODE_NORMAL and "point" in self._hosts

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        ports = self.ports
        try:
            self._socks["discovery"] = _socket(self.ip, ports.discovery)
            if self.listen_broadcast:
                self._socks["discovery_any"] = _socket("", ports.discovery)
            self._socks["cmd"] = _socket(self.ip, ports.lidar_cmd)
            self._socks["push"] = _socket(self.ip, ports.lidar_push)
            self._socks["point"] = _socket(self.ip, ports.lidar_point)
            self._socks["imu"] = _socket(self.ip, ports.lidar_imu)
        except SensorboxError:
            self._close()
            raise
        self._stop.clear()
        self._threads = [
            threading.Thread(target=self._control_loop, name=f"mid360-{self.ip}-ctl", daemon=True),
            threading.Thread(target=self._stream_loop, name=f"mid360-{self.ip}-stream", daemon=True),
        ]
        for t in self._threads:
            t.start()

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5.0)
        self._threads = []
        self._close()

    def wait_done(self, timeout_s: float) -> bool:
        """Block until the source is exhausted and everything was sent; False on timeout."""
        return self._done.wait(timeout_s)

    def __enter__(self) -> Mid360Emulator:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def _close(self) -> None:
        for sock in self._socks.values():
            with contextlib.suppress(OSError):
                sock.close()
        self._socks = {}

    # ------------------------------------------------------------------ control

    def _control_loop(self) -> None:
        sel = selectors.DefaultSelector()
        for name in ("discovery", "discovery_any", "cmd"):
            if name in self._socks:
                sel.register(self._socks[name], selectors.EVENT_READ, name)
        next_push = time.monotonic()
        try:
            while not self._stop.is_set():
                for key, _ in sel.select(0.05):
                    sock: socket.socket = key.fileobj  # type: ignore[assignment]
                    try:
                        raw, src = sock.recvfrom(4096)
                    except OSError:
                        continue
                    if key.data == "cmd":
                        self._on_command(raw, src)
                    else:
                        self._on_discovery(raw)
                now = time.monotonic()
                if "push" not in self._hosts:
                    next_push = now  # first push as soon as the host asked for them
                elif now >= next_push:
                    next_push = now + self.push_period_s
                    self._push()
        finally:
            sel.close()

    def _on_discovery(self, raw: bytes) -> None:
        try:
            frame = proto.parse_control_frame(raw)
        except ProtocolError:
            return
        if frame.cmd_id != proto.CMD_DISCOVERY or frame.cmd_type != proto.REQ:
            return  # e.g. another device's ACK seen by the wildcard listener
        info = proto.DeviceInfo(self.ip, self.serial, proto.DEV_TYPE_MID360, self.ports.lidar_cmd)
        ack = proto.ControlFrame(
            proto.CMD_DISCOVERY, proto.ACK, proto.SENDER_LIDAR, frame.seq, proto.encode_discovery_ack(info)
        )
        self._socks["discovery"].sendto(
            proto.build_control_frame(ack), ("255.255.255.255", self.ports.discovery)
        )
        self.counters.discovery_replies += 1

    def _on_command(self, raw: bytes, src: tuple[str, int]) -> None:
        self.counters.commands.append(bytes(raw))
        try:
            frame = proto.parse_control_frame(raw)
        except ProtocolError:
            return  # the real unit ignores frames whose CRCs do not check
        if frame.cmd_type != proto.REQ:
            return
        if frame.cmd_id == proto.CMD_SET_PARAMS:
            payload = self._set_params(frame.payload)
        elif frame.cmd_id == proto.CMD_QUERY_PARAMS:
            payload = self._query(frame.payload)
        else:
            payload = proto.encode_set_ack(0x01, 0)
        ack = proto.ControlFrame(frame.cmd_id, proto.ACK, proto.SENDER_LIDAR, frame.seq, payload)
        self._socks["cmd"].sendto(proto.build_control_frame(ack), src)

    def _check(self, key: int, value: bytes) -> int:
        """ret_code for setting `key` to `value`: 0 ok, 0x01 unknown/bad length, 0x03 out of range."""
        sizes = {
            proto.KEY_PCL_DATA_TYPE: 1, proto.KEY_PATTERN_MODE: 1, proto.KEY_LIDAR_IP: 12,
            proto.KEY_STATE_HOST: 8, proto.KEY_POINT_HOST: 8, proto.KEY_IMU_HOST: 8,
            proto.KEY_INSTALL_ATTITUDE: 24, proto.KEY_WORK_MODE: 1, proto.KEY_IMU_DATA_EN: 1,
        }  # fmt: skip
        if key in self.fail_keys or sizes.get(key) != len(value):
            return 0x01
        allowed = {
            proto.KEY_PCL_DATA_TYPE: (1, 2, 3), proto.KEY_PATTERN_MODE: (0,),
            proto.KEY_WORK_MODE: (proto.WORK_MODE_NORMAL, proto.WORK_MODE_IDLE, 0x09),
            proto.KEY_IMU_DATA_EN: (0, 1),
        }  # fmt: skip
        if key in allowed and value[0] not in allowed[key]:
            return 0x03
        return 0x00

    def _set_params(self, payload: bytes) -> bytes:
        try:
            items = proto.decode_kv_list(payload)
        except ProtocolError:
            return proto.encode_set_ack(0x01, 0)
        with self._lock:
            for key, value in items:
                ret = self._check(key, value)
                if ret:
                    return proto.encode_set_ack(ret, key)
                self.params[key] = value
                if key in _HOST_KEYS:
                    self._hosts[_HOST_KEYS[key]] = proto.decode_host_address(value)[:2]
                if key == proto.KEY_WORK_MODE:
                    self.params[proto.KEY_WORK_STATE] = value
        return proto.encode_set_ack(0, 0)

    def _query(self, payload: bytes) -> bytes:
        try:
            keys = proto.decode_query(payload)
        except ProtocolError:
            return proto.encode_query_ack(0x01, [])
        with self._lock:
            missing = [k for k in keys if k not in self.params]
            if missing:
                return proto.encode_query_ack(0x01, [])
            return proto.encode_query_ack(0, [(k, self.params[k]) for k in keys])

    def _push(self) -> None:
        host = self._hosts.get("push")
        if host is None:
            return
        with self._lock:
            items = [
                (k, self.params[k])
                for k in (proto.KEY_WORK_STATE, proto.KEY_PCL_DATA_TYPE, proto.KEY_IMU_DATA_EN)
            ]
        frame = proto.ControlFrame(
            proto.CMD_PUSH, proto.REQ, proto.SENDER_LIDAR, self.counters.pushes, proto.encode_kv_list(items)
        )
        with contextlib.suppress(OSError):
            self._socks["push"].sendto(proto.build_control_frame(frame), host)
            self.counters.pushes += 1

    # ------------------------------------------------------------------ stream

    def _stream_loop(self) -> None:
        sweeps = iter(self.source.sweeps())
        nxt = next(sweeps, None)
        udp_cnt = 0
        imu_cnt = 0
        index = 0  # stream index of the next point packet
        imu_from: int | None = None
        wall0 = dev0 = None
        boot_ns: int | None = None
        held: tuple[int, bytes] | None = None  # a reordered packet waits for the next one, across sweeps
        while nxt is not None and not self._stop.is_set():
            sweep, nxt = nxt, next(sweeps, None)
            if not self._wait_streaming():
                return
            pts = sweep.points
            if len(pts) % POINTS_PER_PACKET:
                raise SensorboxError(
                    f"Mid-360 emulator {self.ip}: sweep at {sweep.timebase_ns} has {len(pts)} points, "
                    f"not a multiple of {POINTS_PER_PACKET}"
                )
            pk = pts.reshape(-1, POINTS_PER_PACKET)
            pk_ns = sweep.timebase_ns + pk["offset_time"][:, 0].astype(np.int64)
            if boot_ns is None:
                boot_ns = int(pk_ns[0]) - POWER_ON_LEAD_NS
            clock_ns = (
                0 if self.time_type != packets.TIME_TYPE_NO_SYNC else boot_ns
            )  # device stamp = t - clock_ns
            xyz = np.stack([pk["x"], pk["y"], pk["z"]], axis=-1).astype(np.float64)
            body = packets.quantise_points(self.data_type, xyz, pk["reflectivity"], pk["tag"])
            cnts = (udp_cnt + np.arange(len(pk), dtype=np.int64)) & 0xFFFF
            udp_cnt = (udp_cnt + len(pk)) & 0xFFFF
            datagrams = packets.build_point_packets(
                self.data_type, self.time_type, pk_ns - clock_ns, cnts, body
            )
            end_ns = (
                int(pk_ns[-1]) + packets.MID360_TIME_INTERVAL * 100 // POINTS_PER_PACKET * POINTS_PER_PACKET
            )
            imu = self.source.imu(int(pk_ns[0]) if imu_from is None else imu_from, end_ns)
            imu_from = end_ns
            draws = self._rng.random((len(pk), 4))  # loss, malformed, reorder, duplicate per packet
            # one timeline of (device ns, kind, index): kind 0 = IMU first on ties
            events = sorted(
                [(int(t), 0, k) for k, t in enumerate(imu.stamps_ns.tolist())]
                + [(int(t), 1, k) for k, t in enumerate(pk_ns.tolist())]
            )
            for t_dev, kind, k in events:
                if self._stop.is_set():
                    return
                if not self._streaming():
                    wall0 = None  # paused (standby): resume at the new wall time
                    if not self._wait_streaming():
                        return
                if wall0 is None or dev0 is None:
                    wall0, dev0 = time.monotonic(), t_dev
                delay = wall0 + (t_dev - dev0) / 1e9 / self.rate - time.monotonic()
                if delay > 0.001:
                    time.sleep(delay)
                if kind == 0:
                    if self.has_imu and self.params[proto.KEY_IMU_DATA_EN][0] == 1:
                        self._send_imu(t_dev - clock_ns, imu_cnt, imu.gyro_rad_s[k], imu.acc_g[k])
                        imu_cnt = (imu_cnt + 1) & 0xFFFF
                    continue
                last = nxt is None and k == len(pk) - 1
                held = self._send_point(index, datagrams[k].tobytes(), held, last, draws[k])
                index += 1
            self.counters.sweeps += 1
        if held is not None:  # unreachable: the last packet is never held and releases any held one
            self._send(held[1])
        self._done.set()

    def _wait_streaming(self) -> bool:
        """Block until the host configured the stream and set NORMAL; False when stopped meanwhile."""
        while not self._streaming():
            if self._stop.wait(0.02):
                return False
        return True

    def _send(self, raw: bytes, kind: str = "point") -> None:
        host = self._hosts.get(kind)
        if host is None:
            return
        self._await_credit(kind)
        try:
            self._socks[kind].sendto(raw, host)
        except OSError:
            return
        if kind == "point":
            self.counters.point_datagrams += 1
        elif kind == "imu":
            self.counters.imu_datagrams += 1

    def _await_credit(self, kind: str) -> None:
        """With `credit`, wait until fewer than `window` datagrams of `kind` are in flight (or stop)."""
        if self.credit is None or kind not in ("point", "imu"):
            return
        sent = self.counters.point_datagrams if kind == "point" else self.counters.imu_datagrams
        while sent - self.credit(kind) >= self.window and not self._stop.is_set():
            time.sleep(0.0005)

    def _send_imu(self, stamp: int, cnt: int, gyro: F64, acc: F64) -> None:
        if "imu" not in self._hosts:
            return
        self._send(packets.build_imu_packet(self.time_type, stamp, cnt, gyro, acc), "imu")
        self.counters.imu_sent += 1

    def _send_point(
        self, index: int, raw: bytes, held: tuple[int, bytes] | None, last: bool, draws: F64
    ) -> tuple[int, bytes] | None:
        """Send one point packet with the configured impairments; returns the packet held back, if any."""
        c = self.counters
        u = draws
        if index > 0 and not last and u[0] < self.loss:
            c.dropped.append(index)
            return held
        if u[1] < self.malformed:
            self._send(self._malformed(raw))
        if held is None and not last and u[2] < self.reorder:
            c.points_sent += POINTS_PER_PACKET
            return index, raw  # goes out after the next packet
        self._send(raw)
        c.packets_sent += 1
        c.points_sent += POINTS_PER_PACKET
        if u[3] < self.duplicate:
            self._send(raw)
            c.packets_sent += 1
            c.duplicated += 1
        if held is not None:
            self._send(held[1])
            c.packets_sent += 1
            c.reordered += 1
        return None

    def _malformed(self, raw: bytes) -> bytes:
        kind = next(self._malformed_kind)
        self.counters.malformed += 1
        self.counters.malformed_by_kind[kind] = self.counters.malformed_by_kind.get(kind, 0) + 1
        return malformed_datagram(raw, kind)


def credit_from(received: Callable[[str], tuple[int, int]], ip: str) -> Callable[[str], int]:
    """An emulator `credit` function from a receiver's (point, IMU) datagram counts for `ip`
    (for example `Mid360Driver.received`)."""

    def taken(kind: str) -> int:
        point, imu = received(ip)
        return point if kind == "point" else imu

    return taken
