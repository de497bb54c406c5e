"""The trajectory pass: one read of a recording's LiDARs and IMU, the odometry, and its file.

`read_gyro` collects the IMU's angular rates (small: 200 Hz); `trajectory_pass`
streams every sweep of every LiDAR, filters it as the samples do
(`ingest.train.trajectory.clouds.filter_points`), puts it in cam0 with the rig's
extrinsics and feeds `ingest.train.trajectory.odometry.Odometry`. Sweeps of several
LiDARs interleave in the bag; the odometry registers a chunk only once every
LiDAR has delivered points past its end.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from calibration.errors import CalibrationError
from calibration.rig import Rig
from calibration.types import F64
from ingest.bags.decode import ImuSample, Sweep
from ingest.bags.reader import BagSet, Progress
from ingest.errors import OdometryError, OutputError
from ingest.train.bad_messages import BadMessages
from ingest.train.plausible import check_imu_units
from ingest.train.repeats import FirstCopies
from ingest.train.trajectory import cache as trajectory_cache
from ingest.train.trajectory.clouds import GyroTrack, filter_points, integrate_gyro
from ingest.train.trajectory.imu_check import GyroAgreement, gyro_agreement, turning_stretch
from ingest.train.trajectory.local_map import OdometryParams
from ingest.train.trajectory.odometry import Odometry
from ingest.train.trajectory.rig_trajectory import RigTrajectory, still
from ingest.train.trajectory.segments import SegmentInputs, SegmentJob, Split, SplitSummary, segmented_pass


@dataclass(frozen=True)
class TrajectorySummary:
    """What the trajectory pass measured (for meta, dataset.yaml and the CLI)."""

    knots: int
    span_s: float
    residual_median_mm: float
    residual_p95_mm: float
    gaps: int  # knots carried by prediction (no LiDAR points)
    seconds: float
    file: str
    max_speed_mps: float = 0.0  # fastest knot interval
    max_rate_deg_s: float = 0.0  # fastest turn between knots
    reused: bool = False  # read from the pass an earlier run kept (`trajectory_cache`), not computed
    imu_check: GyroAgreement | None = None  # the IMU's gyro against the knots (`check_gyro`)
    split: SplitSummary | None = None  # the pass ran in joined segments on the workers (`segments`)

    @property
    def static(self) -> bool:
        """The rig stood still (below 5 cm/s and 2 deg/s throughout)."""
        return still(self.max_speed_mps, self.max_rate_deg_s)

    def as_dict(self) -> dict[str, Any]:
        out = dict(self.__dict__)
        out.pop("imu_check")  # dataset.yaml has it beside the trajectory (`ground_truth.imu_check`)
        split = out.pop("split")
        if split is not None:  # a single pass's record stays as it was
            out["segments"] = split.as_dict()
        return out


@dataclass
class GyroReadings:
    """An IMU's angular rates as read (rad/s, IMU frame) with their header stamps (ns): one reading per
    stamp (the first copy), each one that decodes and is plausible (`BadMessages.decoded`)."""

    stamps_ns: list[int] = field(default_factory=list)
    rates_rad_s: list[F64] = field(default_factory=list)

    def add(self, sample: ImuSample) -> None:
        self.stamps_ns.append(sample.stamp_ns)
        self.rates_rad_s.append(np.asarray(sample.gyro_rad_s, np.float64))


def read_gyro(
    bags: BagSet, imu_topic: str | None, R_cam0_imu: F64 | None, bad: BadMessages | None = None,
    readings: GyroReadings | None = None,
) -> GyroTrack | None:  # fmt: skip
    """The integrated gyro of the rig's IMU, or None without one (undecodable readings: see `bad`); a
    `BagError` when its readings are in other units (`check_imu_units`). `readings`: the IMU's, as the
    run's first pass kept them (`ingest.train.run.plan.survey`), instead of reading the bags once more
    (every chunk decompressed again: about a tenth of a trajectory pass)."""
    bad = bad or BadMessages()
    if imu_topic is None or R_cam0_imu is None:
        return None
    where = bags.label
    if readings is None:
        readings = GyroReadings()
        copies = FirstCopies()
        for msg in bags.messages(topics=[imu_topic]):
            sample = bad.decoded(msg, where)
            if sample is None:
                continue
            assert isinstance(sample, ImuSample)
            if copies.stamped(imu_topic, sample.stamp_ns):
                readings.add(sample)
    stamps, rates = readings.stamps_ns, readings.rates_rad_s
    check_imu_units(where, imu_topic, len(stamps), bad.dropped.by_topic().get(imu_topic, {}))
    if len(stamps) < 2:
        return None
    stamps_ns, gyro = np.array(stamps, np.int64), np.array(rates)
    keep = ~bad.dropped.spikes(imu_topic, stamps_ns, gyro)
    return integrate_gyro(stamps_ns[keep], gyro[keep], R_cam0_imu)


def trajectory_pass(
    bags: BagSet,
    lidar_topics: dict[str, str],
    rig: Rig,
    gyro: GyroTrack | None,
    min_range_m: float,
    params: OdometryParams | None = None,
    progress: Progress | None = None,
    bad: BadMessages | None = None,
    span_ns: tuple[int, int] | None = None,
    log_ns: tuple[int, int] | None = None,
    start_ns: int | None = None,
) -> RigTrajectory:
    """Odometry over every sweep of `lidar_topics` (topic -> rig lidar name); `progress` hears of the
    sweeps read (`BagSet.messages`); `start_ns`: the first knot's time (`Odometry`).

    With `span_ns` (first, last) only points within it take part (no sample
    can use the others, and a stray sweep stamped years away would make the
    odometry step knot by knot across the gap); with `log_ns` only the
    messages logged within it are read.
    """
    bad = bad or BadMessages()
    odo = Odometry(gyro, params, start_ns)
    where = bags.label
    last = {topic: -(2**62) for topic in lidar_topics}
    copies = FirstCopies()
    topics = list(lidar_topics)
    reading = (
        bags.messages(topics=topics, progress=progress)
        if log_ns is None
        else bags.messages(topics=topics, start_ns=log_ns[0], stop_ns=log_ns[1], progress=progress)
    )
    for msg in reading:
        sweep = bad.decoded(msg, where)
        assert sweep is None or isinstance(sweep, Sweep)
        if sweep is None or not len(sweep.stamps_ns) or not copies.sweep(msg.topic, sweep):
            continue
        keep, _ = filter_points(sweep.xyz_m, sweep.tag, min_range_m)
        if span_ns is not None:
            keep &= (sweep.stamps_ns >= span_ns[0]) & (sweep.stamps_ns <= span_ns[1])
        T = rig.lidar(lidar_topics[msg.topic]).T_cam0_lidar
        xyz = np.asarray(sweep.xyz_m, np.float64)[keep]
        if len(xyz):  # a sweep wholly outside `span_ns` adds nothing
            odo.add(xyz @ T[:3, :3].T + T[:3, 3], sweep.stamps_ns[keep])
        latest = sweep.span_ns[1] if span_ns is None else min(sweep.span_ns[1], span_ns[1])
        last[msg.topic] = max(last[msg.topic], latest)
        odo.advance(min(last.values()))
    return odo.result()


def judged(agreement: GyroAgreement, bad: BadMessages | None) -> GyroAgreement:
    """`agreement`, or a CalibrationError with its line where the IMU disagrees too far to ingest with.

    Where a LiDAR's sweeps carried no point times (`bad`'s untimed sweeps:
    one warning line of their own) the odometry's knots are misplaced by the
    rig's motion within each sweep; the agreement is recorded, not judged.
    """
    if bad is not None and bad.dropped.untimed:
        return replace(agreement, lidars_timed=False)
    if agreement.refused:
        raise CalibrationError(str(agreement.line()))
    return agreement


CHECK_SPAN_NS = 4_000_000_000
"""The stretch of a recording (where its gyro turns most) whose LiDARs a run without a trajectory pass
(sparse GT) registers to check the IMU (`check_gyro`): 4.4 CPU s on a 20 s walk (0.8 reading the gyro, 3.6
the odometry)."""


def check_gyro(
    bags: BagSet,
    lidar_topics: dict[str, str],
    imu: tuple[str | None, F64 | None],
    imu_name: str,
    rig: Rig,
    min_range_m: float,
    bad: BadMessages | None = None,
    readings: GyroReadings | None = None,
) -> GyroAgreement | None:
    """The IMU's gyro against the odometry of the `CHECK_SPAN_NS` in which it turns most (`judged`: a
    CalibrationError where it disagrees too far); None without an IMU, or where the rig hardly turns or
    the stretch cannot be registered (nothing to judge). A gyro whose every reading is exactly zero (a
    real one reads its bias and noise even at rest: a dead gyro, or a driver that sends no rates) while
    its accelerometer's readings vary is checked over the recording's first `CHECK_SPAN_NS`: the LiDARs
    show whether the rig turned. (A simulated still rig reads exactly zero and one constant acceleration.)"""
    gyro = read_gyro(bags, *imu, bad=bad, readings=readings)
    stretch = turning_stretch(gyro, CHECK_SPAN_NS) if gyro is not None else None
    if gyro is not None and stretch is None and not gyro.steps.any() and _accelerates(bags, imu[0], bad):
        stretch = (int(gyro.stamps_ns[0]), int(gyro.stamps_ns[0]) + CHECK_SPAN_NS)
    if gyro is None or stretch is None or imu[0] is None:
        return None
    span, reach = None, None  # a recording not much longer than the stretch: all of it
    if gyro.stamps_ns[-1] - gyro.stamps_ns[0] > CHECK_SPAN_NS + 1_000_000_000:
        span, reach = stretch, (stretch[0] - 1_000_000_000, stretch[1] + 1_000_000_000)  # log times lag
    try:
        traj = trajectory_pass(
            bags, lidar_topics, rig, gyro, min_range_m, bad=bad, span_ns=span, log_ns=reach
        )
    except OdometryError:
        return None
    return judged(gyro_agreement(traj, gyro, imu_name, imu[0]), bad)


def _accelerates(bags: BagSet, imu_topic: str | None, bad: BadMessages | None) -> bool:
    """Whether the IMU's acceleration readings differ from each other at all (a sensor that is alive)."""
    if imu_topic is None:
        return False
    first: Any = None
    for msg in bags.messages(topics=[imu_topic]):
        sample = (bad or BadMessages()).decoded(msg, bags.label)
        if not isinstance(sample, ImuSample):
            continue
        if first is None:
            first = np.asarray(sample.acc)
        elif not np.array_equal(first, sample.acc):
            return True
    return False


