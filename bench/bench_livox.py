"""Livox Mid-360 decode throughput: numpy batch decoder vs per-packet numpy vs a per-point struct loop.

All decoders turn the same type-1 datagrams (96 points, 1380 B, valid CRC-32)
into metres, per-point ns stamps, reflectivity and tag, checking the header and
the CRC-32 as the driver does:

- `struct loop`: per packet `struct.unpack_from` of the header, then one
  `struct.unpack_from` per point (what a naive Python driver does);
- `numpy per packet`: `np.frombuffer` of one datagram on structured dtypes;
- `numpy batch`: `packets.decode_point_batch` over 256 datagrams in fixed slots
  of one receive buffer (the driver's path), plus unit conversion and times;
- `driver path`: the driver's whole per-batch work without sockets: routing by
  source, validation, udp_cnt accounting, framing into 100 ms sweeps and
  `CustomMsg` serialisation.

The table gives the median packets/s over `--repeats` runs and the ratio to the
struct loop measured in the same run, and the CPU share one real-time Mid-360
(2083 packets/s) would cost. `--live S` (default 3) then streams two emulated
lidars over loopback in real time for S seconds and reads the driver threads'
own CPU time from /proc (emulators excluded). Chart: out/bench/bench_livox.png.
"""

from __future__ import annotations

import argparse
import statistics
import struct
import sys
import time
import zlib
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import OUT_DIR, median_seconds

from sensorbox.livox import DriverConfig, LidarEndpoint, Mid360Driver, Ports, packets
from sensorbox.livox.driver import BATCH, SLOT
from sensorbox.livox.tracking import to_metres

PACKETS_PER_S = 1e9 / 480_000  # one Mid-360: a 96-point packet every 480 us
N_PACKETS = 2048


def make_datagrams(n: int, seed: int = 0) -> list[bytes]:
    rng = np.random.default_rng(seed)
    pts = np.zeros((n, 96), packets.POINT_DTYPES[1])
    for name in ("x", "y", "z"):
        pts[name] = rng.integers(-40_000, 40_000, (n, 96))
    pts["reflectivity"] = rng.integers(0, 256, (n, 96))
    stamps = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 480_000
    rows = packets.build_point_packets(1, 1, stamps, np.arange(n), pts)
    return [row.tobytes() for row in rows]


HEADER = struct.Struct("<BHHHHBBB12sIQ")
POINT = struct.Struct("<iiiBB")


def decode_struct_loop(datagrams: list[bytes]) -> int:
    """Per-point Python: the baseline."""
    n = 0
    for raw in datagrams:
        ver, length, interval, dot_num, _cnt, _f, dtype, _tt, _r, crc, stamp = HEADER.unpack_from(raw)
        if ver != 0 or length != len(raw) or dtype != 1 or zlib.crc32(raw[28:]) != crc:
            continue
        step = interval * 100 // dot_num
        out = []
        for i in range(dot_num):
            x, y, z, refl, tag = POINT.unpack_from(raw, 36 + 14 * i)
            out.append((stamp + i * step, x / 1000.0, y / 1000.0, z / 1000.0, refl, tag))
        n += len(out)
    return n


def decode_numpy_per_packet(datagrams: list[bytes]) -> int:
    n = 0
    pdt = packets.POINT_DTYPES[1]
    for raw in datagrams:
        h = np.frombuffer(raw, packets.HEADER_DTYPE, count=1)[0]
        if h["version"] != 0 or h["length"] != len(raw) or h["data_type"] != 1:
            continue
        if zlib.crc32(memoryview(raw)[28:]) != h["crc32"]:
            continue
        pts = np.frombuffer(raw, pdt, count=int(h["dot_num"]), offset=36)
        xyz = to_metres(1, packets.native_xyz(1, pts)).astype(np.float32)
        packets.point_times_ns(
            np.array([h["timestamp"]], np.int64), np.array([h["time_interval"]]), np.array([h["dot_num"]]), 96
        )
        n += len(xyz)
    return n


