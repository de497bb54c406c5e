"""The Mid-360 driver against the emulator on UDP loopback: discovery, configuration bytes, a 10 s
two-lidar capture equal to the simulator's scan, exact loss/duplicate/reorder/malformed counts,
foreign traffic, unsynced stamps, data types 2/3, extrinsics and the other output formats.

Emulators live on 127.0.0.x (Linux routes all of 127/8 to lo); each test uses its own block of
ports so pytest-xdist workers never share one. Streams run faster than real time (`rate`).
"""

from __future__ import annotations

import binascii
import functools
import itertools
import os
import socket
import struct
import threading
import time
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from ingest.bags.decode import decode_imu, decode_pointcloud2
from ingest.bags.livox_msg import decode_custom_msg
from ingest.bags.rostypes import CUSTOM_MSG_TYPE, IMU_TYPE, POINTCLOUD2_TYPE
from sensorbox.errors import DriverError
from sensorbox.live.livox_node import LivoxDriverNode
from sensorbox.livox import DriverConfig, LidarEndpoint, Mid360Driver, Ports, packets
from sensorbox.livox import protocol as proto
from sensorbox.livox.config import DriverStats, LidarStats
from sensorbox.livox.sockets import udp_socket
from sensorbox.sim.config import SimConfig
from sensorbox.sim.lidar import Sweep, simulate_sweep
from sensorbox.sim.mid360 import Mid360Emulator, credit_from
from sensorbox.sim.nodes import sim_emulators
from sensorbox.sim.run import setup_sim
from sensorbox.sim.scan_source import SimScan, SweepList
from tests.live import HANG_S, ManualClock, wait_for

pytestmark = pytest.mark.realtime  # UDP sockets and receive threads: run serially (make test)

HOST = "127.0.0.1"
LOCAL_BROADCAST = "127.255.255.255"
_blocks = itertools.count()


def _granted_rcvbuf() -> int:
    """The point-socket buffer this host grants the driver (8 MiB as root or with a raised rmem_max)."""
    sock = udp_socket(HOST, 0, rcvbuf=DriverConfig.rcvbuf_bytes)
    try:
        return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
    finally:
        sock.close()


