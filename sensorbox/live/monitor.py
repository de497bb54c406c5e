"""The live monitor: a Foxglove WebSocket view of a recording, off the recording path.

`sensorbox capture --monitor PORT` and `sensorbox launch FILE --monitor PORT`
add a `Monitor` node to the graph. It subscribes to the bus beside the
recorder and serves, with foxglove-sdk's WebSocket server (subprotocol
`foxglove.sdk.v1`, Foxglove's `foxglove.websocket.v1` renamed):

- `/monitor/upper/image`, `/monitor/lower/image` (foxglove.CompressedImage):
  both cameras reduced to at most 640 pixels wide (1/4 of 1920 x 1200), JPEG,
  at most `image_hz` each;
- `/monitor/<lidar>/points` (foxglove.PointCloud): each LiDAR's latest sweep in
  the rig frame `cam0` (x, y, z, intensity float32);
- `/monitor/<imu>` (JSON): gyro (rad/s, in cam0) and acceleration (g, as the
  Livox driver publishes it), at most `imu_hz` each;
- `/monitor/status` (JSON): per-topic rates written, drops by node and stage,
  bag size, free disk, what the monitor sent and skipped, the coverage;
- `/monitor/coverage` (foxglove.CompressedImage): the last `coverage_window_s`
  of both LiDARs' points placed with the gyro into the upper camera over its
  image, with the fraction of its pixels covered (`sensorbox.live.coverage`).

Never slowing the recording: the bus hands every message to `offer` in the
publisher's thread, which only counts and parks a reference to the bytes: a
camera frame in a one-frame slot per camera (a newer frame replaces it), a
sweep or IMU sample in one bounded queue. One worker thread, niced below the
recorder, decodes, reduces and sends; foxglove-sdk's own threads write the
sockets, dropping a slow client's oldest messages beyond its backlog.

The books: every message on a monitored topic ends once as sent (handed to
the server) or skipped for one reason: `no_client` (nobody subscribed to its
channel, nor to the coverage it feeds), `rate` (above the channel's rate),
`superseded` (a newer frame replaced it before the worker took it), `backlog`
(the queue was full), `decode` (not a message the monitor can read), `error`
(the monitor failed on it: logged once, the node's error, the recording goes
on), `stopped` (arrived after the monitor stopped, or still parked then). `counts()` gives
them per topic: received == sent + sum(skipped), exactly.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from calibration.rig import Rig, read_rig
from sensorbox.errors import GraphError
from sensorbox.live.bus import PRIORITY_SINK, Bus, GraphSnapshot, NodeStatus
from sensorbox.live.monitor_channels import Channels, Stream, decode_for_monitor, streams_of
from sensorbox.live.monitor_view import CoverageView

log = logging.getLogger(__name__)

REASONS = ("no_client", "rate", "superseded", "backlog", "decode", "error", "stopped")
WORKER_NICE = 10  # the worker's niceness above the process's: the recording threads come first


@dataclass(frozen=True)
class MonitorConfig:
    """Where the monitor listens and how much it sends; rates in Hz, times in s."""

    port: int  # TCP port of the WebSocket server (0 = any free port, see `Monitor.port`)
    rig: Path  # the rig: camera topics and models, LiDAR and IMU topics and poses
    host: str = "127.0.0.1"  # 0.0.0.0 to be reached from another computer
    image_hz: float = 10.0  # per camera
    imu_hz: float = 50.0  # per IMU
    coverage_hz: float = 2.0
    coverage_window_s: float = 1.0
    queue_msgs: int = 2048  # sweeps and IMU samples parked for the worker (5 s of both IMUs)
    backlog_msgs: int = 256  # per client, in foxglove-sdk: its oldest messages go beyond this

    def validate(self) -> None:
        if not 0 <= self.port <= 65535:
            raise GraphError(f"--monitor {self.port}: expected a TCP port 1..65535")
        for key in ("image_hz", "imu_hz", "coverage_hz", "coverage_window_s"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0):
                raise GraphError(f"monitor {key} must be a finite number > 0, got {value}")


@dataclass
class Tally:
    """One topic's books: received == sent + sum(skipped.values())."""

    received: int = 0
    sent: int = 0
    skipped: dict[str, int] = field(default_factory=dict)

    def skip(self, reason: str, n: int = 1) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + n


@dataclass
class _Item:
    stream: Stream
    topic: str
    msgtype: str
    raw: bytes


