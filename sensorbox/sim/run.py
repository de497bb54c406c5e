"""Simulate a SensorBox recording: one bag plus its truth folder.

Recipe, per 100 ms of simulated time: render the camera frames whose stamps
fall in it, cast the LiDAR sweeps that start in it, sample both IMUs, and queue
every message by its log time (host receive time = stamp + a fixed driver
latency, so log time is deliberately not the header stamp). Messages whose log
time can no longer be preceded are flushed to the bag in log-time order.
"""

from __future__ import annotations

import heapq
import itertools
import math
import os
import shutil
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from calibration.errors import SensorboxError
from calibration.rig import Rig, read_rig, with_timeshifts
from calibration.types import F64
from ingest.bags.rostypes import IMU_TYPE
from ingest.errors import OutputError
from sensorbox import messages
from sensorbox.live.bagwriter import BagWriter
from sensorbox.messages import RosVersion
from sensorbox.sim.appearance import Texture
from sensorbox.sim.camera import CameraSim, render
from sensorbox.sim.config import SimConfig
from sensorbox.sim.lidar import (
    MID360_BEAM_DIVERGENCE_DEG,
    SWEEP_PERIOD_NS,
    LidarSim,
    simulate_sweep,
    sweep_windows,
)
from sensorbox.sim.movers import default_movers
from sensorbox.sim.scenes import Scene, build_scene
from sensorbox.sim.trajectory import Trajectory, TumSpline, imu_readings, static, walk
from sensorbox.sim.truth import truth_dir, write_truth

CAMERA_LATENCY_NS = 18_000_000
LIDAR_LATENCY_NS = 2_000_000  # after the sweep's end
IMU_LATENCY_NS = 1_000_000
LIVOX_IMU_T_LIDAR_IMU_M = (0.011, 0.02329, -0.04412)


@dataclass
class SimSummary:
    bag: Path
    truth: Path
    counts: dict[str, int]
    size_bytes: int
    seconds: float
    stage_seconds: dict[str, float]


MIN_IMAGE_PX = 8
"""Smallest camera image side: `render-benchmark` refuses smaller images too."""


MAX_RAYS_PER_FRAME = 1 << 24
"""Rays cast for one camera frame (pixels x supersample^2). Both cameras render at once, about 450
bytes a ray in all: the reference rig at --supersample 2 (9.2M rays a frame) peaked at 4.5 GB, so
this bound (16.8M) is about 8 GB; it takes the reference camera up to --scale 2.7, or
--supersample 2 at --scale 1."""


