"""Ingest applies each camera's clock offset (the rig's timeshift_cam_imu) and records it, against the
simulator's exact truth: a camera stamped 15 ms late, ingested with and without the offset."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader

from calibration.rig import read_rig, with_timeshifts, write_rig
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from sensorbox.sim.config import SimConfig
from sensorbox.sim.run import simulate
from sensorbox.sim.score import score_dataset
from sensorbox.sim.truth import Truth

OFFSET_NS = 15_000_000


@pytest.fixture(scope="module")
def late_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """0.8 s of noise-free outdoor walking whose cameras stamp each frame 15 ms after its exposure."""
    out = tmp_path_factory.mktemp("late") / "walk"
    cfg = SimConfig(
        scene="outdoor", trajectory="walk", duration_s=0.8, scale=0.15, range_noise_m=0.0, seed=5,
        camera_offset_ns=(OFFSET_NS, OFFSET_NS),
    )  # fmt: skip
    simulate(cfg, out)
    return out


def _median_error_mm(out: Path, truth: Truth) -> float:
    return float(np.median([s.depth_median_abs_m for s in score_dataset(out, truth)])) * 1e3


def test_the_rigs_timeshift_puts_the_gt_at_the_exposure_and_meta_keeps_the_stamp(
    late_bag: Path, tmp_path: Path
) -> None:
    truth = Truth.load(late_bag)
    exact_rig = truth.path / "rig.yaml"
    assert read_rig(exact_rig).upper.timeshift_ns == -OFFSET_NS
    plain_rig = tmp_path / "rig" / "plain.yaml"
    plain_rig.parent.mkdir()
    rig = read_rig(exact_rig)
    write_rig(with_timeshifts(rig, {c.name: 0.0 for c in rig.cameras}), plain_rig)  # stamps = exposures
    ingest([late_bag], IngestConfig(rig=exact_rig, out=tmp_path / "shifted", workers=1))
    ingest([late_bag], IngestConfig(rig=plain_rig, out=tmp_path / "plain", workers=1))

    shifted_mm = _median_error_mm(tmp_path / "shifted", truth)
    plain_mm = _median_error_mm(tmp_path / "plain", truth)
    assert shifted_mm < 2.0, shifted_mm
    assert plain_mm > 5 * shifted_mm, (plain_mm, shifted_mm)

    metas = [json.loads(p.read_text()) for p in sorted((tmp_path / "shifted" / "meta").glob("*.json"))]
    assert len(metas) >= 10
    for m in metas:
        assert m["exposure_ns"] == m["stamp_ns"] - OFFSET_NS
        assert m["clock_offset_ms"] == -15.0
    with AnyReader([late_bag]) as reader:  # meta's stamp_ns is the upper camera's header stamp as recorded
        conns = [c for c in reader.connections if c.topic == truth.rig.upper.topic]
        stamps = set()
        for conn, _, raw in reader.messages(connections=conns):
            msg: Any = reader.deserialize(raw, conn.msgtype)
            header = msg.header.stamp
            stamps.add(header.sec * 10**9 + header.nanosec)
    assert {m["stamp_ns"] for m in metas} <= stamps
    doc = yaml.safe_load((tmp_path / "shifted" / "dataset.yaml").read_text())
    offsets = doc["rig"]["camera_clock_offsets"]
    assert offsets["cam0"]["timeshift_cam_imu_ms"] == pytest.approx(-15.0)
    assert offsets["cam0"]["from"] == f"timeshift_cam_imu in {truth.path / 'camchain.yaml'}"
    plain = yaml.safe_load((tmp_path / "plain" / "dataset.yaml").read_text())
    assert plain["rig"]["camera_clock_offsets"]["cam1"]["timeshift_cam_imu_ms"] == 0.0