def summarize(
    traj: RigTrajectory,
    seconds: float,
    file: Path,
    reused: bool = False,
    imu_check: GyroAgreement | None = None,
    split: SplitSummary | None = None,
) -> TrajectorySummary:
    res = traj.residual_m[1:]
    ok = res[np.isfinite(res)]
    speed, rate = traj.peak_motion()
    return TrajectorySummary(
        knots=len(traj.stamps_ns),
        span_s=float((traj.stamps_ns[-1] - traj.stamps_ns[0]) / 1e9),
        residual_median_mm=float(np.median(ok) * 1e3) if len(ok) else float("nan"),
        residual_p95_mm=float(np.percentile(ok, 95) * 1e3) if len(ok) else float("nan"),
        gaps=int((~np.isfinite(res)).sum()),
        seconds=seconds,
        file=file.as_posix(),
        max_speed_mps=speed,
        max_rate_deg_s=rate,
        reused=reused,
        imu_check=imu_check,
        split=split,
    )


def run_trajectory_pass(
    bags: BagSet,
    lidar_topics: dict[str, str],
    imu: tuple[str | None, F64 | None],
    rig: Rig,
    min_range_m: float,
    out_file: Path,
    params: OdometryParams | None = None,
    bad: BadMessages | None = None,
    span_ns: tuple[int, int] | None = None,
    progress: Progress | None = None,
    imu_name: str = "",
    split: Split | None = None,
    readings: GyroReadings | None = None,
) -> tuple[RigTrajectory, TrajectorySummary]:
    """Gyro, odometry (points within `span_ns`) and `out_file` (TUM, T_world_cam0), with the summary;
    `progress` hears of the odometry's sweeps (`trajectory_pass`). With `split` the odometry runs in
    joined segments, jobs of the run's executor (`ingest.train.trajectory.segments`), instead of here.

    The pass is kept beside it (`out_file` with suffix .npz, `trajectory_cache`)
    and read back instead of computed when a rerun would compute the same.
    The IMU (`imu_name`) is checked against the knots first (`judged`: a
    CalibrationError, and no file, where it disagrees too far). `readings`: the IMU's as the run's first
    pass kept them (`read_gyro`).
    """
    t0 = time.perf_counter()
    params = params or OdometryParams()
    kept = out_file.with_suffix(".npz")
    key = trajectory_cache.cache_key(bags, lidar_topics, imu, rig, min_range_m, params, span_ns, split)
    traj = trajectory_cache.load(kept, key)
    reused = traj is not None
    gyro = read_gyro(bags, *imu, bad=bad, readings=readings)
    split_summary = trajectory_cache.split_of(kept) if reused else None
    if traj is None and split is None:
        traj = trajectory_pass(
            bags, lidar_topics, rig, gyro, min_range_m, params, progress, bad=bad, span_ns=span_ns
        )
    elif traj is None:
        assert split is not None
        inputs = SegmentInputs(split.bag_paths, split.salvage, lidar_topics, rig, gyro, min_range_m, params)
        whole = SegmentJob(span_ns, None, None)  # the single pass, in a worker
        traj, done = segmented_pass(
            split.segments, whole, split.log_of, partial(split.run_jobs, inputs), gyro
        )
        split_summary = SplitSummary.of(split, done)
    agreement = None
    if gyro is not None and imu[0] is not None:
        agreement = judged(gyro_agreement(traj, gyro, imu_name or imu[0], imu[0]), bad)
    try:
        out_file.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"cannot create {out_file.parent}: {err.strerror or err}") from err
    traj.write_tum(out_file)
    if not reused:
        trajectory_cache.save(kept, key, traj, split_summary)
    took = time.perf_counter() - t0
    return traj, summarize(traj, took, out_file, reused, agreement, split_summary)