class Monitor:
    """The live monitor node (see the module docstring); priority: sink, so it starts before the
    sources and stops after them."""

    priority = PRIORITY_SINK

    def __init__(self, cfg: MonitorConfig, bus: Bus, rig: Rig | None = None, name: str = "monitor") -> None:
        cfg.validate()
        self.cfg, self.name = cfg, name
        self.rig = rig if rig is not None else read_rig(cfg.rig)
        self._streams = streams_of(self.rig)
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._slots: dict[str, _Item] = {}  # camera role -> the latest frame not yet taken
        self._queue: deque[_Item] = deque()  # sweeps and IMU samples in arrival order
        self._last_taken: dict[str, int] = {}  # channel -> header stamp (ns) of the last frame / IMU taken
        self._status: GraphSnapshot | None = None
        self.tallies: dict[str, Tally] = {}
        self._running = False
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._server: Any = None
        self._channels: Channels | None = None
        self._view: CoverageView | None = None
        self.error: str | None = None
        bus.subscribe(self.offer, set(self._streams))

    @property
    def port(self) -> int:
        """The port the server listens on (the chosen one when the config said 0)."""
        return int(self._server.port) if self._server is not None else self.cfg.port

    # ------------------------------------------------------------------ Node

    def start(self) -> None:
        import foxglove

        context = foxglove.Context()
        self._channels = Channels(context, self.rig)
        self._view = CoverageView(self.rig, self.cfg.coverage_window_s)
        try:  # a name that resolves nowhere is the host's fault, not the port's
            socket.getaddrinfo(self.cfg.host, None)
        except (socket.gaierror, UnicodeError) as err:
            raise GraphError(
                f"monitor: --monitor-host {self.cfg.host!r} is no address of this computer ({err}); expected "
                "one of its addresses or names (0.0.0.0: every one)"
            ) from err
        try:
            self._server = foxglove.start_server(
                name="sensorbox monitor", host=self.cfg.host, port=self.cfg.port, context=context,
                message_backlog_size=self.cfg.backlog_msgs,
            )  # fmt: skip
        except Exception as err:  # the port is taken, the host is not this computer's
            raise GraphError(
                f"monitor: cannot serve on {self.cfg.host}:{self.cfg.port}: {err}; "
                "choose another --monitor port"
            ) from err
        where = socket.gethostname() if self.cfg.host in ("0.0.0.0", "::") else self.cfg.host
        log.info(
            "monitor: in Foxglove, Open connection > Foxglove WebSocket > ws://%s:%d (layout: %s)",
            where, self.port, "sensorbox/share/foxglove/monitor_layout.json",
        )  # fmt: skip
        with self._lock:
            self._running = True
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-worker", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Refuse what arrives from now on, count what is parked as stopped, join the worker, close."""
        with self._lock:
            self._running = False
            self._stopping = True
            self._wake.notify()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        with self._lock:  # what no worker took (one that never started, or a frame parked at the end)
            for item in [*self._queue, *self._slots.values()]:
                self.tallies[item.topic].skip("stopped")
            self._queue.clear()
            self._slots.clear()
        if self._server is not None:
            self._server.stop()
            self._server = None

    def status(self) -> NodeStatus:
        """Counters: messages sent and skipped by reason, in all and per topic (`TOPIC.sent`,
        `TOPIC.skipped_REASON`, `TOPIC.received`); counters, not drops: the recording loses nothing."""
        counts = self.counts()
        counters = {"sent": float(sum(t.sent for t in counts.values()))}
        for reason in REASONS:
            counters[f"skipped_{reason}"] = float(sum(t.skipped.get(reason, 0) for t in counts.values()))
        for topic, t in counts.items():
            counters[f"{topic}.received"] = float(t.received)
            counters[f"{topic}.sent"] = float(t.sent)
            for reason, n in t.skipped.items():
                counters[f"{topic}.skipped_{reason}"] = float(n)
        return NodeStatus(counters, error=self.error)

    def counts(self) -> dict[str, Tally]:
        """Each monitored topic's books (copies)."""
        with self._lock:
            return {t: Tally(c.received, c.sent, dict(c.skipped)) for t, c in self.tallies.items()}

    def ticker(self, on_tick: Callable[[GraphSnapshot], None] | None) -> Callable[[GraphSnapshot], None]:
        """An `on_tick` for `run_graph` that hands each snapshot to the status channel, then to `on_tick`."""

        def tick(snap: GraphSnapshot) -> None:
            with self._lock:
                self._status = snap
                self._wake.notify()
            if on_tick is not None:
                on_tick(snap)

        return tick

    # ------------------------------------------------------------------ input (publisher threads)

    def offer(self, topic: str, msgtype: str, stamp_ns: int, raw: bytes) -> None:
        """Count one bus message and park it for the worker, or count why not; never blocks on the
        worker (one short lock, no copies). `stamp_ns` (the header stamp) paces frames and IMU samples."""
        stream = self._streams[topic]
        wanted = self._wanted(stream)
        with self._lock:
            tally = self.tallies.get(topic)
            if tally is None:
                tally = self.tallies[topic] = Tally()
            tally.received += 1
            if not self._running:
                tally.skip("stopped")
            elif not wanted:
                tally.skip("no_client")
            elif self._too_soon(stream, stamp_ns):
                tally.skip("rate")
            elif stream.kind == "image":
                self._park_frame(_Item(stream, topic, msgtype, raw))
            elif len(self._queue) >= self.cfg.queue_msgs:
                tally.skip("backlog")
            else:
                self._queue.append(_Item(stream, topic, msgtype, raw))
                self._wake.notify()

    def _wanted(self, stream: Stream) -> bool:
        """Whether a client subscribed to the stream's channel or to the coverage it feeds."""
        ch = self._channels
        if ch is None:
            return False
        return ch.subscribed(stream.channel) or (stream.feeds_coverage and ch.subscribed(ch.COVERAGE))

    def _too_soon(self, stream: Stream, stamp_ns: int) -> bool:
        """Whether a frame (IMU sample) comes less than 1 / image_hz (imu_hz) after the last one of its
        stream taken, by header stamps; sweeps are all taken. Caller holds the lock. A stamp that went
        back (a clock reset) is taken and starts over."""
        hz = {"image": self.cfg.image_hz, "imu": self.cfg.imu_hz}.get(stream.kind)
        if hz is None:
            return False
        last = self._last_taken.get(stream.channel)
        if last is not None and 0 <= stamp_ns - last < 1e9 / hz:
            return True
        self._last_taken[stream.channel] = stamp_ns
        return False

    def _park_frame(self, item: _Item) -> None:
        """The frame into its camera's slot (caller holds the lock); the one it replaces is superseded."""
        role = item.stream.name
        old = self._slots.get(role)
        if old is not None:
            self.tallies[old.topic].skip("superseded")
        self._slots[role] = item
        self._wake.notify()

    # ------------------------------------------------------------------ worker thread

    def _take(self) -> tuple[list[_Item], GraphSnapshot | None, bool]:
        """What is parked (queue first, then frames) and the latest snapshot; True once stopping."""
        with self._lock:
            if not (self._queue or self._slots or self._status or self._stopping):
                self._wake.wait(0.1)
            items = [*self._queue, *self._slots.values()]
            self._queue.clear()
            self._slots.clear()
            snap, self._status = self._status, None
            return items, snap, self._stopping

    def _run(self) -> None:
        with contextlib.suppress(OSError):  # not Linux, or refused: the worker keeps the process's priority
            os.setpriority(
                os.PRIO_PROCESS, threading.get_native_id(), os.getpriority(os.PRIO_PROCESS, 0) + WORKER_NICE
            )
        next_coverage = time.monotonic()
        while True:
            items, snap, stopping = self._take()
            if stopping:
                self._count(items, "stopped")
                return
            for k, item in enumerate(items):
                try:
                    self._handle(item)
                except Exception as err:  # a monitor bug must not stop the recording: counted, logged once
                    self._count(items[k:], "error")
                    self._fail(f"monitor: {type(err).__name__}: {err}")
                    break
            try:
                if snap is not None:
                    self._send_status(snap)
                if time.monotonic() >= next_coverage:
                    next_coverage = time.monotonic() + 1.0 / self.cfg.coverage_hz
                    self._send_coverage()
            except Exception as err:
                self._fail(f"monitor: {type(err).__name__}: {err}")

    def _count(self, items: list[_Item], reason: str) -> None:
        with self._lock:
            for item in items:
                self.tallies[item.topic].skip(reason)

    def _fail(self, line: str) -> None:
        if self.error is None:
            self.error = line
            log.exception("%s", line)

    def _handle(self, item: _Item) -> None:
        """Decode one parked message, feed the coverage, send it on its channel (or count why not)."""
        assert self._channels is not None and self._view is not None
        try:
            decoded = decode_for_monitor(item.stream, item.msgtype, item.raw)
        except Exception as err:  # undecodable bytes: the recorder still records them as they came
            log.debug("monitor: %s: %s", item.topic, err)
            reason: str | None = "decode"
        else:
            self._view.feed(item.stream, decoded)
            reason = self._channels.send(item.stream, decoded)
        with self._lock:
            tally = self.tallies[item.topic]
            if reason is None:
                tally.sent += 1
            else:
                tally.skip(reason)

    def _send_status(self, snap: GraphSnapshot) -> None:
        assert self._channels is not None and self._view is not None
        if self._channels.subscribed(self._channels.STATUS):
            last = self._view.last
            self._channels.send_status(snap, self.counts(), last.coverage.fraction if last else None)

    def _send_coverage(self) -> None:
        assert self._channels is not None and self._view is not None
        if not self._channels.subscribed(self._channels.COVERAGE):
            return
        rendered = self._view.render()
        if rendered is not None:
            self._channels.send_coverage(rendered.image, rendered.stamp_ns)


def plan_rig(nodes: Sequence[Any]) -> Path | None:
    """The rig the first of a launch plan's nodes (`launch.NodeSpec`) with a `rig` parameter names (the
    emulators' and the simulated cameras'), or None."""
    for node in nodes:
        value = node.params.get("rig")
        if value:
            return Path(str(value))
    return None
