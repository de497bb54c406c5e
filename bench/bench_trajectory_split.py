"""The trajectory pass in joined segments on the workers against the single pass: accuracy and CPU.

Issue 46, item 1. On a simulated outdoor walk (`--seconds`, default 20;
2 cm range noise; images at scale 0.125, which the odometry never reads) or
`--bag` (truth beside it), `run_trajectory_pass` runs twice in this process:
as the single pass (`--workers 1`: every sweep through the odometry here)
and split into segments (`ingest.train.trajectory.segments`, the default 10 s
overlapping by 3 s) as jobs of a fork pool of `--workers` (default 2), as
`sensorbox ingest --gt dense --workers 2` runs it. A short pass first loads
numba's cache. Each trajectory against the simulator's truth:

- relative error over 1 s: the motion from t to t + 1 s against the truth's,
  at every 10 ms (poses interpolated between knots), median and 95th
  percentile of the translation (mm), median of the rotation (deg);
- absolute error after alignment: the knots moved by the rigid transform
  that best lays them onto the truth's (rotation the chordal mean,
  translation the mean difference), median and largest (mm, deg).

CPU: this process's own (`time.process_time`, every thread) around each
pass, and for the split pass the workers' (their jobs' own CPU times as the
summary records them); wall time around each. Prints one markdown table and
the machine line.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_line, markdown_table
from bench_lio_peer import at, make_bag, read_tum

Array = np.ndarray[Any, Any]


def relative_errors(est: tuple[Array, Array], truth: tuple[Array, Array]) -> tuple[float, float, float]:
    """(median mm, 95th percentile mm, median deg) of the 1 s motion's error, every 10 ms."""
    s = est[0]
    t = np.arange(s[0], s[-1] - 1_000_000_000, 10_000_000)
    e0, e1 = at(*est, t), at(*est, t + 1_000_000_000)
    g0, g1 = at(*truth, t), at(*truth, t + 1_000_000_000)
    d = np.linalg.inv(np.linalg.inv(g0) @ g1) @ (np.linalg.inv(e0) @ e1)
    mm = np.linalg.norm(d[:, :3, 3], axis=1) * 1e3
    deg = np.degrees(np.linalg.norm(Rotation.from_matrix(d[:, :3, :3]).as_rotvec(), axis=1))
    return float(np.median(mm)), float(np.percentile(mm, 95)), float(np.median(deg))


def absolute_errors(
    est: tuple[Array, Array], truth: tuple[Array, Array]
) -> tuple[float, float, float, float]:
    """(median mm, largest mm, median deg, largest deg) of the knots after the best rigid alignment."""
    s, T = est
    G = at(*truth, s)
    U, _, Vt = np.linalg.svd(np.einsum("nij,nkj->ik", G[:, :3, :3], T[:, :3, :3]))
    R = U @ np.diag([1.0, 1.0, float(np.linalg.det(U @ Vt))]) @ Vt
    p = (G[:, :3, 3] - T[:, :3, 3] @ R.T).mean(axis=0)
    mm = np.linalg.norm(T[:, :3, 3] @ R.T + p - G[:, :3, 3], axis=1) * 1e3
    rel = np.einsum("nji,jk,nkl->nil", G[:, :3, :3], R, T[:, :3, :3])
    deg = np.degrees(np.linalg.norm(Rotation.from_matrix(rel).as_rotvec(), axis=1))
    return float(np.median(mm)), float(mm.max()), float(np.median(deg)), float(deg.max())