STATIC_WINDOW_NS = 1_000_000_000
"""--gt auto widens the default window to this for a rig that stood still: a Mid-360's pattern keeps
filling the view, and nothing the rig does can smear it (bench_dense: 30 % -> 54 % density in the room)."""
AUTO_MAX_RESIDUAL_MM = 30.0
"""--gt auto uses dense GT when the trajectory's median knot residual is below this (mm)."""


def choose_method(asked: str, summary: TrajectorySummary | None, failure: str = "") -> tuple[str, str]:
    """(method, decision) for `--gt asked`: sparse/dense as asked; auto from the trajectory's quality.

    auto takes dense GT when the odometry's registered knots have a median
    residual below `AUTO_MAX_RESIDUAL_MM`, over at least the
    `OdometryParams.refine_start_s` after which the start is solved again
    (before that its first knots are a constant-velocity guess, centimetres
    off for a handheld rig that moves); otherwise sparse GT, which needs no
    trajectory. Knots in LiDAR gaps (carried by prediction alone) do not
    decide for the recording: the frames among them get sparse GT
    (`SampleParams.gap_fallback`).
    """
    if asked != "auto":
        return asked, "asked"
    if summary is None:
        return "sparse", f"auto: no trajectory ({failure})"
    refine_s = OdometryParams().refine_start_s
    if summary.span_s < refine_s and not summary.static:  # standing still, the guess is right
        return "sparse", (
            f"auto: trajectory spans {summary.span_s:.2f} s, under the {refine_s:g} s after which its start "
            "is solved again"
        )
    if not summary.residual_median_mm <= AUTO_MAX_RESIDUAL_MM:
        median = summary.residual_median_mm
        return "sparse", f"auto: trajectory residual median {median:.1f} mm > {AUTO_MAX_RESIDUAL_MM:g} mm"
    decision = f"auto: trajectory residual median {summary.residual_median_mm:.2f} mm, {summary.knots} knots"
    if summary.gaps:
        decision += f"; {summary.gaps} in LiDAR gaps: frames there get sparse GT"
    return "dense", decision
