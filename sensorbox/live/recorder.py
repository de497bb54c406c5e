"""The live recorder: bounded per-topic queues into ROS 2 mcap bags, split by size or duration.

Where it writes, deliberately: each bag is a rosbag2 folder `OUT/<name>_<NNN>/`
written in place (`BagWriter(in_place=True)`), not under a hidden temporary
name. While it records, the folder holds `<name>_<NNN>.mcap` and no
metadata.yaml; closing writes the mcap summary and metadata.yaml. A recorder
killed with SIGKILL (or a power cut) therefore leaves a folder that `ingest
--salvage` reads chunk by chunk: every chunk written so far survives and only
the open chunk is lost. The open chunk is closed and flushed at least every
`flush_s` seconds (and whenever it passes 1 MiB, rosbags' chunk size), so a kill
loses at most about `flush_s` seconds or 1 MiB of messages, plus what sat in
the queues.

Per message: the bus calls `enqueue` in the publisher's thread; it appends to
that topic's queue under one lock and stamps the log time (host receive time,
ns), or drops the message and counts it when the topic's queue is full
(`queue_msgs` messages or `queue_bytes` bytes), so one flooding topic cannot
starve the others nor grow memory without bound. One writer thread drains all
queues in receive order into the bag: embedded message definitions
(`add_connection(typestore=...)`), zstd chunks, rosbag2 metadata version 8.

Stops: `stop()` (SIGINT/SIGTERM through the launch runner) drains the queues and
closes the bag readable. Every `disk_check_s` the free space of OUT is checked;
below `min_free_bytes` the recorder closes its bag, drops (and counts) what
still arrives, and asks the graph to shut down, so the disk never fills. After
`duration_s` of recording (0 = never) it asks the graph to shut down as well;
with `in_graph=True` (the launch runner's recorder node) the time counts from
when every node of the graph has started (`graph_started()`), so slow starters
such as pre-rendering cameras are not cut short; alone, from the first message.

A full disk between two checks (or a quota, or another writer filling it)
makes a write fail: the messages the bag could not take (those of its open
chunk) are moved from written to dropped, the bag is cut back to its last
complete chunk and closed, one line names the bag and the error, and the graph
is asked to shut down with that line as its error. `written` therefore always
counts what a reader finds in the bags.

Drop counters by stage: `queue` (queue full), `disk` (disk full: after the disk
guard stopped recording, or refused by a full disk), `write` (the writer refused
a message, e.g. a type unknown to the typestore, or an I/O error other than a
full disk), `stopped` (arrived after stop()).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Collection
from pathlib import Path
from typing import Any

from calibration.files import file_kind
from sensorbox.errors import RecorderError
from sensorbox.live.bagwriter import NO_SPACE, BagWriteError, BagWriter
from sensorbox.live.bus import PRIORITY_SINK, NodeStatus, Shutdown
from sensorbox.live.recorder_config import (
    DiskFree,
    MiB,
    RecorderConfig,
    TopicCounters,
    default_bag_name,
    disk_free_bytes,
)

log = logging.getLogger(__name__)


class Recorder:
    """Record bus messages into mcap bags (see the module docstring). A `Node` (priority: sink)."""

    priority = PRIORITY_SINK

    def __init__(
        self,
        cfg: RecorderConfig,
        name: str = "recorder",
        shutdown: Shutdown | None = None,
        disk_free: DiskFree = disk_free_bytes,
        clock_ns: Callable[[], int] = time.time_ns,
        in_graph: bool = False,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        """`clock_ns` stamps each message's receive (log) time; `monotonic` (seconds) measures
        `duration_s`. Tests pass their own clocks to make both deterministic."""
        cfg.validate()
        self.cfg = cfg
        self.name = name
        self.bag_name = cfg.name or default_bag_name()
        self._shutdown = shutdown
        self._disk_free = disk_free
        self._clock_ns = clock_ns
        self._monotonic = monotonic
        self._wanted = frozenset(cfg.topics) if cfg.topics else None
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._queues: dict[str, deque[tuple[int, str, bytes]]] = {}
        self._order: deque[str] = deque()  # topic of every queued message, in receive order
        self.topics: dict[str, TopicCounters] = {}
        self._stopping = False
        self._accepting = False
        self._thread: threading.Thread | None = None
        self._bag: BagWriter | None = None
        self._bag_index = 0
        self._bag_start_ns = 0
        self._bag_mcap: Path | None = None
        self.files: list[Path] = []
        self.disk_full = False
        self._halted = False  # recording stopped for good (disk full, a failed write)
        self.disk_free = -1
        self.error: str | None = None
        self._first_write: float | None = None  # monotonic time of the first message written
        self._graph_started: float | None = None
        self._in_graph = in_graph
        self._duration_requested = False
        self._written_total = 0
        self._flushed_total = 0  # messages in complete chunks flushed to the OS: they survive a SIGKILL

    # ------------------------------------------------------------------ Node

    def start(self) -> None:
        out = self.cfg.out
        if out.exists() and not out.is_dir():  # mkdir would say only "File exists"
            what = "a file" if out.is_file() else file_kind(out.stat().st_mode)
            raise RecorderError(f"{out}: is {what}, not a folder; give out a folder for the bags")
        first = self._bag_dir(0)
        if first.exists():
            raise RecorderError(f"{first} exists already; choose another recorder name or out folder")
        self.cfg.out.mkdir(parents=True, exist_ok=True)
        self._check_disk()
        if self.disk_full:
            raise RecorderError(
                f"{self.cfg.out}: only {self.disk_free / MiB:.0f} MiB free, below the recorder's "
                f"min_free_bytes {self.cfg.min_free_bytes / MiB:.0f} MiB; free space or lower min_free"
            )
        with self._lock:
            self._accepting = True
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-writer", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Drain the queues, close the bag (readable), join the writer."""
        with self._lock:
            self._accepting = False
            self._stopping = True
            self._wake.notify()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def graph_started(self) -> None:
        """Every node of the graph runs now: `duration_s` counts from here."""
        self._graph_started = self._monotonic()

    def status(self) -> NodeStatus:
        with self._lock:
            rates = {t: c.rate_hz() for t, c in self.topics.items()}
            topics = {t: (c.written, c.queue_drops, c.disk_drops, c.write_drops, c.stopped_drops, c.bytes)
                      for t, c in self.topics.items()}  # fmt: skip
            queued = sum(len(q) for q in self._queues.values())
        drops = {
            "queue": sum(v[1] for v in topics.values()),
            "disk": sum(v[2] for v in topics.values()),
            "write": sum(v[3] for v in topics.values()),
            "stopped": sum(v[4] for v in topics.values()),
        }
        counters = {
            "bytes_written": float(sum(v[5] for v in topics.values())),
            "disk_free_bytes": float(self.disk_free),
            "queued": float(queued),
            "bags": float(len(self.files)),
            "flushed_msgs": float(self._flushed_total),
        }
        return NodeStatus(
            counters, drops, {t: v[0] for t, v in topics.items()}, tuple(self.files), rates, self.error
        )

    # ------------------------------------------------------------------ input

    def enqueue(self, topic: str, msgtype: str, stamp_ns: int, raw: bytes) -> bool:
        """Queue one message (called by the bus in the publisher's thread); False if it was dropped."""
        del stamp_ns  # the bag's log time is the receive time; header stamps stay inside `raw`
        if self._wanted is not None and topic not in self._wanted:
            return False
        cfg = self.cfg
        with self._lock:
            c = self.topics.get(topic)
            if c is None:
                c = self.topics[topic] = TopicCounters(msgtype)
            c.received += 1
            if not self._accepting:
                if self.disk_full:
                    c.disk_drops += 1
                else:
                    c.stopped_drops += 1
                return False
            q = self._queues.get(topic)
            if q is None:
                q = self._queues[topic] = deque()
            if len(q) >= cfg.queue_msgs or c.queued_bytes + len(raw) > cfg.queue_bytes:
                c.queue_drops += 1
                return False
            q.append((self._clock_ns(), msgtype, raw))
            c.queued_bytes += len(raw)
            c.queue_peak = max(c.queue_peak, len(q))
            self._order.append(topic)
            self._wake.notify()
        return True

    def subscribe_to(self, bus: Any, topics: Collection[str] | None = None) -> None:
        """Subscribe `enqueue` to a `sensorbox.live.bus.Bus` (every topic unless the config names some)."""
        bus.subscribe(self.enqueue, topics if topics is not None else (self.cfg.topics or None))

    # ------------------------------------------------------------------ writer thread

    def _next(self, timeout_s: float) -> tuple[str, int, str, bytes] | None:
        """The oldest queued message (all topics, receive order), waiting up to `timeout_s`."""
        with self._lock:
            if not self._order and not self._stopping:
                self._wake.wait(timeout_s)
            if not self._order:
                return None
            topic = self._order.popleft()
            recv_ns, msgtype, raw = self._queues[topic].popleft()
            self.topics[topic].queued_bytes -= len(raw)
            return topic, recv_ns, msgtype, raw

    def _run(self) -> None:
        next_check = next_flush = time.monotonic()
        try:
            while True:
                item = self._next(0.05)
                if item is not None:
                    self._write(*item)
                now = time.monotonic()
                if now >= next_check:
                    next_check = now + self.cfg.disk_check_s
                    self._check_disk()
                self._check_duration(self._monotonic())
                if now >= next_flush:
                    next_flush = now + self.cfg.flush_s
                    if self._bag is not None:
                        try:
                            self._bag.flush()
                            self._flushed_total = self._written_total
                        except BagWriteError as err:
                            self._write_failed(err)
                if item is None and self._stopping:
                    with self._lock:
                        if not self._order:
                            break
        except Exception as err:
            self.error = f"recorder {self.name!r}: {type(err).__name__}: {err}"
            log.exception("recorder writer failed")
            with self._lock:
                self._accepting = False
            if self._shutdown is not None:
                self._shutdown.request(self.error, error=True)
        finally:
            closing = self._close_bag()
            if closing is not None:
                self._report_error(f"{self.name}: {closing}")

    def _write(self, topic: str, recv_ns: int, msgtype: str, raw: bytes) -> None:
        c = self.topics[topic]
        if self._halted:
            if self.disk_full:
                c.disk_drops += 1
            else:
                c.write_drops += 1
            return
        if c.msgtype != msgtype:
            c.write_drops += 1
            log.warning("%s: %s arrived with type %s, recording %s", self.name, topic, msgtype, c.msgtype)
            return
        bag = self._bag
        if bag is not None and self._should_split(recv_ns):
            closing = self._close_bag()
            bag = None
            if closing is not None:  # no room for its summary: no room for the next bag either
                self._stop_recording(
                    f"{self.name}: {closing}; recording stopped", error=True, no_space=closing.no_space
                )
                self._write(topic, recv_ns, msgtype, raw)  # counted as dropped now that recording halted
                return
        if bag is None:
            try:
                bag = self._open_bag(recv_ns)
            except BagWriteError as err:
                err.lost[topic] = (err.lost.get(topic, (0, 0))[0] + 1, 0)  # this message, never counted
                c.written += 1
                self._written_total += 1
                self._write_failed(err)
                return
        if topic not in bag.counts:
            try:
                bag.add(topic, msgtype)
            except Exception as err:  # rosbags: type unknown to the typestore
                c.write_drops += 1
                log.error("%s: cannot record %s (%s): %s", self.name, topic, msgtype, err)
                return
        if self._first_write is None:
            self._first_write = self._monotonic()
        if not c.written:
            c.first_ns = recv_ns
        c.last_ns = recv_ns
        c.written += 1  # taken back by _uncount if the bag refuses it
        c.bytes += len(raw)
        self._written_total += 1
        try:
            bag.write(topic, recv_ns, raw)
        except BagWriteError as err:
            self._write_failed(err)

    def _write_failed(self, err: BagWriteError) -> None:
        """The bag refused bytes (disk full): what it lost becomes dropped, recording stops, the bag
        is closed (cut back to its last complete chunk), and the graph is asked to shut down."""
        self._uncount(err)
        self._stop_recording(f"{self.name}: {err}; recording stopped", error=True, no_space=err.no_space)

    def _report_error(self, line: str) -> None:
        """A failure of the recording, reported once: the node's error and, in a graph, the graph's.

        In a graph the runner hands the error to whoever runs it (the CLI prints it
        as its one `error:` line), so it is logged at INFO only; alone (no shutdown
        to tell) it is an ERROR record. The first error stays the node's error.
        """
        self.error = self.error or line
        if self._shutdown is not None:
            log.info("%s", line)
            self._shutdown.request(line, error=True)
        else:
            log.error("%s", line)

    def _uncount(self, err: BagWriteError) -> None:
        """Messages counted as written that the bag does not hold: dropped at the disk (or write) stage."""
        for topic, (n, size) in err.lost.items():
            c = self.topics[topic]
            c.written -= n
            c.bytes -= size
            self._written_total -= n
            if err.no_space:
                c.disk_drops += n
            else:
                c.write_drops += n

    def _should_split(self, recv_ns: int) -> bool:
        cfg = self.cfg
        if cfg.split_s > 0 and recv_ns - self._bag_start_ns >= cfg.split_s * 1e9:
            return True
        if cfg.split_bytes > 0 and self._bag_mcap is not None:
            try:
                return self._bag_mcap.stat().st_size >= cfg.split_bytes
            except OSError:
                return False
        return False

    def _bag_dir(self, index: int) -> Path:
        return self.cfg.out / f"{self.bag_name}_{index:03d}"

    def _open_bag(self, recv_ns: int) -> BagWriter:
        path = self._bag_dir(self._bag_index)
        self._bag_index += 1
        if path.exists():  # made since `start` looked: another recorder (a second launch) writes into it
            raise BagWriteError(
                f"{path} exists already: another recorder started into it meanwhile; choose another recorder "
                "name or out folder",
                {},
                False,
            )
        bag = BagWriter(path, "mcap", compress=self.cfg.compress, in_place=True)
        try:
            bag.__enter__()
        except OSError as err:
            raise BagWriteError(
                f"{path}: cannot create the bag: {err.strerror or err}", {}, err.errno in NO_SPACE
            ) from None
        # topics seen before this split are declared again, so every bag is self-contained
        self._bag, self._bag_start_ns = bag, recv_ns
        self._bag_mcap = path / f"{path.name}.mcap"
        self.files.append(path)
        bag.flush()  # the mcap magic and header reach the file now: even an early kill leaves an mcap
        log.info("%s: recording into %s", self.name, path)
        return bag

    def _close_bag(self) -> BagWriteError | None:
        """Close the open bag (summary, metadata.yaml); the error when they did not fit, for the
        caller to report (the bag's complete chunks stay, what it lost is counted as dropped)."""
        bag, self._bag, self._bag_mcap = self._bag, None, None
        if bag is None:
            return None
        failed = None
        try:
            bag.__exit__(None, None, None)
        except BagWriteError as err:  # no room left for the summary: the complete chunks stay
            self._uncount(err)
            failed = err
        self._flushed_total = self._written_total
        return failed

    def _check_disk(self) -> None:
        try:
            self.disk_free = int(self._disk_free(self.cfg.out))
        except OSError as err:
            log.warning("%s: cannot read free space of %s: %s", self.name, self.cfg.out, err)
            return
        if self.disk_free < self.cfg.min_free_bytes and not self.disk_full:
            reason = (
                f"{self.name}: disk free {self.disk_free / MiB:.0f} MiB below min_free "
                f"{self.cfg.min_free_bytes / MiB:.0f} MiB; recording stopped, bag closed"
            )
            log.warning(reason)
            self._stop_recording(reason)

    def _stop_recording(self, reason: str, error: bool = False, no_space: bool = True) -> None:
        """Refuse what arrives from now on, drop (and count) what is queued, close the bag, and
        ask the graph to shut down."""
        self.disk_full = self.disk_full or no_space
        self._halted = True
        with self._lock:
            self._accepting = False
            for topic, q in self._queues.items():
                c = self.topics[topic]
                if no_space:
                    c.disk_drops += len(q)
                else:
                    c.write_drops += len(q)
                c.queued_bytes = 0
                q.clear()
            self._order.clear()
        closing = self._close_bag()
        if closing is not None:  # the summary did not fit either: one line says both
            reason, error = f"{reason}; {closing}", True
        if error:
            self._report_error(reason)
        elif self._shutdown is not None:
            self._shutdown.request(reason)

    def _check_duration(self, now: float) -> None:
        d = self.cfg.duration_s
        first = self._graph_started if self._in_graph else self._first_write
        if d > 0 and first is not None and not self._duration_requested and now - first >= d:
            self._duration_requested = True
            if self._shutdown is not None:
                self._shutdown.request(f"{self.name}: recorded {d:g} s")
