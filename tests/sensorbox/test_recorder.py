"""The live recorder: round trip, queue overflow, splits, disk guard, and what SIGINT/SIGTERM/SIGKILL leave.

Bags are read back with `ingest.bags.reader.open_bags` (what `sensorbox ingest` uses), salvage included.
"""

from __future__ import annotations

import errno
import io
import itertools
import math
import os
import re
import signal
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest

from ingest.bags.decode import header_stamp_ns
from ingest.bags.reader import BagError, open_bags
from ingest.bags.rostypes import IMU_TYPE, typestore
from sensorbox import messages
from sensorbox.errors import RecorderError
from sensorbox.live.bus import Bus, NodeStatus, Shutdown, run_graph
from sensorbox.live.recorder import Recorder
from sensorbox.live.recorder_config import RecorderConfig
from tests.live import HANG_S, NO_DISK_GUARD, ManualClock, wait_for

pytestmark = pytest.mark.realtime  # writer threads, clocks, signals to subprocesses: run serially (make test)

ROOT = Path(__file__).resolve().parents[2]
STRING = "std_msgs/msg/String"
IMAGE = "sensor_msgs/msg/CompressedImage"


def string_msg(text: str) -> bytes:
    ts = typestore(2)
    return bytes(ts.serialize_cdr(ts.types[STRING](data=text), STRING))


def blob_msg(k: int, size: int) -> bytes:
    """A CompressedImage of `size` random (incompressible) bytes, header stamp k ns."""
    data = np.random.default_rng(k).integers(0, 256, size, dtype=np.uint8)
    ts = typestore(2)
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=0, nanosec=k)
    header = ts.types["std_msgs/msg/Header"](stamp=stamp, frame_id="f")
    return bytes(ts.serialize_cdr(ts.types[IMAGE](header=header, format="jpeg", data=data), IMAGE))


def read_all(paths, salvage=False):
    with open_bags(paths, salvage=salvage) as bags:
        return list(bags.messages())


class FakeClock:
    """Receive times 100 ms apart: deterministic log times and duration splits."""

    def __init__(self, start_ns: int = 1_000_000_000_000, step_ns: int = 100_000_000) -> None:
        self.counter = itertools.count()
        self.start, self.step = start_ns, step_ns

    def __call__(self) -> int:
        return self.start + next(self.counter) * self.step


def test_round_trip_keeps_bytes_stamps_and_receive_order(tmp_path):
    rec = Recorder(RecorderConfig(tmp_path, name="rt", min_free_bytes=NO_DISK_GUARD), clock_ns=FakeClock())
    rec.start()
    sent = []
    for k in range(50):
        imu = messages.imu_msg(5_000_000_000 + k, np.array([0.1, 0.2, k]), np.array([0.0, 0.0, 1.0]))
        for topic, msgtype, raw in (("/imu", IMU_TYPE, imu), ("/chatter", STRING, string_msg(f"hi {k}"))):
            assert rec.enqueue(topic, msgtype, 0, raw)
            sent.append((topic, raw))
    rec.stop()
    bag = tmp_path / "rt_000"
    assert rec.files == [bag] and (bag / "metadata.yaml").is_file() and (bag / "rt_000.mcap").is_file()
    got = read_all(bag)
    assert [(m.topic, m.raw) for m in got] == sent
    assert [m.log_ns for m in got] == [1_000_000_000_000 + k * 100_000_000 for k in range(100)]
    imu_msgs = [m for m in got if m.topic == "/imu"]
    assert [header_stamp_ns(m.raw, 2) for m in imu_msgs] == [5_000_000_000 + k for k in range(50)]
    st = rec.status()
    assert st.written == {"/imu": 50, "/chatter": 50} and sum(st.drops.values()) == 0
    assert st.rates_hz == {"/imu": pytest.approx(5.0), "/chatter": pytest.approx(5.0)}  # every 200 ms