# Device time runs this much faster than real time. Flow control (below) keeps every stream lossless
# however busy the machine is; the real-time path at the rig's rate is bench/bench_livox.py's job.
RATE = 3.0
# Datagrams an emulator may have in flight per stream: a quarter of the receive buffer this host grants,
# at 8 KiB per datagram (about three times what a 1380-byte datagram costs the kernel on loopback).
WINDOW = max(4, _granted_rcvbuf() // 8192 // 4)


def settled(
    driver: Mid360Driver, emulators: list[Mid360Emulator], extra: dict[str, int] | None = None
) -> bool:
    """Every datagram each emulator sent (plus `extra` point datagrams from its address) was taken
    by the driver and has an outcome in its counters."""
    st = driver.stats()
    if st.kernel_drops:  # under flow control a kernel drop means WINDOW is wrong, not a slow machine
        pytest.fail(f"the kernel dropped {st.kernel_drops} datagrams despite flow control (window {WINDOW})")
    for emu in emulators:
        s = st.lidars[emu.ip]
        sent_point = emu.counters.point_datagrams + (extra or {}).get(emu.ip, 0)
        if (s.point_datagrams, s.imu_datagrams) != (sent_point, emu.counters.imu_datagrams):
            return False
        if s.unaccounted_point_datagrams() or s.unaccounted_imu_datagrams():
            return False  # taken, still being processed
    return True


def assert_books_balance(stats: DriverStats) -> None:
    """sent = kept + duplicate + stale + late + malformed, on every lidar's point and IMU port."""
    for ip, s in stats.lidars.items():
        assert s.unaccounted_point_datagrams() == 0, (ip, s)
        assert s.unaccounted_imu_datagrams() == 0, (ip, s)


def fresh_ports() -> Ports:
    """A port block no other test (or xdist worker) uses; 20000+ stays below the ephemeral range."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw")
    return Ports.block(20000 + 1000 * int(worker or 0) + 10 * next(_blocks))


class Sink:
    """The publish callback: keeps every (topic, msgtype, stamp, bytes)."""

    def __init__(self) -> None:
        self.msgs: list[tuple[str, str, int, bytes]] = []
        self.lock = threading.Lock()

    def __call__(self, topic: str, msgtype: str, stamp_ns: int, raw: bytes) -> None:
        with self.lock:
            self.msgs.append((topic, msgtype, stamp_ns, raw))

    def on(self, topic: str) -> list[tuple[str, str, int, bytes]]:
        return [m for m in self.msgs if m[0] == topic]


def run_capture(
    emulators: list[Mid360Emulator],
    cfg: DriverConfig,
    during: Callable[[Mid360Driver], None] | None = None,
    extra: dict[str, int] | None = None,
) -> tuple[Sink, Mid360Driver]:
    """Stream every emulator to a driver under flow control until each datagram has an outcome."""
    sink = Sink()
    driver = Mid360Driver(cfg, sink, clock=ManualClock())
    for emu in emulators:
        if emu.credit is None:
            emu.credit, emu.window = credit_from(driver.received, emu.ip), WINDOW
        emu.start()
    try:
        with driver:
            if during is not None:
                during(driver)
            for emu in emulators:
                assert emu.wait_done(HANG_S), emu.ip
            wait_for(lambda: settled(driver, emulators, extra), "the driver to take every datagram")
    finally:
        for emu in emulators:
            emu.stop()
    assert_books_balance(driver.stats())
    return sink, driver


def config(ports: Ports, *ips: str | LidarEndpoint, **kw: object) -> DriverConfig:
    """The driver for emulators on loopback; a command waits up to a minute for its ACK (only a hang
    takes that long), so a busy machine never causes a resend."""
    lidars = tuple(ip if isinstance(ip, LidarEndpoint) else LidarEndpoint(ip) for ip in ips)
    kw = {"command_timeout_s": 60.0, **kw}
    return DriverConfig(HOST, lidars, ports=ports, discovery_address=LOCAL_BROADCAST, **kw)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def sim() -> tuple[list[SimScan], list[list[Sweep]]]:
    """10 s of both reference-rig lidars walking outdoors (noise, dust tags and sky: zero points), simulated once."""
    setup = setup_sim(SimConfig(scene="outdoor", trajectory="walk", duration_s=10.0, scale=0.1, seed=1))
    scans = [SimScan(setup, k) for k in range(2)]
    return scans, [list(s.sweeps()) for s in scans]


def quantised_m(sweep_points: np.ndarray, data_type: int = 1) -> np.ndarray:
    """What the driver must output for simulator points sent as data type 1 or 2 (float32 metres)."""
    xyz = np.stack([sweep_points[n].astype(np.float64) for n in "xyz"], axis=-1)
    scale = 1000.0 if data_type == 1 else 100.0
    return (np.rint(xyz * scale) / scale).astype(np.float32)


def xyz_of(points: np.ndarray) -> np.ndarray:
    return np.stack([points["x"], points["y"], points["z"]], axis=-1)


# --------------------------------------------------------------------------- discovery and configuration


def test_discovery_finds_every_emulator():
    ports = fresh_ports()
    emus = [
        Mid360Emulator(f"127.0.0.{k}", SweepList([]), serial=f"47MDL9A00100{k:02d}", ports=ports)
        for k in (2, 3)
    ]
    for emu in emus:
        emu.start()
    try:
        driver = Mid360Driver(config(ports, "127.0.0.2", "127.0.0.3"), Sink())
        found = driver.discover(timeout_s=HANG_S, until_found=2)
        assert found == [
            proto.DeviceInfo("127.0.0.2", "47MDL9A0010002", 9, ports.lidar_cmd, 0),
            proto.DeviceInfo("127.0.0.3", "47MDL9A0010003", 9, ports.lidar_cmd, 0),
        ]
        unicast = Mid360Driver(
            DriverConfig(HOST, (LidarEndpoint("127.0.0.3"),), ports=ports, discovery_address="127.0.0.3"),
            Sink(),
        )
        assert [d.ip for d in unicast.discover(timeout_s=HANG_S, until_found=1)] == ["127.0.0.3"]
    finally:
        for emu in emus:
            emu.stop()
    # the broadcast reached both, the unicast request only 127.0.0.3 (a slow reply may bring a resend)
    replies = [e.counters.discovery_replies for e in emus]
    assert replies[0] >= 1 and replies[1] >= replies[0] + 1


def test_the_node_reports_each_drop_under_its_own_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    """The graph node's status sums the driver's per-lidar counters by reason: packets missing by udp_cnt
    are `udp_lost`, packets of an already published sweep `udp_late`, never one for the other."""
    node = LivoxDriverNode("livox", config(fresh_ports(), "127.0.0.2", "127.0.0.3"), Sink(), process=False)
    a = LidarStats("127.0.0.2", packets=100, points=9600, lost=3, duplicates=1, late=2, malformed=4,
                   imu_packets=50, imu_lost=5, sweeps=10, time_jumps=1)  # fmt: skip
    b = LidarStats("127.0.0.3", packets=80, points=7680, late=7, imu_packets=40, imu_lost=1, sweeps=8,
                   counter_jumps=2)  # fmt: skip
    stats = DriverStats({a.ip: a, b.ip: b}, foreign=6, rcvbuf_bytes=4096, kernel_drops=2)
    monkeypatch.setattr(node.driver, "stats", lambda: stats)
    status = node.status()
    assert status.drops == {"udp_lost": 3, "udp_late": 9, "udp_malformed": 4, "imu_lost": 6}
    assert status.counters == {
        "foreign": 6.0, "rcvbuf_bytes": 4096.0, "kernel_drops": 2.0,
        **{f"127.0.0.2.{k}": v for k, v in (("sweeps", 10.0), ("points", 9600.0), ("packets", 100.0),
           ("duplicates", 1.0), ("imu_packets", 50.0), ("counter_jumps", 0.0), ("time_jumps", 1.0))},
        **{f"127.0.0.3.{k}": v for k, v in (("sweeps", 8.0), ("points", 7680.0), ("packets", 80.0),
           ("duplicates", 0.0), ("imu_packets", 40.0), ("counter_jumps", 2.0), ("time_jumps", 0.0))},
    }  # fmt: skip
    assert status.error is None


def _hand_parse(raw: bytes) -> tuple[int, int, bytes]:
    """(seq, cmd_id, payload) of a host REQ, every header field and both CRCs checked by hand."""
    sof, ver, length, seq, cmd_id, cmd_type, sender = struct.unpack_from("<BBHIHBB", raw)
    assert (sof, ver, length, cmd_type, sender) == (0xAA, 0, len(raw), 0, 0)
    assert raw[12:18] == b"\0" * 6
    crc16, crc32 = struct.unpack_from("<HI", raw, 18)
    assert crc16 == binascii.crc_hqx(raw[:18], 0xFFFF)
    assert crc32 == zlib.crc32(raw[24:])
    return seq, cmd_id, raw[24:]


def _hand_kv(payload: bytes) -> list[tuple[int, bytes]]:
    count, rsvd = struct.unpack_from("<HH", payload)
    assert rsvd == 0
    items, pos = [], 4
    for _ in range(count):
        key, n = struct.unpack_from("<HH", payload, pos)
        items.append((key, payload[pos + 4 : pos + 4 + n]))
        pos += 4 + n
    assert pos == len(payload)
    return items


def test_configuration_bytes_follow_the_protocol():
    ports = fresh_ports()
    extrinsic = (0.5, -1.25, 180.0, 11.0, -22.0, 33.0)
    emu = Mid360Emulator("127.0.0.2", SweepList([]), ports=ports)
    with emu:
        driver = Mid360Driver(config(ports, LidarEndpoint("127.0.0.2", extrinsic)), Sink())
        driver.start()
        assert emu.work_mode == 0x01 and emu.data_type == 1
        assert driver.query("127.0.0.2", [0x001A, 0x8000]) == {0x001A: b"\x01", 0x8000: b"47MDL9A0010012\0\0"}
        driver.stop()
        assert emu.work_mode == 0x02  # standby on stop
    frames = [_hand_parse(raw) for raw in emu.counters.commands]
    assert len({seq for seq, _, _ in frames}) == len(frames) == 8  # every command its own seq
    assert [cmd for _, cmd, _ in frames] == [0x0100] * 6 + [0x0101, 0x0100]
    assert frames[6][2] == struct.pack("<HHHH", 2, 0, 0x001A, 0x8000)
    host = bytes([127, 0, 0, 1])
    assert [_hand_kv(payload) for _, cmd, payload in frames if cmd == 0x0100] == [
        [
            (0x0005, host + struct.pack("<HH", ports.host_push, ports.lidar_push)),
            (0x0006, host + struct.pack("<HH", ports.host_point, ports.lidar_point)),
            (0x0007, host + struct.pack("<HH", ports.host_imu, ports.lidar_imu)),
        ],
        [(0x0000, b"\x01")],
        [(0x0001, b"\x00")],
        [(0x0012, struct.pack("<fffiii", 0.5, -1.25, 180.0, 11, -22, 33))],
        [(0x001C, b"\x01")],
        [(0x001A, b"\x01")],
        [(0x001A, b"\x02")],
    ]


def test_a_silent_lidar_is_retried_then_named():
    ports = fresh_ports()
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.7", ports.lidar_cmd))  # receives, never answers
    listener.settimeout(0.5)
    try:
        driver = Mid360Driver(config(ports, "127.0.0.7", command_timeout_s=0.05, command_retries=2), Sink())
        with pytest.raises(DriverError, match=r"lidar 127\.0\.0\.7: no ACK to command 0x0100 .* 3 tries"):
            driver.start()
        tries = [listener.recv(2048) for _ in range(3)]
    finally:
        listener.close()
    assert tries[0] == tries[1] == tries[2]  # resent unchanged: same seq, so a late ACK still matches
    assert driver.stats().lidars["127.0.0.7"].packets == 0


def test_a_refused_key_names_the_lidar_the_key_and_the_ret_code():
    ports = fresh_ports()
    with Mid360Emulator("127.0.0.2", SweepList([]), ports=ports, fail_keys=frozenset({0x0001})):
        driver = Mid360Driver(config(ports, "127.0.0.2"), Sink())
        with pytest.raises(
            DriverError, match=r"lidar 127\.0\.0\.2: .*0x0001.* ret_code 0x01 .*error_key 0x0001"
        ):
            driver.start()
    # the failed start released its ports
    for port in (ports.host_cmd, ports.host_push, ports.host_point, ports.host_imu):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.bind((HOST, port))


# --------------------------------------------------------------------------- the capture


def test_ten_second_capture_of_two_lidars_equals_the_simulator(sim):
    """Every point of 2 x 10 s (200 sweeps, ~4M points) with its exact time, plus every IMU sample."""
    scans, sweeps = sim
    ports = fresh_ports()
    ips = ("127.0.0.12", "127.0.0.13")
    emus = [
        Mid360Emulator(ip, SweepList(sweeps[k], scans[k].imu), ports=ports, rate=RATE, seed=k)
        for k, ip in enumerate(ips)
    ]
    endpoints = [LidarEndpoint(ip, topic_ip=f"192.168.1.{ip.rsplit('.', 1)[1]}") for ip in ips]
    sink, driver = run_capture(emus, config(ports, *endpoints))
    stats = driver.stats()
    assert stats.foreign == 0
    for k, ip in enumerate(ips):
        s = stats.lidars[ip]
        n_points = sum(len(sw.points) for sw in sweeps[k])
        assert (s.lost, s.duplicates, s.reordered, s.late, s.malformed, s.imu_lost) == (0, 0, 0, 0, 0, 0)
        assert s.unsynced is False and s.time_type == 1
        assert s.packets * 96 == n_points == s.points == emus[k].counters.points_sent
        assert s.sweeps == len(sweeps[k]) == 100
        suffix = f"192_168_1_{ip.rsplit('.', 1)[1]}"
        msgs = sink.on(f"/livox/lidar_{suffix}")
        assert len(msgs) == 100 and all(m[1] == CUSTOM_MSG_TYPE for m in msgs)
        for (_, _, stamp, raw), truth in zip(msgs, sweeps[k], strict=True):
            got = decode_custom_msg(raw, 2)
            assert stamp == got.stamp_ns == got.timebase_ns == truth.timebase_ns
            assert got.lidar_id == 127 and got.frame_id == "livox_frame"
            np.testing.assert_array_equal(got.points["offset_time"], truth.points["offset_time"])
            np.testing.assert_array_equal(xyz_of(got.points), quantised_m(truth.points))
            for name in ("reflectivity", "tag", "line"):
                np.testing.assert_array_equal(got.points[name], truth.points[name])
        # every 5 ms IMU sample the emulator sent, with the simulator's readings
        imus = sink.on(f"/livox/imu_{suffix}")
        assert len(imus) == emus[k].counters.imu_sent == s.imu_packets >= 1990
        decoded = [decode_imu(m[3], 2) for m in imus]
        stamps = np.array([d.stamp_ns for d in decoded])
        assert (np.diff(stamps) == 5_000_000).all() and all(m[1] == IMU_TYPE for m in imus)
        want = scans[k].imu(int(stamps[0]), int(stamps[-1]) + 1)
        np.testing.assert_array_equal(want.stamps_ns, stamps)
        np.testing.assert_array_equal(
            np.array([d.gyro_rad_s for d in decoded]), want.gyro_rad_s.astype(np.float32)
        )
        np.testing.assert_array_equal(np.array([d.acc for d in decoded]), want.acc_g.astype(np.float32))
    # both lidars' sweeps have dust tags and zero (no-return) points, as the real sensor
    tags = np.concatenate([sw.points["tag"] for sw in sweeps[0]])
    assert (tags == 0b0100).any() and (xyz_of(sweeps[0][0].points) == 0).all(axis=1).any()


def test_loss_duplicates_reordering_and_malformed_packets_are_counted_exactly(sim):
    _, sweeps = sim
    items = sweeps[0][:20]
    ports = fresh_ports()
    emu = Mid360Emulator(
        "127.0.0.2", SweepList(items), ports=ports, rate=RATE, seed=7,
        loss=0.02, reorder=0.02, duplicate=0.02, malformed=0.02,
    )  # fmt: skip
    sink, driver = run_capture([emu], config(ports, "127.0.0.2"))
    c, s = emu.counters, driver.stats().lidars["127.0.0.2"]
    assert min(len(c.dropped), c.duplicated, c.reordered, c.malformed) >= 20  # the test exercises each
    assert s.lost == len(c.dropped)
    assert s.duplicates == c.duplicated
    assert s.reordered == c.reordered
    assert s.malformed == c.malformed and s.malformed_by_reason == c.malformed_by_kind
    assert set(s.malformed_by_reason) == set(packets.REJECT_REASONS)  # every reject reason was exercised
    assert s.late == 0 and driver.stats().foreign == 0
    # the points are the simulator's minus the dropped packets, each in its own sweep, in time order
    dropped = set(c.dropped)
    first = 0
    msgs = sink.on("/livox/lidar_127_0_0_2")
    assert len(msgs) == len(items)
    for (_, _, _, raw), truth in zip(msgs, items, strict=True):
        n_pk = len(truth.points) // 96
        keep = np.repeat([first + j not in dropped for j in range(n_pk)], 96)
        first += n_pk
        got = decode_custom_msg(raw, 2)
        want = truth.points[keep]
        assert got.timebase_ns == truth.timebase_ns + int(want["offset_time"][0])
        np.testing.assert_array_equal(
            got.point_stamps_ns, truth.timebase_ns + want["offset_time"].astype(np.int64)
        )
        np.testing.assert_array_equal(xyz_of(got.points), quantised_m(want))
    assert s.points == sum(len(decode_custom_msg(m[3], 2).points) for m in msgs) == c.points_sent


def test_a_silent_lidars_last_sweep_is_published_before_stop(sim):
    """Nothing follows the last sweep, so only the idle flush (0.25 s of silence by default) can publish it."""
    _, sweeps = sim
    items = sweeps[0][:3]
    ports = fresh_ports()
    sink, clock = Sink(), ManualClock()
    topic = "/livox/lidar_127_0_0_2"
    driver = Mid360Driver(
        config(ports, "127.0.0.2", idle_flush_s=DriverConfig.idle_flush_s), sink, clock=clock
    )
    emu = Mid360Emulator("127.0.0.2", SweepList(items), ports=ports, rate=RATE, window=WINDOW)
    emu.credit = credit_from(driver.received, emu.ip)
    with emu, driver:
        assert emu.wait_done(HANG_S)
        wait_for(lambda: settled(driver, [emu]), "the driver to take every datagram")
        # every packet is in; the last sweep stays open while the driver's clock stands still
        assert [decode_custom_msg(m[3], 2).timebase_ns for m in sink.on(topic)] == [
            sw.timebase_ns for sw in items[:-1]
        ]
        clock.advance(DriverConfig.idle_flush_s + 0.01)
        wait_for(lambda: len(sink.on(topic)) == len(items), "the idle flush")
        published = [decode_custom_msg(m[3], 2).timebase_ns for m in sink.on(topic)]  # before stop()
    assert published == [sw.timebase_ns for sw in items]
    assert len(sink.on(topic)) == len(items)  # stop() found nothing left to publish


def test_traffic_from_other_addresses_is_ignored_and_garbage_never_kills_the_driver(sim):
    _, sweeps = sim
    ports = fresh_ports()
    items = sweeps[1][:5]
    body = packets.quantise_points(
        1, np.ones((3, 96, 3)), np.zeros((3, 96), np.uint8), np.zeros((3, 96), np.uint8)
    )
    valid = packets.build_point_packets(
        1, 1, np.array([1, 2, 3]) * 480_000 + items[0].timebase_ns, np.arange(3), body
    )
    rogue = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rogue.bind(("127.0.0.9", 0))
    rogue_port = rogue.getsockname()[1]
    wrong_port = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    wrong_port.bind(("127.0.0.2", 0))  # the lidar's address, not its point port
    wrong_port_port = wrong_port.getsockname()[1]
    spoof = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    spoof.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    rng = np.random.default_rng(11)
    garbage = [rng.integers(0, 256, int(n), dtype=np.uint8).tobytes() for n in rng.integers(0, 1500, 100)]

    def meddle(driver: Mid360Driver) -> None:
        spoof.bind(("127.0.0.2", ports.lidar_point))  # the lidar's own source: garbage counts as malformed
        for row in valid:
            rogue.sendto(row.tobytes(), (HOST, ports.host_point))
            wrong_port.sendto(row.tobytes(), (HOST, ports.host_point))
        rogue.sendto(packets.build_imu_packet(1, 1, 0, np.zeros(3), np.zeros(3)), (HOST, ports.host_imu))

        def malformed() -> int:
            return driver.stats().lidars["127.0.0.2"].malformed

        for k in range(0, len(garbage), 10):  # ten at a time, each batch taken before the next is sent
            for g in garbage[k : k + 10]:
                spoof.sendto(g, (HOST, ports.host_point))
            wait_for(functools.partial(lambda n: malformed() >= n, k + 10), "the garbage")
        wait_for(lambda: driver.stats().foreign == 7, "the foreign datagrams")

    emu = Mid360Emulator("127.0.0.2", SweepList(items), ports=ports, rate=RATE)
    try:
        sink, driver = run_capture(
            [emu], config(ports, "127.0.0.2"), during=meddle, extra={"127.0.0.2": len(garbage)}
        )
    finally:
        for sock in (rogue, wrong_port, spoof):
            sock.close()
    st = driver.stats()
    s = st.lidars["127.0.0.2"]
    assert st.foreign == 7
    assert st.foreign_sources == {f"127.0.0.9:{rogue_port}": 4, f"127.0.0.2:{wrong_port_port}": 3}
    assert s.malformed == 100
    assert s.points == sum(len(sw.points) for sw in items) and s.lost == 0
    assert len(sink.on("/livox/lidar_127_0_0_2")) == 5


def proc_udp_drops(ip: str, port: int) -> int:
    """The kernel's own count of datagrams dropped on the UDP socket bound to ip:port (/proc/net/udp)."""
    local = f"{socket.htonl(int.from_bytes(socket.inet_aton(ip), 'big')):08X}:{port:04X}"
    for line in Path("/proc/net/udp").read_text().splitlines()[1:]:
        fields = line.split()
        if fields[1] == local:
            return int(fields[-1])
    raise AssertionError(f"no UDP socket bound to {ip}:{port} in /proc/net/udp")


@pytest.mark.skipif(not Path("/proc/net/udp").is_file(), reason="SO_RXQ_OVFL and /proc/net/udp are Linux's")
def test_a_full_kernel_buffer_is_counted_as_loss_and_as_kernel_drops(sim):
    """The consumer stalls on the first sweep while 600 datagrams go to a receive buffer of about two:
    the kernel drops the rest, every gap is counted as lost and as a kernel drop, the driver goes on."""
    _, sweeps = sim
    items = sweeps[0][:5]
    ports = fresh_ports()
    ip, topic, flood = "127.0.0.2", "/livox/lidar_127_0_0_2", 600
    sink = Sink()
    stalled, resumed = threading.Event(), threading.Event()
    flood_from: list[int] = []

    def publish(topic: str, msgtype: str, stamp_ns: int, raw: bytes) -> None:
        sink(topic, msgtype, stamp_ns, raw)
        if not stalled.is_set():
            stalled.set()
            resumed.wait(HANG_S)

    def credit(kind: str) -> int:
        """One datagram in flight at a time (taken or dropped), except the flood while the consumer stalls."""
        sent = emu.counters.point_datagrams
        if stalled.is_set() and not resumed.is_set():
            flood_from[:] = flood_from or [sent]
            if sent - flood_from[0] < flood:
                return sent
            resumed.set()
        return driver.received(ip)[0] + proc_udp_drops(HOST, ports.host_point)

    cfg = config(ports, ip, rcvbuf_bytes=1, batch_wait_s=0.0, imu=False)
    driver = Mid360Driver(cfg, publish, clock=ManualClock())
    emu = Mid360Emulator(ip, SweepList(items), ports=ports, rate=RATE, credit=credit, window=1)
    with emu, driver:
        assert emu.wait_done(HANG_S)
        wait_for(
            lambda: (
                driver.received(ip)[0] + proc_udp_drops(HOST, ports.host_point)
                == emu.counters.point_datagrams
                and driver.stats().lidars[ip].unaccounted_point_datagrams() == 0
            ),
            "every datagram taken or dropped",
        )
        dropped = proc_udp_drops(HOST, ports.host_point)
    st = driver.stats()
    s = st.lidars[ip]
    assert resumed.is_set() and st.rcvbuf_bytes < 10_000  # the kernel's minimum
    # the datagrams after the flood were taken one by one, so every kernel drop is a udp_cnt gap
    assert st.kernel_drops == dropped >= flood - 10 and s.lost == st.kernel_drops
    assert emu.counters.point_datagrams == emu.counters.packets_sent == s.point_datagrams + st.kernel_drops
    assert_books_balance(st)
    assert s.malformed == s.duplicates == 0
    assert s.points == 96 * s.packets and 0 < len(sink.on(topic)) == s.sweeps <= len(items)


# --------------------------------------------------------------------------- time, formats, data types


def test_unsynced_stamps_come_from_the_host_clock(sim):
    _, sweeps = sim
    items = sweeps[0][:5]
    ports = fresh_ports()
    emu = Mid360Emulator("127.0.0.2", SweepList(items), ports=ports, rate=1.0, time_type=0)
    t0 = time.time_ns()
    sink, driver = run_capture([emu], config(ports, "127.0.0.2"))
    t1 = time.time_ns()
    s = driver.stats().lidars["127.0.0.2"]
    assert s.unsynced is True and s.time_type == 0
    msgs = [decode_custom_msg(m[3], 2) for m in sink.on("/livox/lidar_127_0_0_2")]
    stamps = np.concatenate([m.point_stamps_ns for m in msgs])
    assert len(stamps) == sum(len(sw.points) for sw in items) == s.points
    assert t0 <= stamps.min() and stamps.max() <= t1  # host receive time, not the device clock
    per_packet = stamps.reshape(-1, 96)
    assert (np.diff(per_packet, axis=1) == 4947).all()
    # sweeps cut on 100 ms of the host clock: one per 100 ms bin, in order, each packet in its sweep's bin
    bins = [int(m.timebase_ns) // 100_000_000 for m in msgs]
    assert bins == sorted(set(bins))
    for m, b in zip(msgs, bins, strict=True):
        assert (m.point_stamps_ns.reshape(-1, 96)[:, 0] // 100_000_000 == b).all()


@pytest.mark.parametrize(
    ("data_type", "msg_format", "ros", "multi_topic", "extrinsic"),
    [
        (2, "pointcloud2", 2, True, None),
        (3, "custom", 1, False, None),
        (1, "custom", 2, True, (180.0, 0.5, -30.0, 40.0, -50.0, 60.0)),
    ],
)
def test_data_types_formats_and_extrinsics(sim, data_type, msg_format, ros, multi_topic, extrinsic):
    _, sweeps = sim
    items = sweeps[1][:3]
    ports = fresh_ports()
    emu = Mid360Emulator("127.0.0.3", SweepList(items), ports=ports, rate=RATE)
    cfg = config(
        ports, LidarEndpoint("127.0.0.3", extrinsic), data_type=data_type, msg_format=msg_format,
        ros_version=ros, multi_topic=multi_topic, imu=False,
    )  # fmt: skip
    sink, driver = run_capture([emu], cfg)
    assert emu.data_type == data_type and emu.counters.imu_sent == 0  # configured by the driver
    topic = "/livox/lidar_127_0_0_3" if multi_topic else "/livox/lidar"
    msgs = sink.on(topic)
    assert len(msgs) == 3 and not sink.on("/livox/imu") and not sink.on("/livox/imu_127_0_0_3")
    for (_, msgtype, stamp, raw), truth in zip(msgs, items, strict=True):
        if msg_format == "pointcloud2":
            assert msgtype == POINTCLOUD2_TYPE
            cloud = decode_pointcloud2(raw, ros)
            assert cloud.points.dtype.itemsize == 26 and cloud.stamp_ns == stamp == truth.timebase_ns
            got_xyz, got_t = xyz_of(cloud.points), cloud.points["timestamp"]
            want_t = (truth.timebase_ns + truth.points["offset_time"].astype(np.int64)).astype(np.float64)
            np.testing.assert_array_equal(got_t, want_t)
            np.testing.assert_array_equal(cloud.points["intensity"], truth.points["reflectivity"])
        else:
            assert msgtype == CUSTOM_MSG_TYPE
            got = decode_custom_msg(raw, ros)
            assert got.timebase_ns == stamp == truth.timebase_ns
            np.testing.assert_array_equal(got.points["offset_time"], truth.points["offset_time"])
            got_xyz = xyz_of(got.points)
        xyz = np.stack([truth.points[n].astype(np.float64) for n in "xyz"], axis=-1)
        if data_type == 2:
            want = quantised_m(truth.points, 2)
        elif data_type == 3:  # the lidar's integers, then the driver's trigonometry, computed here again
            r_mm = np.rint(np.linalg.norm(xyz, axis=1) * 1000)
            hit = r_mm > 0
            theta = np.where(
                hit,
                np.rint(
                    np.degrees(
                        np.arccos(np.clip(xyz[:, 2] / np.where(hit, np.linalg.norm(xyz, axis=1), 1), -1, 1))
                    )
                    * 100
                ),
                0,
            )
            phi = np.where(
                hit, np.rint((np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0])) % 360) * 100) % 36000, 0
            )
            r, th, ph = r_mm / 1000.0, np.radians(theta / 100.0), np.radians(phi / 100.0)
            want = np.stack([r * np.sin(th) * np.cos(ph), r * np.sin(th) * np.sin(ph), r * np.cos(th)], -1)
            want = want.astype(np.float32)
        else:  # p' = R p + t on the integer millimetres, then metres
            roll, pitch, yaw = np.radians(extrinsic[:3])
            Rx = np.array([[1, 0, 0], [0, np.cos(roll), -np.sin(roll)], [0, np.sin(roll), np.cos(roll)]])
            Ry = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]])
            Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
            mm = np.rint(xyz * 1000)
            want = ((mm @ (Rz @ Ry @ Rx).T + np.array(extrinsic[3:])) / 1000.0).astype(np.float32)
        np.testing.assert_allclose(got_xyz, want, rtol=0, atol=1e-5)
        if extrinsic is None:  # and all of it within the data type's resolution of the simulator's points
            assert np.abs(got_xyz - xyz).max() < {2: 0.0051, 3: 0.013}[data_type]
    assert driver.stats().lidars["127.0.0.3"].malformed == 0


