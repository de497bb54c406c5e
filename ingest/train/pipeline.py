"""Offline ingest: recorded bags -> WideDepth training set (the product's main job).

Recipe:
1. Plan (one cheap pass): camera and IMU header stamps (no pixels decoded)
   and each LiDAR sweep's time span; pair the stereo frames, pick the samples.
   A corrupt chunk stops the run here, before anything is written; with
   --salvage it is skipped, its messages are counted as lost, and samples
   whose LiDAR/IMU window overlaps them are not planned (`ingest.train.lost`).
2. Stream (second pass, log-time order, `ingest.train.stream`): keep the
   planned camera messages as stored (compressed or raw bytes, not decoded;
   an image that ends its MCAP chunk as that chunk's compressed bytes)
   and a sliding buffer of sweeps and the IMU; a sample is handed to a worker
   as soon as every sweep overlapping its +-window has arrived.
3. Each worker decodes the sample's two images and runs
   `ingest.train.sample.process_sample` (clouds -> GT -> images -> files); a
   local process pool by default, or a Dask cluster. The rig's geometry and
   the trajectory go to each worker once, not with every job.
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
decompresses and checks (`ingest.bags.chunks.DeferredData`): on a raw-image
zstd bag that took the main process from about 240 to 165 ms of CPU a sample
(2 workers).
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field, replace
from functools import partial
from itertools import chain, islice
from pathlib import Path
from typing import Any

from calibration.rectify import stereo_warnings
from calibration.rig import Rig, read_rig, write_rig
from calibration.types import F64
from calibration.warp import height_full_problem
from ingest.bags.decode import Frame
from ingest.bags.reader import BagSet, Progress, given_once, open_bags
from ingest.dataset.identity import resume_state
from ingest.dataset.layout import (
    prepare_dirs,
    sample_id,
)
from ingest.dataset.lock import hold_folder
from ingest.errors import BagError, DatasetError, MessageDecodeError, OdometryError, OutputError
from ingest.raster.params import backend_problem
from ingest.runtime.executor import Executor, Handoff, share_cores
from ingest.runtime.heap import retain_freed_memory
from ingest.runtime.jit import compiling
from ingest.topic_map import check_rig
from ingest.train.align import Alignment
from ingest.train.align_check import (
    CalibrationCheck,
    SampleAlignments,
    check_calibration,
    from_metas,
    from_records,
)
from ingest.train.bad_messages import BadMessages
from ingest.train.block_planes import BlockPlanes, PlaneSettings
from ingest.train.dense import DenseParams, free_space_settings
from ingest.train.describe import (
    check_existing,
    check_format,
    record_calibration,
    record_undecodable,
    sample_settings,
    write_dataset_yaml,
)
from ingest.train.lidar_rate import THIN_FRACTION
from ingest.train.plan import LOST_REASON, Plan, Survey, plan, survey
from ingest.train.plausible import check_imu_rate, check_time_order
from ingest.train.refine import Refinement, refine
from ingest.train.rig_trajectory import RigTrajectory
from ingest.train.sample import ALIGNED, GAP_FALLBACK, Geometry, SampleAlignment, SampleParams, SampleResult
from ingest.train.stream import (
    ALREADY_HELD,
    UNDECODABLE_IMAGE,
    Shared,
    StreamedJob,
    check_image_size,
    give_arrays,
    handoff_bytes_bound,
    planned_stamps,
    run_streamed,
    stream_jobs,
    take_arrays,
)
from ingest.train.sync import DEFAULT_LIDAR_WINDOW_NS
from ingest.train.trajectory import STATIC_WINDOW_NS, TrajectorySummary, choose_method, run_trajectory_pass

__all__ = ["UNDECODABLE_IMAGE", "IngestConfig", "IngestSummary", "Topics", "ingest", "stream_jobs"]


@dataclass(frozen=True)
class IngestConfig:
    """Settings of one ingest run (times in ns)."""

    rig: Path
    out: Path
    workers: int = 2
    every: int = 1
    lidar_window_ns: int = DEFAULT_LIDAR_WINDOW_NS
    stereo_tolerance_ns: int | None = None  # default: half the median camera period
    height_full: int | None = None
    salvage: bool = False
    dask: str | None = None
    # sparse | dense | auto (see ingest.train.trajectory.choose_method); `sensorbox ingest` defaults to auto,
    # the library to sparse (no trajectory pass unless asked)
    gt: str = "sparse"
    max_bad: int = 0  # undecodable messages skipped and counted before the run stops (bad_messages)
    sample: SampleParams = field(default_factory=SampleParams)
    widen_static: bool = True  # --gt auto may widen the default dense window for a rig that stood still
    refine: bool = (
        False  # --refine: the cameras' clock offsets and LiDAR rotations refined from the bags first
    )

    def validate(self) -> None:
        """Values a run cannot start with, named as the CLI options that set them."""
        if self.gt not in ("sparse", "dense", "auto"):
            raise DatasetError(f"--gt {self.gt!r}: expected sparse, dense or auto")
        if not self.sample.dense.window_ns > 0:
            raise DatasetError(f"--gt-window-ms must be > 0, got {self.sample.dense.window_ns / 1e6:g}")
        if self.sample.motion not in ("full", "rotation", "off"):
            raise DatasetError(f"--motion {self.sample.motion!r}: expected full, rotation or off")
        if self.gt == "dense" and self.sample.motion != "full":
            raise DatasetError(
                f"--motion {self.sample.motion} does not apply to --gt dense, which places every point with "
                "the trajectory; it chooses the motion model of sparse GT (--gt sparse or auto)"
            )
        backend = self.sample.dense.render.backend
        if (problem := backend_problem(backend)) is not None:
            raise DatasetError(f"--backend {backend!r}: {problem}")
        if self.max_bad < 0:
            raise DatasetError(f"--max-bad must be >= 0, got {self.max_bad}")
        if self.workers < 1:
            raise DatasetError(f"--workers must be >= 1, got {self.workers}")
        if self.every < 1:
            raise DatasetError(f"--every must be >= 1, got {self.every}")
        if self.height_full is not None and (problem := height_full_problem(self.height_full)) is not None:
            raise DatasetError(problem)
        if not 0 <= self.sample.png_level <= 3:
            raise DatasetError(f"--png-level must be 0..3, got {self.sample.png_level}")
        if self.dask:
            from distributed.comm.addressing import get_address_host_port

            try:
                get_address_host_port(self.dask)
            except ValueError as err:
                raise DatasetError(
                    f"--dask {self.dask!r}: expected a scheduler address tcp://HOST:PORT ({err})"
                ) from err
        if not self.lidar_window_ns > 0:
            raise DatasetError(f"--window-ms must be > 0, got {self.lidar_window_ns / 1e6:g}")
        if self.gt == "auto" and self.sample.dense.window_ns < self.lidar_window_ns:
            raise DatasetError(
                f"--gt auto: --gt-window-ms {self.sample.dense.window_ns / 1e6:g} is narrower than "
                f"--window-ms {self.lidar_window_ns / 1e6:g}; the sparse GT it gives frames in trajectory "
                "gaps reads --window-ms of points from the dense window"
            )
        if not (math.isfinite(self.sample.min_range_m) and self.sample.min_range_m >= 0):
            raise DatasetError(f"--min-range must be >= 0 m, got {self.sample.min_range_m:g}")


OVER_UINT16 = "over the depth PNG's 65.535 m, left empty"


@dataclass
class IngestSummary:
    """What an ingest run did, for the CLI's summary table."""

    written: int = 0
    resumed: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    flagged: dict[str, int] = field(default_factory=dict)  # written, with a warning in their meta
    undecodable: dict[str, int] = field(default_factory=dict)  # per topic: messages skipped (--max-bad)
    dropped: dict[str, dict[str, int]] = field(default_factory=dict)  # per topic, reason: `plausible`
    frames: int = 0
    pairs: int = 0
    planned: int = 0
    density_by_method: dict[str, list[float]] = field(default_factory=dict)  # under --gt auto both occur
    skew_ms: list[float] = field(default_factory=list)
    stereo_dt_ms: list[float] = field(default_factory=list)  # lower minus upper header stamp, per sample
    motion_applied: int = 0
    dense_points: dict[str, int] = field(default_factory=dict)  # dense GT: totals over the samples
    stage_ms: dict[str, list[float]] = field(default_factory=dict)  # sequential: they add up per sample
    overlapped_ms: dict[str, list[float]] = field(default_factory=dict)  # helper threads beside them
    seconds: float = 0.0
    dense_warm_up_s: float | None = None  # dense GT's kernels and pixel rays, before the samples
    compile_s: float = 0.0  # numba compiling in this process (`ingest.runtime.jit`): a checkout's first run
    dense_planes: tuple[int, float] | None = None  # dense GT: (blocks fitted, seconds fitting and testing)
    out: Path | None = None
    method: str = "sparse"
    decision: str = ""
    trajectory: TrajectorySummary | None = None
    lost: dict[str, int] = field(default_factory=dict)  # topic -> messages in corrupt chunks (--salvage)
    lost_chunks: list[str] = field(default_factory=list)  # one line per corrupt chunk skipped
    duplicates: dict[str, int] = field(default_factory=dict)  # per topic: repeated stamps, first read
    uncovered: int = 0  # stereo pairs without LiDAR points within the window: not planned
    imu_gaps_ms: list[float] = field(default_factory=list)  # IMU intervals over 5 periods (plan.imu_gaps)
    warnings: list[str] = field(default_factory=list)  # about the inputs, one line each (the rig's layout)
    stale_temporaries: int = 0  # left in the output by a killed run, removed (`ingest.dataset.lock`)
    without_gt: int = 0  # samples written with no GT pixel in their depth PNG
    without_gt_points: dict[str, int] = field(default_factory=dict)  # their windows' points, by filter

    def without_gt_line(self) -> str:
        """One warning line when written samples hold no GT pixel, with their points by filter ('' if none).

        A recording whose points are all NaN, zero, noise-tagged or out of every view writes samples with
        an empty depth PNG, which a training set must not take for ground truth without a word.
        """
        if not self.without_gt:
            return ""
        counts = self.without_gt_points
        points = {why: n for why, n in counts.items() if why not in ("total", OVER_UINT16) and n}
        reasons = ", ".join(f"{n:,} {why}" for why, n in points.items())
        over = counts.get(OVER_UINT16, 0)
        return (
            f"{self.without_gt} of {self.written} samples written hold no ground truth pixel; their windows' "
            f"LiDAR points: {counts.get('total', 0):,}{f' ({reasons})' if reasons else ''}"
            + (f"; {over:,} GT pixels {OVER_UINT16}" if over else "")
        )

    held_elsewhere: int = 0  # of `resumed`: frames that samples of other ids hold (`ingest.dataset.identity`)
    refinement: Refinement | None = None  # --refine: what `ingest.train.refine` found and the rig it made
    alignments: list[tuple[Mapping[str, Alignment], F64 | None]] = field(default_factory=list)  # per sample
    calibration: CalibrationCheck | None = None  # the samples' alignments summed up (`ingest.train.align`)
    damaged: list[str] = field(default_factory=list)  # finished samples found damaged, written again: why
    aligned: dict[str, SampleAlignment] = field(default_factory=dict)  # per sample id: alignment_only's

    @property
    def density(self) -> list[float]:
        """GT density (fisheye) of every written sample, grouped by GT method."""
        return [d for by_method in self.density_by_method.values() for d in by_method]

    def add(self, result: SampleResult) -> None:
        if result.reason == ALIGNED and result.aligned is not None:
            self.aligned[result.sid] = result.aligned
            return
        if result.reason == ALREADY_HELD:
            self.resumed += 1
            self.held_elsewhere += 1
            return
        if not result.written:
            self.skipped[result.reason] = self.skipped.get(result.reason, 0) + 1
            return
        self.written += 1
        meta = result.meta
        assert meta is not None  # written samples carry their metadata
        self.density_by_method.setdefault(meta.gt.method, []).append(meta.gt.density)
        if meta.gt.depth_pixels == 0:
            self.without_gt += 1
            p = meta.points
            for why, n in (
                ("total", p.total), ("zero", p.zero), ("non-finite", p.non_finite),
                ("nearer than --min-range", p.too_close), ("noise-tagged", p.noise_tag),
                ("outside the IMU's span", p.off_imu), ("out of view", p.out_of_view),
                ("occluded", p.occluded), ("visible", p.kept - p.out_of_view - p.occluded),
                (OVER_UINT16, meta.dropped.get("depth_over_uint16", 0)),
            ):  # fmt: skip
                self.without_gt_points[why] = self.without_gt_points.get(why, 0) + n
        if meta.alignment:
            self.alignments.extend(from_metas([meta])[0])
        self.skew_ms.extend(meta.lidar_skew_ms.values())
        self.stereo_dt_ms.append(meta.stereo_dt_ms)
        for name in meta.points.silent_lidars:
            key = f"{name} silent in the window"
            self.flagged[key] = self.flagged.get(key, 0) + 1
        for name in meta.points.thin_lidars:
            key = f"{name} thin in the window (< {THIN_FRACTION:.0%} of its rate)"
            self.flagged[key] = self.flagged.get(key, 0) + 1
        self.motion_applied += meta.motion.applied
        if meta.gt.decision == GAP_FALLBACK:
            key = "sparse GT (frame in a trajectory gap)"
            self.flagged[key] = self.flagged.get(key, 0) + 1
        if meta.gt.method == "dense":
            for key, n in (
                ("accumulated", meta.gt.accumulated_points),
                ("removed as movers", meta.gt.removed_moving),
                ("left out: no registered pose near the frame", meta.points.off_trajectory),
            ):
                self.dense_points[key] = self.dense_points.get(key, 0) + n
        for k, v in result.stage_ms.items():
            self.stage_ms.setdefault(k, []).append(v)
        for k, v in result.overlapped_ms.items():
            self.overlapped_ms.setdefault(k, []).append(v)


