"""The rig's trajectory: T_world_cam0 at knots joined by the gyro (see `ingest.train.trajectory.odometry`).

Between knots k and k+1 the orientation is R(t) = R_k G_k^T G(t) Exp(f Log(E_k))
with f = (t - t_k) / (t_k+1 - t_k), G the integrated gyro and E_k the gyro's
mismatch with the next knot; position is linear between knots.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from calibration.linalg3 import rotation_angle, rotvec_to_matrix
from calibration.types import F64, I64, Bool
from ingest.dataset.layout import write_atomic
from ingest.train.trajectory.clouds import GyroTrack
from ingest.train.trajectory.odometry_kernels import blend_points, gyro_between, log_rotations, node_fractions

STATIC_SPEED_MPS = 0.05
STATIC_RATE_DEG_S = 2.0


def still(max_speed_mps: float, max_rate_deg_s: float) -> bool:
    """A rig whose fastest knot interval and turn stay below `STATIC_SPEED_MPS` and `STATIC_RATE_DEG_S`
    stood still."""
    return max_speed_mps < STATIC_SPEED_MPS and max_rate_deg_s < STATIC_RATE_DEG_S


POSE_NODES = 100  # poses of many points: exact at this many nodes per knot interval, linear in between
POSE_GRID_MIN_RATIO = 4  # ... when there are at least this many points per node


@dataclass(frozen=True)
class RigTrajectory:
    """T_world_cam0 at knots, joined by the gyro (see the module doc); world = cam0 at the first knot."""

    stamps_ns: I64  # (K,)
    R_world_cam0: F64  # (K, 3, 3)
    p_world_cam0: F64  # (K, 3)
    residual_m: F64  # (K,) RMS point-to-plane residual of the solve that placed each knot (0: the first)
    gyro: GyroTrack | None = None

    @classmethod
    def over_window(
        cls, gyro: GyroTrack | None, velocity_cam0_mps: F64 | None, t_ref_ns: int, span_ns: tuple[int, int]
    ) -> RigTrajectory:
        """The motion sparse GT knows over one window as a trajectory: the gyro's turn (None: none) and a
        constant velocity (m/s in cam0 at `t_ref_ns`; None: none); world = cam0 at `t_ref_ns`.

        Two knots at the ends of `span_ns` (widened to hold `t_ref_ns`),
        oriented by the gyro and placed on the velocity's line: between them
        the chain turns as the gyro does (its mismatch with the second knot is
        the identity) and moves linearly, so `to_frame` takes a point measured
        at t by R(t_ref)^T R(t) and v (t - t_ref), through the same interface
        as dense GT's trajectory of the whole recording.
        """
        lo, hi = min(span_ns[0], t_ref_ns), max(span_ns[1], t_ref_ns)
        stamps = np.array([lo, max(hi, lo + 1)], np.int64)
        R = (
            np.tile(np.eye(3), (2, 1, 1))
            if gyro is None
            else gyro_between(gyro, np.array([t_ref_ns]), stamps)
        )
        v = np.zeros(3) if velocity_cam0_mps is None else np.asarray(velocity_cam0_mps, np.float64)
        p = v[None, :] * ((stamps - t_ref_ns) / 1e9)[:, None]
        return cls(stamps, R, p, np.zeros(2), gyro)

    def _segment(self, t_ns: I64) -> tuple[I64, F64]:
        t = np.clip(np.asarray(t_ns, np.int64), self.stamps_ns[0], self.stamps_ns[-1])
        k = np.clip(np.searchsorted(self.stamps_ns, t, side="right") - 1, 0, len(self.stamps_ns) - 2)
        f: F64 = (t - self.stamps_ns[k]) / (self.stamps_ns[k + 1] - self.stamps_ns[k]).astype(np.float64)
        return k, f

    def covers(self, t_ns: I64) -> Bool:
        """Times inside the knots' span (outside it the pose is clamped, so unknown)."""
        out: Bool = (t_ns >= self.stamps_ns[0]) & (t_ns <= self.stamps_ns[-1])
        return out

    def measured_span(self, t_ns: int) -> tuple[int, int] | None:
        """(first, last) knot time of the stretch of registered knots around `t_ns`; None outside the knots
        or where a knot beside it was carried by prediction (a LiDAR gap: residual NaN).

        Within one stretch every pose was placed against the same map. Across
        a gap the prediction drifts (and after a gap longer than the map's
        horizon the map is rebuilt from drifted poses), so points from both
        sides of it need not agree.
        """
        stamps = self.stamps_ns
        if not stamps[0] <= t_ns <= stamps[-1]:
            return None
        measured = np.isfinite(self.residual_m)
        if len(stamps) == 1:
            return (int(stamps[0]), int(stamps[0])) if measured[0] else None
        k = min(int(np.searchsorted(stamps, t_ns, side="right")) - 1, len(stamps) - 2)
        if not (measured[k] and measured[k + 1]) and t_ns == stamps[k] and k > 0 and measured[k - 1]:
            k -= 1  # exactly on a registered knot: the interval before it is the registered one
        if not (measured[k] and measured[k + 1]):
            return None
        gaps = np.flatnonzero(~measured)
        before, after = gaps[gaps < k], gaps[gaps > k + 1]
        lo = int(before[-1]) + 1 if len(before) else 0
        hi = int(after[0]) - 1 if len(after) else len(stamps) - 1
        return int(stamps[lo]), int(stamps[hi])

    def stretch_of(self, t_ns: I64) -> I64:
        """Per time, an id shared by the times of one stretch of registered knots (`measured_span`'s
        stretch), or -1 outside the knots or in an interval beside a predicted knot.

        Points of one stretch were all placed against the same map, so they may
        be neighbours; points of two stretches need not agree.
        """
        t = np.atleast_1d(np.asarray(t_ns, np.int64))
        measured = np.isfinite(self.residual_m)
        if len(self.stamps_ns) == 1:
            one: I64 = np.where((t == self.stamps_ns[0]) & measured[0], 0, -1).astype(np.int64)
            return one
        k, _ = self._segment(t)
        ok = measured[k] & measured[k + 1]
        # exactly on a registered knot: the interval before it counts (as in `measured_span`)
        ok |= (t == self.stamps_ns[k]) & (k > 0) & measured[np.maximum(k - 1, 0)] & measured[k]
        ok &= self.covers(t)
        out: I64 = np.where(ok, np.cumsum(~measured)[k], -1).astype(np.int64)
        return out

    def pose(self, t_ns: I64) -> tuple[F64, F64]:
        """(R_world_cam0 (N, 3, 3), p_world_cam0 (N, 3)) at times `t_ns` (clamped to the knots).

        Many times (a cloud's points) take the exact pose at `POSE_NODES`
        nodes per knot interval (0.5 ms at 50 ms knots) and at every gyro
        reading between (`_node_grid`), blended linearly per point. The chain's
        kinks are at the knots and at the gyro's readings (its rate is constant
        between two), so each node interval turns at one rate, by at most
        omega * 0.5 ms (5e-4 rad at 60 deg/s), and the blend is off by about
        that squared over 8, well under a micrometre at 10 m, at a fraction of
        the cost of three Rodrigues exponentials per point. (Uniform nodes
        alone put kinks inside node intervals: a first-order error, 6e-4 rad
        with a gyro whose rate jumps by 1 rad/s between readings.)
        """
        t = np.atleast_1d(np.asarray(t_ns, np.int64))
        if len(self.stamps_ns) == 1:
            R0 = np.broadcast_to(self.R_world_cam0[0], (len(t), 3, 3)).copy()
            return R0, np.tile(self.p_world_cam0[0], (len(t), 1))
        grid = self._node_grid(t)
        if grid is None:
            return self._pose_exact(t)
        a, g, R_n, p_n = grid
        p = p_n[a] + g[:, None] * (p_n[a + 1] - p_n[a])
        R = R_n[a] + g[:, None, None] * (R_n[a + 1] - R_n[a])
        return R, p

    def transform(self, pts_cam0: F64, t_ns: I64) -> F64:
        """World points (N, 3) of cam0 points (N, 3) measured at times `t_ns`: `pose` applied in one pass."""
        return self._placed(pts_cam0, t_ns, np.eye(3), np.zeros(3))

    def _placed(self, pts_cam0: F64, t_ns: I64, R_world_ref: F64, p_world_ref: F64) -> F64:
        """`transform`, then into the frame (R_world_ref, p_world_ref): R_ref^T (T_world_cam0(t) p - p_ref).

        The reference pose is folded into the grid's nodes (the blend is
        linear in them), so the points are passed over once.
        """
        t = np.atleast_1d(np.asarray(t_ns, np.int64))
        grid = self._node_grid(t) if len(self.stamps_ns) > 1 else None
        if grid is None:
            R, p = self.pose(t)
            out: F64 = (np.einsum("nij,nj->ni", R, pts_cam0) + p - p_world_ref) @ R_world_ref
            return out
        a, g, R_n, p_n = grid
        R_ref_n = np.einsum("ji,njk->nik", R_world_ref, R_n)
        p_ref_n = (p_n - p_world_ref) @ R_world_ref
        return blend_points(np.asarray(pts_cam0, np.float64), a, g, R_ref_n, p_ref_n)

    def _node_grid(self, t: I64) -> tuple[I64, F64, F64, F64] | None:
        """For many times: (node before each a, blend g, node rotations, node positions); None for few.

        The nodes are `POSE_NODES` per knot interval (knots included) and the
        gyro's readings within them: the chain turns at one rate between two.
        """
        if len(t) == 0:
            return None
        ends, _ = self._segment(np.array([t.min(), t.max()]))
        k_lo, k_hi = int(ends[0]), int(ends[1])
        if len(t) < POSE_GRID_MIN_RATIO * POSE_NODES * (k_hi - k_lo + 1):
            return None
        start = self.stamps_ns[k_lo : k_hi + 1, None]
        span = self.stamps_ns[k_lo + 1 : k_hi + 2, None] - start
        nodes = (start + (np.arange(POSE_NODES + 1, dtype=np.int64) * span) // POSE_NODES).reshape(-1)
        if self.gyro is not None:
            lo, hi = self.stamps_ns[k_lo], self.stamps_ns[k_hi + 1]
            readings = self.gyro.stamps_ns[(self.gyro.stamps_ns > lo) & (self.gyro.stamps_ns < hi)]
            nodes = np.union1d(nodes, readings)
        else:
            nodes = np.unique(nodes)
        R_n, p_n = self._pose_exact(nodes)
        a, g = node_fractions(t, nodes)
        return a, g, R_n, p_n

    def _pose_exact(self, t: I64) -> tuple[F64, F64]:
        k, f = self._segment(t)
        p = self.p_world_cam0[k] + f[:, None] * (self.p_world_cam0[k + 1] - self.p_world_cam0[k])
        return _chain_rotation(self, k, f, self.gyro_shape(t)), p

    def gyro_shape(self, t_ns: I64) -> F64:
        """G(t_k)^T G(t) (N, 3, 3): the gyro's turn from the knot before each time to it (identity: none)."""
        t = np.atleast_1d(np.asarray(t_ns, np.int64))
        if self.gyro is None or len(self.stamps_ns) == 1:
            return np.broadcast_to(np.eye(3), (len(t), 3, 3))
        k, _ = self._segment(t)
        return gyro_between(self.gyro, self.stamps_ns[k], np.clip(t, self.stamps_ns[0], self.stamps_ns[-1]))

    def peak_motion(self) -> tuple[float, float]:
        """(fastest knot interval in m/s, fastest turn between knots in deg/s); zeros for one knot."""
        if len(self.stamps_ns) < 2:
            return 0.0, 0.0
        dt_s = np.diff(self.stamps_ns) / 1e9
        speed = np.linalg.norm(np.diff(self.p_world_cam0, axis=0), axis=1) / dt_s
        angle = rotation_angle(np.einsum("nji,njk->nik", self.R_world_cam0[:-1], self.R_world_cam0[1:]))
        return float(speed.max()), float((np.degrees(angle) / dt_s).max())

    def stood_still(self) -> bool:
        """`still` between every two knots."""
        return still(*self.peak_motion())

    def speed_mps(self, t_ns: int) -> float:
        """Speed of cam0 (m/s) over the knot interval holding `t_ns`."""
        if len(self.stamps_ns) < 2:
            return 0.0
        k, _ = self._segment(np.array([t_ns]))
        step = self.p_world_cam0[k[0] + 1] - self.p_world_cam0[k[0]]
        return float(np.linalg.norm(step) / ((self.stamps_ns[k[0] + 1] - self.stamps_ns[k[0]]) / 1e9))

    def motion_from(self, t_ref_ns: int, t0_ns: int, t1_ns: int) -> tuple[float, float]:
        """(largest rotation in rad, largest displacement in m) of cam0 between `t_ref_ns` and any time
        in [t0_ns, t1_ns]: how far the rig moved while the points of that interval were measured.

        Position is linear between knots, so the largest displacement is at a knot or an end; the
        rotation is taken there and at every 5 ms between (the gyro may turn back within an interval).
        """
        inner = self.stamps_ns[(self.stamps_ns > t0_ns) & (self.stamps_ns < t1_ns)]
        t = np.unique(np.r_[np.arange(t0_ns, t1_ns, 5_000_000, dtype=np.int64), inner, t1_ns])
        R, p = self.pose(t)
        R_ref, p_ref = self.pose(np.array([t_ref_ns]))
        angle = float(rotation_angle(np.einsum("ji,njk->nik", R_ref[0], R)).max())
        return angle, float(np.linalg.norm(p - p_ref[0], axis=1).max())

    def to_frame(self, pts_cam0: F64, t_ns: I64, t_ref_ns: int) -> F64:
        """Points measured in cam0 at their times `t_ns` (N, 3), expressed in cam0 at `t_ref_ns`."""
        R_ref, p_ref = self.pose(np.array([t_ref_ns]))
        return self._placed(pts_cam0, t_ns, R_ref[0], p_ref[0])

    def write_tum(self, path: Path) -> None:
        """`t_sec tx ty tz qx qy qz qw` per knot (T_world_cam0), with the residual as a comment header."""
        q = Rotation.from_matrix(self.R_world_cam0).as_quat()
        lines = ["# T_world_cam0 (world = cam0 at the first knot): t_sec tx ty tz qx qy qz qw"]
        for k, t in enumerate(self.stamps_ns):
            sec, nsec = divmod(int(t), 1_000_000_000)
            lines.append(f"{sec}.{nsec:09d} " + " ".join(f"{v:.9f}" for v in (*self.p_world_cam0[k], *q[k])))
        write_atomic(path, ("\n".join(lines) + "\n").encode())


def _chain_rotation(traj: RigTrajectory, k: I64, f: F64, rel: F64) -> F64:
    """R(t) of the module doc in segments `k` at fractions `f`, the gyro's shape `rel` given."""
    # the gyro's mismatch with the next knot, once per segment
    seg, inv = np.unique(k, return_inverse=True)
    if traj.gyro is None:
        shape_next = np.broadcast_to(np.eye(3), (len(seg), 3, 3))
    else:
        shape_next = gyro_between(traj.gyro, traj.stamps_ns[seg], traj.stamps_ns[seg + 1])
    E = np.matmul(
        np.swapaxes(np.matmul(traj.R_world_cam0[seg], shape_next), 1, 2), traj.R_world_cam0[seg + 1]
    )
    err = log_rotations(E)[inv]
    out: F64 = np.matmul(np.matmul(traj.R_world_cam0[k], rel), rotvec_to_matrix(err * f[:, None]))
    return out
