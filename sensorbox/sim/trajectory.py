"""Rig trajectories as smooth functions of time, and the IMU readings they imply.

A trajectory gives `T_world_cam0(t)` for any float time `t_s` (seconds since
the simulation start). World frame: x forward along the walk, y left, z up;
cam0 frame: x right, y down, z forward. `static` and `walk` are closed-form
sums of sinusoids (C-infinity, so the IMU derived from them is exact up to the
finite-difference step); `custom` interpolates a TUM file with a C2 cubic
spline for position and scipy's C2 `RotationSpline` for orientation.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from calibration.errors import SensorboxError
from calibration.files import read_text
from calibration.types import F64

GRAVITY_MPS2 = 9.80665
R_BODY_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""Body (x forward, y left, z up) from camera (x right, y down, z forward)."""
TRAJECTORIES = ("static", "walk", "custom")


@dataclass(frozen=True)
class Sinusoid:
    """amp * sin(2 pi freq_hz t + phase_rad); amp in the unit of the quantity it drives."""

    amp: float
    freq_hz: float
    phase_rad: float

    def __call__(self, t_s: F64) -> F64:
        out: F64 = self.amp * np.sin(2 * np.pi * self.freq_hz * t_s + self.phase_rad)
        return out


def _sum(terms: tuple[Sinusoid, ...], t_s: F64) -> F64:
    out = np.zeros_like(t_s)
    for s in terms:
        out = out + s(t_s)
    return out


class Trajectory(ABC):
    """T_world_cam0 as a smooth function of time."""

    kind: str

    @abstractmethod
    def pose(self, t_s: F64) -> tuple[F64, F64]:
        """(R_world_cam0 (N,3,3), p_world_cam0 (N,3) in m) at times `t_s` (N,)."""

    @abstractmethod
    def params(self) -> dict[str, Any]:
        """Everything needed to rebuild this trajectory (written to sim.yaml)."""

    def T_world_cam0(self, t_s: F64) -> F64:
        """(N,4,4) poses at `t_s`."""
        R, p = self.pose(np.atleast_1d(np.asarray(t_s, np.float64)))
        T = np.zeros((len(p), 4, 4))
        T[:, :3, :3] = R
        T[:, :3, 3] = p
        T[:, 3, 3] = 1.0
        return T


@dataclass(frozen=True)
class Handheld(Trajectory):
    """Walk at `speed_mps` along world x from `start_world`, with sway and yaw/pitch/roll wobble.

    Angles are radians, sway/bob metres. `static` is the same with everything zero.
    """

    start_world: tuple[float, float, float]
    speed_mps: float = 0.0
    yaw: tuple[Sinusoid, ...] = ()
    pitch: tuple[Sinusoid, ...] = ()
    roll: tuple[Sinusoid, ...] = ()
    sway: tuple[Sinusoid, ...] = ()
    bob: tuple[Sinusoid, ...] = ()
    kind: str = "walk"

    def pose(self, t_s: F64) -> tuple[F64, F64]:
        t = np.asarray(t_s, np.float64)
        yaw, pitch, roll = _sum(self.yaw, t), _sum(self.pitch, t), _sum(self.roll, t)
        # intrinsic ZYX: R = Rz(yaw) Ry(pitch) Rx(roll)
        R_world_body = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_matrix()
        p = np.stack([self.speed_mps * t, _sum(self.sway, t), _sum(self.bob, t)], axis=1)
        return R_world_body @ R_BODY_CAM, p + np.asarray(self.start_world)

    def params(self) -> dict[str, Any]:
        return {"kind": self.kind, **asdict(self)}

    @classmethod
    def from_params(cls, d: dict[str, Any]) -> Handheld:
        def sins(key: str) -> tuple[Sinusoid, ...]:
            return tuple(Sinusoid(**s) for s in d.get(key, ()))

        return cls(
            tuple(d["start_world"]), float(d["speed_mps"]), sins("yaw"), sins("pitch"), sins("roll"),
            sins("sway"), sins("bob"), kind=str(d["kind"]),
        )  # fmt: skip


def static(start_world: F64) -> Handheld:
    """The rig held still at `start_world`, looking along world +x."""
    x, y, z = (float(v) for v in start_world)
    return Handheld((x, y, z), kind="static")


def walk(start_world: F64, seed: int, speed_mps: float = 1.2) -> Handheld:
    """A handheld walk: 1.2 m/s, yaw rate up to ~60 deg/s, pitch ~43 deg/s, roll ~25 deg/s.

    Peak rates are the sums of amp * 2 pi f of each axis' terms; the seed only
    draws the phases, so every seed has the same motion budget.
    """
    rng = np.random.default_rng([seed, 0x3A1C])

    def s(amp_deg: float, f: float) -> Sinusoid:
        return Sinusoid(float(np.radians(amp_deg)), f, float(rng.uniform(0, 2 * np.pi)))

    x, y, z = (float(v) for v in start_world)
    return Handheld(
        (x, y, z), speed_mps,
        yaw=(s(24.0, 0.3), s(2.3, 1.0)),
        pitch=(s(8.0, 0.45), s(2.0, 1.6)),
        roll=(s(5.0, 0.8),),
        sway=(Sinusoid(0.04, 0.9, float(rng.uniform(0, 2 * np.pi))),),
        bob=(Sinusoid(0.025, 1.8, float(rng.uniform(0, 2 * np.pi))),),
    )  # fmt: skip