def test_sim_emulators_stream_the_reference_rig_as_simulate_would():
    """The launch convenience: one emulator per rig lidar, lazily simulated, on 127.0.0.<rig octet>."""
    cfg = SimConfig(scene="indoor", duration_s=0.3, scale=0.1, seed=4, range_noise_m=0.0)
    ports = fresh_ports()
    emus = sim_emulators(cfg, ports=ports, rate=RATE)
    assert [(e.ip, e.serial) for e in emus] == [
        ("127.0.0.12", "47MDL9A0010012"),
        ("127.0.0.13", "47MDL9A0010013"),
    ]
    endpoints = [LidarEndpoint(e.ip, topic_ip=f"192.168.1.{e.ip.rsplit('.', 1)[1]}") for e in emus]
    sink, _ = run_capture(emus, config(ports, *endpoints))
    setup = setup_sim(cfg)
    for k, lidar in enumerate(setup.rig.lidars):
        scan = SimScan(setup, k)
        msgs = sink.on(lidar.topic)
        assert len(msgs) == len(scan.windows()) == 3
        for (_, _, stamp, raw), win in zip(msgs, scan.windows(), strict=True):
            truth = simulate_sweep(setup.lidars[k], setup.scene, setup.texture, setup.traj, cfg.start_ns, win)
            assert truth is not None and stamp == truth.timebase_ns
            np.testing.assert_array_equal(xyz_of(decode_custom_msg(raw, 2).points), quantised_m(truth.points))
        assert sink.on(setup.imus[k][0])  # the rig's IMU topic


