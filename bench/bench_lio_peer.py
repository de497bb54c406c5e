"""The trajectory pass against a peer LiDAR-inertial odometry (RKO-LIO) on the same bag: CPU and accuracy.

Issue 46, item 5 (the measurement only): SensorBox's trajectory pass
(`run_trajectory_pass`, both LiDARs and the gyro, as `sensorbox ingest
--gt dense` runs it: the IMU's readings from the run's first pass, the
sweeps read from the bag) and RKO-LIO (`rko_lio` on PyPI: one LiDAR and its IMU)
on the same simulated outdoor walk (`--seconds`, 2 cm range noise; images
at scale 0.125, which the odometry never reads), side by side in one run:
each in a child process pinned to the same single CPU, one after the other,
`--runs` rounds interleaved (medians). CPU seconds are each child's own
(`getrusage`, every thread) around the odometry alone: SensorBox's pass
reads and decodes the LiDARs' sweeps from the bag itself; RKO-LIO gets the sweeps and IMU readings
as arrays the SensorBox child decoded and saved, so its time holds no bag
reading. The SensorBox child also times its odometry alone on the sweeps
and gyro it read before (`odometry_alone`: `trajectory_pass`'s loop without
the bag), as RKO-LIO is timed. Per LiDAR point: CPU over the points each was
given (SensorBox both LiDARs', RKO-LIO the top one's). Accuracy: median relative error over
1 s against the simulator's truth (translation mm, rotation deg), at RKO-LIO's
scan times.

RKO-LIO is not a dependency of the project: it lives in its own virtual
environment, `--rko-python` (default /work/rkovenv/bin/python; made with
`python3 -m venv /work/rkovenv && /work/rkovenv/bin/pip install rko_lio==0.4.0`).
Writes out/bench/bench_lio_peer.png.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import OUT_DIR, machine_line, markdown_table

ROOT = Path(__file__).resolve().parents[1]
G_MPS2 = 9.80665  # the Livox driver publishes acceleration in g
RKO_CHILD = r"""
import json, resource, sys, time
import numpy as np
from rko_lio.config import LIOConfig
from rko_lio.lio import LIO

data = np.load(sys.argv[1])
out = sys.argv[2]
cfg = LIOConfig()
lio = LIO(cfg)
imu_t, acc, gyro = data["imu_t"], data["imu_acc"], data["imu_gyro"]
T_lidar_imu = data["T_lidar_imu"]
starts, ends, counts = data["scan_start"], data["scan_end"], data["scan_count"]
xyz, stamps = data["xyz"], data["stamps"]
offsets = np.concatenate([[0], np.cumsum(counts)])
r0, w0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
k = 0
for s in range(len(counts)):
    while k < len(imu_t) and imu_t[k] <= ends[s]:
        lio.add_imu_measurement(acc[k], gyro[k], int(imu_t[k]), T_lidar_imu)
        k += 1
    a, b = offsets[s], offsets[s + 1]
    lio.register_scan(xyz[a:b], stamps[a:b], np.eye(4), int(starts[s]), int(ends[s]))
r1, w1 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
t, poses = lio.poses_with_timestamps()
np.savez(out + ".npz", t=np.asarray(t, np.int64), poses=np.asarray([np.asarray(p) for p in poses]))
json.dump({"cpu_s": r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime, "wall_s": w1 - w0,
           "points": int(counts.sum()), "scans": int(len(counts))}, open(out, "w"))
