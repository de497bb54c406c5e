"""The trajectory pass's segments as jobs of the run's executor (`ingest.train.trajectory.segments`).

A job names its segment's point times and the log times of its sweeps; the
worker opens the bags itself (`open_bags` at the paths the run was given,
so with `--dask` every worker must reach them there) and runs the odometry
over that stretch. Only the knots come back.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

from calibration.types import I64
from ingest.bags.reader import open_bags
from ingest.errors import BagError, OdometryError
from ingest.runtime.executor import Executor
from ingest.train.bad_messages import BadMessages
from ingest.train.run.settings import IngestConfig
from ingest.train.trajectory.estimate import trajectory_pass
from ingest.train.trajectory.local_map import OdometryParams
from ingest.train.trajectory.segments import SegmentInputs, SegmentJob, SegmentResult, Split, plan_segments


def run_segment(inputs: SegmentInputs, job: SegmentJob) -> SegmentResult:
    """One segment's odometry, in a worker: the bags opened here, the segment's sweeps read; its knots, or
    the odometry's error line (`SegmentResult.failure`).

    The plan pass has decoded every sweep and counted the undecodable and
    dropped ones; this read's own count is not kept.
    """
    cpu0 = time.process_time()
    bad = BadMessages(limit=2**62)
    try:
        with open_bags(list(inputs.bag_paths), salvage=inputs.salvage) as bags:
            traj = trajectory_pass(
                bags, dict(inputs.lidar_topics), inputs.rig, inputs.gyro, inputs.min_range_m,
                inputs.params, bad=bad, span_ns=job.span_ns, log_ns=job.log_ns, start_ns=job.start_ns,
            )  # fmt: skip
    except OdometryError as err:
        empty = np.zeros(0)
        return SegmentResult(
            job.span_ns, empty.astype(np.int64), np.zeros((0, 3, 3)), np.zeros((0, 3)), empty, str(err),
            time.process_time() - cpu0,
        )  # fmt: skip
    except BagError as err:  # a Dask worker on another machine
        raise BagError(f"a worker running the trajectory pass cannot read the bags: {err}") from err
    cpu = time.process_time() - cpu0
    return SegmentResult(
        job.span_ns, traj.stamps_ns, traj.R_world_cam0, traj.p_world_cam0, traj.residual_m, "", cpu
    )


def segment_runner(
    executor: Executor, progress: Callable[[int, int], None] | None = None
) -> Callable[[SegmentInputs, list[SegmentJob]], list[SegmentResult]]:
    """`Split.run_jobs` on `executor`: every job of a round submitted at once, results in order;
    `progress(done, total)` after each job of the round."""

    def run_jobs(inputs: SegmentInputs, jobs: list[SegmentJob]) -> list[SegmentResult]:
        out = []
        for result in executor.run(run_segment, jobs, shared=inputs):
            out.append(result)
            if progress is not None:
                progress(len(out), len(jobs))
        return out

    return run_jobs


def trajectory_split(
    bag_paths: Sequence[Path],
    cfg: IngestConfig,
    executor: Executor,
    sweeps: Mapping[str, I64],
    span_ns: tuple[int, int],
    progress: Callable[[int, int], None] | None = None,
) -> Split | None:
    """The trajectory pass as segments on `executor` (`ingest.train.trajectory.segments`), or None for the
    single pass in this process: sparse GT, one worker (`--workers 1`, inline), or LiDAR points within
    `span_ns` spanning no more than one segment (`IngestConfig.trajectory_segments`).

    `sweeps`: per LiDAR topic, the plan pass's (log ns, first, last point
    ns) of every sweep; `progress(done, total)` hears of the segments' jobs.
    """
    if cfg.gt == "sparse" or executor.backend == "inline":
        return None
    held = [v for v in sweeps.values() if len(v)]
    if not held:
        return None
    lo = max(span_ns[0], min(int(v[:, 1].min()) for v in held))
    hi = min(span_ns[1], max(int(v[:, 2].max()) for v in held))
    segments = plan_segments((lo, hi), cfg.trajectory_segments, OdometryParams().knot_ns)
    if len(segments) < 2:
        return None
    paths = tuple(Path(p) for p in bag_paths)
    return Split(
        segments, cfg.trajectory_segments, sweeps, paths, cfg.salvage, segment_runner(executor, progress)
    )
