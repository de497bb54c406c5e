"""The trajectory pass in overlapping segments, each one job of the run's executor, joined into one.

A long recording's odometry (`ingest.train.trajectory.odometry.Odometry`)
is sequential, about 0.8 CPU s per second of data: in the process that
plans the run it would keep one core busy for as long as the recording
lasts before the workers have anything to do. With more than one worker
(or Dask) and LiDAR points spanning more than one `SegmentParams.length_ns`,
the span is cut into segments that overlap by `SegmentParams.overlap_ns`
(`plan_segments`). Each segment is one job
(`ingest.train.run.trajectory_jobs`): the worker opens the bags itself and
reads only the messages logged while the segment's sweeps were (the plan
pass's table of every sweep's log time and point times), so no point
crosses the pipe; only the knots come back. Every segment's knots lie on
one grid (its first knot on it: `Odometry.start_ns`).

Consecutive segments are joined by the rigid transform that maps the later
segment's knots onto the earlier one's over their overlap (`fit_join`:
rotation the chordal mean of R_earlier R_later^T, translation the mean
difference of the positions), leaving out the later segment's first
`SETTLE_NS` (its start is a constant-velocity guess until the odometry
solves it again). Over the fitted overlap the joined trajectory blends the
two segments' knots, from the earlier's alone to the later's alone
(`joined`): each knot of two independent odometries is a few millimetres
off on its own (2 cm range noise), and a hard switch from one to the other
would put that step into the relative error across it. A join whose RMS residual
over the overlap exceeds `MAX_JOIN_MM` or `MAX_JOIN_DEG`, or that has too
few registered knots in common (a LiDAR gap over the overlap, a segment the
odometry could not start), means the two odometries disagree: the two
segments are run again as one job (`segmented_pass`), down to one job over
the whole recording, which is the single pass itself: two odometries that
disagree never get joined, they cost time. Every join and every such rerun
is recorded (`Join`, `SegmentedPass`). docs/speed.md compares the joined
trajectory with the single pass against the simulator's truth.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np

from calibration.linalg3 import rotvec_to_matrix
from calibration.rig import Rig
from calibration.types import F64, I64
from ingest.errors import OdometryError
from ingest.train.trajectory.clouds import GyroTrack
from ingest.train.trajectory.local_map import OdometryParams
from ingest.train.trajectory.odometry_kernels import log_rotations
from ingest.train.trajectory.rig_trajectory import RigTrajectory

MAX_JOIN_MM = 10.0
"""Largest RMS position residual (mm) of a join over its overlap. Two segments' odometries of the same
seconds agree to 2-4 mm RMS on the simulated 20 s walk (2 cm range noise: each knot a few mm off on its
own); 10 mm is the trajectory test's bound at every knot
(`test_trajectory_matches_the_truth_to_a_centimetre`): two segments that disagree by more on average
cannot both be within it. A join over it is run again as one job, so a bound too tight costs time, never
accuracy."""
MAX_JOIN_DEG = 0.1
"""Largest RMS rotation residual (deg) of a join over its overlap: the trajectory test's bound at every
knot (0.1 deg moves a point at 10 m by 17 mm); the segments agree to about 0.02 deg on the simulated walk."""
SETTLE_NS = 500_000_000
"""The later segment's first seconds left out of a join: its start is a constant-velocity guess until
the odometry solves it again (`OdometryParams.refine_start_s`), against fewer points than the rest."""
MIN_JOIN_KNOTS = 10
"""Registered knots both segments must share past `SETTLE_NS` for a join (0.5 s at 50 ms knots)."""
MIN_OVERLAP_NS = SETTLE_NS + 500_000_000
"""The shortest overlap (`SegmentParams.overlap_ns`): `SETTLE_NS` and `MIN_JOIN_KNOTS` knots."""


@dataclass(frozen=True)
class SegmentParams:
    """How a long trajectory pass is cut (ns): segments of at most `length_ns` overlapping by `overlap_ns`.

    10 s segments with a 3 s overlap: a 20 s walk is 3 jobs of 8.7 s, and
    each join is fitted over 2.5 s of knots (50), past the later segment's
    `SETTLE_NS`. (8 s with 2 s: 4 jobs, joins over 1.5 s, the relative
    error over 1 s 6 % above the single pass's on that walk.) The overlap is
    at least `MIN_OVERLAP_NS` and a segment at least `min_length_ns` long
    (`IngestConfig.validate`).
    """

    length_ns: int = 10_000_000_000
    overlap_ns: int = 3_000_000_000


ONE_PASS_NS = 1 << 62
"""A `SegmentParams.length_ns` longer than any recording (146 years): the trajectory pass as one job."""


def min_length_ns(overlap_ns: int) -> int:
    """The shortest `SegmentParams.length_ns` for `overlap_ns`: 3 overlaps less `SETTLE_NS`.

    `plan_segments` starts consecutive segments at least (length - overlap) / 2
    apart, so this keeps them `overlap_ns - SETTLE_NS / 2` apart or more: each
    join's fitted overlap (from `SETTLE_NS` into the later segment to the end
    of the earlier one) ends a quarter second or more before the next begins.
    """
    return 3 * overlap_ns - SETTLE_NS


def plan_segments(span_ns: tuple[int, int], params: SegmentParams, knot_ns: int) -> list[tuple[int, int]]:
    """(first, last) point times (ns) of the segments of `span_ns`: one (the span) for a span no longer than
    a segment, else the fewest segments of at most `length_ns` that overlap by `overlap_ns`, about equal
    in length, each starting on the knot grid from `span_ns[0]`."""
    lo, hi = span_ns
    length, overlap = params.length_ns, params.overlap_ns
    if hi - lo <= length:
        return [span_ns]
    n = math.ceil((hi - lo - overlap) / (length - overlap))
    step = (hi - lo - overlap) / n
    starts = [lo + int(k * step) // knot_ns * knot_ns for k in range(n)]
    return [(a, min(hi, lo + int(k * step + step) + overlap)) for k, a in enumerate(starts[:-1])] + [
        (starts[-1], hi)
    ]


@dataclass(frozen=True)
class SegmentInputs:
    """What every segment's job needs (the executor's shared state: sent once to each worker)."""

    bag_paths: tuple[Path, ...]
    salvage: bool
    lidar_topics: Mapping[str, str]
    rig: Rig
    gyro: GyroTrack | None
    min_range_m: float
    params: OdometryParams


@dataclass(frozen=True)
class SegmentJob:
    """One segment: its points' times `span_ns`, the log times `log_ns` of its sweeps (stop exclusive; None:
    the whole bag) and its first knot `start_ns` (None: at its first point, as the single pass)."""

    span_ns: tuple[int, int] | None
    log_ns: tuple[int, int] | None
    start_ns: int | None


@dataclass(frozen=True)
class SegmentResult:
    """A segment's knots (its world: cam0 at its first knot) or why there are none; the worker's CPU s."""

    span_ns: tuple[int, int] | None
    stamps_ns: I64
    R_world_cam0: F64
    p_world_cam0: F64
    residual_m: F64
    failure: str
    cpu_s: float

    def trajectory(self, gyro: GyroTrack | None) -> RigTrajectory:
        return RigTrajectory(self.stamps_ns, self.R_world_cam0, self.p_world_cam0, self.residual_m, gyro)


@dataclass(frozen=True)
class Join:
    """Two consecutive segments joined: the later one's world in the earlier one's (`R`, `p`), fitted over
    the overlap's registered knots from `fit_ns[0]` to `fit_ns[1]`, and its RMS residuals there (the
    later's knots moved by it against the earlier's)."""

    fit_ns: tuple[int, int]
    knots: int
    R: F64
    p: F64
    residual_mm: float
    residual_deg: float

    @property
    def within_bound(self) -> bool:
        return self.residual_mm <= MAX_JOIN_MM and self.residual_deg <= MAX_JOIN_DEG


def fit_join(earlier: SegmentResult, later: SegmentResult, settle_ns: int = SETTLE_NS) -> Join | str:
    """The rigid transform that best maps `later`'s knots onto `earlier`'s over their common registered
    knots (module doc), or why there is none (fewer than `MIN_JOIN_KNOTS` in common)."""
    if earlier.failure or later.failure:
        return earlier.failure or later.failure
    common, i, j = np.intersect1d(earlier.stamps_ns, later.stamps_ns, return_indices=True)
    ok = (common >= later.stamps_ns[0] + settle_ns) & np.isfinite(earlier.residual_m[i])
    ok &= np.isfinite(later.residual_m[j])
    i, j, common = i[ok], j[ok], common[ok]
    if len(common) < MIN_JOIN_KNOTS:
        return f"{len(common)} registered knots in common, fewer than {MIN_JOIN_KNOTS}"
    Ra, Rb = earlier.R_world_cam0[i], later.R_world_cam0[j]
    U, _, Vt = np.linalg.svd(np.einsum("nij,nkj->ik", Ra, Rb))  # sum of R_a R_b^T: its nearest rotation
    R = U @ np.diag([1.0, 1.0, float(np.linalg.det(U @ Vt))]) @ Vt
    pa, pb = earlier.p_world_cam0[i], later.p_world_cam0[j]
    p = (pa - pb @ R.T).mean(axis=0)
    moved_mm = np.linalg.norm(pb @ R.T + p - pa, axis=1) * 1e3
    turned_deg = np.degrees(np.linalg.norm(log_rotations(np.einsum("nji,jk,nkl->nil", Ra, R, Rb)), axis=1))
    rms_mm, rms_deg = float(np.sqrt(np.mean(moved_mm**2))), float(np.sqrt(np.mean(turned_deg**2)))
    return Join((int(common[0]), int(common[-1])), len(common), R, p, rms_mm, rms_deg)


def joined(results: Sequence[SegmentResult], joins: Sequence[Join], gyro: GyroTrack | None) -> RigTrajectory:
    """One trajectory of segments `results` and their `joins` (`len(results) - 1`), in the first segment's
    world: each segment's knots placed by the joins before it; over a join's fitted overlap the two
    segments' knots blended, from all the earlier's at its start to all the later's at its end (position
    linearly, rotation along the geodesic; residual the larger, NaN where either is a gap)."""
    R_w, p_w = np.eye(3), np.zeros(3)
    placed = []
    for k, seg in enumerate(results):
        if k:
            R_w, p_w = R_w @ joins[k - 1].R, R_w @ joins[k - 1].p + p_w
        R = np.einsum("ij,njk->nik", R_w, seg.R_world_cam0)
        placed.append((seg.stamps_ns, R, seg.p_world_cam0 @ R_w.T + p_w, seg.residual_m))
    assert all(a.fit_ns[1] < b.fit_ns[0] for a, b in pairwise(joins)), "joins' overlaps overlap"
    parts: list[Placed] = []
    for k, (t, R, p, r) in enumerate(placed):
        lo = joins[k - 1].fit_ns[1] if k else -(2**62)
        hi = joins[k].fit_ns[0] if k < len(joins) else 2**62
        mine = (t > lo) & (t < hi)
        parts.append((t[mine], R[mine], p[mine], r[mine]))
        if k < len(joins):
            parts.append(_blend(placed[k], placed[k + 1], joins[k].fit_ns))
    stamps, Rs, ps, res = (np.concatenate([part[i] for part in parts]) for i in range(4))
    return RigTrajectory(stamps, Rs, ps, res, gyro)


Placed = tuple[I64, F64, F64, F64]


def _blend(a: Placed, b: Placed, fit_ns: tuple[int, int]) -> Placed:
    """The knots of `a` and `b` (stamps, R, p, residual in one world) within `fit_ns`, weighed from `a`'s
    alone at its start to `b`'s alone at its end."""
    t, i, j = np.intersect1d(a[0], b[0], return_indices=True)
    keep = (t >= fit_ns[0]) & (t <= fit_ns[1])
    t, i, j = t[keep], i[keep], j[keep]
    w = (t - fit_ns[0]) / max(fit_ns[1] - fit_ns[0], 1)
    Ra, Rb = a[1][i], b[1][j]
    turn = log_rotations(np.einsum("nji,njk->nik", Ra, Rb))
    R = np.einsum("nij,njk->nik", Ra, rotvec_to_matrix(turn * w[:, None]))
    p = a[2][i] + w[:, None] * (b[2][j] - a[2][i])
    return t, R, p, np.maximum(a[3][i], b[3][j])


