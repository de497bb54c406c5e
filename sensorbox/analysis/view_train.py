"""`sensorbox view` of a training set (`sensorbox ingest`): each sample's images, GT, rig pose and
meta numbers on the timelines `time` and `sample`, and the layout of the viewer's panels."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from calibration import read_rig
from ingest.errors import DatasetError

if TYPE_CHECKING:
    import rerun as rr

from sensorbox.analysis.view_files import (
    F64,
    SAMPLE_ID,
    TIMELINE_SAMPLE,
    TIMELINE_TIME,
    TRAIN_GT,
    TRAIN_IMAGES,
    Logger,
    Progress,
    ViewSummary,
    meta_scalars,
    pose_at,
    read_json,
    read_tum,
    rerun_transform,
    sample_time_ns,
)


def _train_ids(root: Path) -> list[str]:
    """Sample ids of the finished samples (their `meta/<id>.json`, written last), in order."""
    return sorted((p.stem for p in (root / "meta").glob("*.json") if SAMPLE_ID.match(p.stem)), key=int)


def _log_rig(log: Logger, root: Path) -> None:
    """The rig of `root/rig/rig.yaml` as static frames under world/rig (= cam0)."""
    rig_file = root / "rig" / "rig.yaml"
    if not rig_file.is_file():
        return
    rig = read_rig(rig_file)
    rr_mod, rec = log.rr, log.rec
    rec.log("world/rig", rr_mod.TransformAxes3D(0.1), static=True)
    frames: list[tuple[str, F64]] = [(c.name, c.T_cam0_cam) for c in rig.cameras if c.name != "cam0"]
    frames += [(lidar.name, lidar.T_cam0_lidar) for lidar in rig.lidars]
    frames += [(imu.name, imu.T_cam0_imu) for imu in rig.imus]
    for name, T in frames:
        entity = rr_mod.new_entity_path(["world", "rig", name])
        rec.log(
            entity,
            rerun_transform(rr_mod, np.asarray(T, np.float64)),
            rr_mod.TransformAxes3D(0.05),
            static=True,
        )
        log.summary.frames += 1


def _trajectories(log: Logger, root: Path) -> dict[str, tuple[np.ndarray[Any, np.dtype[np.int64]], F64]]:
    """Every `trajectories/<bag>.tum`, by bag name, logged as static lines of cam0's positions."""
    found: dict[str, tuple[np.ndarray[Any, np.dtype[np.int64]], F64]] = {}
    for path in sorted((root / "trajectories").glob("*.tum")):
        stamps, T = read_tum(path)
        found[path.stem] = (stamps, T)
        entity = log.rr.new_entity_path(["world", "trajectory", path.stem])
        log.rec.log(entity, log.rr.LineStrips3D([T[:, :3, 3]]), static=True)
    return found


def log_train(
    rec: rr.RecordingStream, root: Path, max_side_px: int | None, progress: Progress | None
) -> ViewSummary:
    """Every finished sample of a train-layout dataset onto `rec` (module doc); returns what was logged."""
    summary = ViewSummary(layout="train")
    log = Logger(rec, summary, max_side_px)
    ids = _train_ids(root)
    if not ids:
        raise DatasetError(f"{root}: no finished sample (meta/<id>.json); nothing to view")
    _log_rig(log, root)
    trajectories = _trajectories(log, root)
    for n, sid in enumerate(ids):
        meta_path = root / "meta" / f"{sid}.json"
        meta = read_json(meta_path)
        t_ns = sample_time_ns(meta, meta_path)
        rec.set_time(TIMELINE_TIME, timestamp=np.datetime64(t_ns, "ns"))
        rec.set_time(TIMELINE_SAMPLE, sequence=int(sid))
        for folder, entity in TRAIN_IMAGES.items():
            log.colour(entity, root / folder / f"{sid}.png", root)
        for folder, (entity, scale) in TRAIN_GT.items():
            log.depth(entity, root / folder / f"{sid}.png", root, scale)
        log.scalars("meta", meta_scalars(meta))
        bag = meta.get("source_bag")
        pose = pose_at(*trajectories[bag], t_ns) if isinstance(bag, str) and bag in trajectories else None
        if pose is None:
            summary.off_trajectory += 1
        else:
            rec.log("world/rig", rerun_transform(log.rr, pose))
            summary.poses += 1
        summary.samples += 1
        if progress is not None:
            progress(n + 1, len(ids))
    _send_train_blueprint(log)
    return summary


def train_layout(series: Iterable[str]) -> list[tuple[str, list[str]]]:
    """The time-series panels of the train layout's default viewer layout: (title, entity paths) of the
    numbers a bad stretch shows in first, from the series logged; every other series stays one click
    away in the viewer's entity tree."""
    logged = sorted(series)
    picks = (
        ("GT density", lambda e: e == "/meta/gt/density"),
        (
            "misalignment per LiDAR (shift_deg)",
            lambda e: e.startswith("/meta/alignment/") and e.endswith("/shift_deg"),
        ),
        ("points per filter", lambda e: e.startswith("/meta/points/")),
        (
            "motion and trajectory residual",
            lambda e: e in ("/meta/motion/predicted_motion_px", "/meta/gt/trajectory_residual_mm"),
        ),
    )
    panels = [(title, [e for e in logged if keep(e)]) for title, keep in picks]
    return [(title, entities) for title, entities in panels if entities]


def _send_train_blueprint(log: Logger) -> None:
    """The default layout of a train recording: cam0 with its GT depth over it, cam1, the equirects
    with the disparity over the upper one, the rig in 3D and the panels of `train_layout`."""
    import rerun.blueprint as rrb

    images = rrb.Grid(
        rrb.Spatial2DView(origin="cam0", name="cam0 + GT depth"),
        rrb.Spatial2DView(origin="cam1", name="cam1"),
        rrb.Spatial2DView(
            origin="equirect", contents=["equirect/up", "equirect/disparity"], name="equirect up + disparity"
        ),
        rrb.Spatial2DView(origin="equirect/down_virt", name="equirect down (virtual)"),
    )
    charts = [
        rrb.TimeSeriesView(origin="/", contents=entities, name=title)
        for title, entities in train_layout(log.summary.series)
    ]
    rig = rrb.Spatial3DView(origin="world", name="rig and trajectory")
    right = rrb.Vertical(rig, *charts, row_shares=[2.0] + [1.0] * len(charts))
    log.rec.send_blueprint(
        rrb.Blueprint(
            rrb.Horizontal(images, right, column_shares=[3, 2]), auto_views=False, collapse_panels=True
        )
    )
