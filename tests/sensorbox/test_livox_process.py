"""The Mid-360 driver in its own process (issue 20, class 11): the graph's process may stall, the
driver keeps receiving, and every message it publishes reaches the parent once, in order."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from ingest.bags.livox_msg import decode_custom_msg
from sensorbox.errors import DriverError
from sensorbox.livox.process import DriverProcess
from sensorbox.sim.config import SimConfig
from sensorbox.sim.mid360 import Mid360Emulator, credit_from
from sensorbox.sim.run import setup_sim
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


def _report_sigint_blocked(conn) -> None:
    conn.send(signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, set()))
    conn.close()


def test_a_spawned_child_starts_with_sigint_blocked_and_the_parents_sigint_is_kept():
    """Ctrl-C reaches the process group while the driver's child is still importing: it must not raise a
    KeyboardInterrupt traceback there (the child is stopped through its pipe), and the parent still gets it."""
    import multiprocessing

    from ingest.runtime.lifetime import sigint_blocked

    ctx = multiprocessing.get_context("spawn")
    got, send = ctx.Pipe(duplex=False)
    received: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        proc = ctx.Process(target=_report_sigint_blocked, args=(send,), daemon=True)
        with sigint_blocked():
            proc.start()
            signal.pthread_kill(threading.get_ident(), signal.SIGINT)  # to this thread: pending while blocked
            assert received == []
        assert received == [signal.SIGINT]  # delivered once the block ended
        send.close()
        assert got.poll(HANG_S) and got.recv() is True
        proc.join(HANG_S)
        assert proc.exitcode == 0
    finally:
        signal.signal(signal.SIGINT, previous)
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, set())


def test_a_ctrl_c_taken_by_another_thread_waits_for_the_block_to_end():
    """A Ctrl-C is process-directed: with SIGINT blocked in the main thread the kernel gives it to another
    thread, and Python runs the handler in the main thread anyway; inside the block it only waits."""
    from ingest.runtime.lifetime import sigint_blocked

    received: list[int] = []
    stop = threading.Event()
    reader = threading.Thread(target=stop.wait, daemon=True)  # SIGINT unblocked here, as a reader thread
    reader.start()
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        with sigint_blocked():
            os.kill(os.getpid(), signal.SIGINT)
            deadline = time.monotonic() + 0.5
            while time.monotonic() < deadline:  # the handler would run at one of these checks
                time.sleep(0.01)
            assert received == []
        assert received == [signal.SIGINT]
    finally:
        signal.signal(signal.SIGINT, previous)
        stop.set()
        reader.join(HANG_S)
