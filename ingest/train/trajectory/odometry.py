"""LiDAR-inertial odometry: the rig's trajectory over a whole recording, every point at its own time.

The trajectory is a chain of knots (T_world_cam0 every `knot_ns`, 50 ms by
default) joined by the gyro: between knots k and k+1 the orientation is

    R(t) = R_k G_k^T G(t) Exp(f Log(E_k)),  f = (t - t_k) / (t_k+1 - t_k)

where G is the integrated gyro (`ingest.train.trajectory.clouds.GyroTrack`, G_k its
value at t_k) and E_k the gyro's mismatch with the next knot, spread evenly
over the interval (without an IMU G is constant and this is the slerp of the
two knots). Position is linear between knots: 50 ms keeps the chord error of
a handheld rig (bob ~3 m/s^2) under 1 mm.

Registration is continuous-time point-to-plane ICP against a local map
(CT-ICP's idea with the gyro supplying the rotation's shape): each 100 ms
chunk of both LiDARs' points is deskewed with the chain, and the chunk's two
new knots (6 DoF each; the knot at its start is fixed by the previous chunk)
are solved by Gauss-Newton on the point-to-plane residuals, each point's
Jacobian weighted by its position between the knots. The registered chunk
then joins the map: world-frame points on a `map_voxel_m` grid, each with the
PCA normal of its neighbourhood, forgotten after `map_horizon_s`.

LiDAR gaps: a knot after a knot interval with too few points, or solved
far from its prediction, carries the prediction and residual NaN (a gap);
the first chunk after a gap solves its start knot too, against the map from
before the gap (nothing joins the map meanwhile). After a gap longer than
the map's horizon the odometry starts afresh, its new chain placed at the
prediction across the gap (`_joined`).

The world frame is cam0 at the first knot. Every knot keeps the RMS residual
of its solve, written next to the trajectory so a user sees where it is weak.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from calibration.linalg3 import rotvec_to_matrix
from calibration.types import F64, I64, Bool
from ingest.errors import OdometryError
from ingest.train.trajectory.clouds import GyroTrack, estimate_velocity
from ingest.train.trajectory.local_map import LocalMap, OdometryParams, voxel_subsample
from ingest.train.trajectory.odometry_kernels import (
    chain_points,
    gyro_between,
    log_rotations,
    plane_system,
)
from ingest.train.trajectory.rig_trajectory import RigTrajectory


@dataclass
class _Chain:
    """Knots placed so far (lists, appended chunk by chunk)."""

    stamps: list[int]
    R: list[F64]
    p: list[F64]
    residual: list[float]
    refined: bool = True  # False while its start is the constant-velocity guess (`_refine_start`)

    def trajectory(self, gyro: GyroTrack | None) -> RigTrajectory:
        return RigTrajectory(
            np.array(self.stamps, np.int64), np.array(self.R), np.array(self.p), np.array(self.residual), gyro
        )


def _solve_knots(
    knots_ns: list[int],
    R_init: list[F64],
    p_init: list[F64],
    free: list[int],
    pts_cam0: F64,
    t_ns: I64,
    the_map: LocalMap,
    gyro: GyroTrack | None,
    prm: OdometryParams,
) -> tuple[list[F64], list[F64], float]:
    """Gauss-Newton on the knots `free` (indices into `knots_ns`; the others stay) against the map.

    Returns every knot (fixed ones as given) and the weighted RMS residual (m).
    """
    assert the_map.grid is not None
    R, p = [r.copy() for r in R_init], [q.copy() for q in p_init]
    stamps = np.array(knots_ns, np.int64)
    # constant through the iterations: each point's segment and the gyro's turn within it
    chain = RigTrajectory(stamps, np.array(R), np.array(p), np.zeros(len(stamps)), gyro)
    seg, f = chain._segment(t_ns)
    rel = chain.gyro_shape(t_ns)
    shape_next = (
        chain.gyro_shape(stamps[1:] - 1) if gyro is None else gyro_between(gyro, stamps[:-1], stamps[1:])
    )
    free_k = np.array(free, np.int64)
    residual = math.nan
    for _ in range(prm.iterations):
        R_k = np.array(R)
        E = np.matmul(np.swapaxes(np.matmul(R_k[:-1], shape_next), 1, 2), R_k[1:])
        a, world = chain_points(pts_cam0, seg, f, rel, R_k, np.array(p), log_rotations(E))
        j = the_map.grid.query(world, 1, prm.max_correspondence_m)[1][:, 0]
        the_map.normals_at(j[j >= 0])
        H, g, res, _ = plane_system(a, world, j, the_map.planar, the_map.normal, the_map.xyz, seg, f, free_k)
        if math.isnan(res):  # under `plane_system`'s 50 points matched to the map's planes
            break
        dx = np.asarray(np.linalg.solve(H + 1e-9 * np.eye(len(g)), -g), np.float64)
        for u, k in enumerate(free):
            R[k] = rotvec_to_matrix(dx[6 * u : 6 * u + 3][None])[0] @ R[k]
            p[k] = p[k] + dx[6 * u + 3 : 6 * u + 6]
        residual = res
        steps = np.abs(dx).reshape(-1, 2, 3).max(axis=(0, 2))  # (rotation rad, translation m)
        if steps[0] * prm.tol_range_m < prm.tol_m and steps[1] < prm.tol_m:
            break
    return R, p, residual


class Odometry:
    """Incremental odometry: `add` points as they are read, `advance` when they are complete up to a time.

    Points must already be filtered (no zeros, no noise tags, no points on
    the rig) and given in cam0 at their own times.
    """

    def __init__(
        self, gyro_track: GyroTrack | None, params: OdometryParams | None = None, start_ns: int | None = None
    ) -> None:
        """`start_ns`: the first knot's time (at or before the first point; None: the first point's), so
        that the knots of passes over parts of a recording fall on one grid (`segments`)."""
        self.params = params or OdometryParams()
        self.start_ns = start_ns
        ok = gyro_track is not None and len(gyro_track.stamps_ns) > 1
        self.gyro = gyro_track if ok else None
        self._pts: list[F64] = []
        self._t: list[I64] = []
        self._chain: _Chain | None = None
        self._map = LocalMap(self.params)
        self._early: list[tuple[F64, I64]] | None = None  # map points of the chunks before the refinement
        self._before: list[_Chain] = []  # the chains before LiDAR gaps longer than the map's horizon

    @property
    def span_ns(self) -> int:
        return self.params.knot_ns * self.params.knots_per_chunk

    def add(self, pts_cam0: F64, stamps_ns: I64) -> None:
        if len(stamps_ns):
            self._pts.append(np.asarray(pts_cam0, np.float64))
            self._t.append(np.asarray(stamps_ns, np.int64))

    def advance(self, complete_ns: int) -> None:
        """Register every chunk that ends at or before `complete_ns` (no earlier point will come)."""
        if not self._t:
            return
        if self.gyro is not None:  # no knot past the IMU: its rotation there would be a guess
            complete_ns = min(complete_ns, int(self.gyro.stamps_ns[-1]))
        if self._chain is not None and self._chain.stamps[-1] + self.span_ns > complete_ns:
            return  # no chunk complete yet: the points wait as they came
        P, T = np.concatenate(self._pts), np.concatenate(self._t)
        if self._chain is None:
            t0 = int(T.min()) if self.start_ns is None or self._before else min(self.start_ns, int(T.min()))
            if complete_ns - t0 < 2 * self.span_ns:
                self._pts, self._t = [P], [T]
                return
            self._chain, rest = _start(P, T, t0, self._map, self.gyro, self.params)
            self._chain.refined = False
            sub = voxel_subsample(P[~rest], self.params.map_voxel_m)
            self._early = [(P[~rest][sub], T[~rest][sub])]
            P, T = P[rest], T[rest]
        while self._chain.stamps[-1] + self.span_ns <= complete_ns:
            mine = self._chain.stamps[-1] + self.span_ns > T
            if mine.any() and self._stale():  # points again after a long gap: start afresh from them
                self._before.append(self._chain)
                self._chain, self._map, self._early = None, LocalMap(self.params), None
                self._pts, self._t = [P], [T]
                self.advance(complete_ns)
                return
            kept = _register_chunk(self._chain, P[mine], T[mine], self._map, self.gyro, self.params)
            P, T = P[~mine], T[~mine]
            if self._early is not None:
                self._early.append(kept)
                if self._chain.stamps[-1] - self._chain.stamps[0] >= self.params.refine_start_s * 1e9:
                    _refine_start(self._chain, self._early, self._map, self.gyro, self.params)
                    self._chain.refined, self._early = True, None
        self._pts, self._t = [P], [T]

    def _stale(self) -> bool:
        """The chain has gone without a registered knot for longer than the map's horizon.

        The map then still holds the scene from before the gap (nothing joins
        it meanwhile), while the prediction has drifted and the rig may have
        left: registering against it placed the next knots up to 0.7 m apart
        after a 6 s gap. The odometry starts again instead, as at the
        recording's start.
        """
        assert self._chain is not None
        stamps, res = self._chain.stamps, self._chain.residual
        k = len(res) - 1  # back from the end: one step unless the chain is in a gap
        while k > 0 and not math.isfinite(res[k]):
            k -= 1
        return stamps[-1] - stamps[k] > self.params.map_horizon_s * 1e9

    def result(self) -> RigTrajectory:
        """The knots so far (after registering every whole chunk); `OdometryError` below 200 ms of points.

        Between LiDAR gaps longer than the map's horizon, a stretch shorter
        than `refine_start_s` (its start never solved again) is all gap knots
        unless the rig stood still through it.
        """
        pending = np.concatenate(self._t) if self._t else np.zeros(0, np.int64)
        if len(pending) and self._chain is not None:
            end = int(pending.max())
            self.advance(end - (end - self._chain.stamps[-1]) % self.span_ns)
        elif len(pending):
            self.advance(int(pending.max()))
        if self._chain is None:
            if not self._before:
                t = np.concatenate(self._t) if self._t else np.zeros(1, np.int64)
                need, had = 2 * self.span_ns / 1e6, (int(t.max()) - int(t.min())) / 1e6
                raise OdometryError(f"odometry: less than {need:.0f} ms of LiDAR points ({had:.0f} ms)")
            self._chain, self._before = self._before[-1], self._before[:-1]  # too little after the last gap
        chains = [*self._before, self._chain]
        if len(chains) > 1:  # a lone chain is the recording, which `choose_method` judges by its span
            for chain in chains:
                # a stretch between long gaps too short to solve its start again keeps the guess, mm off
                # over a few hundred ms for a rig that moves: its knots are gaps, not registered
                if not chain.refined and not chain.trajectory(self.gyro).stood_still():
                    chain.residual = [math.nan] * len(chain.residual)
        return _joined(chains).trajectory(self.gyro)


def _joined(chains: list[_Chain]) -> _Chain:
    """Chains of the stretches between long LiDAR gaps as one: each later chain's world (cam0 at its first
    knot) placed at the last knot of the one before, a prediction across the gap; knots of the earlier
    chain at or after a later one's start are dropped (gap knots: the prediction)."""
    out = _Chain(list(chains[0].stamps), list(chains[0].R), list(chains[0].p), list(chains[0].residual))
    for c in chains[1:]:
        R_w, p_w = out.R[-1], out.p[-1]
        keep = sum(1 for t in out.stamps if t < c.stamps[0])
        del out.stamps[keep:], out.R[keep:], out.p[keep:], out.residual[keep:]
        out.stamps += c.stamps
        out.R += [R_w @ r for r in c.R]
        out.p += [R_w @ q + p_w for q in c.p]
        out.residual += [math.nan, *c.residual[1:]]  # its first knot was not registered to the one before
    return out


