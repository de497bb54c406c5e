"""The trajectory pass in joined segments on the workers (`ingest.train.trajectory.segments`).

Synthetic knots check the plan, the join and the reruns exactly; a 3 s
simulated walk (1/8 resolution, 2.5 s segments overlapping by 1 s) checks
the joined trajectory against the simulator's truth through `ingest` with
two workers, and a deliberately broken join through the fork pool.
"""

import re
from dataclasses import replace
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from calibration.rig import Rig, read_rig
from ingest.bags.decode import Sweep
from ingest.bags.reader import open_bags
from ingest.errors import BagError
from ingest.runtime.executor import Executor
from ingest.train.run import trajectory_jobs
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig, resolve_topics
from ingest.train.run.trajectory_jobs import trajectory_split
from ingest.train.trajectory.estimate import TrajectorySummary, run_trajectory_pass
from ingest.train.trajectory.local_map import OdometryParams
from ingest.train.trajectory.segments import (
    MAX_JOIN_DEG,
    MAX_JOIN_MM,
    Join,
    SegmentInputs,
    SegmentJob,
    SegmentParams,
    SegmentResult,
    SplitSummary,
    fit_join,
    plan_segments,
    segmented_pass,
)
from sensorbox.cli.ingest import _pass_rows
from sensorbox.sim.config import SimConfig
from sensorbox.sim.run import simulate
from sensorbox.sim.truth import Truth

S = 1_000_000_000
KNOT = 50_000_000
T0 = 1_700_000_000 * S
SHORT = SegmentParams(2_500_000_000, 1_000_000_000)  # the 3 s walk in two segments


