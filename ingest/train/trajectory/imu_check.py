"""Does the IMU's gyro agree with the LiDARs? The odometry's turn between knots against the gyro's.

The odometry's knots (every 100 ms) are registered from the LiDARs' points;
the gyro, integrated in cam0 through the rig's `T_cam0_imu`, shapes the turn
between them. Over each knot interval the two turns are the same rotation
when the IMU is right: on the simulated walks they differ by 0.2 % of the
turn. An IMU whose clock runs 50 ms off the LiDARs' makes them differ by
about 20 % on a handheld walk, 500 ms by 170 %; a gyro axis of the wrong sign
or a wrong `T_cam0_imu` (an IMU mounted upside down) by 50-200 %, although
the knots lean towards the gyro that shapes them. Every sample's motion
compensation and dense GT's trajectory use that gyro, so the check runs
before the first sample is made.

The turn is only observable while the rig turns: below `MIN_TURN_DEG` per
interval (median) the check says nothing. Where it disagrees, the shift of
the IMU's stamps (within `MAX_LAG_MS`) under which they agree best tells a
clock offset from a wrong orientation.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from calibration.types import F64, I64, Bool
from ingest.train.trajectory.clouds import GyroTrack
from ingest.train.trajectory.rig_trajectory import RigTrajectory

MIN_TURN_DEG = 0.5
"""Median turn per knot interval (deg; 5 deg/s at 100 ms knots) below which the gyro's agreement with
the odometry is not judged: a rig that barely turns shows neither a clock offset nor a wrong axis."""
MIN_INTERVALS = 3
"""Knot intervals (within the gyro's span) needed to judge the agreement."""
WARN_MISMATCH = 0.1
"""Median |gyro turn - knot turn| / median |knot turn| above which the IMU is said to disagree (a right
IMU: 0.002-0.06 on the simulated walks, the higher with 2 cm range noise; its x and y axes exchanged:
0.13, 8.6 % depth outliers against truth where a right one gives 2.2 %; its clock 50 ms off: 0.22). The
knots lean towards the gyro that shapes them, so a wrong gyro reads smaller here than it is; noise over a
slow turn is kept apart by `MIN_DISAGREEMENT_DEG`."""
EXPLAINED_MISMATCH = 0.15
"""A shift of the IMU's stamps explains its disagreement when, read shifted, its mismatch falls under this
and half of what it was (500 ms late on the 0.7 s walk: 1.72, shifted 0.10-0.15)."""
REFUSE_MISMATCH = 0.3
"""The same ratio above which ingest refuses: the motion compensation and the trajectory would carry the
error into every sample (a clock 50 ms off: 0.22, GT within 5 % of the right IMU's; an axis of the wrong
sign: 0.54; an IMU upside down in the rig file: 0.75; 500 ms off: 1.7)."""
MIN_DISAGREEMENT_DEG = 0.2
"""The median disagreement per interval (deg) below which the IMU is not blamed whatever the ratio: the
odometry's own knot-to-knot noise (about 0.1 deg with 2 cm range noise) over a slow turn."""
MIN_BIAS_RAD_S = 0.02
"""A constant excess rate (rad/s, 1.1 deg/s) that halves the disagreement is named as the gyro's bias from
this size on (a MEMS gyro's own bias stays under about 0.01 rad/s once calibrated)."""
MAX_LAG_MS = 1000
"""The IMU stamp shifts (ms, either way) searched for a clock offset."""
LAG_STEP_MS = 20
"""The lag search's coarse step (ms); then 1 ms steps around the best."""
MS = 1_000_000
MAX_INTERVALS = 4000
"""Knot intervals used at most (evenly spread): a long recording's lag search stays a fraction of a second."""


@dataclass(frozen=True)
class GyroAgreement:
    """How the IMU's gyro agrees with the odometry's knots (for dataset.yaml and the summary).

    `mismatch`: median |gyro turn - knot turn| over the knot intervals, as a
    fraction of the median knot turn; `lag_ms`: the shift of the IMU's stamps
    under which they agree best (positive: its stamps are late), with the
    mismatch there; `bias_rad_s`: the constant rate (cam0, rad/s) the gyro
    reads beyond the knots' turn (median per axis), with the mismatch once it
    is taken off.
    """

    imu: str
    topic: str
    intervals: int
    median_turn_deg: float
    mismatch: float
    lag_ms: float
    mismatch_at_lag: float
    bias_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mismatch_without_bias: float = float("inf")
    gyro_still: bool = False  # the gyro read no turn at all over the intervals (every rate exactly zero)
    lidars_timed: bool = True  # False: a LiDAR's sweeps carry no point times; the knots cannot judge the gyro

    @property
    def observable(self) -> bool:
        return self.intervals >= MIN_INTERVALS and self.median_turn_deg >= MIN_TURN_DEG

    @property
    def disagrees(self) -> bool:
        """Beyond `WARN_MISMATCH` of the turn and the odometry's noise (`MIN_DISAGREEMENT_DEG`)."""
        noise = self.mismatch * self.median_turn_deg <= MIN_DISAGREEMENT_DEG
        return self.observable and self.lidars_timed and self.mismatch > WARN_MISMATCH and not noise

    @property
    def refused(self) -> bool:
        return self.disagrees and self.mismatch > REFUSE_MISMATCH

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        for key in ("median_turn_deg", "mismatch", "mismatch_at_lag", "mismatch_without_bias"):
            out[key] = round(out[key], 4)
        out["bias_rad_s"] = [round(v, 4) for v in self.bias_rad_s]
        out["observable"] = self.observable
        return out

    def line(self) -> str | None:
        """One line naming the IMU and what its disagreement looks like; None where it agrees or cannot
        be judged."""
        if not self.disagrees:
            return None
        head = (
            f"{self.imu} ({self.topic}): its gyro disagrees with the LiDARs' motion by "
            f"{100 * self.mismatch:.0f} % of the turn (median over {self.intervals} intervals of the "
            f"trajectory; a right IMU: under {100 * WARN_MISMATCH:.0f} %)"
        )
        if self.gyro_still:
            return (
                f"{head}: its gyro reads no turn at all (every rate exactly 0 rad/s) while the LiDARs' "
                f"motion turns {self.median_turn_deg:.1f} deg per interval: a dead gyro, or a driver that "
                "sends no rates; fix the IMU, or remove it from the rig to ingest without it"
            )
        if self.mismatch_at_lag <= min(EXPLAINED_MISMATCH, 0.5 * self.mismatch) and abs(self.lag_ms) >= 5:
            late, later = ("late", "later") if self.lag_ms > 0 else ("early", "earlier")
            lag = f"{abs(self.lag_ms):.0f} ms"
            return (
                f"{head}; read {lag} {later} it agrees to {100 * self.mismatch_at_lag:.0f} %: its stamps run "
                f"{lag} {late} "
                "against the LiDARs' clock; fix the IMU's stamps (or its clock sync)"
            )
        bias = float(np.linalg.norm(self.bias_rad_s))
        if self.mismatch_without_bias <= 0.5 * self.mismatch and bias >= MIN_BIAS_RAD_S:
            axis = ", ".join(f"{v / bias:.2f}" for v in self.bias_rad_s)
            return (
                f"{head}; less {bias:.3f} rad/s ({np.degrees(bias):.1f} deg/s) about cam0's [{axis}] it "
                f"agrees to {100 * self.mismatch_without_bias:.0f} %: its gyro reads that bias; calibrate "
                "the gyro's bias, or remove the IMU from the rig to ingest without it"
            )
        return (
            f"{head}, and neither a shift of its stamps within +-{MAX_LAG_MS} ms nor a constant bias "
            f"explains it: its axes do not match the rig's imus.{self.imu}.T_cam0_imu (a wrong rotation, "
            "an axis of the wrong sign, or rates not in rad/s), its gyro reads a bias large enough to pull "
            "the odometry with it, or the LiDARs' points are misplaced (a LiDAR's pose or clock); check "
            "them, or remove the IMU from the rig to ingest without it"
        )


def no_imu_line(rig_file: Path) -> str:
    """The warning for a rig without an IMU: nothing measures its turns between a sweep's points."""
    return (
        f"{rig_file}: the rig names no IMU under 'imus': the rig's turns within each sweep and window are "
        "not measured, so a moving rig's points are placed as if it held its pose or turned evenly (its GT "
        "smears, and the LiDAR pose check may blame the LiDARs); add the IMU of a LiDAR (its topic, rate_hz "
        "and T_cam0_imu)"
    )


def turning_stretch(gyro: GyroTrack, length_ns: int) -> tuple[int, int] | None:
    """The `length_ns` of the gyro's span in which it turns most (first, last ns), or None where even
    there its median turn per 100 ms stays under `MIN_TURN_DEG` (the check could not judge it)."""
    t = gyro.stamps_ns
    if len(t) < 2:
        return None
    grid = np.arange(t[0], t[-1] - 100_000_000 + 1, 100_000_000, dtype=np.int64)
    if len(grid) < MIN_INTERVALS:
        return None
    turn_deg = np.degrees(
        np.linalg.norm(Rotation.from_matrix(gyro.between(grid, grid + 100_000_000)).as_rotvec(), axis=1)
    )
    per = max(MIN_INTERVALS, min(len(grid), int(length_ns // 100_000_000)))
    sums = np.convolve(turn_deg, np.ones(per), mode="valid")
    first = int(np.argmax(sums))
    if np.median(turn_deg[first : first + per]) < MIN_TURN_DEG:
        return None
    return int(grid[first]), int(grid[first + per - 1] + 100_000_000)


def _gyro_turns(gyro: GyroTrack, t0_ns: I64, t1_ns: I64, lag_ns: int) -> tuple[Bool, F64]:
    """(which intervals the gyro covers read `lag_ns` later, the gyro's rotation vectors over those)."""
    inside: Bool = gyro.covers(t0_ns + lag_ns) & gyro.covers(t1_ns + lag_ns)
    if not inside.any():
        return inside, np.zeros((0, 3))
    g: F64 = Rotation.from_matrix(gyro.between(t0_ns[inside] + lag_ns, t1_ns[inside] + lag_ns)).as_rotvec()
    return inside, g


def _ratio(difference: F64, knot_turn: F64) -> float:
    """median |difference| / median |knot turn| over the intervals; inf below `MIN_INTERVALS` or no turn."""
    scale = float(np.median(np.linalg.norm(knot_turn, axis=1))) if len(knot_turn) else 0.0
    if len(knot_turn) < MIN_INTERVALS or scale <= 0.0:
        return float("inf")
    return float(np.median(np.linalg.norm(difference, axis=1))) / scale


def _mismatch(knot_turn: F64, gyro: GyroTrack, t0_ns: I64, t1_ns: I64, lag_ns: int, need: int) -> float:
    """`_ratio` of gyro minus knot turn with the gyro read `lag_ns` later; inf where it covers fewer than
    `need` intervals (a lag that leaves a short recording's few first or last intervals agrees by chance)."""
    inside, g = _gyro_turns(gyro, t0_ns, t1_ns, lag_ns)
    if int(inside.sum()) < need:
        return float("inf")
    return _ratio(g - knot_turn[inside], knot_turn[inside])


def gyro_agreement(traj: RigTrajectory, gyro: GyroTrack, imu: str, topic: str) -> GyroAgreement:
    """The gyro's agreement with `traj`'s registered knots (intervals in LiDAR gaps left out), and the
    stamp shift within +-`MAX_LAG_MS` that agrees best (`LAG_STEP_MS` steps, then 1 ms around the best)
    over at least half of the intervals. A gyro whose turn is the same over every interval (within
    `MIN_DISAGREEMENT_DEG`) has no shift searched: read at any time it reads the same, so no clock offset
    can show (a still rig's biased gyro agreed with the odometry's first knots, which took its turn, at
    every shift that kept them)."""
    k = np.flatnonzero(np.isfinite(traj.residual_m[1:]))
    if len(k) > MAX_INTERVALS:
        k = k[np.linspace(0, len(k) - 1, MAX_INTERVALS).astype(np.int64)]
    t0, t1 = traj.stamps_ns[k], traj.stamps_ns[k + 1]
    R = traj.R_world_cam0
    knot_turn: F64 = (
        Rotation.from_matrix(np.einsum("kji,kjl->kil", R[k], R[k + 1])).as_rotvec()
        if len(k)
        else np.zeros((0, 3))
    )
    inside, g = _gyro_turns(gyro, t0, t1, 0)
    covered = knot_turn[inside]
    mismatch, intervals = _ratio(g - covered, covered), len(covered)
    turn_deg = float(np.degrees(np.median(np.linalg.norm(covered, axis=1)))) if intervals else 0.0
    best = (mismatch, 0)
    steady = intervals and np.degrees(np.abs(g - np.median(g, axis=0)).max()) < MIN_DISAGREEMENT_DEG
    if not steady and GyroAgreement(imu, topic, intervals, turn_deg, mismatch, 0.0, mismatch).disagrees:
        need = max(MIN_INTERVALS, (intervals + 1) // 2)
        coarse = range(-MAX_LAG_MS, MAX_LAG_MS + 1, LAG_STEP_MS)
        best = min([best] + [(_mismatch(knot_turn, gyro, t0, t1, lag * MS, need), lag) for lag in coarse])
        fine = range(best[1] - LAG_STEP_MS + 1, best[1] + LAG_STEP_MS)
        best = min([best] + [(_mismatch(knot_turn, gyro, t0, t1, lag * MS, need), lag) for lag in fine])
    bias, unbiased = _bias(g, covered, ((t1 - t0)[inside] / 1e9)[:, None])
    still = bool(intervals) and not g.any()
    return GyroAgreement(
        imu, topic, intervals, turn_deg, mismatch, float(best[1]), best[0], bias, unbiased, gyro_still=still
    )


def _bias(gyro_turn: F64, knot_turn: F64, dt_s: F64) -> tuple[tuple[float, float, float], float]:
    """(the gyro's constant excess rate in cam0, rad/s: the median per axis of (gyro - knot turn) / dt;
    the mismatch with it taken off), over the intervals the gyro covers (`dt_s`: (K, 1) their lengths)."""
    if len(knot_turn) < MIN_INTERVALS:
        return (0.0, 0.0, 0.0), float("inf")
    rate = np.median((gyro_turn - knot_turn) / dt_s, axis=0)
    left = _ratio(gyro_turn - rate * dt_s - knot_turn, knot_turn)
    return (float(rate[0]), float(rate[1]), float(rate[2])), left
