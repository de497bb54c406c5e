"""The run's ground-truth method: the trajectory pass where dense GT may need it, the IMU checked against
the LiDARs' odometry (`ingest.train.trajectory.imu_check`), and the run resolved from both.

`--gt dense/auto` run the trajectory pass over every sweep and check the IMU
against its knots; sparse GT checks it against the odometry of a few turning
seconds (`check_gyro`). An IMU that disagrees too far stops the run here,
before anything is written.
"""

from __future__ import annotations

from pathlib import Path

from calibration.rig import Rig
from ingest.bags.reader import BagSet, Progress
from ingest.errors import OdometryError
from ingest.train.bad_messages import BadMessages
from ingest.train.run.resolved import ResolvedRun, resolve_run
from ingest.train.run.settings import IngestConfig, Topics
from ingest.train.run.summary import IngestSummary
from ingest.train.trajectory.estimate import (
    STATIC_WINDOW_NS,
    GyroReadings,
    check_gyro,
    choose_method,
    run_trajectory_pass,
)
from ingest.train.trajectory.imu_check import no_imu_line
from ingest.train.trajectory.rig_trajectory import RigTrajectory
from ingest.train.trajectory.segments import Split


def dense_reach_ns(cfg: IngestConfig) -> int:
    """How far around a frame dense GT may read sweeps (0 for sparse GT): its window, or the wider one
    `--gt auto` may choose for a static rig."""
    if cfg.gt == "sparse":
        return 0
    if cfg.gt == "auto" and cfg.widen_static:
        return max(cfg.sample.dense.window_ns, STATIC_WINDOW_NS)
    return cfg.sample.dense.window_ns


def gt_method(
    bags: BagSet, topics: Topics, rig: Rig, cfg: IngestConfig, summary: IngestSummary, bad: BadMessages,
    trajectory_span_ns: tuple[int, int], busy: bool, progress: Progress | None = None,
    split: Split | None = None, gyro: GyroReadings | None = None,
) -> tuple[ResolvedRun, RigTrajectory | None]:  # fmt: skip
    """Run the trajectory pass when --gt dense/auto needs it (`progress`: its sweeps; `split`: in segments
    on the workers, `ingest.train.run.trajectory_jobs`; `gyro`: the IMU's readings as the survey kept
    them), decide the method: the run as resolved
    (`resolve_run`; `busy`: every core runs a worker) and the trajectory of a dense run.

    Dense GT streams every sweep within its window (`--gt-window-ms`); the
    trajectory goes to `trajectories/<first bag>.tum` in the output and
    spans `trajectory_span_ns` (`dense_reach_ns` around the upper camera's stamps).
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
                imu_name=topics.imu_name,
                split=split,
                readings=gyro,
            )
        except OdometryError as err:
            if cfg.gt == "dense":
                why = f"{bags.label}: {err}; dense GT needs a trajectory (--gt sparse does not)"
                raise OdometryError(why) from err
            failure = str(err)
    method, decision = choose_method(cfg.gt, tsum, failure)
    if tsum is not None:
        summary.imu_check = tsum.imu_check
    else:  # sparse GT: the IMU against the odometry of a few seconds of the recording
        imu = (topics.imu, topics.R_cam0_imu)
        summary.imu_check = check_gyro(
            bags, topics.lidars, imu, topics.imu_name, rig, cfg.sample.min_range_m, bad, gyro
        )
    if topics.imu is None:
        summary.warnings.append(no_imu_line(cfg.rig))
    said = summary.imu_check.line() if summary.imu_check is not None else None
    if said:
        summary.warnings.append(said)
    static = tsum is not None and tsum.static
    run = resolve_run(cfg, method, decision, static, busy)
    summary.method, summary.decision, summary.trajectory = method, run.sample.decision, tsum
    return run, traj if method == "dense" else None