def _truth_pose(t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A synthetic walk: (R (N, 3, 3), p (N, 3)) at times `t_ns`."""
    t = (t_ns - T0) / S
    R = Rotation.from_rotvec(np.c_[0.1 * np.sin(t), 0.05 * t, 0.3 * t]).as_matrix()
    p = np.c_[1.2 * t, 0.1 * np.sin(3 * t), 0.05 * np.cos(2 * t)]
    return R, p


def _segment(span: tuple[int, int], failure: str = "") -> SegmentResult:
    """The synthetic walk's knots over `span` in the segment's own world (cam0 at its first knot)."""
    stamps = np.arange(span[0], span[1] + 1, KNOT, dtype=np.int64)
    R, p = _truth_pose(stamps)
    R_local = np.einsum("ji,njk->nik", R[0], R)
    p_local = (p - p[0]) @ R[0]
    residual = np.full(len(stamps), 0.002)
    residual[0] = 0.0
    if failure:
        return SegmentResult(span, stamps[:0], R_local[:0], p_local[:0], residual[:0], failure, 0.0)
    return SegmentResult(span, stamps, R_local, p_local, residual, "", 1.0)


def _runner(results: dict[Any, SegmentResult], ran: list[SegmentJob]):
    def run_jobs(jobs: list[SegmentJob]) -> list[SegmentResult]:
        ran.extend(jobs)
        return [results.get(j.span_ns) or _segment(j.span_ns or (T0, T0 + 3 * S)) for j in jobs]

    return run_jobs


def test_segments_are_at_most_their_length_overlap_by_theirs_and_start_on_the_knot_grid():
    """20 s: three segments of 8.67 s (the fewest of at most 10 s overlapping by 3 s); 10 s: one."""
    params = SegmentParams()
    segments = plan_segments((T0, T0 + 20 * S), params, KNOT)
    assert [(a - T0, b - T0) for a, b in segments] == [
        (0, 8_666_666_666),
        (5_650_000_000, 14_333_333_333),
        (11_300_000_000, 20 * S),
    ]
    assert plan_segments((T0, T0 + 10 * S), params, KNOT) == [(T0, T0 + 10 * S)]


def test_joined_segments_are_the_walk_in_the_first_segments_world():
    """Four segments of a known walk, each in its own world: joined, every knot is the walk's."""
    segments = plan_segments((T0, T0 + 6 * S), SHORT, KNOT)
    whole = SegmentJob((T0, T0 + 6 * S), None, None)
    ran: list[SegmentJob] = []
    traj, done = segmented_pass(segments, whole, lambda s: s, _runner({}, ran), None)
    assert len(segments) == 4 and len(ran) == 4 and done.jobs == 4 and not done.reruns
    R, p = _truth_pose(traj.stamps_ns)
    np.testing.assert_array_equal(traj.stamps_ns, np.arange(T0, T0 + 6 * S + 1, KNOT))
    np.testing.assert_allclose(traj.p_world_cam0, (p - p[0]) @ R[0], atol=1e-9)
    np.testing.assert_allclose(traj.R_world_cam0, np.einsum("ji,njk->nik", R[0], R), atol=1e-9)
    assert all(j.residual_mm < 1e-6 and j.residual_deg < 1e-6 for j in done.joins)
    assert [j.knots for j in done.joins] == [11, 11, 11]


def test_a_join_over_the_bound_runs_its_two_segments_again_as_one_job():
    """The later segment's knots zigzag 30 mm about the walk over the 12 knots its join is fitted on:
    the fit leaves exactly 30 mm RMS, the two segments run again as one (the whole span: the single pass),
    and the line says so."""
    earlier, later = (T0, T0 + 2_050_000_000), (T0 + S, T0 + 3 * S)
    broken = _segment(later)
    zig = np.where(np.arange(len(broken.stamps_ns)) % 2 == 0, 0.03, -0.03)
    broken = replace(broken, p_world_cam0=broken.p_world_cam0 + np.c_[zig, 0 * zig, 0 * zig])
    fit = fit_join(_segment(earlier), broken)
    assert isinstance(fit, Join) and fit.knots == 12
    assert (round(fit.residual_mm, 6), round(fit.residual_deg, 6)) == (30.0, 0.0)
    whole = SegmentJob((T0, T0 + 3 * S), None, None)
    ran: list[SegmentJob] = []
    traj, done = segmented_pass([earlier, later], whole, lambda s: s, _runner({later: broken}, ran), None)
    assert done.reruns == [
        "trajectory segments 0.00-2.05 s and 1.00-3.00 s (from the first LiDAR point): join residual "
        "30.0 mm / 0.000 deg over the overlap, more than 10 mm / 0.1 deg; run again as one job"
    ]
    assert ran[-1] == whole and done.jobs == 3 and done.joins == []
    np.testing.assert_array_equal(traj.stamps_ns, _segment((T0, T0 + 3 * S)).stamps_ns)


def test_a_segment_without_a_trajectory_is_run_again_with_the_one_before_it():
    """Of three segments the middle one's odometry failed: it runs again with the first, as one job; the
    join of that with the third holds."""
    segments = plan_segments((T0, T0 + 5 * S), SHORT, KNOT)
    assert len(segments) == 3
    middle = segments[1]
    results = {middle: _segment(middle, "odometry: less than 200 ms of LiDAR points (0 ms)")}
    ran: list[SegmentJob] = []
    whole = SegmentJob((T0, T0 + 5 * S), None, None)
    traj, done = segmented_pass(segments, whole, lambda s: s, _runner(results, ran), None)
    a, b = ((t - T0) / S for t in middle)
    assert done.reruns == [
        f"trajectory segments 0.00-{(segments[0][1] - T0) / S:.2f} s and {a:.2f}-{b:.2f} s (from the first "
        "LiDAR point): odometry: less than 200 ms of LiDAR points (0 ms); run again as one job"
    ]
    assert [j.span_ns for j in ran[3:]] == [(segments[0][0], middle[1])] and len(done.joins) == 1
    R, p = _truth_pose(traj.stamps_ns)
    np.testing.assert_allclose(traj.p_world_cam0, (p - p[0]) @ R[0], atol=1e-9)


def test_one_worker_sparse_gt_and_short_recordings_keep_the_single_pass():
    """No split with --workers 1, --gt sparse or points spanning one segment; two workers on a longer
    recording split it."""
    cfg = IngestConfig(rig=Path("rig.yaml"), out=Path("out"), gt="dense", trajectory_segments=SHORT)
    sweeps = {"/a": np.array([[T0, T0, T0 + 100_000_000], [T0 + 3 * S, T0 + 3 * S, T0 + 3 * S + 1]])}
    span = (T0 - S, T0 + 5 * S)
    assert trajectory_split([Path("bag")], cfg, Executor(1), sweeps, span) is None
    assert trajectory_split([Path("bag")], replace(cfg, gt="sparse"), Executor(2), sweeps, span) is None
    assert trajectory_split([Path("bag")], replace(cfg, trajectory_segments=SegmentParams()), Executor(2),
                            sweeps, span) is None  # fmt: skip
    split = trajectory_split([Path("bag")], cfg, Executor(2), sweeps, span)
    assert split is not None and split.segments == plan_segments((T0, T0 + 3 * S + 1), SHORT, KNOT)
    assert split.log_of(split.segments[0]) == (T0, T0 + 1)


def test_a_worker_that_cannot_read_the_bags_says_so(tmp_path):
    """A Dask worker on another machine finds no bag at the client's path: one line naming it."""
    inputs = SegmentInputs((tmp_path / "walk.bag",), False, {}, cast(Rig, None), None, 0.3, OdometryParams())
    with pytest.raises(BagError) as err:
        trajectory_jobs.run_segment(inputs, SegmentJob((T0, T0 + S), (T0, T0 + S), T0))
    assert str(err.value) == (
        f"a worker running the trajectory pass cannot read the bags: {tmp_path / 'walk.bag'}: no such file or "
        "directory"
    )


def test_a_single_pass_records_no_segments_a_split_one_its_joins():
    summary = TrajectorySummary(60, 3.0, 1.0, 2.0, 0, 1.0, "t.tum")
    assert "segments" not in summary.as_dict()
    split = SplitSummary(2, 2.1, 1.0, 2, 3.5, (), ("a line",))
    assert replace(summary, split=split).as_dict()["segments"]["run_again"] == ["a line"]
    assert SplitSummary.from_dict(split.as_dict()) == split


@pytest.fixture(scope="module")
def walk3(tmp_path_factory):
    """A 3 s walk (1/8 resolution, noise-free ranges) and its LiDARs' sweeps as the plan pass tables them."""
    root = tmp_path_factory.mktemp("segments")
    cfg = SimConfig(
        scene="outdoor", trajectory="walk", duration_s=3.0, scale=0.125, range_noise_m=0.0, seed=7
    )
    bag = simulate(cfg, root / "walk").bag
    truth = Truth.load(bag)
    rig = read_rig(truth.path / "rig.yaml")
    with open_bags([bag]) as bags:
        topics = resolve_topics(rig, bags.topics(), str(bag))
        seen: dict[str, list[tuple[int, int, int]]] = {t: [] for t in topics.lidars}
        for msg in bags.messages(topics=list(topics.lidars)):
            sweep = msg.decoded(bags.label)
            if isinstance(sweep, Sweep) and len(sweep.stamps_ns):
                seen[msg.topic].append((msg.log_ns, *sweep.span_ns))
    sweeps = {t: np.array(v, np.int64) for t, v in seen.items()}
    span = (
        min(int(v[:, 1].min()) for v in sweeps.values()),
        max(int(v[:, 2].max()) for v in sweeps.values()),
    )
    return {"root": root, "bag": bag, "truth": truth, "rig": rig, "sweeps": sweeps, "span": span}


def _knot_errors(tum: Path, truth: Truth) -> tuple[float, float]:
    """Largest position (m) and rotation (deg) error of a TUM file's knots against the truth, both worlds
    cam0 at the first knot."""
    rows = [line.split() for line in tum.read_text().splitlines() if not line.startswith("#")]
    ns = np.array([int(r[0].replace(".", "")) for r in rows], np.int64)
    vals = np.array([[float(v) for v in r[1:]] for r in rows])
    T_true = truth.T_world_cam0(ns)
    T_true = np.linalg.inv(T_true[0]) @ T_true
    pos = np.linalg.norm(vals[:, :3] - T_true[:, :3, 3], axis=1)
    rel = np.einsum("nji,njk->nik", T_true[:, :3, :3], Rotation.from_quat(vals[:, 3:]).as_matrix())
    return float(pos.max()), float(
        np.degrees(np.linalg.norm(Rotation.from_matrix(rel).as_rotvec(), axis=1)).max()
    )


def test_a_split_dense_run_matches_the_truth_and_records_its_join(walk3):
    """Two workers: the 3 s walk in two segments joined, every knot within the single pass's bound (1 cm,
    0.1 deg: `test_trajectory_matches_the_truth_to_a_centimetre`); the join's residual in dataset.yaml and
    the summary."""
    out = walk3["root"] / "split"
    cfg = IngestConfig(
        rig=walk3["truth"].path / "rig.yaml",
        out=out,
        workers=2,
        every=64,
        gt="dense",
        trajectory_segments=SHORT,
    )
    summary = ingest([walk3["bag"]], cfg)
    split = summary.trajectory.split if summary.trajectory else None
    assert split is not None and (split.segments, split.jobs, len(split.joins), split.run_again) == (
        2,
        2,
        1,
        (),
    )
    join = split.joins[0]
    assert join.knots >= 10 and join.residual_rms_mm <= MAX_JOIN_MM and join.residual_rms_deg <= MAX_JOIN_DEG
    pos_m, rot_deg = _knot_errors(out / "trajectories" / "walk.tum", walk3["truth"])
    assert pos_m <= 0.01 and rot_deg <= 0.1
    doc = yaml.safe_load((out / "dataset.yaml").read_text())
    recorded = doc["sources"][0]["ground_truth"]["trajectory"]["segments"]
    assert recorded["joins"] == [
        {"overlap_s": list(join.overlap_s), "knots": join.knots, "residual_rms_mm": join.residual_rms_mm,
         "residual_rms_deg": join.residual_rms_deg}
    ]  # fmt: skip
    assert (recorded["segments"], recorded["length_s"], recorded["overlap_s"]) == (2, 2.5, 1.0)
    row = ("trajectory segments on the workers (segments, jobs, joins' largest RMS residual)",
           f"2, 2, {join.residual_rms_mm:.1f} mm / {join.residual_rms_deg:.3f} deg")  # fmt: skip
    assert row in _pass_rows(summary)


def test_a_broken_join_on_the_fork_pool_runs_the_pass_again_as_one_job(walk3, monkeypatch):
    """The second segment's knots zigzag 30 mm (its odometry corrupted in the workers): the join is over the
    bound, the recording runs again as one job, whose trajectory is the single pass's byte for byte; a rerun
    reuses the kept pass with its record."""
    first_segment_start = walk3["span"][0]
    real = trajectory_jobs.run_segment

    def corrupted(inputs: Any, job: SegmentJob) -> SegmentResult:
        result = real(inputs, job)
        if job.start_ns is None or job.start_ns == first_segment_start:
            return result
        zig = np.where(np.arange(len(result.stamps_ns)) % 2 == 0, 0.03, -0.03)
        return replace(result, p_world_cam0=result.p_world_cam0 + np.c_[zig, 0 * zig, 0 * zig])

    monkeypatch.setattr(trajectory_jobs, "run_segment", corrupted)
    rig, bag = walk3["rig"], walk3["bag"]
    cfg = IngestConfig(rig=Path("rig.yaml"), out=Path("out"), gt="dense", trajectory_segments=SHORT)
    with open_bags([bag]) as bags:
        topics = resolve_topics(rig, bags.topics(), str(bag))
        args = (bags, topics.lidars, (topics.imu, topics.R_cam0_imu), rig, 0.3)
        split = trajectory_split([bag], cfg, Executor(2), walk3["sweeps"], walk3["span"])
        assert split is not None and len(split.segments) == 2
        _, s = run_trajectory_pass(*args, walk3["root"] / "broken.tum", span_ns=walk3["span"], split=split)
        run_trajectory_pass(*args, walk3["root"] / "single.tum", span_ns=walk3["span"])
        _, again = run_trajectory_pass(
            *args, walk3["root"] / "broken.tum", span_ns=walk3["span"], split=split
        )
    assert again.reused and again.split == s.split  # a rerun reads the pass and its record back
    assert s.split is not None and (s.split.jobs, s.split.joins) == (3, ())
    (line,) = s.split.run_again
    a, b = ((t - walk3["span"][0]) / 1e9 for t in split.segments[1])
    m = re.fullmatch(
        rf"trajectory segments 0\.00-{(split.segments[0][1] - walk3['span'][0]) / 1e9:.2f} s and {a:.2f}-{b:.2f} s "
        r"\(from the first LiDAR point\): join residual (\d+\.\d) mm / (\d\.\d{3}) deg over the overlap, more "
        r"than 10 mm / 0\.1 deg; run again as one job",
        line,
    )
    assert m is not None and float(m[1]) >= 25.0, line
    assert (walk3["root"] / "broken.tum").read_bytes() == (walk3["root"] / "single.tum").read_bytes()
