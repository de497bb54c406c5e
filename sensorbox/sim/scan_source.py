"""What a Mid-360 emulator streams: sweeps in time order and IMU readings on the device clock."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from calibration.errors import SensorboxError
from calibration.types import F64, I64
from sensorbox.sim.lidar import (
    SWEEP_PERIOD_NS,
    LidarSim,
    Sweep,
    iter_sweep_windows,
    simulate_sweep,
    sweep_windows,
)
from sensorbox.sim.run import SimSetup
from sensorbox.sim.trajectory import imu_readings

IMU_PERIOD_NS = 5_000_000  # 200 Hz


@dataclass(frozen=True)
class ImuSamples:
    """IMU readings on the device clock: gyro in rad/s, acceleration in g (gravity included)."""

    stamps_ns: I64
    gyro_rad_s: F64  # (N, 3)
    acc_g: F64  # (N, 3)


class ScanSource(Protocol):
    """What an emulator streams: sweeps in time order, and the IMU over any device-time window."""

    def sweeps(self) -> Iterator[Sweep]: ...

    def imu(self, start_ns: int, end_ns: int) -> ImuSamples: ...


@dataclass(frozen=True)
class SweepList:
    """A fixed list of sweeps (e.g. simulated ahead); IMU from `imu_fn`, else at rest reading +1 g on z."""

    items: Sequence[Sweep]
    imu_fn: Callable[[int, int], ImuSamples] | None = None
    imu_phase_ns: int = 0

    def sweeps(self) -> Iterator[Sweep]:
        return iter(self.items)

    def imu(self, start_ns: int, end_ns: int) -> ImuSamples:
        if self.imu_fn is not None:
            return self.imu_fn(start_ns, end_ns)
        k0 = -(-(start_ns - self.imu_phase_ns) // IMU_PERIOD_NS)
        k1 = -(-(end_ns - self.imu_phase_ns) // IMU_PERIOD_NS)
        stamps = self.imu_phase_ns + np.arange(k0, max(k0, k1), dtype=np.int64) * IMU_PERIOD_NS
        acc = np.zeros((len(stamps), 3))
        acc[:, 2] = 1.0
        return ImuSamples(stamps, np.zeros((len(stamps), 3)), acc)


class SimScan:
    """One simulated rig LiDAR, swept lazily: the same sweeps and IMU readings `simulate` writes.

    IMU readings are the noise-free ones of the simulator (bag IMU noise/bias
    settings are not applied).
    """

    def __init__(self, setup: SimSetup, index: int) -> None:
        self.setup = setup
        self.lidar: LidarSim = setup.lidars[index]
        self.T_cam0_imu = setup.imus[index][1]

    def windows(self) -> list[tuple[int, int]]:
        return sweep_windows(self.lidar, self.setup.cfg.start_ns, self.setup.duration_ns)

    def sweeps(self) -> Iterator[Sweep]:
        s = self.setup
        for win in iter_sweep_windows(self.lidar, s.cfg.start_ns, s.duration_ns):  # lazily: live runs 1e7 s
            sweep = simulate_sweep(self.lidar, s.scene, s.texture, s.traj, s.cfg.start_ns, win)
            if sweep is not None:
                yield sweep

    def imu(self, start_ns: int, end_ns: int) -> ImuSamples:
        base = self.setup.cfg.start_ns + self.lidar.clock_offset_ns  # device ns at sim time 0
        first = self.lidar.first_packet_ns
        k0 = max(0, -(-(start_ns - base - first) // IMU_PERIOD_NS))
        k1 = -(-(end_ns - base - first) // IMU_PERIOD_NS)
        t_sim = first + np.arange(k0, max(k0, k1), dtype=np.int64) * IMU_PERIOD_NS
        if len(t_sim) == 0:
            return ImuSamples(t_sim, np.zeros((0, 3)), np.zeros((0, 3)))
        gyro, acc = imu_readings(self.setup.traj, t_sim / 1e9, self.T_cam0_imu)
        return ImuSamples(base + t_sim, gyro, acc)


class LoopedScan:
    """A simulated LiDAR's first `loop_s` seconds of sweeps, replayed forever with advancing stamps.

    The simulator casts about 0.75 s of CPU per 1 s of one Mid-360's scan, too
    slow to stream two live on a 2-core box; looping is exact for a static
    trajectory (a moving one jumps back at every loop seam). IMU readings come
    from the trajectory at the looped time.
    """

    def __init__(self, scan: Any, loop_s: float) -> None:
        self.scan = scan
        self.items = list(scan.sweeps())
        if not self.items:
            raise SensorboxError(f"emulator loop of {loop_s} s holds no sweep")
        self.loop_ns = len(scan.windows()) * SWEEP_PERIOD_NS
        self.base_ns = int(scan.setup.cfg.start_ns) + int(scan.lidar.clock_offset_ns)

    def sweeps(self) -> Iterator[Any]:
        for k in itertools.count():
            for sw in self.items:
                yield Sweep(sw.timebase_ns + k * self.loop_ns, sw.points)

    def imu(self, start_ns: int, end_ns: int) -> Any:
        first = self.base_ns + int(self.scan.lidar.first_packet_ns)
        k0 = -(-(start_ns - first) // IMU_PERIOD_NS)
        k1 = -(-(end_ns - first) // IMU_PERIOD_NS)
        stamps = first + np.arange(max(k0, 0), max(k0, k1, 0), dtype=np.int64) * IMU_PERIOD_NS
        if len(stamps) == 0:
            return ImuSamples(stamps, np.zeros((0, 3)), np.zeros((0, 3)))
        t_sim = (stamps - self.base_ns) % self.loop_ns
        gyro, acc = imu_readings(self.scan.setup.traj, t_sim / 1e9, self.scan.T_cam0_imu)
        return ImuSamples(stamps, gyro, acc)
