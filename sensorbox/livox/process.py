"""The Mid-360 driver in a process of its own, so that nothing else in the graph can starve its receive
threads.

In one Python process the driver's point thread shares the interpreter lock
with camera encoding, the recorder and (emulated rigs) the emulators: when the
CPU is contended, a thread that holds the lock while the OS preempts it stalls
every other one, the socket buffer fills and the kernel drops datagrams
(32,134 lost in 14 s on 2 busy cores). Here the driver runs
in a child process (spawned, not forked: the parent has threads) that only
receives, decodes and frames; at startup it asks for a higher scheduling
priority (`nice`, granted only with CAP_SYS_NICE or a raised RLIMIT_NICE; what
it got is reported). Its messages, serialised as the driver publishes them,
come back through a pipe in order; a thread of the parent hands them to
`publish` (never concurrently), so a slow consumer delays them instead of
losing datagrams: the child queues them (memory grows while it waits).

Counters: the child sends `DriverStats` every `STATS_S` and once more after
stopping, so `stats()` after `stop()` is final. `counters()` adds the child's
pid, the niceness it got and the messages delivered to `publish`.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import queue
import signal
import threading
from collections.abc import Callable
from multiprocessing.connection import Connection
from types import TracebackType
from typing import Any

from ingest.runtime.lifetime import orphaned, sigint_blocked
from sensorbox.errors import DriverError
from sensorbox.livox.config import DriverConfig, DriverStats
from sensorbox.livox.discovery import discover
from sensorbox.livox.protocol import DeviceInfo

log = logging.getLogger(__name__)

Publish = Callable[[str, str, int, bytes], None]
STATS_S = 0.2
START_S = 120.0  # spawning imports numpy and the driver: slow on a busy machine, but not this slow


def _child(
    config: DriverConfig, msgs: Connection, status: Connection, control: Connection, nice: int
) -> None:
    """The child: raise priority, run the driver; messages go out on `msgs` (then "end"), starts,
    errors and counters on `status`, so counters stay current while the parent's consumer is slow."""
    from sensorbox.livox.driver import Mid360Driver

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the process group: the parent stops us
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, 0, nice)  # refused without privilege: stays at the default
    pending: queue.SimpleQueue[tuple[str, Any] | None] = queue.SimpleQueue()

    def sender() -> None:
        with contextlib.suppress(OSError):  # the parent is gone (killed): the main thread says so, once
            while (item := pending.get()) is not None:
                msgs.send(item)

    thread = threading.Thread(target=sender, name="livox-ipc", daemon=True)
    thread.start()
    driver = Mid360Driver(config, lambda *msg: pending.put(("msg", msg)))
    try:
        try:
            driver.start()
        except (
            Exception
        ) as err:  # DriverError (a bound port, a silent lidar) or worse: one line to the parent
            why = str(err) if isinstance(err, DriverError) else f"{type(err).__name__}: {err}"
            status.send(("error", why))
        else:
            status.send(("started", os.getpriority(os.PRIO_PROCESS, 0)))
            while not control.poll(STATS_S):  # a parent gone (killed) reads as a stop: the pipe's end
                status.send(("stats", driver.stats()))
            driver.stop()
            status.send(("stats", driver.stats()))
    except OSError:  # BrokenPipeError: the parent was killed (SIGKILL) and reads nothing any more
        driver.stop()
        orphaned("livox driver process")
    pending.put(("end", None))
    pending.put(None)
    thread.join()