"""


def child_env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1"}


def pinned(cmd: list[str], cpu: int) -> None:
    """Run `cmd` in a child process bound to CPU `cpu` (every thread it starts shares it)."""
    subprocess.run(cmd, env=child_env(), check=True, preexec_fn=lambda: os.sched_setaffinity(0, {cpu}))


def sensorbox_child(bag: Path, work: Path, out: Path) -> None:
    """The trajectory pass on `bag` (a short warm-up pass first: numba's cache loaded), its CPU, its points;
    the top LiDAR's sweeps and its IMU saved for RKO-LIO (first run only)."""
    from calibration.rig import read_rig
    from ingest.bags.decode import ImuSample, Sweep
    from ingest.bags.reader import open_bags
    from ingest.train.run.settings import resolve_topics
    from ingest.train.trajectory.estimate import GyroReadings, read_gyro, run_trajectory_pass

    rig = read_rig(Path(f"{bag}.truth") / "rig.yaml")
    with open_bags([bag]) as bags:
        topics = resolve_topics(rig, bags.topics(), str(bag))
        sweeps: dict[str, list[Sweep]] = {t: [] for t in topics.lidars}
        in_order: list[tuple[str, Sweep]] = []
        imu: list[ImuSample] = []
        top = rig.lidars[0]
        imu_top = next(i for i in rig.imus if i.name == top.name.replace("lidar", "imu"))
        readings = GyroReadings()  # the trajectory pass's gyro readings, as ingest's survey hands them over
        assert topics.imu is not None
        for msg in bags.messages(topics=list({*topics.lidars, imu_top.topic, topics.imu})):
            d = msg.decoded(bags.label)
            if isinstance(d, Sweep) and len(d.stamps_ns):
                sweeps[msg.topic].append(d)
                in_order.append((msg.topic, d))
            elif isinstance(d, ImuSample):
                if msg.topic == imu_top.topic:
                    imu.append(d)
                if msg.topic == topics.imu:
                    readings.add(d)
        first = min(s.span_ns[0] for v in sweeps.values() for s in v)
        last = max(s.span_ns[1] for v in sweeps.values() for s in v)
        args = (bags, topics.lidars, (topics.imu, topics.R_cam0_imu), rig, 0.3)
        # fresh files each round: a pass finds the one an earlier round kept beside its file and reuses it
        warm = out.with_suffix(".warm.tum")
        run_trajectory_pass(*args, warm, span_ns=(first, first + 2_000_000_000), readings=readings)
        r0, w0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        run_trajectory_pass(*args, out.with_suffix(".tum"), readings=readings)
        r1, w1 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        gyro = read_gyro(bags, topics.imu, topics.R_cam0_imu, readings=readings)
        alone_s = odometry_alone(in_order, gyro, rig, topics.lidars)
    points = sum(len(s.stamps_ns) for v in sweeps.values() for s in v)
    doc = {"cpu_s": r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime, "wall_s": w1 - w0,
           "points": points, "seconds": (last - first) / 1e9, "alone_cpu_s": alone_s}  # fmt: skip
    out.write_text(json.dumps(doc))
    arrays = work / "rko_input.npz"
    if not arrays.exists():
        mine = sweeps[top.topic]
        T_lidar_imu = np.linalg.inv(top.T_cam0_lidar) @ imu_top.T_cam0_imu
        np.savez(
            arrays,
            imu_t=np.array([s.stamp_ns for s in imu], np.int64),
            imu_acc=np.array([s.acc for s in imu]) * G_MPS2,
            imu_gyro=np.array([s.gyro_rad_s for s in imu]),
            T_lidar_imu=T_lidar_imu,
            scan_start=np.array([s.span_ns[0] for s in mine], np.int64),
            scan_end=np.array([s.span_ns[1] for s in mine], np.int64),
            scan_count=np.array([len(s.stamps_ns) for s in mine], np.int64),
            xyz=np.concatenate([np.asarray(s.xyz_m, np.float64) for s in mine]),
            stamps=np.concatenate([s.stamps_ns for s in mine]),
            T_cam0_lidar=top.T_cam0_lidar,
        )


def odometry_alone(in_order: list[tuple[str, Any]], gyro: Any, rig: Any, lidars: dict[str, str]) -> float:
    """CPU s of SensorBox's odometry on sweeps already decoded and a gyro already read, as RKO-LIO is
    measured: `trajectory_pass`'s loop without the bag (its reading, decoding and message checks)."""
    from ingest.train.trajectory.clouds import filter_points
    from ingest.train.trajectory.odometry import Odometry

    r0 = resource.getrusage(resource.RUSAGE_SELF)
    odo = Odometry(gyro)
    last = {topic: -(2**62) for topic in lidars}
    for topic, sweep in in_order:
        keep, _ = filter_points(sweep.xyz_m, sweep.tag, 0.3)
        T = rig.lidar(lidars[topic]).T_cam0_lidar
        xyz = np.asarray(sweep.xyz_m, np.float64)[keep]
        if len(xyz):
            odo.add(xyz @ T[:3, :3].T + T[:3, 3], sweep.stamps_ns[keep])
        last[topic] = max(last[topic], sweep.span_ns[1])
        odo.advance(min(last.values()))
    odo.result()
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    return r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime


def read_tum(path: Path) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """(stamps ns, poses (N, 4, 4)) of a TUM file."""
    from scipy.spatial.transform import Rotation

    rows = [line.split() for line in path.read_text().splitlines() if line and line[0] != "#"]
    ns = np.array([round(float(r[0]) * 1e9) for r in rows], np.int64)
    vals = np.array([[float(v) for v in r[1:]] for r in rows])
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(vals[:, 3:]).as_matrix()
    T[:, :3, 3] = vals[:, :3]
    return ns, T


def pose_matrices(xyz_quat: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """(N, 4, 4) transforms of RKO-LIO's poses, rows x y z qx qy qz qw."""
    from scipy.spatial.transform import Rotation

    T = np.tile(np.eye(4), (len(xyz_quat), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(xyz_quat[:, 3:]).as_matrix()
    T[:, :3, 3] = xyz_quat[:, :3]
    return T


def at(
    stamps: np.ndarray[Any, Any], poses: np.ndarray[Any, Any], t: np.ndarray[Any, Any]
) -> np.ndarray[Any, Any]:
    """Poses interpolated at `t` (linear position, slerp rotation); `t` within `stamps`."""
    from scipy.spatial.transform import Rotation, Slerp

    slerp = Slerp(stamps.astype(np.float64), Rotation.from_matrix(poses[:, :3, :3]))
    out = np.tile(np.eye(4), (len(t), 1, 1))
    out[:, :3, :3] = slerp(t.astype(np.float64)).as_matrix()
    for i in range(3):
        out[:, i, 3] = np.interp(t, stamps, poses[:, i, 3])
    return out


def relative_error(
    est: tuple[Any, Any], truth: tuple[Any, Any], t: np.ndarray[Any, Any]
) -> tuple[float, float]:
    """Median error (mm, deg) of the motion over 1 s between `est` and `truth` at times `t` (ns)."""
    from scipy.spatial.transform import Rotation

    lo = max(est[0][0], truth[0][0])
    hi = min(est[0][-1], truth[0][-1]) - 1_000_000_000
    t = t[(t >= lo) & (t <= hi)]
    e0, e1 = at(*est, t), at(*est, t + 1_000_000_000)
    g0, g1 = at(*truth, t), at(*truth, t + 1_000_000_000)
    d = np.linalg.inv(np.linalg.inv(g0) @ g1) @ (np.linalg.inv(e0) @ e1)
    trans_mm = np.linalg.norm(d[:, :3, 3], axis=1) * 1e3
    rot_deg = np.degrees(np.linalg.norm(Rotation.from_matrix(d[:, :3, :3]).as_rotvec(), axis=1))
    return float(np.median(trans_mm)), float(np.median(rot_deg))


def make_bag(seconds: float, root: Path) -> Path:
    bag = root / "walk"
    cmd = [sys.executable, "-m", "sensorbox.cli", "simulate", "--out", str(bag), "--scene", "outdoor",
           "--trajectory", "walk", "--scale", "0.125", "--duration", f"{seconds:g}",
           "--range-noise", "0.02"]  # fmt: skip
    subprocess.run(cmd, env=child_env(), check=True, stdout=subprocess.DEVNULL)
    return bag


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--seconds", type=float, default=20.0, help="simulated walk seconds; default 20")
    ap.add_argument("--bag", type=Path, default=None, help="a recording with <bag>.truth/ beside it")
    ap.add_argument("--runs", type=int, default=1, help="interleaved rounds (medians); default 1")
    ap.add_argument("--rko-python", type=Path, default=Path("/work/rkovenv/bin/python"))
    ap.add_argument("--out", type=Path, default=OUT_DIR / "bench_lio_peer.png", help="chart path")
    ap.add_argument("--sensorbox-child", nargs=3, type=Path, help=argparse.SUPPRESS)  # BAG WORK OUT
    args = ap.parse_args()
    if args.sensorbox_child:
        sensorbox_child(*args.sensorbox_child)
        return
    if not args.rko_python.exists():
        raise SystemExit(f"bench_lio_peer: {args.rko_python} missing; see the module docstring to make it")
    cpu = min(os.sched_getaffinity(0))
    with tempfile.TemporaryDirectory(prefix="bench_lio_peer_") as tmp:
        root = Path(tmp)
        bag = args.bag or make_bag(args.seconds, root)
        ours, theirs = [], []
        for k in range(max(1, args.runs)):
            pinned(
                [
                    sys.executable,
                    __file__,
                    "--sensorbox-child",
                    str(bag),
                    str(root),
                    str(root / f"sb{k}.json"),
                ],
                cpu,
            )
            pinned(
                [
                    str(args.rko_python),
                    "-c",
                    RKO_CHILD,
                    str(root / "rko_input.npz"),
                    str(root / f"rko{k}.json"),
                ],
                cpu,
            )
            ours.append(json.loads((root / f"sb{k}.json").read_text()))
            theirs.append(json.loads((root / f"rko{k}.json").read_text()))
            print(f"  round {k + 1}: SensorBox {ours[-1]['cpu_s']:.1f} CPU s, "
                  f"RKO-LIO {theirs[-1]['cpu_s']:.1f} CPU s; load {os.getloadavg()[0]:.1f}",
                  flush=True)  # fmt: skip
        truth = read_tum(Path(f"{bag}.truth") / "trajectory.tum")
        rko = np.load(root / f"rko{len(theirs) - 1}.json.npz")
        T_lidar_cam0 = np.linalg.inv(np.load(root / "rko_input.npz")["T_cam0_lidar"])
        rko_cam0 = (rko["t"], pose_matrices(rko["poses"]) @ T_lidar_cam0)  # T_world_lidar -> T_world_cam0
        ours_tum = read_tum(root / f"sb{len(ours) - 1}.tum")
        err_ours = relative_error(ours_tum, truth, rko["t"])
        err_rko = relative_error(rko_cam0, truth, rko["t"])
    seconds = ours[0]["seconds"]

    def med(xs: list[float]) -> float:
        return statistics.median(xs)

    ours_cpu, rko_cpu = med([r["cpu_s"] for r in ours]), med([r["cpu_s"] for r in theirs])
    ours_us = ours_cpu / ours[0]["points"] * 1e6
    alone_cpu = med([r["alone_cpu_s"] for r in ours])
    alone_us = alone_cpu / ours[0]["points"] * 1e6
    rko_us = rko_cpu / theirs[0]["points"] * 1e6
    print()
    print(machine_line())
    print(f"input: {bag}, {seconds:.1f} s of LiDAR; one CPU each, medians of {len(ours)} round(s)")
    print()
    rows = [
        ["LiDARs / points given", f"2 / {ours[0]['points']:,}", f"1 / {theirs[0]['points']:,}", ""],
        ["CPU s (odometry)", f"{ours_cpu:.1f}", f"{rko_cpu:.1f}", f"{ours_cpu / rko_cpu:.2f}"],
        ["CPU s per second of data", f"{ours_cpu / seconds:.2f}", f"{rko_cpu / seconds:.2f}",
         f"{ours_cpu / rko_cpu:.2f}"],
        ["CPU us per LiDAR point", f"{ours_us:.2f}", f"{rko_us:.2f}", f"{ours_us / rko_us:.2f}"],
        ["... odometry alone: CPU s (sweeps and gyro as arrays)", f"{alone_cpu:.1f}", f"{rko_cpu:.1f}",
         f"{alone_cpu / rko_cpu:.2f}"],
        ["... odometry alone: CPU us per LiDAR point", f"{alone_us:.2f}", f"{rko_us:.2f}",
         f"{alone_us / rko_us:.2f}"],
        ["relative error over 1 s, median mm", f"{err_ours[0]:.1f}", f"{err_rko[0]:.1f}", ""],
        ["relative error over 1 s, median deg", f"{err_ours[1]:.3f}", f"{err_rko[1]:.3f}", ""],
    ]  # fmt: skip
    markdown_table(["measure", "SensorBox trajectory pass", "RKO-LIO 0.4.0", "SensorBox / RKO-LIO"], rows)
    print("\ntarget (issue 46, item 5): CPU per LiDAR point within 2x of RKO-LIO's, at unchanged accuracy")
    chart(ours_us, rko_us, err_ours, err_rko, args.out)


def chart(
    ours_us: float, rko_us: float, err_ours: tuple[float, float], err_rko: tuple[float, float], path: Path
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(8, 2.8))
    ax.bar(["SensorBox", "RKO-LIO"], [ours_us, rko_us], color=["tab:blue", "tab:orange"])
    ax.axhline(2 * rko_us, color="k", ls=":", label="2x RKO-LIO")
    ax.set_ylabel("CPU us per LiDAR point")
    ax.legend(fontsize=7)
    bx.bar(["SensorBox", "RKO-LIO"], [err_ours[0], err_rko[0]], color=["tab:blue", "tab:orange"])
    bx.set_ylabel("relative error over 1 s, mm (median)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"chart: {path}")


if __name__ == "__main__":
    main()
