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

Two switches bring the real sensor's main range errors in (both off by default):
- `noise_model="mid360"`: the range noise's sigma grows with range and falls with
  reflectivity (`range_sigma_m`), `range_noise_m` being its value at 10 m on a
  surface of reflectivity 50 (the datasheet's 2 cm at 10 m);
- `beam_divergence_rad > 0`: mixed returns at depth edges. Each ray is a beam
  of that full divergence, sampled by its centre and four rays on its rim
  (`mixed_ranges`); the single-return receiver reports the energy-weighted
  mean range of the surfaces within one pulse length of the nearest, unless
  a farther group returns more energy (then that group's mean). At a depth
  edge this puts points between the two surfaces or on the farther one, as a
  real beam's footprint does.
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
NOISE_MODELS = ("constant", "mid360")
MID360_NOISE_REF_RANGE_M = 10.0
MID360_NOISE_REF_REFLECTIVITY = 50.0
PULSE_SEPARATION_M = 1.5
"""Surfaces closer than this along one beam merge into one return (about the pulse length)."""
MID360_BEAM_DIVERGENCE_DEG = 0.2
"""Full beam divergence assumed for `--mixed-returns` (Livox does not publish the Mid-360's)."""


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
    noise_model: str = "constant"  # one of NOISE_MODELS
    beam_divergence_rad: float = 0.0  # > 0: mixed returns at depth edges


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
    true_range_m = hits.range_m
    if lidar.beam_divergence_rad > 0:
        true_range_m = mixed_ranges(scene, origins, dirs_world, t_s, hits.range_m, lidar.beam_divergence_rad)
    finite = np.isfinite(true_range_m) & np.isfinite(hits.range_m)  # a return needs the beam's centre
    hit_world = origins[finite] + dirs_world[finite] * hits.range_m[finite, None]
    refl = np.zeros(len(t_ns))
    refl[finite] = np.round(reflectivity(scene, texture, hit_world, hits.triangle[finite]))

    rng = np.random.default_rng([lidar.seed, int(window[0] // SWEEP_PERIOD_NS) + 1_000_000])
    range_m = true_range_m.copy()
    tag = np.zeros(len(t_ns), np.uint8)
    if lidar.range_noise_m > 0:
        sigma_m: F64 | float = lidar.range_noise_m
        if lidar.noise_model == "mid360":
            sigma_m = range_sigma_m(np.where(finite, true_range_m, 0.0), refl, lidar.range_noise_m)
        range_m += rng.normal(0.0, 1.0, len(range_m)) * sigma_m
        dust = rng.random(len(range_m)) < lidar.dust_fraction
        range_m[dust] *= rng.uniform(0.2, 0.9, int(dust.sum()))
        tag[dust] = TAG_DUST
    ok = finite & (range_m >= lidar.min_range_m) & (range_m <= lidar.max_range_m)

    points = np.zeros(len(t_ns), POINT_DTYPE)
    stamps = t0_ns + t_ns + lidar.clock_offset_ns
    timebase = int(stamps[0])
    points["offset_time"] = (stamps - timebase).astype(np.uint32)
    xyz = dirs_lidar[ok] * range_m[ok, None]
    points["x"][ok], points["y"][ok], points["z"][ok] = xyz.T
    points["reflectivity"][ok] = refl[ok]
    points["tag"][ok] = tag[ok]
    points["line"] = line
    return Sweep(timebase, points)


def range_sigma_m(range_m: F64, reflectivity: F64, sigma_ref_m: float) -> F64:
    """1-sigma range noise (m) of the "mid360" model at each return's range (m) and reflectivity (0..255).

    `sigma_ref_m` at 10 m on reflectivity 50; linear in range with half of it
    at the sensor (the datasheet's <= 3 cm at 0.2 m is the near-field's extra
    noise, which this model leaves out), and growing as 1/sqrt(reflectivity)
    as the return's energy falls (floored at reflectivity 5).
    """
    near = 0.5 + 0.5 * np.asarray(range_m) / MID360_NOISE_REF_RANGE_M
    energy = np.sqrt(MID360_NOISE_REF_REFLECTIVITY / np.clip(reflectivity, 5.0, 255.0))
    out: F64 = sigma_ref_m * near * energy
    return out


def _rim_directions(dirs: F64, half_angle_rad: float) -> list[F64]:
    """Four unit rays at `half_angle_rad` from each of `dirs` (N,3), 90 deg apart around it."""
    helper = np.where(np.abs(dirs[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u = np.cross(dirs, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(dirs, u)
    c, s = np.cos(half_angle_rad), np.sin(half_angle_rad)
    return [c * dirs + s * sign * axis for axis in (u, v) for sign in (1.0, -1.0)]


def mixed_ranges(
    scene: Scene, origins: F64, dirs: F64, t_s: F64, centre_range_m: F64, divergence_rad: float
) -> F64:
    """The range (m, inf for no return) a beam of full `divergence_rad` reports along each of `dirs`.

    Five rays sample the beam (its centre, already cast as `centre_range_m`, and
    four on its rim), each weighted by the energy it returns (1/r^2). The
    surfaces within `PULSE_SEPARATION_M` of the nearest merge into one return
    at their weighted mean range; a farther group wins when it returns more
    energy. On one surface this is the centre's range to within the beam's
    curvature (micrometres); at a depth edge it is the mixed return.
    """
    rim = [scene.cast(origins, d, t_s).range_m for d in _rim_directions(dirs, divergence_rad / 2)]
    r = np.stack([centre_range_m, *rim], axis=1)
    hit = np.isfinite(r)
    w = np.where(hit, 1.0 / np.where(hit, r, 1.0) ** 2, 0.0)
    r0 = np.where(hit, r, np.inf).min(axis=1, keepdims=True)
    near = hit & (r <= r0 + PULSE_SEPARATION_M)
    far = hit & ~near

    def mean(mask: np.ndarray) -> tuple[F64, F64]:
        wm = np.where(mask, w, 0.0).sum(axis=1)
        rm = np.where(mask, w * np.where(hit, r, 0.0), 0.0).sum(axis=1) / np.where(wm > 0, wm, 1.0)
        return wm, rm

    w_near, r_near = mean(near)
    w_far, r_far = mean(far)
    out: F64 = np.where(w_far > w_near, r_far, r_near)
    out[~hit.any(axis=1)] = np.inf
    return out