def sweep_table(bags: Any, lidar_topics: dict[str, str]) -> dict[str, Array]:
    """Per LiDAR topic, (log ns, first, last point ns) of every sweep with points, as the plan pass has it."""
    from ingest.bags.decode import Sweep

    rows: dict[str, list[tuple[int, int, int]]] = {t: [] for t in lidar_topics}
    for msg in bags.messages(topics=list(lidar_topics)):
        sweep = msg.decoded(bags.label)
        if isinstance(sweep, Sweep) and len(sweep.stamps_ns):
            rows[msg.topic].append((msg.log_ns, *sweep.span_ns))
    return {t: np.array(v, np.int64).reshape(-1, 3) for t, v in rows.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--seconds", type=float, default=20.0, help="simulated walk seconds; default 20")
    ap.add_argument("--bag", type=Path, default=None, help="a recording with <bag>.truth/ beside it")
    ap.add_argument("--workers", type=int, default=2, help="fork-pool workers of the split pass; default 2")
    args = ap.parse_args()

    from calibration.rig import read_rig
    from ingest.bags.reader import open_bags
    from ingest.runtime.executor import Executor
    from ingest.train.run.settings import resolve_topics
    from ingest.train.run.trajectory_jobs import segment_runner
    from ingest.train.trajectory.estimate import run_trajectory_pass
    from ingest.train.trajectory.local_map import OdometryParams
    from ingest.train.trajectory.segments import SegmentParams, Split, plan_segments

    with tempfile.TemporaryDirectory(prefix="bench_trajectory_split_") as tmp:
        root = Path(tmp)
        bag = args.bag or make_bag(args.seconds, root)
        rig = read_rig(Path(f"{bag}.truth") / "rig.yaml")
        truth = read_tum(Path(f"{bag}.truth") / "trajectory.tum")
        rows, trajs = [], {}
        with open_bags([bag]) as bags:
            topics = resolve_topics(rig, bags.topics(), str(bag))
            sweeps = sweep_table(bags, topics.lidars)
            held = [v for v in sweeps.values() if len(v)]
            span = (min(int(v[:, 1].min()) for v in held), max(int(v[:, 2].max()) for v in held))
            pass_args = (bags, topics.lidars, (topics.imu, topics.R_cam0_imu), rig, 0.3)
            run_trajectory_pass(*pass_args, root / "warm.tum", span_ns=(span[0], span[0] + 2_000_000_000))
            params = SegmentParams()
            segments = plan_segments(span, params, OdometryParams().knot_ns)
            runner = segment_runner(Executor(args.workers))
            split = Split(segments, params, sweeps, (Path(bag),), False, runner)
            for name, chosen in (
                ("single pass", None),
                (f"{len(segments)} segments, {args.workers} workers", split),
            ):
                c0, w0 = time.process_time(), time.perf_counter()
                traj, summary = run_trajectory_pass(
                    *pass_args, root / f"{name[:6]}.tum", span_ns=span, split=chosen
                )
                client, wall = time.process_time() - c0, time.perf_counter() - w0
                workers = summary.split.worker_cpu_s if summary.split else 0.0
                T = np.tile(np.eye(4), (len(traj.stamps_ns), 1, 1))
                T[:, :3, :3], T[:, :3, 3] = traj.R_world_cam0, traj.p_world_cam0
                trajs[name] = (traj.stamps_ns, T)
                rel, ab = relative_errors(trajs[name], truth), absolute_errors(trajs[name], truth)
                joins = (
                    ""
                    if summary.split is None
                    else ", ".join(
                        f"{j.residual_rms_mm:.1f} mm / {j.residual_rms_deg:.3f} deg"
                        for j in summary.split.joins
                    )
                )
                rows.append([
                    name, f"{rel[0]:.2f} mm, {rel[2]:.4f} deg", f"{rel[1]:.2f}", f"{ab[0]:.2f} / {ab[1]:.2f}",
                    f"{ab[2]:.4f} / {ab[3]:.4f}", f"{client:.1f} / {workers:.1f}", f"{wall:.1f}",
                    joins or "-",
                ])  # fmt: skip
                print(
                    f"  {name}: client {client:.1f} CPU s, workers {workers:.1f}, wall {wall:.1f} s",
                    flush=True,
                )
    markdown_table(
        ["pass", "relative 1 s: median", "relative 1 s: p95 mm", "absolute mm: median / max",
         "absolute deg: median / max", "CPU s: client / workers", "wall s", "joins (RMS residual)"],
        rows,
    )  # fmt: skip
    print(machine_line())


if __name__ == "__main__":
    main()
