"""LiDAR points into cam0 at a camera frame time: filters, extrinsics, motion compensation.

A point measured at t_i maps into cam0 at the frame time t_c as

    p_c = R_c_i (T_cam0_lidar p_lidar) + v_c (t_i - t_c)

where R_c_i = R_world_cam0(t_c)^T R_world_cam0(t_i) comes from integrating the
gyro (rotation) and v_c is a constant velocity in cam0 at t_c (translation).
Compensation is applied only when the motion over the window would move a
point by more than `min_motion_px` pixels ("model no more than a scene needs");
the decision and the measured motion are returned for the sample's metadata.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.spatial.transform import Rotation

from calibration.linalg3 import rotvec_to_matrix
from calibration.types import F64, I64, U8, Bool
from ingest.train.plausible import NOISE_TAG_BITS
from ingest.train.trajectory.planes import plane_normals


@dataclass(frozen=True)
class FilterCounts:
    """How many points each filter removed (in this order), and how many remained."""

    total: int = 0
    zero: int = 0
    non_finite: int = 0
    too_close: int = 0
    noise_tag: int = 0
    kept: int = 0

    def __add__(self, other: FilterCounts) -> FilterCounts:
        return FilterCounts(*(a + b for a, b in zip(self.astuple(), other.astuple(), strict=True)))

    def astuple(self) -> tuple[int, ...]:
        return (self.total, self.zero, self.non_finite, self.too_close, self.noise_tag, self.kept)


def filter_points(xyz_m: F64, tag: U8 | None, min_range_m: float) -> tuple[Bool, FilterCounts]:
    """Keep mask for points that are real returns: non-zero, finite, >= min range, no noise tag."""
    xyz = np.asarray(xyz_m, np.float64)
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]  # per column: reductions along rows of 3 are slow
    finite = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
    zero = finite & (x == 0) & (y == 0) & (z == 0)
    with np.errstate(invalid="ignore", over="ignore"):
        r = np.sqrt(x * x + y * y + z * z)
    close = finite & ~zero & (r < min_range_m)
    tagged = np.zeros(len(xyz), bool) if tag is None else (np.asarray(tag) & NOISE_TAG_BITS) != 0
    tagged &= finite & ~zero & ~close
    keep = finite & ~zero & ~close & ~tagged
    counts = FilterCounts(
        len(xyz), int(zero.sum()), int((~finite).sum()), int(close.sum()), int(tagged.sum()), int(keep.sum())
    )
    return keep, counts


@dataclass(frozen=True)
class GyroTrack:
    """cam0 orientation relative to its first sample, integrated from gyro readings."""

    stamps_ns: I64
    rotations: F64  # (K, 3, 3) R_ref_cam0(t_k)

    def covers(self, t_ns: I64) -> Bool:
        """Which times lie inside the integrated span (outside it rotations are unknown)."""
        out: Bool = (t_ns >= self.stamps_ns[0]) & (t_ns <= self.stamps_ns[-1])
        return out

    @cached_property
    def steps(self) -> F64:
        """Rotation vectors (K-1, 3) of R_k^T R_k+1: the track's steps (computed once)."""
        R = self.rotations
        out: F64 = Rotation.from_matrix(np.einsum("kji,kjl->kil", R[:-1], R[1:])).as_rotvec()
        return out

    def _interval(self, t_ns: I64) -> tuple[I64, F64]:
        """The track step k each time falls in (clamped to the track) and the fraction of it."""
        tc = np.clip(np.asarray(t_ns, np.int64), self.stamps_ns[0], self.stamps_ns[-1])
        k = np.clip(np.searchsorted(self.stamps_ns, tc, side="right") - 1, 0, len(self.stamps_ns) - 2)
        t0, t1 = self.stamps_ns[k], self.stamps_ns[k + 1]
        frac: F64 = (tc - t0).astype(np.float64) / (t1 - t0).astype(np.float64)
        return k, frac

    def at(self, t_ns: I64) -> F64:
        """R_ref_cam0 (N, 3, 3) at times `t_ns` (clamped to the track)."""
        t = np.atleast_1d(np.asarray(t_ns, np.int64))
        if len(self.stamps_ns) == 1:
            return np.broadcast_to(np.asarray(self.rotations[0], np.float64), (len(t), 3, 3)).copy()
        k, frac = self._interval(t)
        out: F64 = np.matmul(self.rotations[k], rotvec_to_matrix(self.steps[k] * frac[:, None]))
        return out

    def between(self, t0_ns: I64, t1_ns: I64) -> F64:
        """R(t0)^T R(t1) per pair (N, 3, 3): the rotation of cam0 from t0 to t1 (`t0_ns` may be one time)."""
        G0 = self.at(np.broadcast_to(np.asarray(t0_ns, np.int64), np.shape(np.atleast_1d(t1_ns))))
        out: F64 = np.matmul(np.swapaxes(G0, 1, 2), self.at(t1_ns))
        return out


