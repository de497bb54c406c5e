"""An emulated Mid-360 in its own process: it streams to a driver, reports its counters, fails in one line."""

from __future__ import annotations

import pytest

from sensorbox.errors import GraphError
from sensorbox.livox import DriverConfig, LidarEndpoint, Mid360Driver, Ports
from sensorbox.sim.emulator_process import EmulatorProcess, EmulatorSpec
from sensorbox.sim.run import SimConfig
from tests.live import wait_for

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
