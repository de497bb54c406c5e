"""Capture soak: the emulated rig at full rate on loopback for 60 s, pinned to 2 cores.

Runs launch/sim.launch.yaml in this process: two Mid-360 emulators (200k
points/s each + 200 Hz IMU, 1380-byte UDP packets on 127.0.0.12/13), the
SensorBox Livox driver, the simulator's two 1920x1200 cameras at 30 Hz encoded
to jpeg (quality 90) in their reader threads, and the recorder writing zstd mcap
to a temporary folder (deleted afterwards unless --keep).

Prints markdown tables: per topic the messages sent (published on the bus),
written, lost and the rate; the emulators' packets/points sent vs what the
driver received; drops per stage; CPU (process, % of one core) and memory
(peak RSS); the system load average, since other work on the same cores
perturbs a soak. `--repeats N` repeats the run and reports medians. Writes a
chart (rates over time, CPU and RSS over time, sent vs written) to
out/bench/bench_capture.png or --out. `--hogs N` runs N CPU-bound processes on the
same cores (contention). Target: zero drops; at least zero LiDAR datagrams lost
with `--hogs 2` on 2 cores.

`--monitor` measures the live monitor's cost in the same session: each repeat
records twice, without the monitor and with it (`run_launch(monitor=...)`) and a
Foxglove WebSocket client (tests/foxglove_client.py, its own process on the
same cores) subscribed to every channel and decoding every message, in
alternating order; both reports follow,
then a comparison: per topic what each lost, CPU, what the monitor sent and
skipped, what the client read. Target: the monitor loses nothing that
recording without it keeps.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import OUT_DIR, machine_line

from sensorbox.live.bus import GraphResult, GraphSnapshot
from sensorbox.live.launch import parse_launch
from sensorbox.live.launch_run import run_launch

ROOT = Path(__file__).resolve().parents[1]
SIM_LAUNCH = ROOT / "launch" / "sim.launch.yaml"
EXPECTED_HZ = {"lidar": 10.0, "imu": 200.0, "zed": 30.0}
REPORTED_COUNTERS = ("sent", "points", "packets", "frames", "published", "encode_ms", "pairs", "rcvbuf",
                     "kernel_drops", "nice", "jumps")  # fmt: skip


def rss_bytes() -> tuple[int, int]:
    """(current, peak) resident set size of this process, bytes (Linux /proc)."""
    cur = peak = 0
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            cur = int(line.split()[1]) * 1024
        elif line.startswith("VmHWM:"):
            peak = int(line.split()[1]) * 1024
    return cur, peak


@dataclass
class Sample:
    t_s: float
    written: dict[str, int]
    cpu_pct: float
    rss: int


@dataclass
class Run:
    result: GraphResult
    samples: list[Sample] = field(default_factory=list)
    wall_s: float = 0.0
    cpu_s: float = 0.0
    peak_rss: int = 0
    load: tuple[float, float, float] = (0.0, 0.0, 0.0)
    bytes_on_disk: int = 0
    client_msgs: dict[str, int] = field(default_factory=dict)  # --monitor: messages the client decoded


def start_client(port: int) -> subprocess.Popen[str]:
    """A Foxglove client in its own process (as the app would be): subscribes to every channel, decodes
    every message, prints what it decoded per channel when the server closes."""
    root = Path(__file__).resolve().parents[1]
    return subprocess.Popen(
        [sys.executable, "-m", "tests.foxglove_client", str(port)],
        cwd=root,
        stdout=subprocess.PIPE,
        text=True,
    )


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def hog() -> None:
    """A CPU-bound process (pure Python arithmetic) that never sleeps: the contention beside the rig."""
    x = 0
    while True:
        x = (x * 1103515245 + 12345) & 0x7FFFFFFF


def start_hogs(n: int) -> list[multiprocessing.process.BaseProcess]:
    """`n` CPU-bound processes on this process's CPUs (they inherit its affinity)."""
    ctx = multiprocessing.get_context("spawn")
    procs: list[multiprocessing.process.BaseProcess] = [
        ctx.Process(target=hog, name=f"hog{k}", daemon=True) for k in range(n)
    ]
    for p in procs:
        p.start()
    return procs