def test_queue_overflow_is_counted_per_topic(tmp_path):
    rec = Recorder(RecorderConfig(tmp_path, name="q", queue_msgs=3, min_free_bytes=NO_DISK_GUARD))
    gate, entered = threading.Event(), threading.Event()
    write = rec._write

    def blocked(*args):
        entered.set()
        gate.wait(HANG_S)
        write(*args)

    rec._write = blocked  # type: ignore[method-assign]  # the writer holds the first message until the test lets it go
    rec.start()
    results = [rec.enqueue("/a", STRING, 0, string_msg(str(k))) for k in range(1)]
    assert entered.wait(HANG_S)
    results += [rec.enqueue("/a", STRING, 0, string_msg(str(k))) for k in range(1, 10)]
    results += [rec.enqueue("/b", STRING, 0, string_msg("b"))]  # its own queue: not affected
    gate.set()
    rec.stop()
    assert results == [True] * 4 + [False] * 6 + [True]
    st = rec.status()
    assert st.drops["queue"] == 6 and st.written == {"/a": 4, "/b": 1}
    assert rec.topics["/a"].queue_drops == 6 and rec.topics["/b"].queue_drops == 0
    got = read_all(rec.files)
    assert [m.raw for m in got if m.topic == "/a"] == [string_msg(str(k)) for k in range(4)]


def test_queue_byte_bound(tmp_path):
    rec = Recorder(RecorderConfig(tmp_path, name="qb", queue_bytes=250_000, min_free_bytes=NO_DISK_GUARD))
    rec._accepting = True  # enqueue without a writer draining: only the byte bound decides
    rec.bag_name = "qb"
    accepted = [rec.enqueue("/img", IMAGE, 0, blob_msg(k, 100_000)) for k in range(4)]
    assert accepted == [True, True, False, False]
    assert rec.topics["/img"].queue_drops == 2 and rec.topics["/img"].queued_bytes < 250_000


def test_split_by_duration_gives_several_readable_bags(tmp_path):
    rec = Recorder(
        RecorderConfig(tmp_path, name="d", split_s=1.0, min_free_bytes=NO_DISK_GUARD), clock_ns=FakeClock()
    )
    rec.start()
    for k in range(35):  # receive times 0.0, 0.1, ... 3.4 s
        rec.enqueue("/chatter", STRING, 0, string_msg(f"m{k}"))
    rec.stop()
    assert rec.files == [tmp_path / f"d_{i:03d}" for i in range(4)]
    per_bag = [[m.raw for m in read_all(p)] for p in rec.files]
    assert [len(b) for b in per_bag] == [10, 10, 10, 5]
    assert [raw for bag in per_bag for raw in bag] == [string_msg(f"m{k}") for k in range(35)]
    for p in rec.files:
        assert (p / "metadata.yaml").is_file()


def test_split_by_size(tmp_path):
    split = 2 << 20
    rec = Recorder(RecorderConfig(tmp_path, name="s", split_bytes=split, min_free_bytes=NO_DISK_GUARD))
    rec.start()
    for k in range(40):  # 40 x 200 kB of incompressible data: 8 MB
        rec.enqueue("/img", IMAGE, 0, blob_msg(k, 200_000))
    rec.stop()
    assert len(rec.files) >= 3
    counts, stamps = [], []
    for p in rec.files:
        msgs = read_all(p)
        counts.append(len(msgs))
        stamps += [header_stamp_ns(m.raw, 2) for m in msgs]
    assert stamps == list(range(40))
    for p in rec.files[:-1]:  # a bag ends once its file passed the limit: within a chunk (1 MiB) + a message
        size = (p / f"{p.name}.mcap").stat().st_size
        assert split <= size <= split + (1 << 20) + 2 * 200_000, size


def test_disk_guard_closes_the_bag_and_stops(tmp_path):
    free = {"bytes": 10 << 30}
    sd = Shutdown()
    cfg = RecorderConfig(tmp_path, name="g", min_free_bytes=1 << 30, disk_check_s=0.01)
    rec = Recorder(cfg, shutdown=sd, disk_free=lambda _p: free["bytes"])
    rec.start()
    for k in range(20):
        rec.enqueue("/chatter", STRING, 0, string_msg(f"m{k}"))
    wait_for(lambda: rec.status().written.get("/chatter", 0) == 20, "20 messages written")
    free["bytes"] = 512 << 20  # the disk fills up
    assert sd.event.wait(HANG_S)
    assert "disk free 512 MiB below min_free 1024 MiB" in (sd.reason or "")
    for _ in range(5):
        assert not rec.enqueue("/chatter", STRING, 0, string_msg("late"))
    rec.stop()
    assert rec.disk_full and rec.status().drops["disk"] == 5
    assert [m.raw for m in read_all(tmp_path / "g_000")] == [string_msg(f"m{k}") for k in range(20)]
    # a recorder never starts on a disk that is already too full
    with pytest.raises(RecorderError, match="below the recorder's min_free"):
        Recorder(RecorderConfig(tmp_path, name="g2", min_free_bytes=1 << 30), disk_free=lambda _p: 1).start()