@dataclass(frozen=True)
class Topics:
    """The bag topics of the rig's sensors (images may be raw or `/compressed`)."""

    upper: str
    lower: str
    lidars: dict[str, str]  # topic -> rig lidar name
    imu: str | None
    R_cam0_imu: Any
    imu_name: str = ""  # the rig's name of the IMU on `imu`
    imu_rate_hz: float | None = None  # its rate as the rig states it
    upper_shift_ns: int = 0  # the rig's timeshift_cam_imu: header stamp + shift = exposure on the LiDAR clock
    lower_shift_ns: int = 0


def _resolve_topics(rig: Rig, bag_topics: dict[str, Any], where: str) -> Topics:
    def find(topic: str | None, what: str) -> str:
        for cand in (topic, f"{topic}/compressed"):
            if cand in bag_topics:
                return cand
        if not bag_topics:
            raise BagError(f"{where}: no messages at all (an empty bag, or cut before its first message)")
        listing = ", ".join(sorted(bag_topics))
        raise BagError(f"{where}: no topic {topic!r} for {what} (from the rig); the bag has: {listing}")

    upper = find(rig.upper.topic, "the upper camera")
    lower = find(rig.lower.topic, "the lower camera")
    lidars = {find(li.topic, f"lidar {li.name}"): li.name for li in rig.lidars}
    # every IMU the rig names must be there: a silent fallback skews the motion model
    imu_topics = [find(i.topic, f"imu {i.name}") for i in rig.imus]
    # a topic of another type, or of two (a LiDAR topic that also carries Imu messages), was skipped unsaid
    problems = check_rig(rig, {t: s.msgtype for t, s in bag_topics.items()})
    if problems:
        first = problems[0]
        raise BagError(f"{where}: {first.topic} (the rig's {first.sensor}) {first.problem}")
    imu = rig.imus[0] if rig.imus else None
    return Topics(
        upper, lower, lidars, imu_topics[0] if imu else None, imu.T_cam0_imu[:3, :3] if imu else None,
        imu.name if imu else "", imu.rate_hz if imu else None, rig.upper.timeshift_ns, rig.lower.timeshift_ns,
    )  # fmt: skip