def _start(
    P: F64, T: I64, t0: int, the_map: LocalMap, gyro: GyroTrack | None, prm: OdometryParams
) -> tuple[_Chain, Bool]:
    """The first knots (the first at `t0`, at or before the first point) and map, from the first two chunks
    deskewed with the gyro and a fitted velocity."""
    span = prm.knot_ns * prm.knots_per_chunk
    first = t0 + 2 * span > T
    p, t = P[first], T[first]
    t_mid = t0 + span
    p_rot = np.einsum("nij,nj->ni", gyro.between(np.array([t_mid]), t), p) if gyro is not None else p
    dt = (t - t_mid) / 1e9
    est = estimate_velocity(p_rot, dt)
    v = est.velocity_cam0_mps if est is not None else np.zeros(3)
    stamps = [t0 + i * prm.knot_ns for i in range(2 * prm.knots_per_chunk + 1)]
    # knots in the frame of cam0 at t0: rotation from the gyro, position from the constant velocity
    R_mid = gyro.between(np.array([t0]), np.array([t_mid]))[0] if gyro is not None else np.eye(3)
    v_world = R_mid @ v
    Rs = [(gyro.between(np.array([t0]), np.array([s]))[0] if gyro is not None else np.eye(3)) for s in stamps]
    ps = [v_world * (s - t0) / 1e9 for s in stamps]
    chain = _Chain(stamps, Rs, ps, [0.0] * len(stamps))
    sel = voxel_subsample(p, prm.map_voxel_m)
    the_map.add(chain.trajectory(gyro).transform(p[sel], t[sel]), stamps[-1], ps[-1])
    return chain, ~first