def test_duration_counts_from_the_first_message(tmp_path):
    sd, clock = Shutdown(), ManualClock(100.0)
    rec = Recorder(
        RecorderConfig(tmp_path, name="t", duration_s=0.2, min_free_bytes=NO_DISK_GUARD),
        shutdown=sd,
        monotonic=clock,
    )
    rec.start()
    clock.advance(10.0)
    assert not sd.event.wait(0.3)  # nothing recorded yet: the clock has not started
    rec.enqueue("/chatter", STRING, 0, string_msg("x"))
    wait_for(lambda: rec.status().written.get("/chatter", 0) == 1, "the first message written")
    clock.advance(0.1)
    assert not sd.event.wait(0.3)  # half of the duration
    clock.advance(0.15)
    assert sd.event.wait(HANG_S) and sd.reason == "recorder: recorded 0.2 s"
    rec.stop()


def test_duration_counts_from_graph_start(tmp_path):
    bus, sd, clock = Bus(), Shutdown(), ManualClock(100.0)
    cfg = RecorderConfig(tmp_path, name="g", duration_s=0.3, min_free_bytes=NO_DISK_GUARD)
    rec = Recorder(cfg, shutdown=sd, in_graph=True, monotonic=clock)
    rec.subscribe_to(bus)

    class SlowSource:  # publishes at once, then takes 10 s more to start (a pre-rendering camera)
        name, priority = "slow", 2

        def start(self):
            bus.publish("/chatter", STRING, 0, string_msg("early"))
            wait_for(lambda: rec.status().written.get("/chatter", 0) == 1, "the early message written")
            clock.advance(10.0)
            assert not sd.event.wait(0.3)  # counted from the first message, the recording would end here

        def stop(self):
            pass

        def status(self):
            return NodeStatus()

    # after every node started, the clock moves 0.1 s per tick of the graph
    res = run_graph([rec, SlowSource()], bus, sd, tick_s=0.01, on_tick=lambda _snap: clock.advance(0.1))
    assert res.reason == "recorder: recorded 0.3 s" and res.error is None
    assert [m.raw for m in read_all(tmp_path / "g_000")] == [string_msg("early")]


def test_existing_bag_and_bad_config_are_errors(tmp_path):
    (tmp_path / "x_000").mkdir()
    with pytest.raises(RecorderError, match="x_000 exists already"):
        Recorder(RecorderConfig(tmp_path, name="x")).start()
    with pytest.raises(RecorderError, match="queue_msgs"):
        Recorder(RecorderConfig(tmp_path, queue_msgs=0))
    with pytest.raises(RecorderError, match="letters, digits"):
        Recorder(RecorderConfig(tmp_path, name="a/b"))


def test_a_bag_made_by_another_recorder_after_the_start_is_one_line(tmp_path, caplog):
    """Issue 49: a second launch into the same out:= and name:=, started while the first had not yet
    opened its bag, printed the recorder's traceback before its error line."""
    sd = Shutdown()
    rec = Recorder(RecorderConfig(tmp_path, name="x", min_free_bytes=NO_DISK_GUARD), shutdown=sd)
    rec.start()
    (tmp_path / "x_000").mkdir()  # the other launch's recorder opened its bag first
    rec.enqueue("/chatter", STRING, 0, string_msg("a"))
    assert sd.event.wait(HANG_S)
    rec.stop()
    assert all(r.exc_info is None for r in caplog.records)  # no traceback
    assert [r for r in caplog.records if r.levelname == "ERROR"] == []
    assert (
        sd.error
        == rec.error
        == (
            f"recorder: {tmp_path}/x_000 exists already: another recorder started into it meanwhile; choose "
            "another recorder name or out folder; recording stopped"
        )
    )
    assert rec.status().drops["write"] == 1 and list((tmp_path / "x_000").iterdir()) == []


def test_bus_subscription_with_topic_filter(tmp_path):
    bus = Bus()
    rec = Recorder(RecorderConfig(tmp_path, name="f", topics=("/keep",), min_free_bytes=NO_DISK_GUARD))
    rec.subscribe_to(bus)
    rec.start()
    bus.publish("/keep", STRING, 0, string_msg("a"))
    bus.publish("/other", STRING, 0, string_msg("b"))
    rec.stop()
    assert [(m.topic, m.raw) for m in read_all(rec.files)] == [("/keep", string_msg("a"))]