def check_rays(rig: Rig, scale: float, supersample: int) -> None:
    """Refuse, before any array is made, a --scale or --supersample whose frames would not fit in memory.

    `rig` is already scaled. `--scale 100` asked for 172 GiB at the first
    allocation; `--supersample 1000` for far more.
    """
    for cam in rig.cameras:
        w, h = cam.model.width, cam.model.height
        if w * h > MAX_RAYS_PER_FRAME:
            largest = math.floor(1000 * scale * math.sqrt(MAX_RAYS_PER_FRAME / (w * h))) / 1000
            raise SensorboxError(
                f"--scale {scale:g} makes camera {cam.name} {w}x{h} px; expected <= {MAX_RAYS_PER_FRAME:,} "
                f"px (--scale <= {largest:g})"
            )
        if (rays := w * h * supersample * supersample) > MAX_RAYS_PER_FRAME:
            largest_s = math.isqrt(MAX_RAYS_PER_FRAME // (w * h))
            raise SensorboxError(
                f"--supersample {supersample} casts {rays:,} rays a frame for camera {cam.name} ({w}x{h} px "
                f"at --scale {scale:g}); expected <= {MAX_RAYS_PER_FRAME:,} (--supersample <= {largest_s})"
            )


def scaled_rig(rig: Rig, scale: float) -> Rig:
    """The rig with every camera model at `scale` x its resolution (extrinsics unchanged).

    A scale that leaves a camera under `MIN_IMAGE_PX` on a side is refused,
    naming the scale, the camera, its scaled size and the smallest scale that works.
    """
    if scale == 1.0:
        return rig
    for cam in rig.cameras:  # before scaling: a tiny scale also takes the focal lengths out of range
        width, height = max(1, round(cam.model.width * scale)), max(1, round(cam.model.height * scale))
        if min(width, height) < MIN_IMAGE_PX:
            smallest = math.ceil(1000 * MIN_IMAGE_PX / min(cam.model.width, cam.model.height)) / 1000
            raise SensorboxError(
                f"--scale {scale:g} makes camera {cam.name} {width}x{height} px; "
                f"expected >= {MIN_IMAGE_PX} px on each side (--scale >= {smallest:g})"
            )
    cams = tuple(replace(c, model=c.model.scaled(scale)) for c in rig.cameras)
    return replace(rig, cameras=cams, camchain=None)


def _imu_pose(rig: Rig, lidar_index: int) -> tuple[str, F64]:
    """IMU topic and T_cam0_imu for a LiDAR: the rig's IMU on the same IP, else the Mid-360 default."""
    lidar = rig.lidars[lidar_index]
    key = lidar.ip.replace(".", "_") if lidar.ip else lidar.topic.rsplit("lidar", 1)[-1]
    for imu in rig.imus:
        if imu.topic.endswith(key):
            return imu.topic, imu.T_cam0_imu
    T = np.eye(4)
    T[:3, 3] = LIVOX_IMU_T_LIDAR_IMU_M
    return lidar.topic.replace("/lidar", "/imu"), lidar.T_cam0_lidar @ T


def build_trajectory(cfg: SimConfig, start_world: F64) -> Trajectory:
    """The rig's trajectory of `cfg`; a TUM file must span the whole simulated duration.

    Simulated time 0 is the TUM file's first row; a file shorter than
    `--duration` is refused rather than holding its last pose to the end.
    """
    if cfg.trajectory == "static":
        return static(start_world)
    if cfg.trajectory == "walk":
        return walk(start_world, cfg.seed)
    assert cfg.tum is not None
    traj = TumSpline(cfg.tum)
    if traj.duration_s < cfg.duration_s:
        span_s = round(traj.duration_s, 6)  # epoch stamps in float64: the span carries ~1e-7 s of noise
        raise SensorboxError(
            f"{cfg.tum}: the trajectory spans {span_s:g} s (first to last row), shorter than "
            f"--duration {cfg.duration_s:g} s; expected a TUM file covering the whole simulation "
            "(which starts at its first row)"
        )
    return traj


@dataclass(frozen=True)
class SimSetup:
    """Everything a time window of the simulation needs, built once from the config."""

    cfg: SimConfig
    rig: Rig
    scene: Scene
    texture: Texture
    traj: Trajectory
    lidars: list[LidarSim]
    cams: list[CameraSim]
    cam_topics: list[str]
    imus: list[tuple[str, F64]]
    camera_phase_ns: int
    duration_ns: int
    ros: RosVersion

    def params(self) -> dict[str, Any]:
        """sim.yaml: the config plus every derived parameter (phases, offsets, trajectory)."""
        out: dict[str, Any] = {
            k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(self.cfg).items() if k != "tum"
        }
        out["rig"] = "rig.yaml"
        out["trajectory"] = self.traj.params()
        out["lidars"] = [
            {
                "name": sim.name, "topic": lidar.topic, "clock_offset_ns": sim.clock_offset_ns,
                "first_packet_ns": sim.first_packet_ns, "pattern_phase": sim.pattern_phase, "seed": sim.seed,
                "min_range_m": sim.min_range_m, "max_range_m": sim.max_range_m,
            }
            for sim, lidar in zip(self.lidars, self.rig.lidars, strict=True)
        ]  # fmt: skip
        out["imus"] = [{"topic": t, "T_cam0_imu": T.tolist()} for t, T in self.imus]
        for k in ("camera_offset_ns", "range_noise_model", "mixed_returns"):
            out.pop(k)
        if self.cfg.realism:
            out["realism"] = self.cfg.realism
        if self.cfg.gyro_bias_rad_s or self.cfg.acc_bias_g:
            for i, entry in enumerate(out["imus"]):
                gyro_bias, acc_bias = imu_biases(self.cfg, i)
                entry["gyro_bias_rad_s"], entry["acc_bias_g"] = gyro_bias.tolist(), acc_bias.tolist()
        out["cameras"] = {"topics": self.cam_topics, "first_frame_ns": self.camera_phase_ns}
        out["latency_ns"] = {
            "camera": CAMERA_LATENCY_NS, "lidar_after_sweep": LIDAR_LATENCY_NS, "imu": IMU_LATENCY_NS
        }  # fmt: skip
        return out


def setup_sim(cfg: SimConfig) -> SimSetup:
    """The scene, rig, trajectory and sensors of a simulated recording, built once from `cfg`."""
    cfg.validate()
    rig = scaled_rig(read_rig(cfg.rig), cfg.scale)
    if any(cfg.camera_offset_ns) or any(c.timeshift_cam_imu is not None for c in rig.cameras):
        # the truth rig carries the exact offsets, in Kalibr's convention: t_lidar = stamp + shift
        names = (rig.upper.name, rig.lower.name)
        rig = with_timeshifts(rig, {n: -ns / 1e9 for n, ns in zip(names, cfg.camera_offset_ns, strict=True)})
    check_rays(rig, cfg.scale, cfg.supersample)
    if not rig.lidars:
        raise SensorboxError(f"{cfg.rig}: the rig has no lidars to simulate")
    scene = build_scene(cfg.scene, cfg.seed)
    if cfg.movers:
        scene.movers = default_movers(cfg.scene, scene.start_world)
    rng = np.random.default_rng([cfg.seed, 0xC0FFEE])
    lidars = [
        LidarSim(
            lidar.name, lidar.T_cam0_lidar, clock_offset_ns=cfg.lidar_clock_offset_ns if k else 0,
            first_packet_ns=int(rng.integers(0, 480_000)), pattern_phase=float(rng.uniform(0, 2 * np.pi)),
            range_noise_m=cfg.range_noise_m, dust_fraction=cfg.dust_fraction, seed=cfg.seed * 100 + k,
            noise_model=cfg.range_noise_model,
            beam_divergence_rad=math.radians(MID360_BEAM_DIVERGENCE_DEG) if cfg.mixed_returns else 0.0,
        )
        for k, lidar in enumerate(rig.lidars)
    ]  # fmt: skip
    pair = (rig.upper, rig.lower)
    suffix = "/compressed" if cfg.image == "jpeg" else ""
    return SimSetup(
        cfg, rig, scene, Texture(cfg.seed), build_trajectory(cfg, scene.start_world), lidars,
        [CameraSim(c.name, c.model, c.T_cam0_cam) for c in pair],
        [(c.topic or f"/{c.name}/image") + suffix for c in pair],
        [_imu_pose(rig, k) for k in range(len(lidars))],
        int(rng.integers(0, int(1e9 / cfg.camera_rate_hz))), round(cfg.duration_s * 1e9),
        1 if cfg.format == "bag" else 2,
    )  # fmt: skip


Message = tuple[int, str, bytes]  # (log_ns, topic, serialised bytes)


def _camera_messages(s: SimSetup, w0: int, w1: int, pool: ThreadPoolExecutor) -> list[Message]:
    """Both cameras' frames whose nominal time lies in the sim-time window [w0, w1) ns."""
    cfg = s.cfg
    period_ns = 1e9 / cfg.camera_rate_hz
    k0 = max(0, int(np.ceil((w0 - s.camera_phase_ns) / period_ns)))
    out: list[Message] = []
    for k in range(k0, 10**9):
        nominal = s.camera_phase_ns + k * period_ns
        if nominal >= w1:
            break
        jitter = np.random.default_rng([cfg.seed, k, 0x1A]).uniform(-1, 1, 2) * cfg.camera_jitter_ns
        t_ns = [round(nominal + c * cfg.stereo_offset_ns + jitter[c]) for c in range(2)]
        poses = s.traj.T_world_cam0(np.array(t_ns) / 1e9)
        # numpy sines and Embree both release the GIL: the two cameras render in parallel
        jobs = [
            pool.submit(render, s.cams[c], s.scene, s.texture, poses[c], cfg.supersample, t_ns[c] / 1e9)
            for c in (0, 1)
        ]
        images = [job.result() for job in jobs]
        for c, img in enumerate(images):
            stamp = cfg.start_ns + t_ns[c] + cfg.camera_offset_ns[c]
            frame_id = f"{s.cams[c].name}_optical_frame"
            raw = (
                messages.compressed_image_msg(stamp, frame_id, img, cfg.jpeg_quality, s.ros)
                if cfg.image == "jpeg"
                else messages.image_msg(stamp, frame_id, img, s.ros)
            )
            out.append((stamp + CAMERA_LATENCY_NS, s.cam_topics[c], raw))
    return out


def _lidar_messages(s: SimSetup, w0: int, w1: int) -> list[Message]:
    """Every sweep (of each LiDAR) whose 100 ms sensor-clock window starts in [w0, w1)."""
    encode = messages.custom_msg if s.cfg.lidar_msg == "custom" else messages.pointcloud2_msg
    out: list[Message] = []
    for sim, lidar in zip(s.lidars, s.rig.lidars, strict=True):
        for win in sweep_windows(sim, s.cfg.start_ns, s.duration_ns):
            if w0 <= win[0] < w1:
                sweep = simulate_sweep(sim, s.scene, s.texture, s.traj, s.cfg.start_ns, win)
                if sweep is not None:
                    log_ns = s.cfg.start_ns + win[1] + LIDAR_LATENCY_NS
                    out.append((log_ns, lidar.topic, encode(sweep.timebase_ns, sweep.points, s.ros)))
    return out


def _imu_messages(s: SimSetup, w0: int, w1: int) -> list[Message]:
    """Each LiDAR's IMU samples in [w0, w1), on that LiDAR's clock, with optional noise and bias."""
    cfg = s.cfg
    period = round(1e9 / cfg.imu_rate_hz)
    out: list[Message] = []
    for k, (sim, (topic, T_cam0_imu)) in enumerate(zip(s.lidars, s.imus, strict=True)):
        first, last = -(-(w0 - sim.first_packet_ns) // period), -(-(w1 - sim.first_packet_ns) // period)
        t_ns = sim.first_packet_ns + np.arange(max(first, 0), last, dtype=np.int64) * period
        if len(t_ns) == 0:
            continue
        gyro, acc = imu_readings(s.traj, t_ns / 1e9, T_cam0_imu)
        rng = np.random.default_rng([cfg.seed, k, w0 // SWEEP_PERIOD_NS, 0x1B])
        gyro_bias, acc_bias = imu_biases(cfg, k)
        gyro = gyro + gyro_bias + rng.normal(0, 1, gyro.shape) * cfg.gyro_noise_rad_s
        acc = acc + acc_bias + rng.normal(0, 1, acc.shape) * cfg.acc_noise_g
        for j, t in enumerate(t_ns.tolist()):
            stamp = cfg.start_ns + t + sim.clock_offset_ns
            raw = messages.imu_msg(stamp, gyro[j], acc[j], s.ros)
            out.append((cfg.start_ns + t + IMU_LATENCY_NS, topic, raw))
    return out


def imu_biases(cfg: SimConfig, k: int) -> tuple[F64, F64]:
    """IMU `k`'s constant gyro (rad/s) and accelerometer (g) bias per axis, drawn once from the seed."""
    rng = np.random.default_rng([cfg.seed, k, 0x1C])
    draw = rng.normal(0, 1, (2, 3))
    return draw[0] * cfg.gyro_bias_rad_s, draw[1] * cfg.acc_bias_g


def simulate(cfg: SimConfig, out: Path, progress: Callable[[float], None] | None = None) -> SimSummary:
    """Write a bag at `out` (rosbag2 folder or `.bag`) and its truth at `<bag>.truth/`.

    `progress` is called with the simulated seconds done after every 100 ms window.
    """
    t_start = time.perf_counter()
    s = setup_sim(cfg)
    stage = {"cameras": 0.0, "lidars": 0.0, "imu": 0.0, "write": 0.0}
    queue: list[tuple[int, int, str, bytes]] = []
    order = itertools.count()  # tie-break equal log times by creation order: deterministic
    with BagWriter(out, cfg.format, compress=cfg.compress) as bag, ThreadPoolExecutor(2) as pool:
        for topic in s.cam_topics:
            bag.add(topic, messages.IMAGE_MSG_TYPES[cfg.image])
        for lidar, (imu_topic, _) in zip(s.rig.lidars, s.imus, strict=True):
            bag.add(lidar.topic, messages.LIDAR_MSG_TYPES[cfg.lidar_msg])
            bag.add(imu_topic, IMU_TYPE)
        for w0 in range(0, s.duration_ns, SWEEP_PERIOD_NS):
            w1 = min(w0 + SWEEP_PERIOD_NS, s.duration_ns)
            for name in ("cameras", "lidars", "imu"):
                t0 = time.perf_counter()
                if name == "cameras":
                    made = _camera_messages(s, w0, w1, pool)
                else:
                    made = (_lidar_messages if name == "lidars" else _imu_messages)(s, w0, w1)
                for log_ns, topic, raw in made:
                    heapq.heappush(queue, (log_ns, next(order), topic, raw))
                stage[name] += time.perf_counter() - t0
            # later windows only add messages logged at or after start + w1: flush the rest in order
            t0 = time.perf_counter()
            last = w1 >= s.duration_ns
            while queue and (last or queue[0][0] < cfg.start_ns + w1):
                log_ns, _, topic, raw = heapq.heappop(queue)
                bag.write(topic, log_ns, raw)
            stage["write"] += time.perf_counter() - t0
            if progress is not None:
                progress(w1 / 1e9)
        counts = dict(bag.counts)
    tdir = truth_dir(bag.path)
    try:
        _write_truth_whole(tdir, s, cfg.tum)
    except OSError as err:  # a bag without its truth is not a fixture: neither stays
        _remove(bag.path)
        where = err.filename or tdir
        raise OutputError(f"cannot write {where}: {err.strerror or err}; no bag written") from err
    return SimSummary(bag.path, tdir, counts, bag.size_bytes, time.perf_counter() - t_start, stage)


def _write_truth_whole(tdir: Path, s: SimSetup, tum: Path | None) -> None:
    """The truth folder `tdir`, written into a staging folder beside it and renamed into place (a stale
    one of an earlier bag replaced), so that it is whole or absent."""
    staging = tdir.with_name(f".{tdir.name}.{os.getpid()}.tmp")
    try:
        write_truth(staging, s.scene, s.traj, s.rig, s.params(), tum)
        if tdir.exists():
            shutil.rmtree(tdir)  # stale truth of a bag that is no longer there
        staging.rename(tdir)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _remove(path: Path) -> None:
    """Delete a written bag: a rosbag2 folder or a .bag file."""
    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)
