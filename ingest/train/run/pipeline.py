"""Offline ingest: recorded bags -> WideDepth training set (the product's main job).

Recipe:
1. Plan (one cheap pass): camera and IMU header stamps (no pixels decoded)
   and each LiDAR sweep's time span; pair the stereo frames, pick the samples.
   A corrupt chunk stops the run here, before anything is written; with
   --salvage it is skipped, its messages are counted as lost, and samples
   whose LiDAR/IMU window overlaps them are not planned (`ingest.train.run.lost`).
2. Stream (second pass, log-time order, `ingest.train.run.stream`): keep the
   planned camera messages as stored (compressed or raw bytes, not decoded; an image that ends its
   MCAP chunk as that chunk's compressed bytes) and a sliding buffer of sweeps and the IMU; a sample
   is handed to a worker as soon as every sweep overlapping its +-window has arrived.
3. Each worker decodes the sample's two images and runs
   `ingest.train.run.sample.process_sample` (clouds -> GT -> images -> files); a
   local process pool by default, or a Dask cluster. The rig's geometry and
   the trajectory go to each worker once, not with every job. Dense GT's
   blocks (planes and free space, once per 1 s of points) are tasks of the
   same workers, which the stream pass hands out when they are due
   (`ingest.train.run.block_jobs`); each sample's job needs the blocks its
   window holds.
Finished samples (their meta/<id>.json exists, every file they wrote is
whole) are skipped on a rerun, damaged ones written again, and a frame that
another sample of the folder holds (the same stamps and images: a recording
given again under another name, or in overlapping bags) is not written twice
(`ingest.dataset.identity`).

Why two passes over the bags, not one: the plan needs the whole recording
before the first sample can be decided exactly as it is now (the stereo
tolerance is half the median camera period of the recording, each LiDAR's
thin-window rate is its median over the recording, a LiDAR with no point in
the whole bag is an error), and a corrupt chunk must stop the run before
anything is written, which only a read of every chunk can promise. Neither
pass decodes an image: the plan pass reads the camera messages' header
stamps, the stream pass hands their stored bytes to the workers. An MCAP
chunk is one compressed block, so the plan pass decompresses all of it and
checks its CRC. The later passes (trajectory, stream) decompress a checked
chunk only as far as their wanted messages reach, found through the chunk's
message index (`ingest.bags.chunks`): a sweep or an IMU reading logged before
a raw image in the same chunk costs no decompression of the image. An image
that ends its chunk travels as the chunk's compressed bytes, which the worker
decompresses and checks (`ingest.bags.chunks.DeferredData`), so the main
process does not decompress the image it hands on.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, contextmanager
from dataclasses import replace
from functools import partial
from itertools import chain
from pathlib import Path
from typing import Any

from calibration.housing import housing_warnings
from calibration.rectify import stereo_warnings
from calibration.rig import Rig, read_rig, write_rig
from ingest.bags.decode import Frame
from ingest.bags.reader import BagSet, Progress, given_once, open_bags
from ingest.dataset.identity import resume_state
from ingest.dataset.layout import prepare_dirs, sample_id
from ingest.dataset.lock import hold_folder
from ingest.errors import DatasetError, MessageDecodeError, OutputError, SettingError
from ingest.runtime.executor import Executor, Handoff, share_cores
from ingest.runtime.heap import retain_freed_memory
from ingest.runtime.jit import compiling
from ingest.runtime.kept import Release, Task
from ingest.train.bad_messages import BadMessages
from ingest.train.gt.align_check import SampleAlignments, check_calibration, combine, from_records
from ingest.train.gt.block_planes import PlaneSettings
from ingest.train.plausible import check_imu_rate, check_time_order
from ingest.train.run.block_jobs import BlockReport, BlockTasks
from ingest.train.run.describe import (
    check_existing,
    check_format,
    record_calibration,
    record_undecodable,
    sample_settings,
    write_dataset_yaml,
)
from ingest.train.run.gt_method import dense_reach_ns, gt_method
from ingest.train.run.handoff import give_arrays, handoff_bytes_bound, take_arrays
from ingest.train.run.lidar_poses import camera_mismatch_lines, stereo_alignment, stereo_lines, stereo_record
from ingest.train.run.plan import CROSSED_REASON, LOST_REASON, Plan, Survey, plan, survey
from ingest.train.run.refine import Refinement, refine, refuse_unsynced
from ingest.train.run.resolved import ResolvedRun
from ingest.train.run.sample_job import Geometry, SampleParams, SampleResult
from ingest.train.run.settings import IngestConfig, Topics, resolve_topics
from ingest.train.run.stream import (
    AlreadyDone,
    Shared,
    StreamedJob,
    check_image_size,
    planned_stamps,
    run_streamed,
    stream_jobs,
)
from ingest.train.run.summary import IngestSummary
from ingest.train.run.trajectory_jobs import trajectory_split
from ingest.train.sync import unsynced_line
from ingest.train.trajectory.rig_trajectory import RigTrajectory


@contextmanager
def _warming_up(geometry: Geometry, cfg: IngestConfig) -> Iterator[Callable[[], float | None]]:
    """Load the remap maps and, for --gt dense/auto, warm dense GT up (`Geometry.warm_dense`) in a thread.

    It runs while the main thread reads the bags for the trajectory and the
    plan (on 2 cores the two overlap: a dense run starts about 2 s sooner),
    and yields `ready`, which waits for it, raises what it raised and
    returns the dense warm-up's seconds (None without one). The
    thread is joined on the way out whatever happens, so no worker forks
    while it runs. The trajectory pass and the stream pass up to its first
    sample call no parallel (renderer) kernel, so numba's thread pool is the
    warm-up's alone. With Dask the workers build their own. `--gt
    auto` may still choose sparse GT; its dense warm-up is then a few seconds
    of CPU spent beside the passes.
    """
    dense = cfg.gt in ("dense", "auto")

    def warm() -> float | None:
        geometry.warm_maps()
        if not dense:
            return None
        t0 = time.perf_counter()
        geometry.warm_dense(cfg.sample.dense)
        return time.perf_counter() - t0

    if cfg.dask:
        yield lambda: None
        return
    with ThreadPoolExecutor(1, thread_name_prefix="warm-up") as pool:
        yield pool.submit(warm).result


@contextmanager
def _held_output(out: Path) -> Iterator[int]:
    """`hold_folder` on `out`, created for it when missing; a folder this creates is removed again when
    the run fails before writing into it (yields the stale temporaries removed)."""
    try:
        out.mkdir(parents=True)
        created = True  # by this run (a run starting beside it finds it there)
    except FileExistsError:
        created = False
    except OSError as err:
        raise OutputError(f"cannot create {out}: {err.strerror or err}") from err
    try:
        with hold_folder(out) as stale:
            yield stale
    except BaseException:
        if created and not any(out.iterdir()):
            out.rmdir()
        raise


PASS_REFINE = "refining the rig's clocks and rotations"
"""`passes` name of `--refine`'s read of the cameras and IMUs."""
PASS_READ = "reading the bags"
"""`ingest`'s first pass: every message of the rig's topics read, every chunk checked (unit: messages)."""
PASS_TRAJECTORY = "trajectory"
"""`ingest`'s trajectory pass for dense GT: every LiDAR sweep through the odometry (unit: sweeps)."""
PASS_TRAJECTORY_JOBS = "trajectory in segments on the workers"
"""The same pass in segments, jobs of the workers (`ingest.train.run.trajectory_jobs`; unit: jobs)."""


def _init_worker(workers: int) -> None:
    """Every worker keeps freed image-sized arrays mapped and runs numba on its share of the cores."""
    retain_freed_memory()
    share_cores(workers)


def ingest(
    bag_paths: list[Path],
    cfg: IngestConfig,
    progress: Callable[[int, int], None] | None = None,
    warn: Callable[[str], None] | None = None,
    passes: Callable[[str, int, int], None] | None = None,
) -> IngestSummary:
    """Run the whole job; `progress(done, total)` after each sample, `warn(line)` per skipped message.

    `passes(what, done, total)` hears of the passes over the bags before the
    first sample, which on a long recording take minutes: `PASS_READ`
    (messages of every topic read, every chunk checked) and, for dense GT,
    `PASS_TRAJECTORY` (LiDAR sweeps through the odometry). The summary's
    `compile_s` is what numba spent compiling in this process: a checkout's
    first run, which the stage times then include.
    """
    t_start = time.perf_counter()
    cfg.validate()
    given_once(bag_paths)  # before the rig and the output are touched
    check_format(cfg.out)  # another tool's dataset.yaml is never overwritten
    retain_freed_memory()  # chunks and images: ~20 MB per sample pass through this process too
    rig = given = read_rig(cfg.rig)
    refinement = None
    if (
        cfg.refine
    ):  # before the output is touched: a recording refine cannot read is one line, nothing written
        refine_pass = partial(passes, PASS_REFINE) if passes else None
        refinement = refine_rig([Path(p) for p in bag_paths], rig, cfg.workers, refine_pass)
        rig = refinement.rig
    if not rig.lidars:
        raise DatasetError(f"{cfg.rig}: the rig has no LiDAR under 'lidars'; ingest needs at least one")
    geometry = Geometry.from_rig(rig, cfg.height_full)
    check_existing(cfg, geometry, [Path(p) for p in bag_paths])  # settings, rig, data: before the passes
    lines = [*stereo_warnings(rig), *housing_warnings(given), *filter(None, [geometry.coarse_line()])]
    summary = IngestSummary(out=cfg.out, warnings=lines, refinement=refinement)
    if refinement is not None:
        summary.warnings += refinement.unobserved_lines()
    bad = BadMessages(cfg.max_bad, warn)
    executor = Executor(cfg.workers, dask=cfg.dask, worker_init=partial(_init_worker, cfg.workers))
    try:
        executor.connect()  # an unreachable Dask scheduler fails here, before the output is touched
    except OSError as err:  # distributed's connect timeout is an OSError
        raise SettingError("dask", cfg.dask, f"a scheduler that answers ({err})") from err
    with ExitStack() as held:  # the output folder, once it exists (`_run`), until dataset.yaml is final
        compile_s = held.enter_context(compiling())  # the passes and the samples: where numba compiles
        try:
            _run(bag_paths, cfg, rig, geometry, summary, bad, executor, progress, held, passes)
        finally:
            executor.close()
        # the stream pass found more (images; IMU readings of a sparse run): update dataset.yaml
        if bad.by_topic() != summary.undecodable or bad.dropped.by_topic() != summary.dropped:
            summary.undecodable, summary.dropped = bad.by_topic(), bad.dropped.by_topic()
            record_undecodable(cfg.out, [Path(p) for p in bag_paths], summary.undecodable, summary.dropped)
        summary.warnings += bad.dropped.lines()
        summary.flag_frames()
        upper, lower = summary.unflagged_alignments()
        summary.calibration = check_calibration(upper)
        if summary.calibration is not None:
            stereo = stereo_alignment(rig, summary.calibration.combined, combine(lower))
            record = {**summary.calibration.as_yaml(), **stereo_record(stereo)}
            record_calibration(cfg.out, [Path(p) for p in bag_paths], record)
            upper_off, lower_off = camera_mismatch_lines(summary.alignments, summary.alignments_lower)
            summary.warnings += upper_off or summary.calibration.warnings(cfg.rig, refined=cfg.refine)
            summary.warnings += stereo_lines(stereo, cfg.rig)
            if stereo is None or not stereo.disagrees:
                summary.lower_off_unexplained()
            summary.warnings += lower_off
        summary.warnings += summary.closing_lines(rig.lidars[0].name)
    summary.seconds = time.perf_counter() - t_start
    summary.compile_s = compile_s[0]
    return summary


ALIGN_SAMPLES = 40
"""Frames of a recording that `refine_rig` aligns per round (evenly spread): enough for a LiDAR's pose
to 0.01 deg and 1 mm on the simulated walks, at a sparse ingest's cost."""


def refine_rig(
    bags: list[Path],
    rig: Rig,
    workers: int = 2,
    progress: Callable[[int, int], None] | None = None,
    aligning: Callable[[int, int], None] | None = None,
) -> Refinement:
    """`ingest.train.run.refine.refine` with every step: the clocks and IMU rotations from the gyros
    (`progress` over the messages read), then each LiDAR's pose from the alignments of `ALIGN_SAMPLES`
    frames, found by sparse ingests that write no sample (`SampleParams.alignment_only`) into a temporary
    folder, removed (`aligning` over each round's samples)."""

    def align(candidate: Rig, frames: int) -> tuple[SampleAlignments, SampleAlignments]:
        every = max(1, -(-frames // ALIGN_SAMPLES))  # at most ALIGN_SAMPLES frames
        with tempfile.TemporaryDirectory(prefix="sensorbox-align-") as tmp:
            rig_file = Path(tmp) / "rig" / "rig.yaml"
            rig_file.parent.mkdir()
            write_rig(replace(candidate, camchain=None), rig_file)
            out = Path(tmp) / "out"
            sample = SampleParams(align_lower=True, alignment_only=True)
            cfg = IngestConfig(
                rig=rig_file, out=out, workers=workers, every=every, gt="sparse", sample=sample
            )
            summary = ingest(bags, cfg, progress=aligning)
            refuse_unsynced(summary.clock_spread)
            found = [summary.aligned[sid] for sid in sorted(summary.aligned)]
            return from_records([(a.upper, a.lower, a.twist_cam0) for a in found])

    return refine(bags, rig, progress, align)


def _block_planes(
    rig: Rig, topics: Topics, the_plan: Plan, run: ResolvedRun, traj: RigTrajectory | None
) -> BlockTasks | None:
    """Dense GT's plane fit and free-space test, once per point, as tasks of the executor that the stream
    pass hands out (`ingest.train.run.block_jobs`); None: sparse."""
    if run.sample.method != "dense" or traj is None:
        return None
    dense = run.sample.dense
    settings = PlaneSettings(
        {t: rig.lidar(name).T_cam0_lidar for t, name in topics.lidars.items()}, dense.plane_block_ns,
        dense.plane_neighbours, dense.plane_max_flatness, run.sample.min_range_m, run.free_space,
    )  # fmt: skip
    return BlockTasks(traj, {t: the_plan.spans[t] for t in topics.lidars}, settings)


FIRST_FRAMES_TRIED = 10
"""Camera messages tried for a decodable first frame (undecodable ones are counted by the passes)."""


def _check_first_frames(bags: BagSet, topics: Topics, rig: Rig) -> None:
    """Each camera's first decodable frame has the size of the rig's camera (`check_image_size`), so a
    rig file of another rig stops the run before the passes (a dense run's trajectory pass takes minutes)."""
    for topic, camera in ((topics.upper, rig.upper), (topics.lower, rig.lower)):
        for k, msg in enumerate(bags.messages(topics=[topic])):
            if k >= FIRST_FRAMES_TRIED:
                break
            try:
                frame = msg.decoded(bags.label, keep_bgra=True)
            except MessageDecodeError:
                continue
            if isinstance(frame, Frame):
                check_image_size(frame.image, camera, msg, bags.label)
                break


def _checked_survey(
    bags: BagSet, topics: Topics, rig: Rig, window_ns: int, bad: BadMessages, read: Progress | None
) -> Survey:
    """The first pass (`survey`) and the checks on what it read, all before any write: the first frames'
    size against the rig (before the pass: one line instead of minutes of reading), every topic's time
    order and the IMU's rate against the rig's."""
    _check_first_frames(bags, topics, rig)
    surveyed = survey(bags, topics, window_ns, bad, read)
    for topic, rows in surveyed.seen.items():
        what = "first point times" if topic in topics.lidars else "header stamps"
        line = check_time_order(bags.label, topic, what, rows)
        if line is not None:
            surveyed.warnings.append(line)
    if topics.imu:
        stamps_ns = surveyed.seen[topics.imu][:, 1]
        repeated = surveyed.duplicates.get(topics.imu, 0)
        check_imu_rate(bags.label, topics.imu, topics.imu_name, topics.imu_rate_hz, stamps_ns, repeated)
    return surveyed


def _count_plan(summary: IngestSummary, the_plan: Plan, bags: BagSet, bad: BadMessages) -> None:
    """The plan pass's counts into the summary: frames, pairs, planned samples, undecodable and dropped
    messages, messages lost in corrupt chunks, repeats, uncovered pairs and lost samples."""
    summary.undecodable, summary.dropped = bad.by_topic(), bad.dropped.by_topic()
    summary.frames, summary.pairs, summary.planned = the_plan.frames, the_plan.pairs, len(the_plan.upper_ns)
    summary.lost, summary.lost_chunks = bags.lost_counts(), [c.describe() for c in bags.lost_chunks]
    summary.duplicates, summary.uncovered = the_plan.duplicates, the_plan.uncovered
    if the_plan.lost_samples:
        summary.skipped[LOST_REASON] = the_plan.lost_samples
    if the_plan.crossed_samples:
        summary.skipped[CROSSED_REASON] = the_plan.crossed_samples
    if the_plan.unpaired is not None:
        summary.warnings.append(the_plan.unpaired)
    if (line := unsynced_line(the_plan.stereo_dt_ns, the_plan.upper_ns)) is not None:
        summary.warnings.append(line)


def _ground_truth(
    bags: BagSet, bag_paths: list[Path], topics: Topics, rig: Rig, geometry: Geometry, cfg: IngestConfig,
    summary: IngestSummary, bad: BadMessages, executor: Executor, surveyed: Survey,
    span: tuple[int, int], held: ExitStack, passes: Callable[[str, int, int], None] | None,
) -> tuple[ResolvedRun, RigTrajectory | None, Callable[[], float | None]]:  # fmt: skip
    """The trajectory pass (in segments on the workers where `trajectory_split` says) and the method
    (`gt_method`), with the warm-up (`_warming_up`, held by `held`) started beside what runs in this
    process: before a single pass, after a fork pool's segments (a process forked while another thread
    runs may inherit a lock that thread holds). Returns the run, its trajectory and the warm-up's `ready`.
    """
    sweeps = {t: surveyed.seen[t] for t in topics.lidars}
    split = trajectory_split(bag_paths, cfg, executor, sweeps, span, _pass(passes, PASS_TRAJECTORY_JOBS))
    warm_first = split is None or executor.backend != "fork"
    ready = held.enter_context(_warming_up(geometry, cfg)) if warm_first else None
    odometry, busy = _pass(passes, PASS_TRAJECTORY), executor.every_core_busy
    run, traj = gt_method(bags, topics, rig, cfg, summary, bad, span, busy, odometry, split, surveyed.gyro)
    return run, traj, ready or held.enter_context(_warming_up(geometry, cfg))


def _pass(passes: Callable[[str, int, int], None] | None, name: str) -> Progress | None:
    """`passes` told of the pass `name` (None: nobody listens)."""
    return partial(passes, name) if passes else None


def _run(
    bag_paths: list[Path],
    cfg: IngestConfig,
    rig: Rig,
    geometry: Geometry,
    summary: IngestSummary,
    bad: BadMessages,
    executor: Executor,
    progress: Callable[[int, int], None] | None,
    held: ExitStack,
    passes: Callable[[str, int, int], None] | None = None,
) -> None:
    """The passes over the bags (survey, trajectory, plan, stream), the samples run on `executor`; `held`
    keeps the output folder locked (`hold_folder`) from before its first write on."""
    with open_bags(bag_paths, salvage=cfg.salvage) as bags:
        topics = resolve_topics(rig, bags.topics(), ", ".join(str(p) for p in bag_paths))
        reach = dense_reach_ns(cfg)
        read = _pass(passes, PASS_READ)
        surveyed = _checked_survey(bags, topics, rig, max(cfg.lidar_window_ns, reach), bad, read)
        summary.add_survey(surveyed)
        summary.stale_temporaries = held.enter_context(_held_output(cfg.out))
        span = (surveyed.span_ns[0] - reach, surveyed.span_ns[1] + reach)
        run, traj, ready = _ground_truth(
            bags, bag_paths, topics, rig, geometry, cfg, summary, bad, executor, surveyed, span, held, passes
        )
        the_plan = plan(bags, topics, run, bad, surveyed)
        _count_plan(summary, the_plan, bags, bad)
        prepare_dirs(run.out, run.sample.exr)
        first_id = write_dataset_yaml(run, geometry, [Path(p) for p in bag_paths], summary)
        done = 0

        def tick() -> None:
            nonlocal done
            done += 1
            if progress:
                progress(done, summary.planned)

        planes = _block_planes(rig, topics, the_plan, run, traj)
        sids = [sample_id(first_id + k) for k in range(len(the_plan.upper_ns))]
        resume = resume_state(run.out, sids, planned_stamps(the_plan))
        summary.damaged = list(resume.damaged.values())
        # damaged samples of other ids whose frame this run has: the worker writes it again under their id
        damaged_held = {h.sid: h.problem for held in resume.same_stamps.values() for h in held if h.problem}
        settings = sample_settings(cfg, geometry, [Path(p) for p in bag_paths])  # into every sample's meta

        def jobs() -> Iterator[StreamedJob | Task[Any] | Release]:
            """The jobs to run (samples, dense GT's blocks); resumed and skipped samples are counted here, in
            stream order."""
            for item in stream_jobs(bags, topics, the_plan, run, first_id, bad, planes, resume, settings):
                if isinstance(item, StreamedJob | Task | Release):
                    yield item
                    continue
                if isinstance(item, AlreadyDone):
                    summary.add_resumed(resume.done[item.sid])  # its meta, as resume_state read it
                else:
                    summary.skipped[item.reason] = summary.skipped.get(item.reason, 0) + 1
                tick()

        # the first sample's job (and the blocks' tasks before it) is made while the warm-up ends on the other
        # core; the workers fork with the first submitted job, after the warm-up. Its arrays size the slots.
        queued = jobs()
        head = _through_first_sample(queued)
        warm_up_s = ready()  # before the workers fork: they inherit what it built
        summary.dense_warm_up_s = warm_up_s if run.sample.method == "dense" else None
        first_job = next((s for s in map(_sample_of, head) if s is not None), None)
        longest = planes.settings.task_span_ns if planes is not None else 0
        bound = first_job and handoff_bytes_bound(geometry, first_job, the_plan.rates, run.window_ns, longest)
        handoff = Handoff(take_arrays, give_arrays, bound or 0)
        results = executor.run(
            run_streamed, chain(head, queued), shared=Shared(geometry, traj), handoff=handoff,
            keep_in=run.out,
        )  # fmt: skip
        blocks: list[BlockReport] = []
        try:
            _collect(results, summary, bad, damaged_held, tick, blocks)
        finally:
            results.close()
            if planes is not None:
                summary.dense_planes = (sum(b.fitted for b in blocks), sum(b.seconds for b in blocks))


def _sample_of(item: object) -> StreamedJob | None:
    """The sample job `item` is or wraps (a `Task`), None for a block's task or a release."""
    job = item.job if isinstance(item, Task) else item
    return job if isinstance(job, StreamedJob) else None


def _through_first_sample(queued: Iterator[StreamedJob | Task[Any] | Release]) -> list[Any]:
    """The jobs of `queued` up to its first sample's (the blocks' tasks before it), taken from it."""
    head: list[Any] = []
    for item in queued:
        head.append(item)
        if _sample_of(item) is not None:
            break
    return head


def _collect(
    results: Iterable[SampleResult | BlockReport],
    summary: IngestSummary,
    bad: BadMessages,
    damaged_held: Mapping[str, str],
    tick: Callable[[], None],
    blocks: list[BlockReport],
) -> None:
    """Count every finished sample into `summary` in job order (its undecodable images into `bad`); one
    written under the id of a damaged sample (`damaged_held`: id -> its damage) records that damage. The
    reports of dense GT's blocks go to `blocks`."""
    for result in results:
        if isinstance(result, BlockReport):
            blocks.append(result)
            continue
        for topic, log_ns, why in result.undecodable:  # decoded in the worker, counted here
            bad.add(topic, log_ns, why)
        summary.add(result)
        if result.written and result.sid in damaged_held:
            summary.damaged.append(damaged_held[result.sid])
        tick()
