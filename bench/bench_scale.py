"""Past one machine: how much of a dense ingest's CPU the client spends, and the speed-up that leaves.

Input: a simulated half-resolution outdoor walk (`sensorbox simulate --scene
outdoor --trajectory walk --scale 0.5`, `--seconds`, default 20, 2 cm range
noise, its images JPEG as `sensorbox capture` records them, or `--image
raw`) in a temporary folder, or `--bag PATH` (rig from its truth folder).
Each run is the command `sensorbox ingest BAG --gt dense --every N --workers 2
--no-preview` (`--every`, default 2: the setting issue 46 measured; the
client's work is per second of recording, the workers' mostly per sample,
so the share grows with N) into a fresh folder (no trajectory cache to reuse), as a child
process of this one, either with its fork pool or with `--dask` on a local
cluster of 2 single-threaded worker processes (a fresh cluster per run,
started in a helper process before the run and not counted); each of the two
once as it runs by default (the trajectory pass in 10 s segments on the
workers, where the recording is longer than one) and once with `--segment-s
inf` (the single pass, in the client), so the split's wall time and the
client's share are measured against the single pass's in the same session.

The CPU figures are the processes' own, from the kernel's counters
(`/proc/PID/stat`), not wall time:

- client: the `sensorbox ingest` process itself (reading, planning, and
  whatever else it does: the trajectory pass, the dense-GT blocks), read
  once it has exited and before it is reaped, so nothing is lost;
- workers: with the fork pool, the client's reaped children (the pool's
  processes, whose counters the kernel adds to the client's `cutime` and
  `cstime` when it reaps them); with Dask, every process under the
  cluster's helper (its worker processes), before against after the run;
- scheduler: with Dask, the helper process itself (scheduler and nannies),
  before against after the run.

The client's share is client / (client + workers + scheduler); the Amdahl
speed-up it allows at N workers is 1 / (s + (1 - s) / N), s the share
(the client's work as the serial part, the rest spread over N workers).
The trajectory pass's wall time comes from the run's dataset.yaml, the dense
blocks' count and time from the run's summary. Before the runs, one
unmeasured ingest of a few samples compiles (or loads) the numba kernels,
so no measured run pays for compiling, and writes every module's bytecode
(into a temporary folder, `PYTHONPYCACHEPREFIX`, whatever
PYTHONDONTWRITEBYTECODE says) for the measured runs to read. Fork-pool and
Dask runs, split and single, alternate (`--runs` rounds) and the table gives
each one's median. Writes a chart of the CPU split and the speed-ups to
out/bench/bench_scale.png.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import OUT_DIR, machine_line, markdown_table

ROOT = Path(__file__).resolve().parents[1]
WORKER_COUNTS = (8, 32, 128)
CLIENT_SHARE_TARGET = 0.03  # issue 46: client CPU <= 3 % of the run's CPU
TICK = os.sysconf("SC_CLK_TCK")


def sensorbox(*args: str) -> list[str]:
    """The `sensorbox` command line of this checkout (its modules first on the path)."""
    return [sys.executable, "-m", "sensorbox.cli", *args]


PYCACHE: dict[str, str] = {}  # "prefix": where the children keep their bytecode (`main` sets it)


def child_env() -> dict[str, str]:
    """This checkout first on the path, a wide terminal (the summary table is parsed), BLAS on one thread,
    and bytecode written and read (in `PYCACHE`'s folder, not the source tree): with
    PYTHONDONTWRITEBYTECODE set, every process would compile each module it imports again (about 5 CPU s
    of a client's start on this project, which an installed checkout does not spend)."""
    path = os.environ.get("PYTHONPATH", "")
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{path}" if path else str(ROOT),
           "COLUMNS": "200", "OPENBLAS_NUM_THREADS": "1"}  # fmt: skip
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    if "prefix" in PYCACHE:
        env["PYTHONPYCACHEPREFIX"] = PYCACHE["prefix"]
    return env


def stat_cpu_s(pid: int) -> tuple[float, float]:
    """(own, reaped children's) user + system CPU seconds of process `pid`, from /proc/PID/stat."""
    text = Path(f"/proc/{pid}/stat").read_text()
    fields = text[text.rindex(")") + 2 :].split()  # after the command name, which may hold spaces
    utime, stime, cutime, cstime = (int(f) for f in fields[11:15])
    return (utime + stime) / TICK, (cutime + cstime) / TICK


def descendants(pid: int) -> list[int]:
    """Every process under `pid` (children, theirs, ...), from /proc/PID/task/*/children."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                kids = [int(k) for k in (task / "children").read_text().split()]
            except OSError:
                continue
            out += kids
            todo += kids
    return out


def tree_cpu_s(pid: int) -> tuple[float, dict[int, float]]:
    """CPU seconds of `pid` itself and of each process under it (own time each)."""
    under = {}
    for p in descendants(pid):
        try:
            under[p] = stat_cpu_s(p)[0]
        except OSError:  # ended meanwhile
            continue
    return stat_cpu_s(pid)[0], under


@dataclass(frozen=True)
class Run:
    """One ingest's CPU split (seconds) and times."""

    mode: str  # a `MODES` key
    client_s: float
    workers_s: float
    scheduler_s: float
    wall_s: float
    trajectory_s: float
    blocks: int
    blocks_s: float
    written: int

    @property
    def total_s(self) -> float:
        return self.client_s + self.workers_s + self.scheduler_s

    @property
    def share(self) -> float:
        return self.client_s / self.total_s

    def amdahl(self, workers: int) -> float:
        """The speed-up over one worker's time that the client's share allows with `workers` workers."""
        return 1.0 / (self.share + (1.0 - self.share) / workers)


MODES = {
    "fork": "fork pool (--workers 2)",
    "fork, one pass": "fork pool, --segment-s inf",
    "dask": "Dask (2 local workers)",
    "dask, one pass": "Dask, --segment-s inf",
}
"""The runs' executors and trajectory passes, as the table's columns name them."""


def ingest_args(
    bag: Path, rig: Path, out: Path, every: int, dask: str | None, one_pass: bool = False
) -> list[str]:
    args = [str(bag), "--rig", str(rig), "--out", str(out), "--gt", "dense", "--every", str(every)]
    args += ["--workers", "2", "--no-preview"] + (["--segment-s", "inf"] if one_pass else [])
    return args + (["--dask", dask] if dask else [])


def run_client(args: list[str]) -> tuple[float, float, float, str]:
    """Run `sensorbox ingest ARGS`: (its own CPU s, its reaped children's, wall s, its output).

    The counters are read from the exited process before it is reaped (`waitid` with WNOWAIT), so they
    are whole.
    """
    with tempfile.TemporaryFile() as log:
        t0 = time.perf_counter()
        cmd = sensorbox("ingest", *args)
        proc = subprocess.Popen(cmd, env=child_env(), stdout=log, stderr=subprocess.STDOUT)
        os.waitid(os.P_PID, proc.pid, os.WEXITED | os.WNOWAIT)
        wall = time.perf_counter() - t0
        own, kids = stat_cpu_s(proc.pid)
        proc.wait()
        log.seek(0)
        text = log.read().decode(errors="replace")
    if proc.returncode != 0:
        raise SystemExit(f"bench_scale: sensorbox ingest exited {proc.returncode}:\n{text[-3000:]}")
    return own, kids, wall, text


BLOCKS_ROW = re.compile(r"dense GT blocks[^│|]*[│|]\s*(\d+),\s*([\d.]+) s")


def run_facts(out: Path, text: str) -> tuple[float, int, float, int]:
    """(trajectory pass s, dense blocks, their s, samples written) of a finished run."""
    doc = yaml.safe_load((out / "dataset.yaml").read_text())
    traj_s = float(doc["sources"][-1]["ground_truth"]["trajectory"]["seconds"])
    m = BLOCKS_ROW.search(text)
    blocks, blocks_s = (int(m.group(1)), float(m.group(2))) if m else (0, float("nan"))
    written = len(list((out / "meta").glob("*.json")))
    return traj_s, blocks, blocks_s, written


CLUSTER = """
import sys
from distributed import LocalCluster
cluster = LocalCluster(n_workers=int(sys.argv[1]), threads_per_worker=1, processes=True,
                       dashboard_address=None)
print(cluster.scheduler_address, flush=True)
sys.stdin.read()
cluster.close()
"""


@contextmanager
def dask_cluster(workers: int) -> Iterator[tuple[str, int]]:
    """A local Dask cluster of `workers` single-threaded worker processes in a helper process: (address,
    the helper's pid); it ends when the block does."""
    proc = subprocess.Popen([sys.executable, "-c", CLUSTER, str(workers)], env=child_env(),
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)  # fmt: skip
    assert proc.stdout is not None and proc.stdin is not None
    try:
        address = proc.stdout.readline().strip()
        if not address:
            raise SystemExit("bench_scale: the local Dask cluster did not start")
        yield address, proc.pid
    finally:
        proc.stdin.close()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def measure(mode: str, bag: Path, rig: Path, root: Path, every: int) -> Run:
    """One measured ingest (`mode` a `MODES` key) into a fresh folder under `root`."""
    out = Path(tempfile.mkdtemp(prefix=f"{mode.split(',')[0]}_", dir=root)) / "ds"
    one_pass = mode.endswith("one pass")
    if mode.startswith("fork"):
        own, kids, wall, text = run_client(ingest_args(bag, rig, out, every, None, one_pass))
        run = Run(mode, own, kids, 0.0, wall, *run_facts(out, text))
    else:
        with dask_cluster(2) as (address, helper):
            time.sleep(1.0)  # the workers' own start-up settles
            sched0, under0 = tree_cpu_s(helper)
            own, _, wall, text = run_client(ingest_args(bag, rig, out, every, address, one_pass))
            sched1, under1 = tree_cpu_s(helper)
        workers = sum(s - under0.get(p, 0.0) for p, s in under1.items())
        run = Run(mode, own, workers, sched1 - sched0, wall, *run_facts(out, text))
    shutil.rmtree(out.parent, ignore_errors=True)
    return run


def make_bag(seconds: float, image: str, root: Path) -> tuple[Path, Path]:
    """The half-resolution outdoor walk, simulated into `root` by `sensorbox simulate` (`image`: jpeg or
    raw)."""
    bag = root / "walk"
    cmd = sensorbox("simulate", "--out", str(bag), "--scene", "outdoor", "--trajectory", "walk",
                    "--scale", "0.5", "--duration", f"{seconds:g}", "--range-noise", "0.02",
                    "--image", image)  # fmt: skip
    subprocess.run(cmd, env=child_env(), check=True, stdout=subprocess.DEVNULL)
    return bag, root / "walk.truth" / "rig.yaml"


def med(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def table(runs: dict[str, list[Run]]) -> tuple[list[str], list[list[str]]]:
    """The header and rows: one column per mode run, the medians of its runs."""
    modes = [m for m in MODES if runs.get(m)]

    def col(mode: str, fmt: str, f: object) -> str:
        return fmt.format(med([f(r) for r in runs[mode]]))  # type: ignore[operator]

    def against_one_pass(mode: str) -> str:
        single = runs.get(f"{mode}, one pass") if not mode.endswith("one pass") else None
        if not single:
            return "-"
        ratio = med([r.trajectory_s for r in runs[mode]]) / med([r.trajectory_s for r in single])
        return f"{ratio:.2f}"

    rows = [
        ("samples written", "{:.0f}", lambda r: r.written),
        ("wall s (client start to exit)", "{:.1f}", lambda r: r.wall_s),
        ("CPU s: client (the `sensorbox ingest` process)", "{:.1f}", lambda r: r.client_s),
        ("CPU s: workers", "{:.1f}", lambda r: r.workers_s),
        ("CPU s: Dask scheduler and nannies", "{:.1f}", lambda r: r.scheduler_s),
        ("client's share of the run's CPU", "{:.1%}", lambda r: r.share),
        ("trajectory pass, wall s", "{:.1f}", lambda r: r.trajectory_s),
        ("dense GT blocks", "{:.0f}", lambda r: r.blocks),
        ("dense GT blocks, s (summary)", "{:.1f}", lambda r: r.blocks_s),
        *((f"Amdahl speed-up at {n} workers", "{:.1f}x", lambda r, n=n: r.amdahl(n)) for n in WORKER_COUNTS),
    ]
    body = [[name, *(col(m, fmt, f) for m in modes)] for name, fmt, f in rows]
    body.insert(7, ["trajectory pass, wall: split / one pass", *(against_one_pass(m) for m in modes)])
    return ["measure", *(MODES[m] for m in modes)], body


def chart(runs: dict[str, list[Run]], path: Path) -> None:
    """The CPU split of the median-share run of each mode, and the speed-ups its share allows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    modes = [m for m in runs if runs[m]]
    picked = [sorted(runs[m], key=lambda r: r.share)[len(runs[m]) // 2] for m in modes]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(9, 3.2))
    labels = [f"{m} ({r.share:.1%} client)" for m, r in zip(modes, picked, strict=True)]
    left = [0.0] * len(picked)
    for part, colour in (("client_s", "tab:red"), ("workers_s", "tab:blue"), ("scheduler_s", "tab:grey")):
        vals = [getattr(r, part) for r in picked]
        ax.barh(labels, vals, left=left, color=colour, label=part.removesuffix("_s"))
        left = [a + b for a, b in zip(left, vals, strict=True)]
    ax.set_xlabel("CPU s of one run")
    ax.legend(fontsize=7)
    ns = [1, 2, 4, 8, 16, 32, 64, 128]
    for m, r in zip(modes, picked, strict=True):
        bx.plot(ns, [r.amdahl(n) for n in ns], marker="o", label=m)
    bx.plot(ns, ns, "k:", label="ideal")
    bx.set_xscale("log", base=2)
    bx.set_yscale("log", base=2)
    bx.set_xlabel("workers")
    bx.set_ylabel("speed-up (Amdahl, client serial)")
    bx.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"chart: {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--runs", type=int, default=1, help="rounds of one run of each mode; default 1")
    ap.add_argument("--seconds", type=float, default=20.0, help="simulated walk seconds; default 20")
    every = "ingest every N-th frame pair; default 2, as issue 46 measured (ingest's own default is 1)"
    ap.add_argument("--every", type=int, default=2, help=every)
    images = "the simulated walk's images; default jpeg, as `sensorbox capture` records them"
    ap.add_argument("--image", choices=("jpeg", "raw"), default="jpeg", help=images)
    ap.add_argument("--bag", type=Path, default=None, help="a recording with <bag>.truth/ beside it")
    ap.add_argument("--no-dask", action="store_true", help="skip the Dask runs")
    ap.add_argument("--no-one-pass", action="store_true", help="skip the runs with --segment-s inf")
    ap.add_argument("--out", type=Path, default=OUT_DIR / "bench_scale.png", help="chart path")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_scale_") as tmp:
        root = Path(tmp)
        if args.bag is None:
            walk = f"a {args.seconds:g} s half-resolution outdoor walk ({args.image} images)"
            print(f"simulating {walk} ...", flush=True)
            bag, rig = make_bag(args.seconds, args.image, root)
        else:
            bag, rig = args.bag, Path(f"{args.bag}.truth") / "rig.yaml"
        PYCACHE["prefix"] = str(root / "pycache")
        run_client(ingest_args(bag, rig, root / "warm", 30, None))  # bytecode written, numba's kernels cached
        modes = [m for m in MODES if not (args.no_dask and m.startswith("dask"))]
        modes = [m for m in modes if not (args.no_one_pass and m.endswith("one pass"))]
        runs: dict[str, list[Run]] = {m: [] for m in modes}
        for _ in range(max(1, args.runs)):
            for mode in modes:
                r = measure(mode, bag, rig, root, args.every)
                runs[mode].append(r)
                print(f"  {mode}: {r.written} samples, {r.wall_s:.1f} s; CPU client {r.client_s:.1f} s, "
                      f"workers {r.workers_s:.1f} s, scheduler {r.scheduler_s:.1f} s: client "
                      f"{r.share:.1%}; trajectory {r.trajectory_s:.1f} s, {r.blocks} blocks "
                      f"{r.blocks_s:.1f} s; load {os.getloadavg()[0]:.1f}", flush=True)  # fmt: skip
        print()
        print(machine_line())
        given = f"{bag} ({args.image} images)" if args.bag is None else str(bag)
        print(f"input: {given} (--every {args.every}, --gt dense, 2 workers); medians of {args.runs} run(s)")
        print()
        markdown_table(*table(runs))
        print(f"\ntarget (issue 46): client's share <= {CLIENT_SHARE_TARGET:.0%}")
        chart(runs, args.out)


if __name__ == "__main__":
    main()