def soak(seconds: float, scale: float, port_base: int, out: Path, monitor: bool = False) -> Run:
    args = {"out": str(out), "duration": str(seconds), "scale": str(scale), "name": "soak",
            "port_base": str(port_base), "image": "jpeg"}  # fmt: skip
    plan = parse_launch(SIM_LAUNCH, args)
    samples: list[Sample] = []
    last = {"wall": time.monotonic(), "cpu": time.process_time()}

    def tick(snap: GraphSnapshot) -> None:
        now, cpu = time.monotonic(), time.process_time()
        pct = 100.0 * (cpu - last["cpu"]) / max(now - last["wall"], 1e-9)
        last["wall"], last["cpu"] = now, cpu
        samples.append(Sample(snap.elapsed_s, dict(snap.written), pct, rss_bytes()[0]))
        line = f"\r{snap.elapsed_s:5.1f} s  CPU {pct:5.0f} %  drops {snap.total_drops()}"
        print(line, end="", file=sys.stderr)

    mon, client = None, None
    if monitor:
        from calibration.rig import REFERENCE_RIG
        from sensorbox.live.monitor import MonitorConfig

        mon = MonitorConfig(free_tcp_port(), REFERENCE_RIG)
        client = start_client(mon.port)
    t0, c0 = time.monotonic(), time.process_time()
    result = run_launch(plan, on_tick=tick, tick_s=1.0, monitor=mon)
    print(file=sys.stderr)
    wall, cpu = time.monotonic() - t0, time.process_time() - c0
    run = Run(result, samples, wall, cpu, rss_bytes()[1], os.getloadavg())
    if client is not None:
        printed, _ = client.communicate(timeout=60)
        run.client_msgs = json.loads(printed or "{}")
    run.bytes_on_disk = sum(f.stat().st_size for p in result.files for f in Path(p).rglob("*") if f.is_file())
    return run


def _group(topic: str) -> str:
    for key in EXPECTED_HZ:
        if key in topic:
            return key
    return "?"