def slot_batches(datagrams: list[bytes]) -> list[tuple[bytearray, np.ndarray]]:
    out = []
    for start in range(0, len(datagrams), BATCH):
        chunk = datagrams[start : start + BATCH]
        buf = bytearray(SLOT * BATCH)
        for k, raw in enumerate(chunk):
            buf[k * SLOT : k * SLOT + len(raw)] = raw
        out.append((buf, np.array([len(r) for r in chunk], np.int64)))
    return out


def decode_numpy_batch(batches: list[tuple[bytearray, np.ndarray]]) -> int:
    n = 0
    for buf, sizes in batches:
        groups, _ = packets.decode_point_batch(buf, SLOT, sizes)
        for g in groups:
            xyz = to_metres(g.data_type, packets.native_xyz(g.data_type, g.points)).astype(np.float32)
            h = g.header
            packets.point_times_ns(h["timestamp"].astype(np.int64), h["time_interval"], h["dot_num"], 96)
            n += xyz.shape[0] * xyz.shape[1]
    return n


class DriverReplay:
    """The driver's per-batch work (no sockets); each call replays the batches as new packets."""

    def __init__(self, batches: list[tuple[bytearray, np.ndarray]]) -> None:
        self.batches = batches
        self.ports = Ports.block(29000)
        self.published = 0
        self.driver = Mid360Driver(
            DriverConfig("127.0.0.1", (LidarEndpoint("127.0.0.2"),), ports=self.ports), self._publish
        )
        self.sent = 0

    def _publish(self, topic: str, msgtype: str, stamp_ns: int, raw: bytes) -> None:
        self.published += 1

    def __call__(self) -> float:
        """Seconds the driver spent on one replay (the header rewrite is not timed)."""
        # udp_cnt and time continue (CRCs rewritten) so nothing counts as a duplicate
        for buf, sizes in self.batches:
            k = self.sent + np.arange(len(sizes))
            hdr = np.ndarray((len(sizes),), packets.header_dtype(SLOT), buf, 0)
            hdr["udp_cnt"] = k & 0xFFFF
            hdr["timestamp"] = 1_700_000_000_000_000_000 + k * 480_000
            mv = memoryview(buf)
            hdr["crc32"] = [
                zlib.crc32(mv[j * SLOT + 28 : j * SLOT + int(sizes[j])]) for j in range(len(sizes))
            ]
            self.sent += len(sizes)
        src = [("127.0.0.2", self.ports.lidar_point)] * BATCH
        t0 = time.perf_counter()
        for buf, sizes in self.batches:
            recv = np.zeros(len(sizes), np.int64)
            self.driver._on_point_batch(buf, len(sizes), sizes.copy(), recv, src[: len(sizes)])
        return time.perf_counter() - t0


