"""Issue 49: ground truth that holds nothing is said, and the density describes the PNGs as written.

Points all NaN, all zero or all tagged as noise leave every sample without a
GT pixel: one warning line counts the samples and their points by filter.
Points 30 times as far (an indoor room at 30-300 m) have ranges the depth PNG
(uint16 mm, up to 65.535 m) cannot hold: the meta's pixel counts and density,
and the summary's, are those of the written PNGs.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from calibration.rig import read_rig
from ingest.bags.livox_msg import decode_custom_msg, encode_custom_msg
from ingest.dataset.layout import DEPTH_SCALE, read_png_u16
from ingest.dataset.meta import read_meta
from ingest.train.plausible import NOISE_TAG_BITS
from ingest.train.run.pipeline import ingest
from ingest.train.run.sample_job import Geometry
from ingest.train.run.settings import IngestConfig
from sensorbox.sim.truth import truth_dir
from tests.faults.bags import INDOOR, LIDAR_BOTTOM, LIDAR_TOP, rewrite

FAST = {"workers": 1, "every": 3, "height_full": 64}


def _all_points(change: Callable[[Any], None]) -> Callable[[str, int, bytes], list[tuple[str, bytes]]]:
    def keep(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic not in (LIDAR_TOP, LIDAR_BOTTOM):
            return [(topic, raw)]
        msg = decode_custom_msg(raw)
        pts = msg.points.copy()
        change(pts)
        return [(topic, encode_custom_msg(msg.stamp_ns, msg.frame_id, msg.timebase_ns, pts, msg.lidar_id))]

    return keep


def _nan(pts: Any) -> None:
    pts["x"] = np.nan


def _zero(pts: Any) -> None:
    for c in "xyz":
        pts[c] = 0.0


def _noise(pts: Any) -> None:
    pts["tag"] = 0b0001_0000  # the "other" field: medium confidence
    assert pts["tag"][0] & NOISE_TAG_BITS


@pytest.mark.parametrize(("change", "why"), [(_nan, "non-finite"), (_zero, "zero"), (_noise, "noise-tagged")])
def test_samples_without_any_gt_pixel_are_one_warning_with_their_points_by_filter(
    tmp_path: Path, change: Callable[[Any], None], why: str
) -> None:
    bag, rig = rewrite(tmp_path / "bag", _all_points(change))
    out = tmp_path / "ds"
    summary = ingest([bag], IngestConfig(rig=rig, out=out, **FAST))  # type: ignore[arg-type]
    metas = [read_meta(out, p.stem) for p in sorted((out / "meta").glob("*.json"))]
    assert summary.written == len(metas) == 7
    total = sum(m.points.total for m in metas)
    assert total > 100_000 and all(m.gt.depth_pixels == 0 for m in metas)
    assert summary.warnings[-1] == (
        f"7 of 7 samples written hold no ground truth pixel; their windows' LiDAR points: {total:,} "
        f"({total:,} {why})"
    )


def test_the_density_is_that_of_the_written_depth_png(tmp_path: Path) -> None:
    def farther(pts: Any) -> None:
        for c in "xyz":
            pts[c] *= 30

    bag, rig = rewrite(tmp_path / "bag", _all_points(farther))
    out = tmp_path / "ds"
    summary = ingest([bag], IngestConfig(rig=rig, out=out, **FAST))  # type: ignore[arg-type]
    assert summary.written == 7
    valid_px = Geometry.from_rig(read_rig(rig), FAST["height_full"]).fisheye_valid_px
    over, densities = 0, []
    for p in sorted((out / "meta").glob("*.json")):
        meta = read_meta(out, p.stem)
        written = int(np.count_nonzero(read_png_u16(out / "depth_fisheye" / f"{p.stem}.png", DEPTH_SCALE)))
        assert meta.gt.depth_pixels == written
        assert meta.gt.density == pytest.approx(written / valid_px, rel=1e-12)
        over += meta.dropped["depth_over_uint16"]
        densities.append(meta.gt.density)
    assert over > 1000  # ranges beyond 65.535 m were computed, and left out of the PNG and the counts
    assert summary.density == densities


def test_points_outside_the_imus_span_are_counted_and_the_counts_add_up(tmp_path: Path) -> None:
    """The rig's IMU stops at 0.3 s: points of later windows have no known rotation and are left out,
    counted (they were taken off `kept` with every filter's counter at 0)."""
    imu = "/livox/imu_192_168_1_12"

    def imu_stops(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        return [] if topic == imu and k >= 60 else [(topic, raw)]

    bag, rig = rewrite(tmp_path / "bag", imu_stops)
    out = tmp_path / "ds"
    summary = ingest([bag], IngestConfig(rig=rig, out=out, workers=1, every=1, height_full=64))
    assert summary.written > 10
    points = [read_meta(out, p.stem).points for p in sorted((out / "meta").glob("*.json"))]
    for p in points:
        assert p.total == p.zero + p.non_finite + p.too_close + p.noise_tag + p.off_imu + p.kept
    assert sum(p.off_imu > 0 for p in points) >= 1


def test_samples_with_depth_but_no_disparity_gt_are_one_warning(tmp_path: Path) -> None:
    """Sweep 6: at `--height-full 64` every sample's disparity PNG held no valid pixel, without a word (96
    rows keep some, 128 thousands)."""
    rig = truth_dir(INDOOR) / "rig.yaml"
    coarse = ingest([INDOOR], IngestConfig(rig=rig, out=tmp_path / "64", gt="sparse", **FAST))  # type: ignore[arg-type]
    disp = sorted((tmp_path / "64" / "disp_equirect").glob("*.png"))
    assert coarse.written == len(disp) > 0
    assert all(not np.asarray(cv2.imread(str(p), cv2.IMREAD_UNCHANGED)).any() for p in disp)
    assert [w for w in coarse.warnings if "disparity" in w] == [
        f"{coarse.written} of {coarse.written} samples written hold depth GT but no disparity GT pixel: the "
        "equirect pair is too coarse for the baseline's disparity (more --height-full rows keep it: 128 and up)"
    ]
    finer = {**FAST, "height_full": 128}
    fine = ingest([INDOOR], IngestConfig(rig=rig, out=tmp_path / "128", gt="sparse", **finer))  # type: ignore[arg-type]
    assert fine.without_disparity == 0 and not any("disparity" in w for w in fine.warnings)