def integrate_gyro(stamps_ns: I64, gyro_imu_rad_s: F64, R_cam0_imu: F64) -> GyroTrack:
    """Integrate body rates (rad/s, IMU frame) into cam0 orientations with the midpoint rule."""
    order = np.argsort(stamps_ns, kind="stable")
    t = np.asarray(stamps_ns, np.int64)[order]
    keep = np.concatenate([[True], np.diff(t) > 0])  # duplicated stamps add nothing
    t = t[keep]
    w = (np.asarray(gyro_imu_rad_s, np.float64)[order][keep]) @ np.asarray(R_cam0_imu).T
    dt = np.diff(t) / 1e9
    step_mats = rotvec_to_matrix(0.5 * (w[1:] + w[:-1]) * dt[:, None])
    mats = np.empty((len(t), 3, 3))
    mats[0] = np.eye(3)
    for k in range(len(dt)):
        mats[k + 1] = mats[k] @ step_mats[k]
    return GyroTrack(t, mats)


@dataclass(frozen=True)
class MotionDecision:
    """What the compensation step measured and decided for one sample."""

    applied: bool
    max_rotation_deg: float
    speed_mps: float
    motion_px: float  # predicted worst-case image motion of an uncompensated point
    source: str  # "imu", "imu+velocity", "none"
    velocity_cam0_mps: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])


REFERENCE_RANGE_M = 2.0
"""The range (m) at which a translation of the rig is turned into predicted image motion."""


def motion_decision(
    dt_s: F64,
    max_rotation_rad: float,
    velocity_cam0_mps: F64 | None,
    px_per_rad: float,
    min_motion_px: float = 0.25,
    reference_range_m: float = REFERENCE_RANGE_M,
    source: str = "none",
) -> MotionDecision:
    """Whether points measured `dt_s` (s) from the frame time move enough to be compensated.

    The predicted image motion is the rig's largest rotation over the window
    (`max_rotation_rad`) times `px_per_rad` plus the translation at
    `velocity_cam0_mps` over the largest |dt| seen from `reference_range_m`;
    below `min_motion_px` the points stay as they are (a still rig is not
    "compensated" with the gyro's noise). The points are moved by the
    window's trajectory (`RigTrajectory.over_window(...).to_frame`).
    """
    v = np.zeros(3) if velocity_cam0_mps is None else np.asarray(velocity_cam0_mps, np.float64)
    angle = max_rotation_rad if len(dt_s) else 0.0
    speed = float(np.linalg.norm(v))
    span_s = float(np.abs(dt_s).max()) if len(dt_s) else 0.0
    motion_px = angle * px_per_rad + speed * span_s / reference_range_m * px_per_rad
    return MotionDecision(
        motion_px > min_motion_px, float(np.degrees(angle)), speed, motion_px, source, v.tolist()
    )


@dataclass(frozen=True)
class VelocityEstimate:
    """Constant velocity of cam0 (m/s, cam0 frame at the frame time) and how well it was determined."""

    velocity_cam0_mps: F64
    pairs: int
    residual_m: float  # RMS point-to-plane residual after the fit
    weakest_m_s: float  # 1-sigma of the worst-determined direction (from the normal equations)