def _source_points(pts_cam0: F64, prm: OdometryParams) -> I64:
    """The points of a chunk that take part in its fit: one per `source_voxel_m` cube, in the map's reach.

    The map keeps what lies within `map_range_m` of the rig, so a point much
    farther cannot find a match; searching for one costs the most of all.
    """
    reach = prm.map_range_m + prm.max_correspondence_m
    near = np.flatnonzero(np.einsum("ij,ij->i", pts_cam0, pts_cam0) <= reach**2)
    return near[voxel_subsample(pts_cam0[near], prm.source_voxel_m)]


def _register_chunk(
    chain: _Chain, P: F64, T: I64, the_map: LocalMap, gyro: GyroTrack | None, prm: OdometryParams
) -> tuple[F64, I64]:
    """Solve the next chunk's knots, append them, add the chunk to the map; its map points (cam0, stamps)."""
    t_last = chain.stamps[-1]
    knots = [t_last + i * prm.knot_ns for i in range(prm.knots_per_chunk + 1)]
    # prediction: the gyro's rotation and the last chunk's velocity
    span_s = (chain.stamps[-1] - chain.stamps[-1 - prm.knots_per_chunk]) / 1e9
    v = (chain.p[-1] - chain.p[-1 - prm.knots_per_chunk]) / span_s
    R_guess, p_guess = [], []
    for s in knots[1:]:
        if gyro is not None:
            R_guess.append(chain.R[-1] @ gyro_between(gyro, np.array([t_last]), np.array([s]))[0])
        else:
            R_guess.append(chain.R[-1].copy())
        p_guess.append(chain.p[-1] + v * (s - t_last) / 1e9)
    src = _source_points(P, prm)
    if len(src) > prm.max_source_points:
        src = src[np.linspace(0, len(src) - 1, prm.max_source_points).astype(np.int64)]
    supported = _supported_knots(T[src], t_last, prm.knots_per_chunk, prm)
    R_new, p_new, res, m = R_guess, p_guess, math.nan, 0
    if supported:
        src = src[T[src] < knots[supported]]
        # after a gap the chunk's first knot is a prediction too: solved with the others
        first = 1 if math.isfinite(chain.residual[-1]) else 0
        R_0, p_0 = [chain.R[-1], *R_guess[:supported]], [chain.p[-1], *p_guess[:supported]]
        free = list(range(first, supported + 1))
        R_all, p_all, res = _solve_knots(
            knots[: supported + 1], R_0, p_0, free, P[src], T[src], the_map, gyro, prm
        )
        # right after a gap the prediction has drifted by however long the gap was: the map decides
        if math.isfinite(res) and (first == 0 or _plausible(p_all, p_0, prm)):
            m = supported
            if first == 0:
                chain.R[-1], chain.p[-1], chain.residual[-1] = R_all[0], p_all[0], res
            R_new, p_new = R_all[1:], p_all[1:]
            # the knots after the last supported one: its pose carried on with the gyro and the velocity
            for s in knots[m + 1 :]:
                turn = np.eye(3) if gyro is None else gyro_between(gyro, np.array([knots[m]]), np.array([s]))
                R_new.append(R_all[m] @ turn.reshape(3, 3))
                p_new.append(p_all[m] + v * (s - knots[m]) / 1e9)
    # a LiDAR gap (no or too few points, or a failed solve) carries the prediction: residual NaN marks it
    residuals = [res] * m + [math.nan] * (len(knots) - 1 - m)
    chain.stamps.extend(knots[1:])
    chain.R.extend(R_new)
    chain.p.extend(p_new)
    chain.residual.extend(residuals)
    # the map takes the points the registered knots placed; after a gap the map keeps what it held, so the
    # next chunk registers against the scene before the gap. Only a chunk with points throughout whose
    # solve found too few matches (the map does not reach it: a long gap, the rig far from there) starts
    # the map again from its own points at the predicted poses.
    if m:
        joins = np.less(T, knots[m])
    elif supported == prm.knots_per_chunk and not math.isfinite(res):
        joins = np.ones(len(T), bool)
    else:
        joins = np.zeros(len(T), bool)
    P, T = P[joins], T[joins]
    dense = voxel_subsample(P, prm.map_voxel_m)  # in cam0: the deskew moves points far less than a voxel
    if len(dense):
        the_map.add(chain.trajectory(gyro).transform(P[dense], T[dense]), knots[-1], chain.p[-1])
    return P[dense], T[dense]


