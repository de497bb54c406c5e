"""Dense vs sparse ground truth at full resolution against the simulator's exact truth.

Scenes (simulated once, noise-free unless said): the static room, a handheld
outdoor walk, the walk with movers (people, a door, a car), and the walk with
2 cm range noise. Bags are simulated with small images (the GT needs only the
LiDARs and IMU); every sample is computed and scored with the reference rig's
full-resolution upper camera (1920x1200) and its equirect.

Methods x windows (+- around the frame time):
- constant velocity: the sparse GT (gyro rotation + a velocity fitted to the
  window's own points), +-50/100/200 ms;
- odometry: the recording's trajectory places every sweep of the window,
  free-space test off, +-200/500/1000 ms;
- odometry + movers filter: the same with the free-space test (the default),
  +-200/500/1000 ms.

Dense samples get their points' planes as ingest's stream pass fits them,
once per 1 s block (`block_planes`; seconds per sample leave that fit out,
as a worker's time does).

`run_dense_study` returns a table row per scene and method (density, range
median, outliers, disparity median and > 1 px, disparity GT pixels per
depth GT pixel, mover trail, seconds per sample) and the trajectory's error
over the walk; `dense_chart` draws density against range error with each
scene's Pareto front.
"""

from __future__ import annotations

import shutil
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from calibration.rig import REFERENCE_RIG, read_rig
from ingest.bags.decode import ImuSample, Sweep, decode
from ingest.bags.reader import open_bags
from ingest.dataset.layout import prepare_dirs
from ingest.train.gt.block_planes import BlockPlanes, PlaneSettings
from ingest.train.gt.dense import DenseParams, free_space_settings
from ingest.train.run.sample import process_sample
from ingest.train.run.sample_job import Geometry, ImuWindow, SampleJob, SampleParams
from ingest.train.run.stream import lidar_window
from ingest.train.trajectory.estimate import run_trajectory_pass
from ingest.train.trajectory.rig_trajectory import RigTrajectory
from sensorbox.sim.config import SimConfig
from sensorbox.sim.run import simulate
from sensorbox.sim.score import score_sample
from sensorbox.sim.truth import Truth

MS = 1_000_000


@dataclass(frozen=True)
class Method:
    name: str
    window_ms: int

    @property
    def label(self) -> str:
        return f"{self.name} +-{self.window_ms} ms"

    def params(self) -> SampleParams:
        w = self.window_ns
        if self.name == "constant velocity":
            return SampleParams(window_ns=w, method="sparse", overlap_images=False)
        free = self.name.endswith("movers filter")
        return SampleParams(
            method="dense", dense=DenseParams(window_ns=w, free_space=free), overlap_images=False
        )

    @property
    def window_ns(self) -> int:
        return self.window_ms * MS


METHODS = [
    *(Method("constant velocity", w) for w in (50, 100, 200)),
    *(Method("odometry", w) for w in (200, 500, 1000)),
    *(Method("odometry + movers filter", w) for w in (200, 500, 1000)),
]


@dataclass
class Recording:
    """A simulated bag read into memory: sweeps per LiDAR, gyro, the truth and the trajectory."""

    name: str
    bag: Path
    truth: Truth
    sweeps: dict[str, list[Sweep]]
    imu_t: np.ndarray
    imu_g: np.ndarray
    trajectory: RigTrajectory
    trajectory_s: float
    planes: dict[tuple[Any, ...], BlockPlanes] = field(default_factory=dict)