def seconds_line(span_ns: tuple[int, int], origin_ns: int) -> str:
    """`span_ns` as seconds from `origin_ns` (the trajectory's first point), e.g. '6.00-14.00 s'."""
    return f"{(span_ns[0] - origin_ns) / 1e9:.2f}-{(span_ns[1] - origin_ns) / 1e9:.2f} s"


def rerun_line(earlier: tuple[int, int], later: tuple[int, int], why: Join | str, origin_ns: int) -> str:
    """The line recorded when two segments are run again as one job."""
    if isinstance(why, Join):
        why = (
            f"join residual {why.residual_mm:.1f} mm / {why.residual_deg:.3f} deg over the overlap, more "
            f"than {MAX_JOIN_MM:g} mm / {MAX_JOIN_DEG:g} deg"
        )
    return (
        f"trajectory segments {seconds_line(earlier, origin_ns)} and {seconds_line(later, origin_ns)} "
        f"(from the first LiDAR point): {why}; run again as one job"
    )


@dataclass
class SegmentedPass:
    """What `segmented_pass` did: its joins, the lines of the segments it ran again as one, the jobs it
    ran and their CPU s (the workers')."""

    joins: list[Join] = field(default_factory=list)
    reruns: list[str] = field(default_factory=list)
    jobs: int = 0
    cpu_s: float = 0.0