def _supported_knots(t_ns: I64, t0_ns: int, k: int, prm: OdometryParams) -> int:
    """How many of the `k` knots after the one at `t0_ns` points at times `t_ns` can place: those after
    knot intervals that each hold `min_segment_points` (counted from the first; a knot whose interval
    before it is thin is left almost unconstrained by the solve, and so are the knots after it)."""
    seg = np.clip((t_ns - t0_ns) // prm.knot_ns, 0, k - 1)
    full = np.bincount(seg, minlength=k)[:k] >= prm.min_segment_points
    return k if full.all() else int(np.argmin(full))


def _plausible(p: list[F64], p_guess: list[F64], prm: OdometryParams) -> bool:
    """Solved knot positions within `max_jump_m` of their predictions.

    Over one 100 ms chunk a handheld rig leaves the constant-velocity
    prediction by centimetres (bob ~3 m/s^2), so a larger step is a solve
    that went astray (few points, or points on one plane), not motion. The
    rotation is not tested: across a gap in the IMU's readings the gyro's
    prediction is the one that is wrong.
    """
    return all(float(np.linalg.norm(pk - pg)) <= prm.max_jump_m for pk, pg in zip(p, p_guess, strict=True))


def _refine_start(
    chain: _Chain,
    early: list[tuple[F64, I64]],
    the_map: LocalMap,
    gyro: GyroTrack | None,
    prm: OdometryParams,
) -> None:
    """Solve the start's knots again against the map of the chunks after it, then re-anchor and re-map.

    The start's knots come from a constant-velocity guess (there is no map
    yet), which a handheld rig's bob (~3 m/s^2) breaks by centimetres; the
    chunks after it were registered to that map, so they agree with each
    other but not with it. The start is registered again, every knot but its
    last free, against a map of the later chunks; the chain is then moved
    rigidly so that its first knot is again the world origin, and the live map
    is rebuilt from the early chunks with the new knots.
    """
    n_start = 3 * prm.knots_per_chunk  # knots 0 .. n_start: the start and the first chunk fixed to it
    P = np.concatenate([e[0] for e in early])
    T = np.concatenate([e[1] for e in early])
    start = chain.stamps[n_start] > T
    traj = chain.trajectory(gyro)
    later = LocalMap(replace(prm, map_horizon_s=1e6))
    later.add(traj.transform(P[~start], T[~start]), chain.stamps[-1], chain.p[-1])
    src = _source_points(P[start], prm)
    # as in a chunk: only the knots after intervals that hold points are solved, the others are gaps
    m = _supported_knots(T[start][src], chain.stamps[0], n_start, prm)
    res = math.nan
    if m:
        free = list(range(min(m + 1, n_start)))
        keep = T[start][src] < chain.stamps[m]
        R, p, res = _solve_knots(
            chain.stamps[: n_start + 1], chain.R[: n_start + 1], chain.p[: n_start + 1], free,
            P[start][src][keep], T[start][src][keep], later, gyro, prm,
        )  # fmt: skip
        if math.isfinite(res):
            chain.R[: len(free)], chain.p[: len(free)] = R[: len(free)], p[: len(free)]
    solved = min(m, n_start - 1) if math.isfinite(res) else 0  # knot n_start is the first chunk's
    chain.residual[1:n_start] = [res] * solved + [math.nan] * (n_start - 1 - solved)
    R0, p0 = chain.R[0].copy(), chain.p[0].copy()
    chain.R = [R0.T @ r for r in chain.R]
    chain.p = [R0.T @ (q - p0) for q in chain.p]
    traj = chain.trajectory(gyro)
    fresh = LocalMap(prm)
    fresh.add(traj.transform(P, T), chain.stamps[-1], chain.p[-1])
    vars(the_map).update(vars(fresh))
