"""The Mid-360 driver in its own process (issue 20, class 11): the graph's process may stall, the
driver keeps receiving, and every message it publishes reaches the parent once, in order."""

from __future__ import annotations

import os
import signal
import threading

import numpy as np
import pytest

from ingest.bags.livox_msg import decode_custom_msg
from sensorbox.errors import DriverError
from sensorbox.livox.process import DriverProcess
from sensorbox.sim.mid360 import Mid360Emulator, credit_from
from sensorbox.sim.run import SimConfig, setup_sim
from sensorbox.sim.scan_source import SimScan, SweepList
from tests.live import HANG_S, wait_for
from tests.sensorbox.test_livox_driver import WINDOW, Sink, config, fresh_ports, quantised_m, xyz_of

pytestmark = pytest.mark.realtime  # a child process, UDP sockets and threads


def test_the_driver_process_keeps_receiving_while_the_graph_is_stalled():
    """The first message the parent gets blocks its consumer until the emulator has sent everything
    and the child has taken it: only a receive path outside the parent can get there. Afterwards
    every sweep and IMU sample the child published arrived once, in order, with the simulator's points."""
    setup = setup_sim(SimConfig(scene="indoor", duration_s=0.5, scale=0.1, seed=2))
    items = list(SimScan(setup, 0).sweeps())
    ports = fresh_ports()
    ip, topic = "127.0.0.2", "/livox/lidar_127_0_0_2"
    sink, stalled = Sink(), threading.Event()
    emu = Mid360Emulator(ip, SweepList(items), ports=ports, rate=3.0, window=WINDOW)

    def publish(*msg) -> None:
        if not stalled.is_set():
            stalled.set()
            assert emu.wait_done(HANG_S)  # the graph's consumer is stuck meanwhile
            wait_for(lambda: driver.received(ip)[0] == emu.counters.point_datagrams, "the child to take all")
        sink(*msg)

    driver = DriverProcess(config(ports, ip), publish)
    emu.credit = credit_from(driver.received, ip)
    with emu, driver:
        assert driver.pid is not None and driver.pid != os.getpid()
        assert emu.wait_done(HANG_S)
        wait_for(lambda: driver.received(ip)[0] == emu.counters.point_datagrams, "the child to take all")
    st = driver.stats()
    s = st.lidars[ip]
    assert s.unaccounted_point_datagrams() == s.unaccounted_imu_datagrams() == 0
    assert (s.point_datagrams, s.imu_datagrams) == (emu.counters.point_datagrams, emu.counters.imu_datagrams)
    assert (s.lost, s.late, st.kernel_drops) == (0, 0, 0)  # under flow control nothing may go missing
    assert len(sink.msgs) == driver.delivered == s.sweeps + s.imu_packets  # each once, none lost in the pipe
    got = [decode_custom_msg(m[3], 2) for m in sink.on(topic)]
    assert [g.timebase_ns for g in got] == [sw.timebase_ns for sw in items]
    np.testing.assert_array_equal(xyz_of(np.concatenate([g.points for g in got])),
                                  quantised_m(np.concatenate([sw.points for sw in items])))  # fmt: skip
    assert driver.granted_nice == (-10 if os.geteuid() == 0 else driver.granted_nice)  # root: raised


def test_a_driver_process_that_dies_is_one_clear_error():
    ports = fresh_ports()
    driver = DriverProcess(config(ports, "127.0.0.2", command_timeout_s=0.05, command_retries=0), Sink())
    with pytest.raises(
        DriverError, match=r"^livox driver process: lidar 127\.0\.0\.2: no ACK to command 0x0100"
    ):
        driver.start()  # no lidar answers: the child's DriverError comes back as one line
    emu = Mid360Emulator("127.0.0.2", SweepList([]), ports=ports)
    driver = DriverProcess(config(ports, "127.0.0.2"), Sink())
    with emu:
        driver.start()
        assert driver.pid is not None
        os.kill(driver.pid, signal.SIGKILL)
        wait_for(lambda: driver.error is not None, "the parent to notice")
        driver.stop()
    assert driver.error == "the driver process ended unexpectedly (exit code -9)"