def block_planes(rec: Recording, geo: Geometry, params: SampleParams) -> BlockPlanes:
    """The recording's blocks (planes, free-space bits) as ingest's stream pass runs them
    (`ingest.train.gt.block_planes`), every block done; once per recording and settings."""
    dense = params.dense
    free = free_space_settings(dense) if dense.free_space else None
    key = (dense.plane_block_ns, dense.plane_neighbours, dense.plane_max_flatness, params.min_range_m, free)
    if key not in rec.planes:
        settings = PlaneSettings(
            {name: geo.rig.lidar(name).T_cam0_lidar for name in rec.sweeps}, dense.plane_block_ns,
            dense.plane_neighbours, dense.plane_max_flatness, params.min_range_m, free,
        )  # fmt: skip
        spans = {name: [s.span_ns for s in v] for name, v in rec.sweeps.items()}
        planes = BlockPlanes(rec.trajectory, spans, settings)
        stamps = [t for v in rec.sweeps.values() for s in v for t in s.span_ns]
        planes.complete(rec.sweeps, min(stamps), max(stamps), final=True)
        rec.planes[key] = planes
    return rec.planes[key]


def record(name: str, cfg: SimConfig, root: Path) -> Recording:
    """Simulate the scene afresh (a previous run's recording and trajectory under `root` are replaced)
    and read it."""
    for old in (root / name, root / f"{name}.truth"):
        if old.is_dir():
            shutil.rmtree(old)
    for cached in (root / f"{name}.tum", root / f"{name}.npz"):  # the pass is timed: never read back
        cached.unlink(missing_ok=True)
    bag = simulate(cfg, root / name).bag
    truth = Truth.load(bag)
    rig = truth.rig
    topics = {li.topic: li.name for li in rig.lidars}
    sweeps: dict[str, list[Sweep]] = {n: [] for n in topics.values()}
    imu_t, imu_g = [], []
    with open_bags([bag]) as bags:
        for msg in bags.messages(topics=[*topics, rig.imus[0].topic]):
            item = decode(msg.msgtype, msg.raw, msg.ros_version)
            if isinstance(item, ImuSample):
                imu_t.append(item.stamp_ns)
                imu_g.append(item.gyro_rad_s)
            elif isinstance(item, Sweep) and len(item.stamps_ns):
                sweeps[topics[msg.topic]].append(item)
        t0 = time.perf_counter()
        traj, _ = run_trajectory_pass(
            bags, topics, (rig.imus[0].topic, rig.imus[0].T_cam0_imu[:3, :3]), rig, 0.3, root / f"{name}.tum"
        )
        seconds = time.perf_counter() - t0
    return Recording(name, bag, truth, sweeps, np.array(imu_t), np.array(imu_g), traj, seconds)


def job(rec: Recording, geo: Geometry, tc: int, method: Method, out: Path, sid: str) -> SampleJob:
    """The sample at `tc` as ingest hands it to a worker (dense: with its points' block planes)."""
    w = method.window_ns
    params = method.params()
    planes = block_planes(rec, geo, params) if params.method == "dense" else None
    lidars = tuple(lidar_window(sweeps, name, tc, w, planes) for name, sweeps in rec.sweeps.items())
    sel = (rec.imu_t >= tc - w - 20 * MS) & (rec.imu_t <= tc + w + 20 * MS)
    imu = ImuWindow(rec.imu_t[sel], rec.imu_g[sel], rec.truth.rig.imus[0].T_cam0_imu[:3, :3])
    up = np.zeros((geo.rig.upper.model.height, geo.rig.upper.model.width, 3), np.uint8)
    lo = np.zeros((geo.rig.lower.model.height, geo.rig.lower.model.width, 3), np.uint8)
    traj = rec.trajectory
    return SampleJob(out, sid, rec.name, tc, tc, up, lo, lidars, imu, None, geo, params, traj)


