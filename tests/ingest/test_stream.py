"""The stream pass hands the workers each sample's camera messages exactly as the bag stores them."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any, NamedTuple

import numpy as np
import pytest

from calibration.rig import read_rig
from ingest.bags.decode import Sweep
from ingest.bags.reader import open_bags
from ingest.runtime.kept import Kept, Release, Task
from ingest.runtime.transport import ArraySlots, slot_views
from ingest.train.gt.block_planes import BlockPlanes, FreeSpaceSettings, PlaneSettings, world_normals
from ingest.train.run.block_jobs import BlockReport, BlockTasks, ClearJob, FitJob, fill_window, run_block
from ingest.train.run.handoff import _lidar_arrays, give_arrays, handoff_bytes_bound, take_arrays
from ingest.train.run.plan import Plan, plan
from ingest.train.run.resolved import resolve_run
from ingest.train.run.sample_job import Geometry
from ingest.train.run.settings import IngestConfig, Topics, resolve_topics
from ingest.train.run.stream import Shared, StreamedJob, _sweeps_needed, decode_images, stream_jobs
from ingest.train.sync import IMU_MARGIN_NS
from ingest.train.trajectory.rig_trajectory import RigTrajectory
from tests.ingest.test_pipeline import INDOOR, _rig


def test_jobs_carry_the_stored_bytes_and_the_worker_decodes_them(tmp_path: Path) -> None:
    cfg = IngestConfig(rig=_rig(INDOOR), out=tmp_path / "ds", workers=1, every=10)
    run = resolve_run(cfg)
    geometry = Geometry.from_rig(read_rig(cfg.rig), 64)
    with open_bags([INDOOR]) as bags:
        topics = resolve_topics(geometry.rig, bags.topics(), str(INDOOR))
        stored = {
            (m.topic, m.stamp(bags.label)): m.raw for m in bags.messages(topics=[topics.upper, topics.lower])
        }
        jobs = [
            j for j in stream_jobs(bags, topics, plan(bags, topics, run), run) if isinstance(j, StreamedJob)
        ]
    assert len(jobs) == 3
    for job in jobs:
        assert job.upper.raw == stored[(topics.upper, job.upper_stamp_ns)]  # CompressedImage JPEG, untouched
        assert job.lower.raw == stored[(topics.lower, job.lower_stamp_ns)]
        light, arrays = take_arrays(job)
        assert light.upper.raw == light.lower.raw == b""
        back = give_arrays(light, tuple(np.array(a) for a in arrays))  # through a slot and back
        assert (back.upper, back.lower) == (job.upper, job.lower)
        _assert_same_windows(back, job)
        images, errors = decode_images(job, Shared(geometry))
        assert errors == [] and [i.shape for i in images] == [(300, 480, 3), (300, 480, 3)]


def _assert_same_windows(got: StreamedJob, want: StreamedJob) -> None:
    assert len(got.lidars) == len(want.lidars) > 0
    for a, b in zip(got.lidars, want.lidars, strict=True):
        assert a.name == b.name
        for field in ("xyz_m", "stamps_ns", "tag", "normal_world", "clear_bits"):
            x, y = getattr(a, field), getattr(b, field)
            assert (x is None) == (y is None), field
            if y is not None:
                assert x.dtype == y.dtype and x.shape == y.shape, field
                np.testing.assert_array_equal(x, y, err_msg=field)


def test_every_job_holds_the_gyro_readings_its_points_need(tmp_path: Path) -> None:
    """A sample is handed out once its IMU readings reach IMU_MARGIN_NS past its window (or the IMU's
    last reading): a sweep logged at its end can arrive before them, and the sparse path drops the
    points the gyro does not cover. On the indoor fixture 7 of 21 jobs were handed out short of the
    margin (their points still covered); an IMU logged later than the sweeps would lose points."""
    cfg = IngestConfig(rig=_rig(INDOOR), out=tmp_path / "ds", workers=1, every=1)
    run = resolve_run(cfg)
    rig = read_rig(cfg.rig)
    with open_bags([INDOOR]) as bags:
        topics = resolve_topics(rig, bags.topics(), str(INDOOR))
        assert topics.imu is not None
        imu_stamps = [m.stamp(bags.label) for m in bags.messages(topics=[topics.imu])]
        imu_first, imu_last = min(imu_stamps), max(imu_stamps)
        jobs = [
            j for j in stream_jobs(bags, topics, plan(bags, topics, run), run) if isinstance(j, StreamedJob)
        ]
    assert len(jobs) == 21
    for job in jobs:
        assert job.imu is not None
        want = min(job.upper_stamp_ns + cfg.lidar_window_ns + IMU_MARGIN_NS, imu_last)
        last_point = max(int(lp.stamps_ns.max()) for lp in job.lidars if len(lp.stamps_ns))
        first = job.upper_stamp_ns - cfg.lidar_window_ns - IMU_MARGIN_NS
        assert int(job.imu.stamps_ns.min()) <= max(first + 5_000_000, imu_first), job.sid  # none forgotten
        got = int(job.imu.stamps_ns.max())
        assert got >= min(want - 5_000_000, imu_last), job.sid  # the readings' period is 5 ms
        assert got >= min(last_point, imu_last), job.sid  # every point the IMU's recording covers


def test_sweeps_needed_counts_the_sweeps_overlapping_each_window() -> None:
    """Against its definition (a sweep [a, b] overlaps [t - w, t + w]) on random sweeps and times,
    overlapping and touching ones included."""
    rng = np.random.default_rng(3)
    for _ in range(50):
        a = rng.integers(0, 1_000, 30)
        spans = [(int(x), int(x + d)) for x, d in zip(a, rng.integers(0, 150, 30), strict=True)]
        upper = np.sort(rng.integers(-100, 1_200, 20))
        w = int(rng.integers(0, 120))
        the_plan = Plan(upper, upper, {"/l": spans}, len(upper), len(upper))
        topics = SimpleNamespace(lidars={"/l": "lidar"})
        got = _sweeps_needed(the_plan, topics, w)  # type: ignore[arg-type]
        want = {k: {"/l": sum(1 for x, y in spans if y >= t - w and x <= t + w)} for k, t in enumerate(upper)}
        assert got == want


# every frame with +-300 ms windows; every 5th frame (167 ms apart) with +-50 ms windows, farther apart
# than the windows reach
DENSE_STREAMS = pytest.mark.parametrize(
    ("every", "window_ns", "block_ns", "n_jobs"),
    [(1, 300_000_000, 400_000_000, 21), (5, 50_000_000, 150_000_000, 5)],
)


class Streamed(NamedTuple):
    jobs: list[StreamedJob]
    sweeps: dict[str, list[Sweep]]  # per LiDAR topic, read straight from the bag
    whole: BlockPlanes  # every block done at once, over all the sweeps (as `final` does)
    topics: Topics
    trajectory: RigTrajectory
    settings: PlaneSettings
    the_plan: Plan


def _dense_jobs(
    tmp_path: Path, every: int, window_ns: int, block_ns: int, free: FreeSpaceSettings | None = None,
    events: list[Any] | None = None,
) -> Streamed:  # fmt: skip
    """The indoor fixture's dense jobs, streamed with block planes on a still trajectory (into `events`:
    the same stream with the blocks as tasks, `BlockTasks`)."""
    cfg = IngestConfig(rig=_rig(INDOOR), out=tmp_path / "ds", workers=1, every=every)
    dense = replace(cfg.sample.dense, window_ns=window_ns)
    run = resolve_run(
        replace(cfg, lidar_window_ns=window_ns, sample=replace(cfg.sample, dense=dense)), "dense"
    )
    rig = read_rig(cfg.rig)
    with open_bags([INDOOR]) as bags:
        topics = resolve_topics(rig, bags.topics(), str(INDOOR))
        sweeps: dict[str, list[Sweep]] = {t: [] for t in topics.lidars}
        for msg in bags.messages(topics=list(topics.lidars)):
            sweep = msg.decoded(bags.label)
            assert isinstance(sweep, Sweep)
            sweeps[msg.topic].append(sweep)
        t_all = np.concatenate([s.stamps_ns for v in sweeps.values() for s in v])
        knots = np.arange(int(t_all.min()) - 10**8, int(t_all.max()) + 2 * 10**8, 50_000_000, dtype=np.int64)
        still = RigTrajectory(knots, np.tile(np.eye(3), (len(knots), 1, 1)), np.zeros((len(knots), 3)),
                              np.zeros(len(knots)))  # fmt: skip
        T = {t: rig.lidar(name).T_cam0_lidar for t, name in topics.lidars.items()}
        settings = PlaneSettings(T, block_ns, 10, 0.02, cfg.sample.min_range_m, free)
        the_plan = plan(bags, topics, run)
        spans = {t: the_plan.spans[t] for t in topics.lidars}
        planes = BlockPlanes(still, spans, settings)
        jobs = [
            j for j in stream_jobs(bags, topics, the_plan, run, planes=planes) if isinstance(j, StreamedJob)
        ]
        if events is not None:
            events += stream_jobs(bags, topics, the_plan, run, planes=BlockTasks(still, spans, settings))
    whole = BlockPlanes(still, spans, settings)
    whole.complete(sweeps, int(t_all.min()), int(t_all.max()), final=True)
    return Streamed(jobs, sweeps, whole, topics, still, settings, the_plan)


@DENSE_STREAMS
def test_dense_jobs_carry_each_points_normal_from_its_whole_block(
    tmp_path: Path, every: int, window_ns: int, block_ns: int, n_jobs: int
) -> None:
    """With block planes every job's points carry the normal fitted among all the points of their block
    (read here straight from the bag), whichever sample carries them: the stream pass keeps a block's
    first sweeps until its last one has arrived and fits it then, also where samples lie farther apart
    than their windows reach (every 5th frame, 167 ms apart, +-50 ms)."""
    run = _dense_jobs(tmp_path, every, window_ns, block_ns)
    assert len(run.jobs) == n_jobs
    # the same fits from the whole recording, block by block
    want: dict[tuple[str, int], np.ndarray] = {}
    t_all = np.concatenate([s.stamps_ns for v in run.sweeps.values() for s in v])
    for j in range(int(t_all.min()) // block_ns, int(t_all.max()) // block_ns + 1):
        lo, hi = j * block_ns, (j + 1) * block_ns - 1
        parts, keys = [], []
        for topic, v in run.sweeps.items():
            T = run.settings.T_cam0_lidar[topic]
            for s in v:
                m = np.flatnonzero((s.stamps_ns >= lo) & (s.stamps_ns <= hi))
                if len(m):
                    parts.append((s.xyz_m[m], s.stamps_ns[m], None if s.tag is None else s.tag[m], T))
                    keys.append((run.topics.lidars[topic], s.stamps_ns[m]))
        for (name, stamps), normal in zip(
            keys, world_normals(parts, run.trajectory, run.settings), strict=True
        ):
            for t, n in zip(stamps.tolist(), normal, strict=True):
                want[(name, t)] = n
    checked = 0
    for job in run.jobs:
        for lp in job.lidars:
            assert lp.normal_world is not None and len(lp.normal_world) == len(lp.stamps_ns)
            assert lp.clear_bits is None  # no free-space test asked for
            expect = np.array([want[(lp.name, t)] for t in lp.stamps_ns.tolist()])
            np.testing.assert_array_equal(lp.normal_world, expect, err_msg=job.sid)
            checked += int(np.isfinite(expect[:, 0]).sum())
    assert checked > 1_000 * n_jobs


@DENSE_STREAMS
def test_dense_jobs_carry_each_points_free_space_bits_from_every_slice_that_can_test_it(
    tmp_path: Path, every: int, window_ns: int, block_ns: int, n_jobs: int
) -> None:
    """The free-space bits a job's points carry are those of their blocks tested against every slice
    within a window and a reference span of them, as if the whole recording were at hand: the stream
    pass keeps the sweeps before a block that can test it and waits for those after it."""
    free = FreeSpaceSettings(window_ns, 0, 50_000_000)
    run = _dense_jobs(tmp_path, every, window_ns, block_ns, free)
    assert len(run.jobs) == n_jobs
    want = {
        (run.topics.lidars[topic], t): b
        for topic, v in run.sweeps.items()
        for s in v
        for t, b in zip(s.stamps_ns.tolist(), run.whole.clear_bits(s), strict=True)
    }
    set_bits = 0
    for job in run.jobs:
        for lp in job.lidars:
            assert lp.clear_bits is not None and len(lp.clear_bits) == len(lp.stamps_ns)
            expect = np.array([want[(lp.name, t)] for t in lp.stamps_ns.tolist()])
            np.testing.assert_array_equal(lp.clear_bits, expect, err_msg=job.sid)
            set_bits += int(np.unpackbits(expect.view(np.uint8)).sum())
    assert set_bits > 100 * n_jobs  # a still rig's room: some points lie where later slices saw through


def test_dense_jobs_travel_through_the_shared_slots_whole(tmp_path: Path) -> None:
    """Every dense job's camera bytes and LiDAR arrays (points, stamps, tags, normals, free-space bits)
    fit the slots sized from the first job and the LiDARs' fastest sweep, and come back out of them
    equal to what was taken: the job itself carries none of their rows."""
    window_ns = 300_000_000
    run = _dense_jobs(tmp_path, 1, window_ns, 400_000_000, FreeSpaceSettings(window_ns, 0, 50_000_000))
    geometry = Geometry.from_rig(read_rig(_rig(INDOOR)), 64)
    bound = handoff_bytes_bound(geometry, run.jobs[0], run.the_plan.rates, window_ns)
    slots = ArraySlots(2, bound)
    try:
        for job in run.jobs:
            light, arrays = take_arrays(job)
            assert all(len(a) == 0 for p in light.lidars for a in _lidar_arrays(p))
            assert len(arrays) == 2 + 6 * len(
                job.lidars
            )  # tags, normals, bits and reflectivity all present here
            ref = slots.put(arrays)
            assert ref is not None, f"{job.sid}: {sum(a.nbytes for a in arrays)} bytes, slot {bound}"
            back = give_arrays(light, slot_views(ref))
            slots.release(ref)
            assert (back.upper, back.lower) == (job.upper, job.lower)
            _assert_same_windows(back, job)
    finally:
        slots.close()


def test_block_tasks_travel_through_the_shared_slots_whole(tmp_path: Path) -> None:
    """Every dense-GT block's fit and free-space test leaves its sweeps' arrays (rows, points, stamps,
    tags) in a slot sized from the first job, the LiDARs' fastest sweep and the longest task's span, keeps
    none of their rows itself, and runs on what comes back out of the slot to the value it has whole."""
    window_ns = 300_000_000
    events: list[Any] = []
    run = _dense_jobs(
        tmp_path, 1, window_ns, 400_000_000, FreeSpaceSettings(window_ns, 0, 50_000_000), events
    )
    geometry = Geometry.from_rig(read_rig(_rig(INDOOR)), 64)
    first = next(e.job for e in events if isinstance(e, Task) and isinstance(e.job, StreamedJob))
    span_ns = run.settings.task_span_ns
    assert span_ns == run.settings.free_space.n_bits(400_000_000) * 50_000_000 > 400_000_000  # type: ignore[union-attr]
    bound = handoff_bytes_bound(geometry, first, run.the_plan.rates, window_ns, span_ns)
    assert bound > handoff_bytes_bound(geometry, first, run.the_plan.rates, window_ns)
    tasks = [e for e in events if isinstance(e, Task) and isinstance(e.job, FitJob | ClearJob)]
    assert {type(t.job) for t in tasks} == {FitJob, ClearJob}
    kept: dict[str, Any] = {}
    slots = ArraySlots(2, bound)
    try:
        for task in tasks:
            light, arrays = take_arrays(task.job)
            items = light.parts if isinstance(light, FitJob) else light.sweeps
            assert len(items) > 0 and all(len(i.xyz_m) == len(i.stamps_ns) == 0 for i in items)
            ref = slots.put(arrays)
            assert ref is not None, f"{task.key}: {sum(a.nbytes for a in arrays)} bytes, slot {bound}"
            back = give_arrays(light, slot_views(ref))
            slots.release(ref)
            needs = {k: kept[k] for k in task.needs}
            got, want = run_block(run.trajectory, back, needs), run_block(run.trajectory, task.job, needs)
            assert isinstance(got, Kept) and isinstance(want, Kept) and task.key is not None
            assert got.value.rows.keys() == want.value.rows.keys()
            for serial, (rows, value) in want.value.rows.items():
                np.testing.assert_array_equal(got.value.rows[serial][0], rows)
                np.testing.assert_array_equal(got.value.rows[serial][1], value)
            kept[task.key] = want.value
    finally:
        slots.close()


@DENSE_STREAMS
def test_blocks_as_tasks_give_every_job_the_normals_and_bits_the_stream_pass_gave_it(
    tmp_path: Path, every: int, window_ns: int, block_ns: int, n_jobs: int
) -> None:
    """With `BlockTasks` each block's fit and free-space test is a keyed task, due before the first job
    that needs it and run once; a job carries no normals or bits, and the ones its worker puts together
    from the blocks it needs are those `BlockPlanes` gave it in the stream pass, bit for bit. Every key is
    released once no buffered sweep holds its rows, never before the last job that needs it."""
    free = FreeSpaceSettings(window_ns, 0, 50_000_000)
    events: list[Any] = []
    run = _dense_jobs(tmp_path, every, window_ns, block_ns, free, events)
    kept: dict[str, Any] = {}
    made: list[str] = []
    released: list[str] = []
    jobs: list[StreamedJob] = []
    for event in events:
        if isinstance(event, Release):
            released += event.keys
            for key in event.keys:
                del kept[key]
            continue
        assert isinstance(event, Task)
        assert set(event.needs) <= set(kept)  # every needed block is due before the job
        if isinstance(event.job, FitJob | ClearJob):
            done = run_block(run.trajectory, event.job, {k: kept[k] for k in event.needs})
            assert isinstance(done, Kept) and isinstance(done.report, BlockReport)
            assert event.key is not None and event.key not in made
            kept[event.key] = done.value
            made.append(event.key)
            continue
        job = event.job
        assert isinstance(job, StreamedJob) and job.blocks is not None
        assert all(lp.normal_world is None and lp.clear_bits is None for lp in job.lidars)
        values = {k: kept[k] for k in event.needs}
        filled = zip(job.lidars, job.blocks.lidars, strict=True)
        jobs.append(
            replace(job, lidars=tuple(fill_window(lp, p, job.blocks.words, values) for lp, p in filled))
        )
    assert len(jobs) == len(run.jobs) == n_jobs
    for got, want in zip(jobs, run.jobs, strict=True):
        _assert_same_windows(got, want)
    assert {k.split(":")[0] for k in made} == {"fit", "clear"}
    assert set(released) <= set(made) and len(released) == len(set(released))