def report(runs: list[Run], seconds: float, hogs: int = 0) -> str:
    med = statistics.median
    snaps = [r.result.snapshot for r in runs]
    topics = sorted(set().union(*(s.published for s in snaps)))
    lines = [
        f"### Capture soak: {seconds:g} s, emulated rig, 2 x Mid-360 + 2 x 1920x1200 jpeg cameras"
        f" ({len(runs)} run{'s' if len(runs) > 1 else ''}, medians)"
        + (
            f", {hogs} CPU-bound process{'es' if hogs > 1 else ''} beside it on the same cores"
            if hogs
            else ""
        ),
        "",
        "| topic | sent | written | lost | rate [Hz] | expected [Hz] |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for t in topics:
        sent = med([s.published.get(t, 0) for s in snaps])
        wr = med([s.written.get(t, 0) for s in snaps])
        rate = med([s.rates_hz.get(t, 0.0) for s in snaps])
        expected = EXPECTED_HZ[_group(t)]
        lines.append(f"| {t} | {sent:.0f} | {wr:.0f} | {sent - wr:.0f} | {rate:.1f} | {expected:.0f} |")
    lines += ["", "| device / stage | value |", "|---|---:|"]
    keys: list[str] = []
    for s in snaps:
        for node, st in s.nodes.items():
            for k in st.counters:
                if any(w in k for w in REPORTED_COUNTERS):
                    name = f"{node}.{k}"
                    if name not in keys:
                        keys.append(name)
    for name in keys:
        node, k = name.split(".", 1)
        vals = [s.nodes[node].counters.get(k, 0.0) for s in snaps if node in s.nodes]
        lines.append(f"| {name} | {med(vals):.1f} |" if "ms" in k else f"| {name} | {med(vals):.0f} |")
    lines += ["", "| drops by stage | count |", "|---|---:|"]
    for stage in sorted(snaps[0].drops):
        lines.append(f"| {stage} | {med([s.drops.get(stage, 0) for s in snaps]):.0f} |")
    lines.append(f"| **total** | **{med([s.total_drops() for s in snaps]):.0f}** |")
    cpu = med([100 * r.cpu_s / r.wall_s for r in runs])
    peak = med([r.peak_rss for r in runs])
    rss_rec = med([statistics.median([x.rss for x in r.samples[2:]] or [0]) for r in runs])
    steady = med([statistics.median([x.cpu_pct for x in r.samples[2:]] or [0.0]) for r in runs])
    lines += [
        "", "| resource | value |", "|---|---:|",
        f"| CPU, whole run incl. start-up (% of one core, 2 cores = 200 %) | {cpu:.0f} % |",
        f"| CPU, recording (median of 1 s samples) | {steady:.0f} % |",
        f"| peak RSS (start-up renders both cameras at full resolution) | {peak / 2**20:.0f} MiB |",
        f"| RSS while recording (median of 1 s samples) | {rss_rec / 2**20:.0f} MiB |",
        f"| written to disk | {med([r.bytes_on_disk for r in runs]) / 2**20:.0f} MiB"
        f" ({med([r.bytes_on_disk / r.wall_s for r in runs]) / 2**20:.1f} MiB/s over the wall time) |",
        f"| wall time (start-up + recording + stop) | {med([r.wall_s for r in runs]):.1f} s |",
        f"| load average after the run (1/5/15 min) | {'/'.join(f'{v:.1f}' for v in runs[-1].load)} |",
        f"| CPUs this process may use | {len(os.sched_getaffinity(0))} |",
    ]  # fmt: skip
    return "\n".join(lines)


def chart(run: Run, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 4.8))
    s = run.samples
    topics = sorted(run.result.snapshot.published)
    ax = axes[0]
    for t in topics:
        rates = [
            (b.written.get(t, 0) - a.written.get(t, 0)) / max(b.t_s - a.t_s, 1e-9) for a, b in pairwise(s)
        ]
        ax.plot([b.t_s for b in s[1:]], rates, label=t.replace("/rgb/color/rect/image/compressed", " jpeg"))
    ax.set_yscale("log")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("written [msg/s]")
    ax.set_title("Rates written per topic")
    ax.legend(fontsize=7)
    ax = axes[1]
    ax.plot([x.t_s for x in s], [x.cpu_pct for x in s], color="tab:red", label="CPU % (one core = 100)")
    ax.axhline(200, color="tab:red", ls=":", lw=1)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("CPU [%]")
    ax2 = ax.twinx()
    ax2.plot([x.t_s for x in s], [x.rss / 2**20 for x in s], color="tab:blue", label="RSS")
    ax2.set_ylabel("RSS [MiB]")
    ax.set_ylim(0, 210)
    ax2.set_ylim(bottom=0)
    ax.set_title("CPU and memory")
    ax.legend(loc="lower left", fontsize=8)
    ax2.legend(loc="lower right", fontsize=8)
    ax = axes[2]
    snap = run.result.snapshot
    short = [t.split("/")[2] if t.startswith("/livox") else t.split("/")[1] for t in topics]
    x = range(len(topics))
    ax.bar([i - 0.2 for i in x], [snap.published.get(t, 0) for t in topics], 0.4, label="sent")
    ax.bar([i + 0.2 for i in x], [snap.written.get(t, 0) for t in topics], 0.4, label="written")
    ax.set_xticks(list(x), short, rotation=30, ha="right", fontsize=8)
    ax.set_yscale("log")
    ax.set_title(f"Sent vs written, drops {snap.total_drops()}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def compare(off: list[Run], on: list[Run]) -> str:
    """Without vs with the monitor: per topic what each lost, drops, CPU, the monitor's books, the client."""
    med = statistics.median
    lost: dict[str, tuple[float, float]] = {}
    topics = sorted(set().union(*(r.result.snapshot.published for r in off + on)))
    lines = [
        "### Without vs with --monitor (a client subscribed to every channel)",
        "",
        "| topic | lost without | lost with | written without | written with |",
        "|---|---:|---:|---:|---:|",
    ]
    for t in topics:
        lo = [r.result.snapshot.published.get(t, 0) - r.result.snapshot.written.get(t, 0) for r in off]
        ln = [r.result.snapshot.published.get(t, 0) - r.result.snapshot.written.get(t, 0) for r in on]
        lost[t] = (med(lo), med(ln))
        wo = med([r.result.snapshot.written.get(t, 0) for r in off])
        wn = med([r.result.snapshot.written.get(t, 0) for r in on])
        lines.append(f"| {t} | {med(lo):.0f} | {med(ln):.0f} | {wo:.0f} | {wn:.0f} |")
    steady = [
        med([statistics.median([x.cpu_pct for x in r.samples[2:]] or [0.0]) for r in rs]) for rs in (off, on)
    ]
    drops = [med([r.result.snapshot.total_drops() for r in rs]) for rs in (off, on)]
    lines += [
        "",
        "| | without | with |",
        "|---|---:|---:|",
        f"| drops, all stages | {drops[0]:.0f} | {drops[1]:.0f} |",
        f"| CPU recording (median of 1 s samples, % of one core) | {steady[0]:.0f} % | {steady[1]:.0f} % |",
    ]
    mon = on[-1].result.snapshot.nodes["monitor"].counters
    lines += ["", "| monitor (last run with it) | messages |", "|---|---:|"]
    for key in ("sent", *(k for k in sorted(mon) if k.startswith("skipped_"))):
        lines.append(f"| {key} | {mon[key]:.0f} |")
    for channel, n in sorted(on[-1].client_msgs.items()):
        lines.append(f"| client decoded {channel} | {n} |")
    worse = [t for t, (a, b) in lost.items() if b > a]
    verdict = "none" if not worse else ", ".join(worse)
    lines += ["", f"Topics where recording with the monitor lost more than without: {verdict}"]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="recording time per run")
    ap.add_argument("--repeats", type=int, default=1, help="runs (the tables give medians)")
    ap.add_argument("--scale", type=float, default=1.0, help="camera resolution scale (1.0 = 1920x1200)")
    ap.add_argument("--cores", type=int, default=2, help="pin to this many CPUs (0 = do not pin)")
    ap.add_argument("--port-base", type=int, default=46000, help="first of the nine UDP ports")
    ap.add_argument("--hogs", type=int, default=0, help="CPU-bound processes to run beside the rig")
    ap.add_argument("--out", type=Path, default=OUT_DIR / "bench_capture.png", help="chart path")
    ap.add_argument("--keep", type=Path, default=None, help="keep the bags in this folder")
    ap.add_argument("--monitor", action="store_true", help="each repeat records without and with the monitor")
    a = ap.parse_args()
    if a.cores:
        cpus = sorted(os.sched_getaffinity(0))[: a.cores]
        os.sched_setaffinity(0, cpus)
    hogs = start_hogs(a.hogs)
    runs: dict[bool, list[Run]] = {False: [], True: []}
    try:
        for k in range(a.repeats):
            modes = ([False, True] if k % 2 == 0 else [True, False]) if a.monitor else [False]
            for j, monitor in enumerate(modes):
                tmp = Path(tempfile.mkdtemp(prefix="bench_capture_", dir=a.keep.parent if a.keep else None))
                try:
                    runs[monitor].append(
                        soak(a.seconds, a.scale, a.port_base + 20 * k + 10 * j, tmp, monitor)
                    )
                finally:
                    if a.keep:
                        shutil.copytree(
                            tmp, a.keep / f"run{k}{'_monitor' if monitor else ''}", dirs_exist_ok=True
                        )
                    shutil.rmtree(tmp, ignore_errors=True)
    finally:
        for p in hogs:
            p.kill()
    print(machine_line() + "\n")
    if a.monitor:
        print("## Without --monitor\n")
    print(report(runs[False], a.seconds, a.hogs))
    if a.monitor:
        print("\n## With --monitor and a connected Foxglove client\n")
        print(report(runs[True], a.seconds, a.hogs))
        print("\n" + compare(runs[False], runs[True]))
    chart(runs[False][-1], a.out)
    print(f"\nchart: {a.out}")


if __name__ == "__main__":
    main()
