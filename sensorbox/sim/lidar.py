"""A Mid-360-like LiDAR: non-repetitive scan pattern, true per-point motion skew.

Timing follows the real sensor and livox_ros_driver2 (notes/livox.md): packets
of 96 points every 480 us (200 000 points/s); point i of a packet is stamped
packet_time + i * 4947 ns (the driver's `time_interval * 100 // dot_num` with
time_interval 4750); sweeps are cut at multiples of 100 ms of the sensor clock;
`line` is i % 4. The simulator fires each ray at exactly its reported time
(minus the sensor's clock offset), so stamps are the truth.

Pattern (an approximation; Livox does not publish the prism geometry): four
emitters, 90 deg apart in azimuth, rotate at 10.37 rev/s while their elevation
oscillates over the Mid-360's -7..+52 deg at 1234.567 Hz with per-emitter
phases. Neither frequency is commensurate with the 10 Hz sweep, so successive
sweeps interleave and coverage keeps growing with integration time, as on the
real sensor; each 100 ms sweep covers the full 360 deg with about 500 zig-zag
passes (0.7 deg apart at the horizon, ~1.5 deg along each pass). The real
sensor's density peaks differ; GT code must not rely on the exact pattern.

Returns: range = exact hit distance (+ optional Gaussian noise); no hit,
beyond `max_range_m` or inside the 0.1 m blind zone -> an all-zero point.
With noise on, `dust_fraction` of the returns become "dust" echoes short of the
surface and carry tag bits 2-3 = 01 (the rain/fog/dust field), like the real
sensor's low-confidence flags; with noise off every return is exact and tag 0.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from calibration.types import F64, I64
from ingest.bags.livox_msg import POINT_DTYPE, Points
from sensorbox.sim.appearance import Texture, reflectivity
from sensorbox.sim.scenes import Scene
from sensorbox.sim.trajectory import Trajectory

PACKET_PERIOD_NS = 480_000
POINTS_PER_PACKET = 96
POINT_SPACING_NS = 4750 * 100 // POINTS_PER_PACKET  # 4947 ns, as the driver computes it
SWEEP_PERIOD_NS = 100_000_000
AZ_REV_HZ = 10.37
EL_OSC_HZ = 1234.567
EL_MIN_DEG, EL_MAX_DEG = -7.0, 52.0
TAG_DUST = 0b0000_0100


@dataclass(frozen=True)
class LidarSim:
    """One simulated Mid-360 mounted at `T_cam0_lidar` on the rig."""

    name: str
    T_cam0_lidar: F64
    clock_offset_ns: int = 0  # reported stamp = true time + offset
    first_packet_ns: int = 0  # true time of the first packet after the sim start (ns)
    pattern_phase: float = 0.0  # radians, so two sensors do not scan in lockstep
    range_noise_m: float = 0.02
    dust_fraction: float = 0.01
    min_range_m: float = 0.1
    max_range_m: float = 70.0
    seed: int = 0


@dataclass(frozen=True)
class Sweep:
    """One published sweep: `points` in the LiDAR frame, times relative to `timebase_ns`."""

    timebase_ns: int  # sensor clock, the first point's stamp (= header.stamp)
    points: Points  # POINT_DTYPE


def scan_directions(t_s: F64, line: I64, phase: float) -> F64:
    """Unit ray directions (N,3) in the LiDAR frame (x forward, y left, z up) at sensor times `t_s`."""
    az = 2 * np.pi * AZ_REV_HZ * t_s + line * (np.pi / 2) + phase
    mid, amp = np.radians((EL_MAX_DEG + EL_MIN_DEG) / 2), np.radians((EL_MAX_DEG - EL_MIN_DEG) / 2)
    el = mid + amp * np.sin(2 * np.pi * EL_OSC_HZ * t_s + line * 2.3999632 + 0.61 * phase)
    ce = np.cos(el)
    return np.stack([ce * np.cos(az), ce * np.sin(az), np.sin(el)], axis=1)


def packet_times_ns(lidar: LidarSim, start_ns: int, end_ns: int) -> I64:
    """True times (sim ns since start) of the packets whose first point lies in [start, end)."""
    k0 = max(0, -(-(start_ns - lidar.first_packet_ns) // PACKET_PERIOD_NS))
    k1 = -(-(end_ns - lidar.first_packet_ns) // PACKET_PERIOD_NS)
    return lidar.first_packet_ns + np.arange(k0, max(k0, k1), dtype=np.int64) * PACKET_PERIOD_NS


def iter_sweep_windows(lidar: LidarSim, t0_ns: int, duration_ns: int) -> Iterator[tuple[int, int]]:
    """Sim-time [start, end) of each 100 ms sensor-clock window that starts inside the run, one at a time
    (a live emulator's run is 1e7 s long: 1e8 windows, never listed)."""
    k = -(-(t0_ns + lidar.clock_offset_ns) // SWEEP_PERIOD_NS) * SWEEP_PERIOD_NS
    while k - lidar.clock_offset_ns - t0_ns < duration_ns:
        s = k - lidar.clock_offset_ns - t0_ns
        yield s, s + SWEEP_PERIOD_NS
        k += SWEEP_PERIOD_NS


def sweep_windows(lidar: LidarSim, t0_ns: int, duration_ns: int) -> list[tuple[int, int]]:
    """Sim-time [start, end) of every 100 ms sensor-clock window that starts inside the run."""
    return list(iter_sweep_windows(lidar, t0_ns, duration_ns))


def simulate_sweep(
    lidar: LidarSim, scene: Scene, texture: Texture, traj: Trajectory, t0_ns: int, window: tuple[int, int]
) -> Sweep | None:
    """Cast one sweep (sim ns window) with every ray leaving from the pose at its own time."""
    pk = packet_times_ns(lidar, *window)
    if len(pk) == 0:
        return None
    idx = np.arange(POINTS_PER_PACKET, dtype=np.int64)
    t_ns = (pk[:, None] + idx[None, :] * POINT_SPACING_NS).ravel()
    line = np.tile(idx % 4, len(pk))
    t_s = t_ns / 1e9
    dirs_lidar = scan_directions(t_s, line, lidar.pattern_phase)
    R_wc, p_wc = traj.pose(t_s)
    R_cl, t_cl = lidar.T_cam0_lidar[:3, :3], lidar.T_cam0_lidar[:3, 3]
    R_wl = R_wc @ R_cl
    origins = p_wc + R_wc @ t_cl
    dirs_world = np.einsum("nij,nj->ni", R_wl, dirs_lidar)
    hits = scene.cast(origins, dirs_world, t_s)

    rng = np.random.default_rng([lidar.seed, int(window[0] // SWEEP_PERIOD_NS) + 1_000_000])
    range_m = hits.range_m.copy()
    tag = np.zeros(len(t_ns), np.uint8)
    if lidar.range_noise_m > 0:
        range_m += rng.normal(0.0, lidar.range_noise_m, len(range_m))
        dust = rng.random(len(range_m)) < lidar.dust_fraction
        range_m[dust] *= rng.uniform(0.2, 0.9, int(dust.sum()))
        tag[dust] = TAG_DUST
    ok = np.isfinite(hits.range_m) & (range_m >= lidar.min_range_m) & (range_m <= lidar.max_range_m)

    points = np.zeros(len(t_ns), POINT_DTYPE)
    stamps = t0_ns + t_ns + lidar.clock_offset_ns
    timebase = int(stamps[0])
    points["offset_time"] = (stamps - timebase).astype(np.uint32)
    xyz = dirs_lidar[ok] * range_m[ok, None]
    points["x"][ok], points["y"][ok], points["z"][ok] = xyz.T
    hit_world = origins[ok] + dirs_world[ok] * hits.range_m[ok, None]
    points["reflectivity"][ok] = np.round(reflectivity(scene, texture, hit_world, hits.triangle[ok]))
    points["tag"][ok] = tag[ok]
    points["line"] = line
    return Sweep(timebase, points)