def thread_cpu_s(native_ids: list[int]) -> float:
    """utime + stime of the given threads of this process (Linux /proc), seconds."""
    import os

    tick = os.sysconf("SC_CLK_TCK")
    total = 0
    for tid in native_ids:
        fields = Path(f"/proc/self/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
        total += int(fields[11]) + int(fields[12])
    return total / tick


def live_cpu(seconds: float, batch_wait_s: float) -> tuple[float, dict[str, int]]:
    """Two emulators streaming the simulator in real time; CPU of the driver's threads per wall second."""
    from sensorbox.sim.config import SimConfig
    from sensorbox.sim.run import setup_sim
    from sensorbox.sim.scan_source import SimScan, SweepList

    setup = setup_sim(SimConfig(scene="outdoor", trajectory="walk", duration_s=seconds, scale=0.1))
    scans = [SimScan(setup, k) for k in range(2)]
    sweeps = [list(s.sweeps()) for s in scans]
    from sensorbox.sim.mid360 import Mid360Emulator

    ports = Ports.block(29100)
    emus = [
        Mid360Emulator(f"127.0.0.{12 + k}", SweepList(sweeps[k], scans[k].imu), ports=ports) for k in range(2)
    ]
    for e in emus:
        e.start()
    cfg = DriverConfig(
        "127.0.0.1", tuple(LidarEndpoint(e.ip) for e in emus), ports=ports, batch_wait_s=batch_wait_s
    )
    driver = Mid360Driver(cfg, lambda *a: None)
    driver.start()
    ids = [t.native_id for t in driver._threads if t.native_id is not None]
    c0, t0 = thread_cpu_s(ids), time.perf_counter()
    for e in emus:
        e.wait_done(seconds * 3 + 10)
    c1, t1 = thread_cpu_s(ids), time.perf_counter()
    driver.stop()
    for e in emus:
        e.stop()
    st = driver.stats()
    counts = {
        "packets": sum(s.packets for s in st.lidars.values()),
        "lost": sum(s.lost for s in st.lidars.values()),
        "sweeps": sum(s.sweeps for s in st.lidars.values()),
    }
    return (c1 - c0) / (t1 - t0), counts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument(
        "--live", type=float, default=3.0, help="seconds of real-time two-lidar capture (0: skip)"
    )
    ap.add_argument("--out", type=Path, default=OUT_DIR / "bench_livox.png")
    args = ap.parse_args()

    datagrams = make_datagrams(N_PACKETS)
    batches = slot_batches(datagrams)
    assert decode_struct_loop(datagrams) == decode_numpy_per_packet(datagrams) == decode_numpy_batch(batches)
    cases: dict[str, float] = {
        "struct loop (per point)": median_seconds(lambda: decode_struct_loop(datagrams), args.repeats, 1),
        "numpy per packet": median_seconds(lambda: decode_numpy_per_packet(datagrams), args.repeats),
        f"numpy batch of {BATCH}": median_seconds(lambda: decode_numpy_batch(batches), args.repeats),
    }
    replay = DriverReplay(batches)
    times = [replay() for _ in range(args.repeats + 1)][1:]
    cases["driver path (decode+count+sweeps+CustomMsg)"] = statistics.median(times)
    stats = replay.driver.stats().lidars["127.0.0.2"]
    assert stats.lost == stats.malformed == stats.duplicates == 0 and replay.published > 0

    base = cases["struct loop (per point)"]
    print(f"\n{N_PACKETS} type-1 datagrams (96 points each), median of {args.repeats} runs\n")
    print("| decoder | packets/s | points/s | x struct loop | CPU for one real-time Mid-360 |")
    print("|---|---:|---:|---:|---:|")
    rates = {}
    for name, sec in cases.items():
        pps = N_PACKETS / sec
        rates[name] = pps
        share = PACKETS_PER_S / pps * 100
        print(f"| {name} | {pps:,.0f} | {pps * 96:,.0f} | {base / sec:.1f} | {share:.1f} % |")

    if args.live > 0:
        print(f"\nLive loopback: 2 emulated Mid-360s in real time for {args.live:g} s (emulators excluded)\n")
        print("| point thread wakes | driver threads' CPU (one core) | packets | lost | sweeps |")
        print("|---|---:|---:|---:|---:|")
        for wait in (0.0, DriverConfig.batch_wait_s):
            cpu, counts = live_cpu(args.live, wait)
            label = "per datagram" if wait == 0 else f"every {wait * 1000:g} ms (default)"
            row = [f"{cpu * 100:.1f} %", *(str(counts[k]) for k in ("packets", "lost", "sweeps"))]
            print(f"| {label} | {' | '.join(row)} |")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.2))
    names = list(rates)
    ax.barh(names, [rates[n] for n in names], color=["#999", "#6a9fd4", "#2a6fb0", "#1d4f80"])
    ax.axvline(PACKETS_PER_S, color="r", ls="--", lw=1, label="one Mid-360 (2083 packets/s)")
    ax.axvline(2 * PACKETS_PER_S, color="r", ls=":", lw=1, label="two Mid-360s")
    ax.set_xscale("log")
    ax.set_xlabel("packets/s (log)")
    ax.invert_yaxis()
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title("Mid-360 datagram decoding, one core")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"\nchart: {args.out}")


if __name__ == "__main__":
    main()