def _gt_method(
    bags: BagSet, topics: Topics, rig: Rig, cfg: IngestConfig, summary: IngestSummary, bad: BadMessages,
    trajectory_span_ns: tuple[int, int], progress: Progress | None = None,
) -> tuple[IngestConfig, RigTrajectory | None]:  # fmt: skip
    """Run the trajectory pass when --gt dense/auto needs it (`progress`: its sweeps), decide the method,
    set the window.

    Dense GT streams every sweep within its window (`--gt-window-ms`); the
    trajectory goes to `trajectories/<first bag>.tum` in the output and
    spans `trajectory_span_ns` (`_dense_reach_ns` around the upper camera's stamps).
    """
    traj, tsum, failure = None, None, ""
    if cfg.gt in ("dense", "auto"):
        out_file = cfg.out / "trajectories" / f"{Path(bags.paths[0]).name}.tum"
        try:
            traj, tsum = run_trajectory_pass(
                bags,
                topics.lidars,
                (topics.imu, topics.R_cam0_imu),
                rig,
                cfg.sample.min_range_m,
                out_file,
                bad=bad,
                span_ns=trajectory_span_ns,
                progress=progress,
            )
        except OdometryError as err:
            if cfg.gt == "dense":
                why = f"{bags.label}: {err}; dense GT needs a trajectory (--gt sparse does not)"
                raise OdometryError(why) from err
            failure = str(err)
    method, decision = choose_method(cfg.gt, tsum, failure)
    dense = cfg.sample.dense
    default_window = cfg.widen_static and dense.window_ns == DenseParams().window_ns  # not the user's choice
    if cfg.gt == "auto" and method == "dense" and tsum is not None and tsum.static and default_window:
        dense = replace(dense, window_ns=STATIC_WINDOW_NS)
        decision += f"; rig static: window +-{STATIC_WINDOW_NS / 1e6:.0f} ms"
    summary.method, summary.decision, summary.trajectory = method, decision, tsum
    fallback = cfg.gt == "auto"  # sparse GT for frames in trajectory gaps; --gt dense skips them
    sample = replace(
        cfg.sample,
        method=method,  # type: ignore[arg-type]
        decision=decision,
        dense=dense,
        gap_fallback=fallback,
    )
    window = dense.window_ns if method == "dense" else cfg.lidar_window_ns
    return replace(cfg, sample=sample, lidar_window_ns=window), traj if method == "dense" else None