# ---------------------------------------------------------------- signals, in a subprocess

TALKER_LAUNCH = """\
launch:
- arg: {name: out}
- node: {pkg: sensorbox, exec: talker, name: talker, param: [{name: rate_hz, value: 200.0}]}
- node:
    pkg: sensorbox
    exec: recorder
    param: [{name: out, value: $(var out)}, {name: name, value: sig}, {name: flush_s, value: 0.1}, {name: min_free_mb, value: 0}]
"""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_sigint_sigterm_leave_a_readable_bag(tmp_path, sig):
    launch = tmp_path / "talker.launch.yaml"
    launch.write_text(TALKER_LAUNCH)
    out = tmp_path / "bags"
    proc = subprocess.Popen(
        [sys.executable, "-m", "sensorbox.cli", "launch", str(launch), f"out:={out}"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    mcap = out / "sig_000" / "sig_000.mcap"
    wait_for(lambda: mcap.exists() and mcap.stat().st_size > 2000, "the first chunk on disk", child=proc)
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=HANG_S)
    assert proc.returncode == 0, stderr
    assert f"stopped: {signal.Signals(sig).name} received" in " ".join(stdout.split())  # title may wrap
    assert (out / "sig_000" / "metadata.yaml").is_file()
    got = read_all(out / "sig_000")  # no salvage needed: the bag was closed
    assert len(got) > 10
    ts = typestore(2)
    texts = [ts.deserialize_cdr(m.raw, STRING).data for m in got]  # type: ignore[attr-defined]
    assert texts == [f"Hello World: {k}" for k in range(len(got))]  # nothing lost, nothing duplicated
    row = next(line for line in stdout.splitlines() if "/chatter" in line)
    published, written, lost = (int(v) for v in row.split("│")[2:5])
    assert published == written == len(got) and lost == 0


KILL_SCRIPT = """\
import sys, time
from pathlib import Path
from sensorbox.live.recorder import Recorder
from sensorbox.live.recorder_config import RecorderConfig
out, n, size, flush_s = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
rec = Recorder(RecorderConfig(out, name="k", flush_s=flush_s, queue_msgs=n, min_free_bytes=0))
rec.start()
from tests.sensorbox.test_recorder import string_msg
for k in range(n):
    rec.enqueue("/chatter", "std_msgs/msg/String", 0, string_msg(f"{k:06d}" + "x" * size))
while rec.status().written.get("/chatter", 0) < n and not any(rec.status().drops.values()):
    time.sleep(0.01)
if flush_s < 1:  # wait for the periodic flush to cover every message
    while rec.status().counters["flushed_msgs"] < n:
        time.sleep(0.01)
print("written", rec.status().written.get("/chatter", 0), flush=True)
time.sleep(60)
"""


@pytest.mark.parametrize(("flush_s", "exact"), [(1000.0, False), (0.1, True)])
def test_sigkill_loses_at_most_the_open_chunk(tmp_path, flush_s, exact):
    n, size = 4000, 900  # about 3.7 MB: three complete 1 MiB chunks and an open one
    script = tmp_path / "kill.py"
    script.write_text(textwrap.dedent(KILL_SCRIPT))
    proc = subprocess.Popen(
        [sys.executable, str(script), str(tmp_path), str(n), str(size), str(flush_s)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={"PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    try:
        line = proc.stdout.readline() if proc.stdout else ""
        assert line.strip() == f"written {n}", proc.stderr.read() if proc.stderr else ""
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(HANG_S)
    bag = tmp_path / "k_000"
    assert not (bag / "metadata.yaml").exists()
    with pytest.raises(BagError, match="--salvage"):
        read_all(bag)
    got = read_all(bag, salvage=True)
    ts = typestore(2)
    seqs = [int(ts.deserialize_cdr(m.raw, STRING).data[:6]) for m in got]  # type: ignore[attr-defined]
    assert seqs == list(range(len(got)))  # a prefix of what was sent, in order
    record = 4 + 4 + 6 + size + 1 + 2 + 4 + 8 + 8 + 9  # CDR string + mcap message record header
    per_chunk = math.ceil((1 << 20) / record) + 1
    if exact:  # the open chunk was flushed before the kill
        assert len(got) == n
    else:
        assert n - per_chunk <= len(got) < n


class SmallDisk:
    """A file system of `capacity` bytes for the bag's mcap files: a write past it writes what fits and
    fails with ENOSPC, as a full disk does. `sticky`: once full it stays full (another writer takes
    whatever is freed), so not even the summary fits after the bag is cut back."""

    def __init__(self, capacity: int, sticky: bool) -> None:
        self.capacity, self.sticky, self.full = capacity, sticky, False

    def open(self, path: Path, mode: str) -> io.BufferedWriter:
        disk = self

        class Raw(io.FileIO):
            def write(self, b) -> int:
                room = 0 if disk.full and disk.sticky else disk.capacity - os.fstat(self.fileno()).st_size
                if room <= 0 and len(b):
                    disk.full = True
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                return super().write(bytes(b)[:room])

        return io.BufferedWriter(Raw(str(path), mode.replace("b", "")))


@pytest.mark.parametrize("sticky", [False, True], ids=["summary-fits", "stays-full"])
def test_a_disk_that_fills_between_checks_loses_nothing_silently(tmp_path, monkeypatch, caplog, sticky):
    """Issue 20, class 9: the disk fills between two free-space checks. `written` is exactly what the
    bag holds, the rest is dropped at stage "disk", one error line (no traceback) names the bag, the
    graph is asked to stop, and the bag is closed readable (cut back to its last complete chunk)."""
    disk = SmallDisk(capacity=int(2.5 * (1 << 20)), sticky=sticky)
    real_open = Path.open

    def open_(self: Path, mode: str = "r", *args, **kw):
        writes = self.suffix == ".mcap" and any(c in mode for c in "xwa+")
        return disk.open(self, mode) if writes else real_open(self, mode, *args, **kw)

    monkeypatch.setattr(Path, "open", open_)
    sd = Shutdown()
    rec = Recorder(RecorderConfig(tmp_path, name="full"), shutdown=sd, disk_free=lambda _p: 100 << 30)
    rec.start()
    sent = []
    for k in range(200):  # 4 MB of incompressible images (chunks of 1 MiB) and small strings
        for topic, msgtype, raw in (
            ("/img", IMAGE, blob_msg(k, 20_000)),
            ("/chatter", STRING, string_msg(f"m{k}")),
        ):
            if rec.enqueue(topic, msgtype, 0, raw):  # refused (and counted) once recording stopped
                sent.append((topic, raw))
    assert sd.event.wait(HANG_S)
    rec.stop()
    st = rec.status()
    bag = tmp_path / "full_000"
    got = read_all(bag, salvage=sticky)
    assert [(m.topic, m.raw) for m in got] == sent[: len(got)]  # what it holds is a prefix of what came
    assert st.written == {t: sum(m.topic == t for m in got) for t in ("/img", "/chatter")}
    assert 0 < len(got) < 400 and st.drops["disk"] == 400 - len(got)  # queued, in flight and refused
    assert {t: c.received for t, c in rec.topics.items()} == {"/img": 200, "/chatter": 200}
    assert st.counters["bytes_written"] == sum(len(m.raw) for m in got)
    assert all(r.exc_info is None for r in caplog.records)  # no traceback
    # reported once, as the graph's error (the CLI's one `error:` line), not logged as an ERROR besides
    assert [r for r in caplog.records if r.levelname == "ERROR"] == []
    assert sd.error is not None and sd.error == rec.error and sd.error == st.error
    assert sd.error.startswith(f"recorder: {bag}: cannot write the bag: No space left on device; ")
    if sticky:  # no room for the summary: the complete chunks stay, nothing else; the same line says so
        assert re.search(
            rf"of the open chunk not in it; recording stopped; {re.escape(str(bag))}: cannot write the bag's "
            r"summary: No space left on device; its \d+ complete chunk\(s\) stay readable with "
            r"`sensorbox ingest --salvage`$",
            sd.error,
        ), sd.error
        assert sorted(p.name for p in bag.iterdir()) == ["full_000.mcap"]
        with pytest.raises(BagError):
            read_all(bag)
    else:
        assert sd.error.endswith("of the open chunk not in it; recording stopped")
        assert sorted(p.name for p in bag.iterdir()) == ["full_000.mcap", "metadata.yaml"]