def estimate_velocity(
    pts_cam0: F64,
    dt_s: F64,
    iterations: int = 5,
    min_dt_s: float = 0.02,
    max_gap_m: float = 0.2,
    max_points: int = 12_000,
    tol_m_s: float = 1e-3,
    neighbours: int = 8,
    significance: float = 4.0,
    min_cos: float = 0.95,
    refit_m: float = 0.005,
) -> VelocityEstimate | None:
    """Velocity that makes points measured at different times agree (rotation already compensated).

    A point measured dt after the frame time moved by v * dt relative to where it
    would have been seen at the frame time, so q = p + v * dt puts every point in
    cam0 at the frame time. The window is split at its median time into an
    early and a late part, `min_dt_s` apart. Each late point is paired with its
    nearest early point; both must lie on local planes (PCA of `neighbours`
    nearest in their own part) whose normals agree to `min_cos`, so that pairs
    across an edge are not used. n . (q_late - q_early) = 0 is linear in v,
    solved by iterated, trimmed least squares (an ICP of the sweep against
    itself) until the update is below `tol_m_s` or a quarter of the fit's own
    standard error (further steps would only chase noise). Planes from one
    part of the window are not smeared by the motion of the other; they are
    refitted only when the velocity changed enough to move points of one part
    against each other by more than `refit_m` (the first update, rarely a
    later one). When the first fit (from v = 0) is below `significance`
    standard errors, the rig is taken as not translating and that fit is
    returned as is: iterating on noise only makes it wander. None when the
    scene does not constrain all three directions.
    """
    from ingest.train.trajectory.voxel_hash import VoxelHash  # numba: loaded with the first estimate

    if len(pts_cam0) < 200:
        return None
    step = max(1, len(pts_cam0) // max_points)  # a regular subsample keeps the fit deterministic
    p = np.asarray(pts_cam0, np.float64)[::step]
    dt = np.asarray(dt_s, np.float64)[::step]
    split = float(np.median(dt))  # the median, not 0: a one-sided window (bag start/end) still splits
    early, late = dt <= split - min_dt_s / 2, dt >= split + min_dt_s / 2
    if early.sum() < 100 or late.sum() < 100:
        return None
    pe, dte, pl, dtl = p[early], dt[early], p[late], dt[late]
    v = np.zeros(3)
    span_s = max(float(np.ptp(dte)), float(np.ptp(dtl)))
    fitted_at: F64 | None = None  # the velocity the planes were fitted at
    for it in range(iterations):
        qe, ql = pe + dte[:, None] * v, pl + dtl[:, None] * v
        if fitted_at is None or np.linalg.norm(v - fitted_at) * span_s > refit_m:
            planes, own = plane_normals(qe, neighbours, 0.02), plane_normals(ql, neighbours, 0.02)
            fitted_at = v
        dist, j = VoxelHash.build(qe, max_gap_m).query(ql, 1, max_gap_m)
        i = np.nonzero(np.isfinite(dist[:, 0]))[0]
        j = j[i, 0]
        n = planes.normal[j]
        # both ends on a plane, the same plane: a pair across a corner would pull v off
        same = np.abs(np.einsum("ij,ij->i", n, own.normal[i])) >= min_cos
        keep = planes.planar[j] & own.planar[i] & same
        i, j, n = i[keep], j[keep], n[keep]
        if len(i) < 100:
            return None
        r = np.einsum("ij,ij->i", n, ql[i] - qe[j])
        A = n * (dtl[i] - dte[j])[:, None]
        cut = max(3.0 * 1.4826 * float(np.median(np.abs(r))), 0.1)  # never trim the informative pairs
        inl = np.abs(r) <= cut
        H = np.einsum("ni,nj->ij", A[inl], A[inl])
        if np.linalg.cond(H) > 1e6:
            return None
        dv = np.linalg.solve(H, -np.einsum("ni,n->i", A[inl], r[inl]))
        v = v + dv
        res = float(np.sqrt(np.mean(r[inl] ** 2)))
        weakest = float(res * np.sqrt(np.linalg.inv(H).diagonal().max()))
        if it == 0 and np.linalg.norm(v) <= significance * weakest:
            break
        if np.linalg.norm(dv) < max(tol_m_s, 0.25 * weakest):
            break
    return VelocityEstimate(v, int(inl.sum()), res, weakest)