class DriverProcess:
    """`Mid360Driver`'s interface (discover, start, stop, stats, received) with the driver in a child."""

    def __init__(self, config: DriverConfig, publish: Publish, *, nice: int = -10) -> None:
        config.validate()
        self.config = config
        self.nice = nice
        self._publish = publish
        self._stats = DriverStats({})
        self._proc: multiprocessing.process.BaseProcess | None = None
        self._control: Connection | None = None
        self._readers: list[threading.Thread] = []
        self._started = threading.Event()
        self._error: str | None = None
        self.granted_nice: int | None = None
        self.delivered = 0

    def discover(self, timeout_s: float = 3.0, *, until_found: int = 0) -> list[DeviceInfo]:
        """Broadcast discovery from this process (before `start`), as `Mid360Driver.discover`."""
        return discover(self.config, 1, timeout_s, until_found)

    def start(self) -> None:
        """Spawn the child and wait until its driver configured every lidar; DriverError if it cannot."""
        if self._proc is not None:
            return
        ctx = multiprocessing.get_context("spawn")
        pipes = [ctx.Pipe(duplex=False) for _ in range(3)]  # (receive end, send end): msgs, status, control
        args = (self.config, pipes[0][1], pipes[1][1], pipes[2][0], self.nice)
        proc = ctx.Process(target=_child, args=args, name="livox-driver", daemon=True)
        with sigint_blocked():
            proc.start()
        for conn in (pipes[0][1], pipes[1][1], pipes[2][0]):
            conn.close()
        self._proc, self._control = proc, pipes[2][1]
        self._readers = [
            threading.Thread(target=loop, args=(conn,), name=name, daemon=True)
            for loop, conn, name in ((self._read_msgs, pipes[0][0], "livox-msgs"),
                                     (self._read_status, pipes[1][0], "livox-status"))
        ]  # fmt: skip
        for t in self._readers:
            t.start()
        self._started.wait(START_S)
        if self.granted_nice is None:  # an error, a child that died, or no answer at all
            self._join(10.0)
            error = self._error or f"no answer from the driver process within {START_S:g} s"
            raise DriverError(f"livox driver process: {error}")

    def _read_msgs(self, conn: Connection) -> None:
        """Hand the child's messages to `publish` in order, until it says "end"."""
        try:
            while True:
                kind, payload = conn.recv()
                if kind == "end":
                    return
                try:
                    self._publish(*payload)
                except Exception:
                    log.exception("livox driver: publish callback failed for %s", payload[0])
                self.delivered += 1
        except (EOFError, OSError):  # the child is gone without saying "end"
            self._died()
        finally:
            conn.close()

    def _read_status(self, conn: Connection) -> None:
        """Keep the child's latest counters; note its start or the error that stopped it."""
        try:
            while True:
                kind, payload = conn.recv()
                if kind == "stats":
                    self._stats = payload
                elif kind == "started":
                    self.granted_nice = payload
                    self._started.set()
                elif kind == "error":
                    self._error = payload
                    self._started.set()
        except (EOFError, OSError):  # the child closed it: it ended (normally after "end")
            pass
        finally:
            conn.close()
            self._started.set()

    def _died(self) -> None:
        proc = self._proc
        if proc is not None:
            proc.join(1.0)
        code = proc.exitcode if proc is not None else None
        self._error = self._error or f"the driver process ended unexpectedly (exit code {code})"
        log.error("livox driver: %s", self._error)

    def stop(self) -> None:
        """Stop the child's driver (standby, open sweeps published), deliver what it sent, join it."""
        if self._proc is None:
            return
        if self._control is not None:
            with contextlib.suppress(OSError):
                self._control.send("stop")
        self._join(30.0)

    def _join(self, timeout_s: float) -> None:
        for t in self._readers:
            t.join(timeout_s)
        self._readers = []
        proc, self._proc = self._proc, None
        if proc is not None:
            proc.join(timeout_s)
            if proc.is_alive():
                proc.kill()
                proc.join()
        if self._control is not None:
            self._control.close()
            self._control = None

    @property
    def error(self) -> str | None:
        """Why the child failed or ended early, if it did."""
        return self._error

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    def stats(self) -> DriverStats:
        """The child's counters as of its last report (every STATS_S; final after `stop()`)."""
        return self._stats

    def received(self, ip: str) -> tuple[int, int]:
        """(point, IMU) datagrams taken from lidar `ip`'s ports, as of the child's last report."""
        s = self._stats.lidars.get(ip)
        return (s.point_datagrams, s.imu_datagrams) if s is not None else (0, 0)

    def __enter__(self) -> DriverProcess:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()
