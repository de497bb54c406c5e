"""An emulated Mid-360 in a process of its own, like the driver it talks to (`sensorbox.livox.process`).

In the graph's process an emulator's stream thread shares the interpreter
lock with camera encoding and the recorder; on contended cores it stalled
for more than a quarter second at a time, the driver closed the open sweep
and counted the rest of its datagrams as late (475 in 15 s of
`bench_capture --hogs 2`). A real Mid-360 does not stall, so neither should
its emulator: here it runs in a spawned child, which sends its counters back
every `STATS_S` and once more after stopping.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import threading
from dataclasses import dataclass, replace
from multiprocessing.connection import Connection
from typing import Any

from ingest.runtime.lifetime import orphaned, sigint_blocked

STATS_S = 0.2
START_S = 120.0  # spawning imports the simulator and builds its scene: slow on a busy machine


@dataclass(frozen=True)
class EmulatorSpec:
    """What the child needs to build one emulator (all picklable)."""

    name: str
    sim_cfg: Any  # sensorbox.sim.config.SimConfig
    lidar: str
    ip: str
    loop_s: float
    options: dict[str, Any]


def build_emulator(spec: EmulatorSpec) -> Any:
    """The `Mid360Emulator` of `spec`, on its looped (or live) simulated scan; GraphError for a bad lidar."""
    from sensorbox.errors import GraphError
    from sensorbox.sim.mid360 import Mid360Emulator
    from sensorbox.sim.run import setup_sim
    from sensorbox.sim.scan_source import LoopedScan, SimScan

    cfg = replace(spec.sim_cfg, duration_s=spec.loop_s if spec.loop_s > 0 else 1e7)
    setup = setup_sim(cfg)
    names = [li.name for li in setup.rig.lidars]
    if spec.lidar not in names:
        raise GraphError(f"emulator {spec.name}: rig has no lidar {spec.lidar!r}; it has {', '.join(names)}")
    index = names.index(spec.lidar)
    scan = SimScan(setup, index)
    source = LoopedScan(scan, spec.loop_s) if spec.loop_s > 0 else scan
    last = (setup.rig.lidars[index].ip or "0.0.0.0").rsplit(".", 1)[-1]
    serial = f"47MDL9A00100{int(last) % 100:02d}"
    return Mid360Emulator(spec.ip, source, serial=serial, seed=cfg.seed * 100 + index, **spec.options)


def counters_of(emulator: Any) -> dict[str, float]:
    c = emulator.counters
    counts = {"packets_sent": c.packets_sent, "points_sent": c.points_sent, "imu_sent": c.imu_sent,
              "sweeps_sent": c.sweeps}  # fmt: skip
    return {k: float(v) for k, v in counts.items()}


def _child(spec: EmulatorSpec, status: Connection, control: Connection) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the process group: the parent stops us
    try:
        emulator = build_emulator(spec)
        emulator.start()
    except Exception as err:  # GraphError (a bad lidar name), an occupied port, ...: one line to the parent
        status.send(("error", str(err)))
        return
    try:
        status.send(("started", os.getpid()))
        while not control.poll(STATS_S):  # a parent gone (killed) reads as a stop: the pipe's end
            status.send(("stats", counters_of(emulator)))
        emulator.stop()
        status.send(("stats", counters_of(emulator)))
    except OSError:  # BrokenPipeError: the parent was killed (SIGKILL) and reads nothing any more
        emulator.stop()
        orphaned(f"emulator {spec.name}")


class EmulatorProcess:
    """One emulator in a spawned child: `start` (raises GraphError if it cannot), `counters`, `stop`."""

    def __init__(self, spec: EmulatorSpec) -> None:
        self.spec = spec
        self.counters: dict[str, float] = {}
        self._proc: multiprocessing.process.BaseProcess | None = None
        self._control: Connection | None = None
        self._reader: threading.Thread | None = None
        self._answered = threading.Event()
        self._error: str | None = None
        self._started = False

    def start(self) -> None:
        from sensorbox.errors import GraphError

        ctx = multiprocessing.get_context("spawn")
        status_r, status_w = ctx.Pipe(duplex=False)
        control_r, control_w = ctx.Pipe(duplex=False)
        args = (self.spec, status_w, control_r)
        proc = ctx.Process(target=_child, args=args, name=self.spec.name, daemon=True)
        with sigint_blocked():  # Ctrl-C never reaches the child, even while it imports: we stop it
            proc.start()
        status_w.close()
        control_r.close()
        self._proc, self._control = proc, control_w
        self._reader = threading.Thread(target=self._read, args=(status_r,), name=f"{self.spec.name}-status",
                                        daemon=True)  # fmt: skip
        self._reader.start()
        self._answered.wait(START_S)
        if not self._started:
            self.stop()
            raise GraphError(self._error or f"emulator {self.spec.name}: no answer within {START_S:g} s")

    def _read(self, conn: Connection) -> None:
        try:
            while True:
                kind, payload = conn.recv()
                if kind == "stats":
                    self.counters = payload
                elif kind == "started":
                    self._started = True
                    self._answered.set()
                elif kind == "error":
                    self._error = payload
                    self._answered.set()
        except (EOFError, OSError):  # the child ended
            pass
        finally:
            conn.close()
            self._answered.set()

    def stop(self) -> None:
        """Stop the child's emulator, keep its final counters, join it."""
        if self._control is not None:
            with contextlib.suppress(OSError):
                self._control.send("stop")
            self._control.close()
            self._control = None
        if self._reader is not None:
            self._reader.join(30.0)
            self._reader = None
        proc, self._proc = self._proc, None
        if proc is not None:
            proc.join(30.0)
            if proc.is_alive():
                proc.kill()
                proc.join()