def test_a_data_port_taken_by_another_driver_is_a_clear_error() -> None:
    """No SO_REUSEADDR on data/command ports: a second driver cannot silently share a stream (issue 20, 7)."""
    from sensorbox.livox.sockets import udp_socket

    first = udp_socket("127.0.0.1", 0)
    port = first.getsockname()[1]
    try:
        with pytest.raises(
            DriverError, match=rf"cannot bind UDP 127.0.0.1:{port}: Address already in use \(another"
        ):
            udp_socket("127.0.0.1", port)
    finally:
        first.close()


def test_a_spoofed_counter_or_clock_jump_is_a_counted_anomaly_not_loss(sim):
    """Issue 20, class 7: two datagrams from the lidar's own address and port, mid-sweep, between
    packets N-1 and N: one with udp_cnt 27,546 ahead and its clock 1000 s ahead, one with udp_cnt
    20,000 behind and a clock that fits the stream. Both are kept and counted as jumps; nothing is
    counted lost or late, no real packet is dropped, and every real point is published once, in order."""
    _, sweeps = sim
    items = sweeps[0][:8]
    ports = fresh_ports()
    ip, topic = "127.0.0.2", "/livox/lidar_127_0_0_2"
    truth = np.concatenate([sw.points for sw in items])
    packet_ns = np.concatenate([sw.timebase_ns + sw.points["offset_time"].astype(np.int64) for sw in items])[
        ::96
    ]
    n = sum(len(sw.points) // 96 for sw in items[:3]) + 50  # mid-sweep
    marker = 0b1100_0000  # tag bits 6-7 (reserved): the simulator never sets them
    body = packets.quantise_points(
        1, np.full((2, 96, 3), 1.5), np.zeros((2, 96), np.uint8), np.full((2, 96), marker, np.uint8)
    )
    t_prev, cnt_prev = int(packet_ns[n - 1]), n - 1
    spoofed = packets.build_point_packets(
        1, packets.TIME_TYPE_PTP, np.array([t_prev + 1000 * 10**9, t_prev + 240_000]),
        np.array([cnt_prev + 27_546, cnt_prev - 20_000]) & 0xFFFF, body,
    )  # fmt: skip
    released = threading.Event()
    spoof = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    spoof.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)

    def meddle(driver: Mid360Driver) -> None:
        wait_for(lambda: driver.received(ip)[0] == n, f"the first {n} packets")
        spoof.bind((ip, ports.lidar_point))
        for row in spoofed:
            spoof.sendto(row.tobytes(), (HOST, ports.host_point))
        wait_for(lambda: driver.received(ip)[0] == n + 2, "the spoofed datagrams")
        released.set()

    emu = Mid360Emulator(ip, SweepList(items), ports=ports, rate=RATE, window=WINDOW)
    point_credit = None

    def credit(kind: str) -> int:
        """Flow control that holds point packet N until both spoofed datagrams were taken."""
        assert point_credit is not None
        if kind == "point" and emu.counters.point_datagrams >= n and not released.is_set():
            return -(10**9)
        return point_credit(kind)

    emu.credit = credit
    cfg = config(ports, ip)
    try:
        sink = Sink()
        driver = Mid360Driver(cfg, sink, clock=ManualClock())
        point_credit = credit_from(driver.received, ip)
        emu.start()
        try:
            with driver:
                meddle(driver)
                assert emu.wait_done(HANG_S)
                wait_for(lambda: settled(driver, [emu], {ip: 2}), "the driver to take every datagram")
        finally:
            emu.stop()
    finally:
        spoof.close()
    s = driver.stats().lidars[ip]
    assert (s.lost, s.late, s.duplicates, s.malformed) == (0, 0, 0, 0)
    assert (s.counter_jumps, s.time_jumps) == (3, 2)  # ahead, back (to the 2nd), ahead again; clock out, back
    assert s.packets == len(truth) // 96 + 2 and s.unaccounted_point_datagrams() == 0
    got = [decode_custom_msg(m[3], 2) for m in sink.on(topic)]
    # the real sweep cut open by the jump is published in two parts; the jumped-ahead datagram alone
    assert len(got) == len(items) + 2
    ahead = [g for g in got if g.timebase_ns == t_prev + 1000 * 10**9]
    assert len(ahead) == 1 and (ahead[0].points["tag"] == marker).all() and len(ahead[0].points) == 96
    points = np.concatenate([g.points for g in got])
    stamps = np.concatenate([g.point_stamps_ns for g in got])
    real = points["tag"] != marker
    assert (~real).sum() == 192
    np.testing.assert_array_equal(xyz_of(points[real]), quantised_m(truth))
    np.testing.assert_array_equal(
        stamps[real],
        np.concatenate([sw.timebase_ns + sw.points["offset_time"].astype(np.int64) for sw in items]),
    )