def evaluate(rec: Recording, geo: Geometry, method: Method, stamps: list[int], out: Path) -> dict[str, float]:
    """Mean scores over the samples, and seconds per sample.

    `removed` is the share of the window's accumulated points the free-space
    test removed as movers (0 with the test off).
    """
    prepare_dirs(out, False)
    (out / "dataset.yaml").write_text(f"height_full: {geo.equirect.height_full}\n")
    truth = replace(rec.truth, rig=geo.rig)
    rows, secs = [], []
    for k, tc in enumerate(stamps):
        t0 = time.perf_counter()
        res = process_sample(job(rec, geo, tc, method, out, f"{k:06d}"))
        secs.append(time.perf_counter() - t0)
        if not res.written:
            continue
        s = score_sample(out, truth, res.sid, trail_window_ns=method.window_ns)
        assert res.meta is not None
        wrong = s.depth_outlier_rate + s.depth_no_surface_rate  # GT on the sky counts as an outlier
        disp_per_depth = s.disp_pixels / max(1, s.depth_pixels)
        gt = res.meta.gt
        removed = gt.removed_moving / max(1, gt.accumulated_points + gt.removed_moving)
        rows.append((gt.density, s.depth_median_abs_m * 1e3, wrong, s.disp_median_abs_px,
                     s.disp_over_1px_rate, s.mover_trail_rate, disp_per_depth, removed))  # fmt: skip
    a = np.array(rows)
    keys = ("density", "median_mm", "outliers", "disp_median_px", "disp_over_1px", "trail", "disp_per_depth",
            "removed")  # fmt: skip
    return {
        **{k: float(np.mean(a[:, i])) for i, k in enumerate(keys)},
        "s_per_sample": statistics.median(secs),
    }


def trajectory_error(rec: Recording) -> tuple[float, float]:
    """Max position (m) and rotation (deg) error at every knot, world = cam0 at the first knot."""
    traj = rec.trajectory
    T = rec.truth.T_world_cam0(traj.stamps_ns)
    T = np.linalg.inv(T[0]) @ T
    pos = np.linalg.norm(T[:, :3, 3] - traj.p_world_cam0, axis=1)
    rel = np.einsum("nji,njk->nik", T[:, :3, :3], traj.R_world_cam0)
    rot = np.degrees(np.linalg.norm(Rotation.from_matrix(rel).as_rotvec(), axis=1))
    return float(pos.max()), float(rot.max())