TUM_COLUMNS = ("t", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
MAX_TUM_BYTES = 256 * 1024 * 1024
"""Largest TUM file read (256 MiB): a pose at 1 kHz for an hour is ~3.6 M rows of ~70 bytes."""


def read_tum(path: Path) -> F64:
    """The pose rows (N, 8) of a TUM file, `t tx ty tz qx qy qz qw` (t in s, position in m).

    Blank lines and `#` comments are skipped. A row that is not 8 finite
    numbers, whose quaternion has zero norm or whose time is not after the
    previous row's is refused with its line number: the spline through it
    would fail deep in scipy or be NaN. What is no regular UTF-8 text file of
    at most `MAX_TUM_BYTES` (a link to /dev/zero, a FIFO, a folder) is refused
    before it is read (`calibration.files.read_text`).
    """
    text = read_text(path, "TUM trajectory", "text", MAX_TUM_BYTES, SensorboxError)
    rows: list[list[float]] = []
    previous_t = ""  # the previous row's time as written
    for line_no, line in enumerate(text.splitlines(), start=1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        row = _tum_row(path, line_no, fields)
        if rows and not row[0] > rows[-1][0]:
            raise SensorboxError(
                f"{path}: line {line_no}: t is {fields[0]}, not after the previous row's {previous_t}; "
                "expected strictly increasing timestamps"
            )
        rows.append(row)
        previous_t = fields[0]
    if len(rows) < 4:
        raise SensorboxError(f"{path}: {len(rows)} pose rows; expected >= 4 rows 't tx ty tz qx qy qz qw'")
    return np.array(rows, np.float64)


def _tum_row(path: Path, line_no: int, fields: list[str]) -> list[float]:
    """One TUM row as 8 floats, or a SensorboxError naming the file, line and column at fault."""
    where = f"{path}: line {line_no}"
    if len(fields) != len(TUM_COLUMNS):
        raise SensorboxError(f"{where}: {len(fields)} columns; expected 8, 't tx ty tz qx qy qz qw'")
    values = []
    for name, field in zip(TUM_COLUMNS, fields, strict=True):
        try:
            value = float(field)
        except ValueError:
            raise SensorboxError(f"{where}: {name} is {field!r}; expected a number") from None
        if not math.isfinite(value):
            raise SensorboxError(f"{where}: {name} is {field}; expected a finite number")
        values.append(value)
    if math.hypot(*values[4:8]) == 0.0:
        raise SensorboxError(f"{where}: the quaternion qx qy qz qw is all zeros; expected a rotation")
    return values


class TumSpline(Trajectory):
    """Interpolates T_world_cam0 poses of a TUM file (`t tx ty tz qx qy qz qw`); t0 = first row."""

    kind = "custom"

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        rows = read_tum(self.path)
        t = rows[:, 0] - rows[0, 0]  # s since the first row
        self.duration_s = float(t[-1])
        self._pos = CubicSpline(t, rows[:, 1:4])
        self._rot = RotationSpline(t, Rotation.from_quat(rows[:, 4:8]))

    def pose(self, t_s: F64) -> tuple[F64, F64]:
        # The simulator samples up to about 1 ms outside [0, duration] (camera jitter, IMU finite
        # differences); those times take the end pose. `build_trajectory` refuses a file shorter
        # than the simulated duration, so nothing longer is ever clamped.
        t = np.clip(np.asarray(t_s, np.float64), 0.0, self.duration_s)
        return self._rot(t).as_matrix().reshape(-1, 3, 3), self._pos(t).reshape(-1, 3)

    def params(self) -> dict[str, Any]:
        return {"kind": "custom", "tum": self.path.name}


def trajectory_from_params(d: dict[str, Any], base_dir: Path) -> Trajectory:
    """Rebuild the trajectory recorded in sim.yaml (`custom` reads its TUM copy from `base_dir`)."""
    if d.get("kind") == "custom":
        return TumSpline(base_dir / str(d["tum"]))
    return Handheld.from_params(d)


def angular_velocity_cam0(traj: Trajectory, t_s: F64, h_s: float = 1e-4) -> F64:
    """Body rate of cam0 (rad/s, in cam0) by a central difference of the rotation: O(h^2) exact."""
    R0, _ = traj.pose(t_s - h_s)
    R1, _ = traj.pose(t_s + h_s)
    dR = np.einsum("nji,njk->nik", R0, R1)  # R0^T R1
    out: F64 = Rotation.from_matrix(dR).as_rotvec() / (2 * h_s)
    return out


def imu_readings(traj: Trajectory, t_s: F64, T_cam0_imu: F64, h_s: float = 1e-3) -> tuple[F64, F64]:
    """Noise-free gyro (rad/s) and accelerometer (g, gravity included) in the IMU frame.

    The accelerometer measures specific force R_world_imu^T (a_world + g_up): at
    rest it reads +1 g along the IMU axis that points up.
    """
    t = np.asarray(t_s, np.float64)
    R_cam0_imu, t_cam0_imu = T_cam0_imu[:3, :3], T_cam0_imu[:3, 3]
    gyro = angular_velocity_cam0(traj, t) @ R_cam0_imu  # R_imu_cam0 @ w, row-wise

    def p_imu(tt: F64) -> tuple[F64, F64]:
        R, p = traj.pose(tt)
        return R, p + R @ t_cam0_imu

    _, pm = p_imu(t - h_s)
    R, p0 = p_imu(t)
    _, pp = p_imu(t + h_s)
    acc_world = (pp - 2 * p0 + pm) / h_s**2 + np.array([0.0, 0.0, GRAVITY_MPS2])
    R_world_imu = R @ R_cam0_imu
    acc_imu = np.einsum("nji,nj->ni", R_world_imu, acc_world)
    return gyro, acc_imu / GRAVITY_MPS2