@contextmanager
def _warming_up(geometry: Geometry, cfg: IngestConfig) -> Iterator[Callable[[], float | None]]:
    """Load the remap maps and, for --gt dense/auto, warm dense GT up (`Geometry.warm_dense`) in a thread.

    It runs while the main thread reads the bags for the trajectory and the
    plan (on 2 cores the two overlap: a dense run starts about 2 s sooner),
    and yields `ready`, which waits for it, raises what it raised and
    returns the dense warm-up's seconds (None without one). The
    thread is joined on the way out whatever happens, so no worker forks
    while it runs. The trajectory pass and the first job (the stream pass's
    first blocks) call no parallel (renderer) kernel, so numba's thread pool
    is the warm-up's alone. With Dask the workers build their own. `--gt
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


def _dense_reach_ns(cfg: IngestConfig) -> int:
    """How far around a frame dense GT may read sweeps (0 for sparse GT): its window, or the wider one
    `--gt auto` may choose for a static rig."""
    if cfg.gt == "sparse":
        return 0
    if cfg.gt == "auto" and cfg.widen_static:
        return max(cfg.sample.dense.window_ns, STATIC_WINDOW_NS)
    return cfg.sample.dense.window_ns


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
    cfg = replace(cfg, sample=replace(cfg.sample, window_ns=cfg.lidar_window_ns))
    rig = read_rig(cfg.rig)
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
    summary = IngestSummary(out=cfg.out, warnings=stereo_warnings(rig), refinement=refinement)
    if refinement is not None:
        summary.warnings += refinement.unobserved_lines()
    bad = BadMessages(cfg.max_bad, warn)
    executor = Executor(cfg.workers, dask=cfg.dask, worker_init=partial(_init_worker, cfg.workers))
    try:
        executor.connect()  # an unreachable Dask scheduler fails here, before the output is touched
    except OSError as err:  # distributed's connect timeout is an OSError
        raise DatasetError(f"--dask {cfg.dask!r}: cannot reach the scheduler ({err})") from err
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
        summary.calibration = check_calibration(summary.alignments)
        if summary.calibration is not None:
            record_calibration(cfg.out, [Path(p) for p in bag_paths], summary.calibration.as_yaml())
            summary.warnings += summary.calibration.warnings(cfg.rig)
        if summary.without_gt_line():
            summary.warnings.append(summary.without_gt_line())
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
    """`ingest.train.refine.refine` with every step: the clocks and IMU rotations from the gyros
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
            cfg = IngestConfig(rig=rig_file, out=out, workers=workers, every=every, gt="sparse")
            cfg = replace(cfg, sample=sample)
            summary = ingest(bags, cfg, progress=aligning)
            found = [summary.aligned[sid] for sid in sorted(summary.aligned)]
            return from_records([(a.upper, a.lower, a.twist_cam0) for a in found])

    return refine(bags, rig, progress, align)