def test_publish_interval_limits_are_inclusive() -> None:
    """publish_freq 0.5..100 Hz as livox_ros_driver2 allows: 10 ms and 2 s themselves are accepted,
    one nanosecond beyond either is refused."""
    lidars = (LidarEndpoint("192.168.1.12"),)
    for ns in (10_000_000, 2_000_000_000):
        DriverConfig("192.168.1.5", lidars, publish_interval_ns=ns).validate()
    for ns in (9_999_999, 2_000_000_001):
        with pytest.raises(DriverError, match=rf"publish_interval_ns {ns}: expected 10 ms\.\.2 s"):
            DriverConfig("192.168.1.5", lidars, publish_interval_ns=ns).validate()


def test_point_datagram_books_balance_with_late_packets() -> None:
    """Every point datagram is kept, a duplicate, late or a listed reject: 6 + 1 + 2 + 1 (short) = 10
    balances; a malformed reason that is not a point reject (imu) does not count for the point port."""
    s = LidarStats("192.168.1.12", packets=6, duplicates=1, late=2, point_datagrams=10,
                   malformed_by_reason={"short": 1, "imu": 3})  # fmt: skip
    assert s.unaccounted_point_datagrams() == 0
    assert (
        LidarStats("192.168.1.12", packets=6, late=2, point_datagrams=10).unaccounted_point_datagrams() == 2
    )