RunJobs = Callable[[list[SegmentJob]], list[SegmentResult]]


def segmented_pass(
    segments: list[tuple[int, int]],
    whole: SegmentJob,
    log_of: Callable[[tuple[int, int]], tuple[int, int]],
    run_jobs: RunJobs,
    gyro: GyroTrack | None,
) -> tuple[RigTrajectory, SegmentedPass]:
    """The odometry of `segments` (point times, ns), each a job of `run_jobs`, joined into one trajectory.

    Two segments whose join fails (over the bound, too few knots in common,
    a segment without a trajectory) are run again as one job, until every
    join holds; one job over the whole span is `whole` (the single pass,
    whose `OdometryError` is raised as it is). `log_of` gives a segment's
    log times (`SegmentJob.log_ns`).
    """
    pieces = list(segments)
    origin = segments[0][0]
    done: dict[tuple[int, int], SegmentResult] = {}
    out = SegmentedPass()
    while True:
        if len(pieces) == 1:
            (result,) = run_jobs([whole])
            out.jobs, out.cpu_s = out.jobs + 1, out.cpu_s + result.cpu_s
            if result.failure:
                raise OdometryError(result.failure)
            out.joins = []
            return result.trajectory(gyro), out
        todo = [s for s in pieces if s not in done]
        jobs = [SegmentJob(s, log_of(s), s[0]) for s in todo]
        for s, result in zip(todo, run_jobs(jobs), strict=True):
            done[s] = result
            out.jobs, out.cpu_s = out.jobs + 1, out.cpu_s + result.cpu_s
        fits = [fit_join(done[a], done[b]) for a, b in pairwise(pieces)]
        failed = [k for k, f in enumerate(fits) if not isinstance(f, Join) or not f.within_bound]
        if not failed:
            out.joins = [f for f in fits if isinstance(f, Join)]
            return joined([done[s] for s in pieces], out.joins, gyro), out
        merged: list[tuple[int, int]] = []
        k = 0
        while k < len(pieces):  # each failed join's two segments as one (left to right, no segment twice)
            if k in failed and k + 1 < len(pieces):
                out.reruns.append(rerun_line(pieces[k], pieces[k + 1], fits[k], origin))
                merged.append((pieces[k][0], pieces[k + 1][1]))
                k += 2
            else:
                merged.append(pieces[k])
                k += 1
        pieces = merged


