"""SDK-free Livox Mid-360 driver: UDP discovery, configuration, point/IMU streams, sweeps.

What it does, in the order livox_ros_driver2 + Livox-SDK2 do it (notes/livox.md):

1. `discover()` (`sensorbox.livox.discovery`) collects the lidars' answers.
2. `start()` binds the host's command, push, point and IMU ports (large
   SO_RCVBUF), starts the receive threads, then configures each lidar with
   0x0100 commands: keys 0x0005/6/7 (push, point and IMU host addresses),
   0x0000 data type, 0x0001 pattern 0, 0x0012 install attitude (when an
   extrinsic is given), 0x001C IMU enable, 0x001A work mode normal. Each command
   is matched to its ACK by sequence number and source, retried on timeout and
   its ret_code/error_key checked; a lidar that never answers is a DriverError
   naming its IP.
3. Point datagrams are received in batches (the thread wakes, waits
   `batch_wait_s`, then drains the socket) into fixed-size slots of one buffer
   and decoded with numpy (packets.decode_point_batch): no Python per point.
   Only the configured lidars' (IP, port) are accepted; anything else is counted
   as foreign. Malformed, short or oversized datagrams are counted by reason and
   dropped. udp_cnt is unwrapped (16 bits) per lidar to count lost, duplicate
   (dropped) and reordered packets; a counter leap no real gap explains (more
   packets than the elapsed time allows) is a counted jump, not loss
   (`sensorbox.livox.tracking.SeqTracker`).
4. Point time: packet timestamp when time_type is 1/2 (PTP/GPS), otherwise the
   host clock at reception (the kernel's SO_TIMESTAMPNS arrival time on Linux;
   the lidar is then flagged unsynced); point i adds
   i * (time_interval * 100 // dot_num) ns.
5. Sweeps (`sensorbox.livox.sweeps`): a packet belongs to the sweep
   floor(packet time / publish interval), aligned to multiples of 100 ms of
   device time (unsynced: of the host clock); livox_ros_driver2 instead cuts
   after the packet whose last point passes the ms boundary. Cutting on the
   packet's first point is what the simulator's sweeps do, so emulated
   captures compare 1:1.
6. Optional extrinsic (roll, pitch, yaw deg; x, y, z mm) applied as
   livox_ros_driver2 does (`sensorbox.livox.tracking.to_metres`); IMU samples
   are published unrotated.
7. Output: livox_ros_driver2 `CustomMsg` or `PointCloud2` per sweep and
   `sensor_msgs/Imu` per IMU packet (acceleration in g), serialised by
   sensorbox.messages, handed to `publish(topic, msgtype, stamp_ns, raw)`.
   `publish` is never called concurrently (a lock serialises both threads).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import selectors
import socket
import threading
import time
from collections.abc import Callable
from types import TracebackType

import numpy as np

from calibration.types import I64
from ingest.bags.rostypes import IMU_TYPE
from sensorbox import messages
from sensorbox.errors import DriverError, ProtocolError
from sensorbox.livox import packets
from sensorbox.livox import protocol as proto
from sensorbox.livox.config import (
    DriverConfig,
    DriverStats,
)
from sensorbox.livox.discovery import discover
from sensorbox.livox.protocol import DeviceInfo
from sensorbox.livox.sockets import ANC_SIZE, MSG_TRUNC, arrival_ns, kernel_drops_so_far, udp_socket
from sensorbox.livox.sweeps import SweepAssembler
from sensorbox.livox.tracking import LidarState

log = logging.getLogger(__name__)

Publish = Callable[[str, str, int, bytes], None]
"""(topic, msgtype, stamp_ns, serialised bytes) -> None."""

SLOT = 2048  # receive slot per datagram: any datagram that fills it is oversized (real ones are <= 1380 B)
BATCH = 256  # datagrams drained per wake-up of the point thread
POLL_S = 0.05
DATAGRAM_TRUESIZE = 3072  # kernel buffer bytes a 1380-byte datagram costs (skb overhead; conservative)


class _Waiter:
    def __init__(self) -> None:
        self.event = threading.Event()
        self.frame: proto.ControlFrame | None = None


class Mid360Driver:
    """Configure one or more Mid-360s and publish their sweeps and IMU samples."""

    def __init__(
        self, config: DriverConfig, publish: Publish, *, clock: Callable[[], float] = time.monotonic
    ) -> None:
        """`clock` (seconds) decides when a silent lidar's open sweeps are flushed (`idle_flush_s`);
        tests pass a manual clock so that a stalled sender never looks like a silent lidar."""
        config.validate()
        self.config = config
        self._clock = clock
        self._publish_fn = publish
        self._publish_lock = threading.Lock()
        self._lock = threading.Lock()  # guards the counters for stats()
        self._sweeps = SweepAssembler(config, self._lock, clock, self._emit)
        self._lidars = {li.ip: LidarState(li, config) for li in config.lidars}
        ports = config.ports
        self._by_point_src = {(li.ip, ports.lidar_point): li for li in self._lidars.values()}
        self._by_imu_src = {(li.ip, ports.lidar_imu): li for li in self._lidars.values()}
        self._by_push_src = {(li.ip, ports.lidar_push): li for li in self._lidars.values()}
        self._foreign = 0
        self._foreign_sources: dict[str, int] = {}
        self._seq = itertools.count(1)
        self._pending: dict[tuple[str, int], _Waiter] = {}
        self._socks: dict[str, socket.socket] = {}
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()
        self._started = False
        self._devices: dict[str, DeviceInfo] = {}
        self._rcvbuf = 0
        self._kernel_drops = 0

    # ------------------------------------------------------------------ public API

    def discover(self, timeout_s: float = 3.0, *, until_found: int = 0) -> list[DeviceInfo]:
        """Broadcast discovery every second for `timeout_s`; every lidar that answered (any IP).

        With `until_found` > 0 it returns as soon as that many lidars have answered.
        """
        found = discover(self.config, next(self._seq) & 0xFFFF, timeout_s, until_found)
        self._devices.update((info.ip, info) for info in found)
        for info in found:
            if info.ip in self._lidars:
                self._lidars[info.ip].cmd_port = info.cmd_port
        return found

    def start(self) -> None:
        """Bind the host ports, start the receive threads and configure every lidar."""
        if self._started:
            return
        cfg, ports = self.config, self.config.ports
        try:
            self._socks["cmd"] = udp_socket(cfg.host_ip, ports.host_cmd)
            self._socks["push"] = udp_socket(cfg.host_ip, ports.host_push)
            self._socks["imu"] = udp_socket(cfg.host_ip, ports.host_imu, rcvbuf=1 << 20)
            self._socks["point"] = udp_socket(cfg.host_ip, ports.host_point, rcvbuf=cfg.rcvbuf_bytes)
            self._rcvbuf = self._socks["point"].getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
            if self._rcvbuf < cfg.rcvbuf_bytes:
                log.warning(
                    "livox driver: point socket buffer is %d bytes, asked for %d; raise net.core.rmem_max "
                    "(or grant CAP_NET_ADMIN) so bursts are not dropped by the kernel",
                    self._rcvbuf, cfg.rcvbuf_bytes,
                )  # fmt: skip
        except DriverError:
            self._close_sockets()
            raise
        self._stop.clear()
        self._threads = [
            threading.Thread(
                target=self._run_guarded, args=(self._control_loop,), name="livox-control", daemon=True
            ),
            threading.Thread(
                target=self._run_guarded, args=(self._point_loop,), name="livox-points", daemon=True
            ),
        ]
        for t in self._threads:
            t.start()
        self._started = True
        try:
            for lidar in self._lidars.values():
                self._configure(lidar)
        except BaseException:
            self._shutdown(standby=False)
            raise

    def stop(self) -> None:
        """Standby every lidar, stop the threads, publish the open sweeps, close the sockets."""
        if self._started:
            self._shutdown(standby=True)

    def stats(self) -> DriverStats:
        """A snapshot of every counter (safe to call from any thread)."""
        with self._lock:
            lidars = {ip: li.snapshot() for ip, li in self._lidars.items()}
            return DriverStats(
                lidars, self._foreign, dict(self._foreign_sources), self._rcvbuf, self._kernel_drops
            )

    def received(self, ip: str) -> tuple[int, int]:
        """(point, IMU) datagrams taken from lidar `ip`'s ports so far: a cheap read for flow control."""
        stats = self._lidars[ip].stats
        return stats.point_datagrams, stats.imu_datagrams

    def set_params(self, ip: str, items: list[proto.KV]) -> None:
        """Send one 0x0100 with `items` to lidar `ip`; DriverError unless it ACKs with ret_code 0."""
        ack = self._command(ip, proto.CMD_SET_PARAMS, proto.encode_kv_list(items))
        try:
            ret, key = proto.decode_set_ack(ack.payload)
        except ProtocolError as err:
            raise DriverError(f"lidar {ip}: bad ACK to set-parameters: {err}") from err
        if ret != 0:
            keys = ", ".join(f"{k:#06x}" for k, _ in items)
            raise DriverError(
                f"lidar {ip}: set-parameters ({keys}) refused: ret_code {ret:#04x} "
                f"({proto.RET_CODES.get(ret, 'unknown')}), error_key {key:#06x}"
            )

    def query(self, ip: str, keys: list[int]) -> dict[int, bytes]:
        """0x0101: read parameters of lidar `ip`, e.g. KEY_WORK_MODE or KEY_SN."""
        ack = self._command(ip, proto.CMD_QUERY_PARAMS, proto.encode_query(keys))
        try:
            ret, items = proto.decode_query_ack(ack.payload)
        except ProtocolError as err:
            raise DriverError(f"lidar {ip}: bad ACK to query: {err}") from err
        if ret != 0:
            raise DriverError(
                f"lidar {ip}: query refused: ret_code {ret:#04x} ({proto.RET_CODES.get(ret, 'unknown')})"
            )
        return dict(items)

    def __enter__(self) -> Mid360Driver:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    # ------------------------------------------------------------------ configuration

    def _configure(self, lidar: LidarState) -> None:
        cfg, ports = self.config, self.config.ports
        host = cfg.host_ip
        self.set_params(
            lidar.ip,
            [
                (proto.KEY_STATE_HOST, proto.host_address_value(host, ports.host_push, ports.lidar_push)),
                (proto.KEY_POINT_HOST, proto.host_address_value(host, ports.host_point, ports.lidar_point)),
                (proto.KEY_IMU_HOST, proto.host_address_value(host, ports.host_imu, ports.lidar_imu)),
            ],
        )
        self.set_params(lidar.ip, [(proto.KEY_PCL_DATA_TYPE, proto.u8_value(cfg.data_type))])
        self.set_params(lidar.ip, [(proto.KEY_PATTERN_MODE, proto.u8_value(0))])
        if lidar.endpoint.extrinsic is not None:
            self.set_params(
                lidar.ip,
                [(proto.KEY_INSTALL_ATTITUDE, proto.install_attitude_value(lidar.endpoint.extrinsic))],
            )
        self.set_params(lidar.ip, [(proto.KEY_IMU_DATA_EN, proto.u8_value(1 if cfg.imu else 0))])
        self.set_params(lidar.ip, [(proto.KEY_WORK_MODE, proto.u8_value(proto.WORK_MODE_NORMAL))])

    def _command(self, ip: str, cmd_id: int, payload: bytes) -> proto.ControlFrame:
        """Send a REQ and wait for the ACK with the same seq from `ip`; resend on timeout."""
        if ip not in self._lidars:
            raise DriverError(f"lidar {ip} is not in the driver's configuration")
        sock = self._socks.get("cmd")
        if sock is None:
            raise DriverError(f"lidar {ip}: the driver is not started (no command socket)")
        cfg = self.config
        seq = next(self._seq) & 0xFFFF
        raw = proto.build_control_frame(
            proto.ControlFrame(cmd_id, proto.REQ, proto.SENDER_HOST, seq, payload)
        )
        waiter = _Waiter()
        self._pending[(ip, seq)] = waiter
        try:
            for _ in range(cfg.command_retries + 1):
                try:
                    sock.sendto(raw, (ip, self._lidars[ip].cmd_port))
                except OSError as err:
                    raise DriverError(f"lidar {ip}: cannot send command {cmd_id:#06x}: {err}") from err
                if waiter.event.wait(cfg.command_timeout_s):
                    assert waiter.frame is not None
                    if waiter.frame.cmd_id != cmd_id:
                        raise DriverError(
                            f"lidar {ip}: ACK seq {seq} is for command {waiter.frame.cmd_id:#06x}, "
                            f"sent {cmd_id:#06x}"
                        )
                    return waiter.frame
        finally:
            self._pending.pop((ip, seq), None)
        raise DriverError(
            f"lidar {ip}: no ACK to command {cmd_id:#06x} (seq {seq}) after {cfg.command_retries + 1} tries "
            f"of {cfg.command_timeout_s} s on port {self._lidars[ip].cmd_port}"
        )

    # ------------------------------------------------------------------ threads

    def _run_guarded(self, loop: Callable[[], None]) -> None:
        """Run a receive loop; restart it after an unexpected error so bad input never kills it."""
        while not self._stop.is_set():
            try:
                loop()
            except Exception:
                log.exception("livox driver: receive loop failed; restarting it")
                time.sleep(0.01)

    def _count_foreign(self, src: tuple[str, int]) -> None:
        key = f"{src[0]}:{src[1]}"
        with self._lock:
            self._foreign += 1
            self._foreign_sources[key] = self._foreign_sources.get(key, 0) + 1

    def _control_loop(self) -> None:
        """Command ACKs, status pushes and IMU datagrams (all low-rate) on one selector."""
        sel = selectors.DefaultSelector()
        handlers = {"cmd": self._on_cmd, "push": self._on_push, "imu": self._on_imu}
        for name, handler in handlers.items():
            self._socks[name].setblocking(False)
            sel.register(self._socks[name], selectors.EVENT_READ, handler)
        try:
            while not self._stop.is_set():
                for key, _ in sel.select(POLL_S):
                    sock: socket.socket = key.fileobj  # type: ignore[assignment]
                    while True:
                        try:
                            raw, anc, _flags, src = sock.recvmsg(SLOT, ANC_SIZE)
                        except (BlockingIOError, InterruptedError):
                            break
                        except OSError:
                            if self._stop.is_set():
                                return
                            break  # e.g. ICMP port unreachable surfaced on a UDP socket
                        key.data(raw, src, arrival_ns(anc))
        finally:
            sel.close()

    def _on_cmd(self, raw: bytes, src: tuple[str, int], _now: int) -> None:
        lidar = self._lidars.get(src[0])
        if lidar is None or src[1] != lidar.cmd_port:
            self._count_foreign(src)
            return
        try:
            frame = proto.parse_control_frame(raw)
        except ProtocolError as err:
            log.debug("lidar %s: bad control frame: %s", src[0], err)
            with self._lock:
                lidar.malformed("control")
            return
        if frame.cmd_type != proto.ACK:
            return
        waiter = self._pending.get((src[0], frame.seq))
        if waiter is not None and not waiter.event.is_set():
            waiter.frame = frame
            waiter.event.set()

    def _on_push(self, raw: bytes, src: tuple[str, int], _now: int) -> None:
        lidar = self._by_push_src.get(src)
        if lidar is None:
            self._count_foreign(src)
            return
        try:
            frame = proto.parse_control_frame(raw)
            items = dict(proto.decode_kv_list(frame.payload)) if frame.cmd_id == proto.CMD_PUSH else {}
        except ProtocolError as err:
            log.debug("lidar %s: bad push: %s", src[0], err)
            with self._lock:
                lidar.malformed("push")
            return
        with self._lock:
            lidar.stats.pushes += 1
            state = items.get(proto.KEY_WORK_STATE)
            if state is not None and len(state) == 1:
                lidar.stats.work_state = state[0]

    def _on_imu(self, raw: bytes, src: tuple[str, int], now_ns: int) -> None:
        lidar = self._by_imu_src.get(src)
        if lidar is None:
            self._count_foreign(src)
            return
        with self._lock:
            lidar.stats.imu_datagrams += 1
        try:
            pkt = packets.decode_imu_packet(raw, self.config.check_crc)
        except ProtocolError as err:
            with self._lock:
                lidar.malformed("imu")
            log.debug("lidar %s: bad IMU datagram: %s", src[0], err)
            return
        stamp = pkt.timestamp_ns if pkt.time_type != packets.TIME_TYPE_NO_SYNC else now_ns
        with self._lock:
            if lidar.imu_seq.add(pkt.udp_cnt, stamp, now_ns) is None:  # duplicate
                return
            lidar.stats.imu_packets += 1
        if not self.config.imu:
            return
        raw_msg = messages.imu_msg(stamp, pkt.gyro_rad_s, pkt.acc_g, self.config.ros_version)
        self._emit(lidar.imu_topic, IMU_TYPE, stamp, raw_msg)

    def _point_loop(self) -> None:
        sock = self._socks["point"]
        sock.setblocking(False)
        buf = bytearray(SLOT * BATCH)
        mv = memoryview(buf)
        sel = selectors.DefaultSelector()
        sel.register(sock, selectors.EVENT_READ)
        sizes = np.zeros(BATCH, np.int64)
        recv_ns = np.zeros(BATCH, np.int64)
        backlog = False
        capacity = max(8, self._rcvbuf // DATAGRAM_TRUESIZE)  # datagrams the kernel can queue
        wait_s, last_drain = self.config.batch_wait_s, time.monotonic()
        try:
            while not self._stop.is_set():
                if not sel.select(POLL_S):
                    self._sweeps.flush_idle(self._lidars.values())
                    continue
                if wait_s > 0 and not backlog:
                    time.sleep(wait_s)
                srcs: list[tuple[str, int]] = []
                n = 0
                while n < BATCH:
                    try:
                        size, anc, flags, src = sock.recvmsg_into([mv[n * SLOT : (n + 1) * SLOT]], ANC_SIZE)
                    except (BlockingIOError, InterruptedError):
                        break
                    except OSError:
                        if self._stop.is_set():
                            return
                        break
                    sizes[n] = SLOT if flags & MSG_TRUNC else size
                    recv_ns[n] = arrival_ns(anc)
                    if anc and len(anc) > 1:
                        self._kernel_drops = max(self._kernel_drops, kernel_drops_so_far(anc))
                    srcs.append(src)
                    n += 1
                backlog = n == BATCH
                now = time.monotonic()
                if n:
                    # never let more than a quarter of the kernel buffer pile up while sleeping
                    rate = n / max(now - last_drain, 1e-4)
                    wait_s = min(self.config.batch_wait_s, capacity / 4 / rate)
                last_drain = now
                if n:
                    self._on_point_batch(buf, n, sizes[:n].copy(), recv_ns[:n].copy(), srcs)
                if not backlog:  # socket drained: a lidar's packets may wait behind a full batch
                    self._sweeps.flush_idle(self._lidars.values())
        finally:
            sel.close()

    # ------------------------------------------------------------------ point processing

    def _on_point_batch(
        self, buf: bytearray, n: int, sizes: I64, recv_ns: I64, srcs: list[tuple[str, int]]
    ) -> None:
        owner = np.full(n, -1, np.int64)
        lidars = list(self._lidars.values())
        index = {id(li): k for k, li in enumerate(lidars)}
        for k, src in enumerate(srcs):
            lidar = self._by_point_src.get(src)
            if lidar is None:
                self._count_foreign(src)
                sizes[k] = 0  # never parsed
            else:
                owner[k] = index[id(lidar)]
        if (owner < 0).all():
            return
        groups, rejects = packets.decode_point_batch(buf, SLOT, sizes, self.config.check_crc)
        with self._lock:
            for o, count in enumerate(np.bincount(owner[owner >= 0], minlength=len(lidars)).tolist()):
                lidars[o].stats.point_datagrams += count
            for reason, rows in rejects.items():
                for k in rows.tolist():
                    if owner[k] >= 0:
                        lidars[owner[k]].malformed(reason)
        for g in sorted(groups, key=lambda g: int(g.rows[0])):
            owners = owner[g.rows]
            for o in np.unique(owners[owners >= 0]).tolist():
                sel = owners == o
                self._sweeps.add(lidars[o], g.data_type, g.header[sel], g.points[sel], recv_ns[g.rows[sel]])

    def _emit(self, topic: str, msgtype: str, stamp_ns: int, raw: bytes) -> None:
        with self._publish_lock:
            try:
                self._publish_fn(topic, msgtype, stamp_ns, raw)
            except Exception:
                log.exception("livox driver: publish callback failed for %s", topic)

    # ------------------------------------------------------------------ shutdown

    def _shutdown(self, standby: bool) -> None:
        if standby:
            for lidar in self._lidars.values():
                try:
                    self.set_params(lidar.ip, [(proto.KEY_WORK_MODE, proto.u8_value(proto.WORK_MODE_IDLE))])
                except DriverError as err:
                    log.warning("livox driver: could not set lidar %s to standby: %s", lidar.ip, err)
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5.0)
        self._threads = []
        for lidar in self._lidars.values():
            self._sweeps.publish_open(lidar)
        self._close_sockets()
        self._started = False

    def _close_sockets(self) -> None:
        for sock in self._socks.values():
            with contextlib.suppress(OSError):
                sock.close()
        self._socks = {}
