"""An emulated Mid-360 in its own process: it streams to a driver, reports its counters, fails in one line."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from sensorbox.errors import GraphError
from sensorbox.livox import DriverConfig, LidarEndpoint, Mid360Driver, Ports
from sensorbox.sim.config import SimConfig
from sensorbox.sim.emulator_process import EmulatorProcess, EmulatorSpec
from tests.live import HANG_S, wait_for
from tests.paths import ROOT

pytestmark = pytest.mark.realtime


def _spec(lidar: str, base: int) -> EmulatorSpec:
    sim = SimConfig(scene="indoor", trajectory="static", scale=0.125, range_noise_m=0.0)
    return EmulatorSpec("emu", sim, lidar, "127.0.0.12", 0.5, {"ports": Ports.block(base)})


def test_a_bad_lidar_name_is_one_graph_error_from_the_child() -> None:
    proc = EmulatorProcess(_spec("lidar_sideways", 57300))
    with pytest.raises(
        GraphError, match=r"^emulator emu: rig has no lidar 'lidar_sideways'; it has lidar_top"
    ):
        proc.start()


def test_the_child_streams_to_a_driver_and_its_final_counters_add_up() -> None:
    base = 57400
    proc = EmulatorProcess(_spec("lidar_top", base))
    proc.start()
    sweeps: list[str] = []
    try:
        cfg = DriverConfig(
            "127.0.0.1", (LidarEndpoint("127.0.0.12"),), ports=Ports.block(base),
            discovery_address="127.0.0.12", command_timeout_s=60.0,
        )  # fmt: skip
        with Mid360Driver(cfg, lambda topic, *_: sweeps.append(topic)) as driver:
            wait_for(
                lambda: sum("lidar" in t for t in sweeps) >= 5, "five sweeps from the emulator's process"
            )
            received = driver.received("127.0.0.12")
    finally:
        proc.stop()
    assert sum("lidar" in t for t in sweeps) >= 5
    counters = proc.counters
    assert counters["packets_sent"] >= received[0] > 0 and counters["sweeps_sent"] >= 5
    assert counters["imu_sent"] >= received[1] > 0


KILLED_PARENT = """
import sys, time
from sensorbox.livox import DriverConfig, LidarEndpoint, Ports
from sensorbox.livox.process import DriverProcess
from sensorbox.sim.emulator_process import EmulatorProcess, EmulatorSpec
from sensorbox.sim.config import SimConfig

base = int(sys.argv[1])
sim = SimConfig(scene="indoor", trajectory="static", scale=0.125, range_noise_m=0.0)
EmulatorProcess(EmulatorSpec("emu", sim, "lidar_top", "127.0.0.12", 0.5, {"ports": Ports.block(base)})).start()
cfg = DriverConfig("127.0.0.1", (LidarEndpoint("127.0.0.12"),), ports=Ports.block(base),
                   discovery_address="127.0.0.12", command_timeout_s=60.0)
DriverProcess(cfg, lambda *msg: None).start()
print("running", flush=True)
time.sleep(600)
"""


def test_children_of_a_killed_launch_stop_with_one_line_each() -> None:
    """Issue 49: SIGKILL of a launch printed BrokenPipeError tracebacks from its emulator and driver
    children; each now stops and says so in one line."""
    proc = subprocess.Popen(
        [sys.executable, "-c", KILLED_PARENT, "57600"], cwd=ROOT, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    try:
        assert proc.stdout is not None and proc.stdout.readline() == "running\n"
        time.sleep(1.0)  # the children report and stream
        proc.kill()
        _, err = proc.communicate(timeout=HANG_S)  # EOF once every child, which shares stderr, ended
    finally:
        proc.kill()
    assert sorted(err.splitlines()) == [
        "emulator emu: stopped; the process that started it is gone (killed)",
        "livox driver process: stopped; the process that started it is gone (killed)",
    ]