RunSegments = Callable[[SegmentInputs, list[SegmentJob]], list[SegmentResult]]


@dataclass(frozen=True)
class Split:
    """How a trajectory pass runs in segments: `segments` (point times, ns) as jobs of `run_jobs` (the run's
    executor), each reading the bags `bag_paths` (`salvage` as the run) over the log times of its sweeps,
    from `sweeps` (per LiDAR topic: the plan pass's (log ns, first, last point ns) of every sweep)."""

    segments: list[tuple[int, int]]
    params: SegmentParams
    sweeps: Mapping[str, I64]
    bag_paths: tuple[Path, ...]
    salvage: bool
    run_jobs: RunSegments

    def log_of(self, span_ns: tuple[int, int]) -> tuple[int, int]:
        """Log times (first, stop exclusive) of the sweeps with points within `span_ns`."""
        logs = [v[(v[:, 2] >= span_ns[0]) & (v[:, 1] <= span_ns[1]), 0] for v in self.sweeps.values()]
        held = np.concatenate(logs) if logs else np.zeros(0, np.int64)
        if not len(held):
            return span_ns[0], span_ns[0]
        return int(held.min()), int(held.max()) + 1


@dataclass(frozen=True)
class JoinRecord:
    """A join as the summary keeps it: its fitted overlap (s from the first LiDAR point), knots, RMS
    residuals (mm, deg)."""

    overlap_s: tuple[float, float]
    knots: int
    residual_rms_mm: float
    residual_rms_deg: float

    @classmethod
    def of(cls, join: Join, origin_ns: int) -> JoinRecord:
        a, b = ((t - origin_ns) / 1e9 for t in join.fit_ns)
        return cls(
            (round(a, 3), round(b, 3)), join.knots, round(join.residual_mm, 3), round(join.residual_deg, 4)
        )