def _block_planes(
    rig: Rig, topics: Topics, the_plan: Plan, cfg: IngestConfig, traj: RigTrajectory | None, busy: bool
) -> BlockPlanes | None:
    """Dense GT's plane fit and free-space test, once per point in the stream pass
    (`ingest.train.block_planes`); None: sparse."""
    if cfg.sample.method != "dense" or traj is None:
        return None
    dense = cfg.sample.dense
    settings = PlaneSettings(
        {t: rig.lidar(name).T_cam0_lidar for t, name in topics.lidars.items()}, dense.plane_block_ns,
        dense.plane_neighbours, dense.plane_max_flatness, cfg.sample.min_range_m,
        free_space_settings(dense) if dense.free_space else None,
    )  # fmt: skip
    return BlockPlanes(traj, {t: the_plan.spans[t] for t in topics.lidars}, settings, 1 if busy else None)


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
        check_time_order(bags.label, topic, what, rows)
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
        topics = _resolve_topics(rig, bags.topics(), ", ".join(str(p) for p in bag_paths))
        asked = cfg
        reach = _dense_reach_ns(cfg)
        read = partial(passes, PASS_READ) if passes else None
        surveyed = _checked_survey(bags, topics, rig, max(cfg.lidar_window_ns, reach), bad, read)
        summary.imu_gaps_ms = [float(g) / 1e6 for g in surveyed.imu_gaps_ns]
        summary.warnings += surveyed.warnings
        summary.stale_temporaries = held.enter_context(_held_output(cfg.out))
        first, last = surveyed.span_ns
        ready = held.enter_context(_warming_up(geometry, cfg))  # beside the trajectory pass
        odometry = partial(passes, PASS_TRAJECTORY) if passes else None
        cfg, traj = _gt_method(bags, topics, rig, cfg, summary, bad, (first - reach, last + reach), odometry)
        the_plan = plan(bags, topics, cfg, bad, surveyed)
        _count_plan(summary, the_plan, bags, bad)
        prepare_dirs(cfg.out, cfg.sample.exr)
        first_id = write_dataset_yaml(asked, cfg, geometry, [Path(p) for p in bag_paths], summary)
        if executor.every_core_busy:
            # every core runs a worker: a helper thread per worker would only add thread switches
            cfg = replace(cfg, sample=replace(cfg.sample, overlap_images=False))
        done = 0

        def tick() -> None:
            nonlocal done
            done += 1
            if progress:
                progress(done, summary.planned)

        planes = _block_planes(rig, topics, the_plan, cfg, traj, executor.every_core_busy)
        sids = [sample_id(first_id + k) for k in range(len(the_plan.upper_ns))]
        resume = resume_state(cfg.out, sids, planned_stamps(the_plan))
        summary.damaged = list(resume.damaged.values())
        # damaged samples of other ids whose frame this run has: the worker writes it again under their id
        damaged_held = {h.sid: h.problem for held in resume.same_stamps.values() for h in held if h.problem}
        settings = sample_settings(asked, geometry, [Path(p) for p in bag_paths])  # into every sample's meta

        def jobs() -> Iterator[StreamedJob]:
            """The jobs to run; resumed and skipped samples are counted here, in stream order."""
            for item in stream_jobs(bags, topics, the_plan, cfg, first_id, bad, planes, resume, settings):
                if not isinstance(item, tuple):
                    yield item
                    continue
                if item[1] == "done":
                    summary.resumed += 1
                else:
                    summary.skipped[item[1]] = summary.skipped.get(item[1], 0) + 1
                tick()

        # the first job (for dense GT: the first blocks' planes and free space) is made while the warm-up
        # ends on the other core; the workers fork with the first submitted job, after the warm-up
        queued = jobs()
        head = list(islice(queued, 1))
        warm_up_s = ready()  # before the workers fork: they inherit what it built
        summary.dense_warm_up_s = warm_up_s if cfg.sample.method == "dense" else None
        bound = handoff_bytes_bound(geometry, head[0], the_plan.rates, cfg.lidar_window_ns) if head else 0
        handoff = Handoff(take_arrays, give_arrays, bound)
        results = executor.run(
            run_streamed, chain(head, queued), shared=Shared(geometry, traj), handoff=handoff
        )
        try:
            for result in results:
                for topic, log_ns, why in result.undecodable:  # decoded in the worker, counted here
                    bad.add(topic, log_ns, why)
                summary.add(result)
                if result.written and result.sid in damaged_held:
                    summary.damaged.append(damaged_held[result.sid])
                tick()
        finally:
            results.close()
            if planes is not None:
                summary.dense_planes = (planes.blocks_fitted, planes.seconds)
