"""The ingest preview: images shrunk for the figure, sparse GT still visible and with its value."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sensorbox.analysis.plots import PREVIEW_WIDTH_PX, _shrunk


def test_a_single_gt_pixel_survives_the_shrinking_with_its_value() -> None:
    h, w = 1200, 2 * PREVIEW_WIDTH_PX + 50  # shrinks by 3
    image = np.full((h, w, 3), 100, np.uint8)
    gt = np.zeros((h, w), np.float32)
    gt[777, 1000] = 5.25
    gt[10, 9], gt[10, 10] = 2.0, 9.0  # in one 3x3 block: its largest value is kept
    small, small_gt = _shrunk(image, gt)
    assert small.shape == (h // 3, w // 3, 3) and small_gt is not None and small_gt.shape == (h // 3, w // 3)
    assert np.count_nonzero(small_gt == np.float32(5.25)) == 1
    assert set(np.unique(small_gt).tolist()) == {0.0, 5.25, 9.0}
    assert (small == 100).all()


def test_small_images_are_drawn_as_they_are() -> None:
    image = np.zeros((300, 480, 3), np.uint8)
    gt = np.ones((300, 480), np.float32)
    small, small_gt = _shrunk(image, gt)
    assert small is image and small_gt is gt


def test_no_preview_writes_the_dataset_and_no_figure(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from tests.faults.cli import sensorbox
    from tests.ingest.test_pipeline import INDOOR, _rig

    out = tmp_path / "ds"
    args = ["ingest", str(INDOOR), "--rig", str(_rig(INDOOR)), "--out", str(out), "--workers", "1"]
    code, stdout, _ = sensorbox(
        capsys, *args, "--every", "10", "--height-full", "64", "--no-preview", "--gt", "sparse"
    )
    assert code == 0 and "Preview" not in stdout
    assert len(list((out / "meta").glob("*.json"))) == 3 and not (out / "preview.png").exists()