@dataclass(frozen=True)
class SplitSummary:
    """What a split trajectory pass did, for the summary and dataset.yaml (`ground_truth.trajectory`)."""

    segments: int  # as planned
    length_s: float
    overlap_s: float
    jobs: int  # run, reruns included
    worker_cpu_s: float
    joins: tuple[JoinRecord, ...]
    run_again: tuple[str, ...]  # `rerun_line` of each pair of segments run again as one job

    @classmethod
    def of(cls, split: Split, done: SegmentedPass) -> SplitSummary:
        origin = split.segments[0][0]
        return cls(
            len(split.segments), split.params.length_ns / 1e9, split.params.overlap_ns / 1e9, done.jobs,
            round(done.cpu_s, 3), tuple(JoinRecord.of(j, origin) for j in done.joins), tuple(done.reruns),
        )  # fmt: skip

    def worst(self) -> tuple[float, float]:
        """The joins' largest RMS residuals (mm, deg); zeros without a join."""
        return (
            max((j.residual_rms_mm for j in self.joins), default=0.0),
            max((j.residual_rms_deg for j in self.joins), default=0.0),
        )

    def as_dict(self) -> dict[str, Any]:
        """For dataset.yaml and the kept pass (`from_dict`)."""
        out = asdict(self)
        out["joins"] = [{**asdict(j), "overlap_s": list(j.overlap_s)} for j in self.joins]
        out["run_again"] = list(self.run_again)
        return out

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> SplitSummary:
        joins = tuple(JoinRecord(**{**j, "overlap_s": tuple(j["overlap_s"])}) for j in doc["joins"])
        return cls(**{**doc, "joins": joins, "run_again": tuple(doc["run_again"])})