def pareto_front(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """(density, error) points no other point beats on both (denser and no less accurate), by density."""
    return sorted(p for p in points if not any(q[0] >= p[0] and q[1] <= p[1] and q != p for q in points))


def meets_targets(r: dict[str, float]) -> bool:
    """Outliers (incl. GT on the sky) <= 0.5 %, disparity > 1 px <= 0.5 %, mover trail <= 0.1 %."""
    return r["outliers"] <= 0.005 and r["disp_over_1px"] <= 0.005 and r["trail"] <= 0.001


def dense_chart(results: dict[str, dict[str, dict[str, float]]], path: Path) -> None:
    """Density (x) vs range median error (y) per scene; colour = method, size and label = window.

    Points that break a target other than the median (`meets_targets`) are
    crosses and stay off the Pareto front, drawn over the others.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import ScalarFormatter

    fig, axes = plt.subplots(1, len(results), figsize=(5.2 * len(results), 4.6), squeeze=False)
    colors = {
        "constant velocity": "tab:gray",
        "odometry": "tab:blue",
        "odometry + movers filter": "tab:green",
    }
    for ax, (scene, rows) in zip(axes[0], results.items(), strict=True):
        pts = []
        for m in METHODS:
            r = rows.get(m.label)
            if r is None:
                continue
            xy = (100 * r["density"], r["median_mm"])
            ok = meets_targets(r)
            ax.scatter(*xy, color=colors[m.name], s=30 + m.window_ms / 10, marker="o" if ok else "x")
            ax.annotate(f"{m.window_ms}", xy, fontsize=7, xytext=(3, 3), textcoords="offset points")
            pts += [xy] if ok else []
        if pts:
            ax.plot(*zip(*pareto_front(pts), strict=True), "k--", lw=0.8, label="Pareto front (targets met)")
        target = 15.0 if "noise" in scene else 2.0
        ax.axhline(target, color="r", lw=0.6, ls=":", label=f"target: median <= {target:g} mm")
        ax.set(
            title=scene,
            xlabel="GT density, % of fisheye pixels",
            ylabel="range median error, mm",
            yscale="log",
        )
        ax.yaxis.set_major_formatter(ScalarFormatter())
        for name, c in colors.items():
            ax.scatter([], [], color=c, label=name)
        ax.scatter([], [], color="k", marker="x", label="misses outlier/trail targets")
        ax.legend(fontsize=7)
    fig.suptitle("Dense GT: density vs accuracy (full resolution 1920x1200; labels: +- window in ms)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


@dataclass(frozen=True)
class StudyResult:
    """Per scene, per method label: the mean scores; and the trajectory over the walk."""

    rows: dict[str, dict[str, dict[str, float]]]
    trajectory_span_s: float
    trajectory_max_m: float
    trajectory_max_deg: float
    trajectory_seconds: float

    def trajectory_line(self) -> str:
        rate = self.trajectory_seconds / self.trajectory_span_s if self.trajectory_span_s else float("nan")
        return (
            f"trajectory over {self.trajectory_span_s:.1f} s: max {self.trajectory_max_m * 1e3:.2f} mm, "
            f"{self.trajectory_max_deg:.4f} deg; {self.trajectory_seconds:.1f} s to compute "
            f"({rate:.2f} s per s of data, one process)"
        )


def study_scenes(walk_s: float) -> dict[str, SimConfig]:
    base = SimConfig(scale=0.125, image="jpeg", range_noise_m=0.0, dust_fraction=0.0, seed=11)
    return {
        "static room": replace(base, scene="indoor", trajectory="static", duration_s=3.0),
        "outdoor walk": replace(base, scene="outdoor", trajectory="walk", duration_s=walk_s),
        "walk with movers": replace(base, scene="outdoor", trajectory="walk", duration_s=4.0, movers=True),
        "walk, 2 cm noise": replace(
            base, scene="outdoor", trajectory="walk", duration_s=4.0, range_noise_m=0.02
        ),
    }


def run_dense_study(
    out: Path,
    samples: int = 3,
    walk_s: float = 20.0,
    on_row: Callable[[str, str, dict[str, float]], None] | None = None,
) -> StudyResult:
    """Simulate the scenes into `out`, score every method on `samples` frames of each (see the module doc)."""
    out.mkdir(parents=True, exist_ok=True)
    geo = Geometry.from_rig(read_rig(REFERENCE_RIG))
    rows: dict[str, dict[str, dict[str, float]]] = {}
    traj_stats = (0.0, float("nan"), float("nan"), 0.0)
    for scene, cfg in study_scenes(walk_s).items():
        rec = record(scene.replace(" ", "_").replace(",", ""), cfg, out)
        t0, t1 = int(rec.trajectory.stamps_ns[0]), int(rec.trajectory.stamps_ns[-1])
        stamps = np.linspace(t0 + 1_100 * MS, t1 - 1_100 * MS, samples).astype(np.int64).tolist()
        if scene == "outdoor walk":
            traj_stats = ((t1 - t0) / 1e9, *trajectory_error(rec), rec.trajectory_s)
        methods = METHODS if "noise" not in scene else [m for m in METHODS if m.window_ms in (50, 500)]
        rows[scene] = {}
        for m in methods:
            rows[scene][m.label] = evaluate(rec, geo, m, stamps, out / "samples")
            if on_row is not None:
                on_row(scene, m.label, rows[scene][m.label])
    return StudyResult(rows, *traj_stats)


def table_header() -> str:
    return (
        "| scene | method | density | range median [mm] | outliers | disp median [px] | disp > 1 px | "
        "disp px / depth px | mover trail | s/sample |\n|---|---|---|---|---|---|---|---|---|---|"
    )


def format_row(scene: str, label: str, r: dict[str, float]) -> str:
    """One markdown row of the study's table."""
    cells = [
        scene, label, f"{100 * r['density']:.1f} %", f"{r['median_mm']:.2f}", f"{100 * r['outliers']:.2f} %",
        f"{r['disp_median_px']:.3f}", f"{100 * r['disp_over_1px']:.2f} %", f"{r['disp_per_depth']:.2f}",
        f"{100 * r['trail']:.3f} %",
        f"{r['s_per_sample']:.1f}",
    ]  # fmt: skip
    return "| " + " | ".join(cells) + " |"
