"""A finished trajectory pass kept beside the dataset (`trajectories/<bag>.npz`).

A rerun into the same output (resuming after a crash, Ctrl-C or a full disk)
would otherwise repeat the odometry, which takes about as long as the
recording. The file is used only when everything the pass read and ran is
the same: the bags (`bag_identity`), the LiDAR topics with their poses in
the rig, the IMU topic and pose, the minimum range, the odometry's
parameters, the time span, how it was split into segments (`segments`),
and the code (a digest of the `ingest` and
`calibration` packages' sources, so that a new version computes it again).
Anything else, or a file that cannot be read, means the pass runs again.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from dataclasses import asdict
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from calibration.rig import Rig
from calibration.types import F64
from ingest.bags.reader import BagSet
from ingest.dataset.identity import bag_identity
from ingest.dataset.layout import write_atomic
from ingest.train.trajectory.clouds import GyroTrack
from ingest.train.trajectory.local_map import OdometryParams
from ingest.train.trajectory.rig_trajectory import RigTrajectory
from ingest.train.trajectory.segments import Split, SplitSummary

_PACKAGES = (Path(__file__).resolve().parents[1], Path(__file__).resolve().parents[2] / "calibration")


@cache
def code_digest() -> str:
    """sha256 over the sources of the packages the trajectory pass runs (file names and bytes)."""
    digest = hashlib.sha256()
    for package in _PACKAGES:
        for path in sorted(package.rglob("*.py")):
            digest.update(path.relative_to(package.parent).as_posix().encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()


def cache_key(
    bags: BagSet,
    lidar_topics: dict[str, str],
    imu: tuple[str | None, F64 | None],
    rig: Rig,
    min_range_m: float,
    params: OdometryParams,
    span_ns: tuple[int, int] | None,
    split: Split | None = None,
) -> str:
    """What decides the pass's result, as one JSON string (floats exact: json writes their repr); a single
    pass's key has no "segments"."""
    doc: dict[str, Any] = {
        "bags": [bag_identity(Path(p)) for p in bags.paths],
        "lidars": {topic: rig.lidar(name).T_cam0_lidar.tolist() for topic, name in lidar_topics.items()},
        "imu": [imu[0], None if imu[1] is None else np.asarray(imu[1]).tolist()],
        "min_range_m": min_range_m,
        "params": asdict(params),
        "span_ns": None if span_ns is None else [int(span_ns[0]), int(span_ns[1])],
        "code": code_digest(),
    }
    if split is not None:
        doc["segments"] = [[int(a), int(b)] for a, b in split.segments]
    return json.dumps(doc, sort_keys=True)


def load(path: Path, key: str) -> RigTrajectory | None:
    """The trajectory kept in `path` under `key`; None when there is none, or another, or it is unreadable."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return None
            gyro = GyroTrack(z["gyro_stamps_ns"], z["gyro_rotations"]) if "gyro_stamps_ns" in z else None
            return RigTrajectory(z["stamps_ns"], z["R_world_cam0"], z["p_world_cam0"], z["residual_m"], gyro)
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None


def split_of(path: Path) -> SplitSummary | None:
    """The record of the split pass kept in `path` (`save`), None for a single pass or an unreadable one."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return SplitSummary.from_dict(json.loads(str(z["split"]))) if "split" in z else None
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile):
        return None


def save(path: Path, key: str, traj: RigTrajectory, split: SplitSummary | None = None) -> None:
    """Keep `traj` in `path` under `key` (atomically: a killed run leaves the old file or none), with the
    record of its split pass (`split_of`)."""
    arrays: dict[str, Any] = {
        "key": np.array(key),
        "stamps_ns": traj.stamps_ns,
        "R_world_cam0": traj.R_world_cam0,
        "p_world_cam0": traj.p_world_cam0,
        "residual_m": traj.residual_m,
    }
    if split is not None:
        arrays["split"] = np.array(json.dumps(split.as_dict()))
    if traj.gyro is not None:
        arrays |= {"gyro_stamps_ns": traj.gyro.stamps_ns, "gyro_rotations": traj.gyro.rotations}
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    write_atomic(path, buf.getvalue())
