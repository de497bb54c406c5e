"""Issue 49 (F15): `stats` and `eval` refuse a device or FIFO (or a link to one) where a file or folder
belongs, one line naming the path and what it is, exit 2, before a byte is read.

A depth map linked to /dev/zero was "cannot be decoded (0 bytes: empty, cut
short or not an image)", a dataset root linked to it "is a file", a
prediction linked to it was skipped as missing (`.png`) or misread (`.npy`),
and a FIFO in a prediction's place waited forever.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from ingest.dataset.layout import DEPTH_SCALE
from ingest.dataset.png import encode_png
from tests.faults.cli import sensorbox

ZERO = "a character device (a link to /dev/zero)"


def _dataset(root: Path) -> Path:
    """A train-layout dataset of two 8x8 samples (depth in mm, a grey image each)."""
    for folder in ("depth_fisheye", "left_fisheye"):
        (root / folder).mkdir(parents=True)
    depth_mm = np.full((8, 8), 2.5 * DEPTH_SCALE, np.uint16)
    for sid in ("000000", "000001"):
        (root / "depth_fisheye" / f"{sid}.png").write_bytes(encode_png(depth_mm))
        (root / "left_fisheye" / f"{sid}.png").write_bytes(encode_png(np.zeros((8, 8), np.uint8)))
    return root


def _zero_link(path: Path) -> Path:
    path.unlink(missing_ok=True)
    path.symlink_to("/dev/zero")
    return path


def _fifo(path: Path) -> Path:
    path.unlink(missing_ok=True)
    os.mkfifo(path)
    return path


def test_stats_refuses_a_depth_map_an_image_or_a_dataset_yaml_linked_to_a_device(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cases: list[tuple[str, Callable[[Path], Path], str]] = [
        ("depth_fisheye/000001.png", _zero_link,
         f"is {ZERO}, not a PNG image file; ground truth must be a 16-bit single-channel PNG"),
        ("left_fisheye/000001.png", _zero_link, f"is {ZERO}, not a PNG image file"),
        ("left_fisheye/000001.png", _fifo, "is a FIFO (named pipe), not a PNG image file"),
        ("dataset.yaml", _zero_link, f"is {ZERO}, not a dataset description file"),
    ]  # fmt: skip
    for i, (name, make, what) in enumerate(cases):
        ds = _dataset(tmp_path / f"ds{i}")
        bad = make(ds / name)
        code, _, err = sensorbox(capsys, "stats", str(ds))
        assert (code, err) == (2, [f"error: {bad}: {what}"]), name
        assert not (ds / "stats.json").exists()


def test_stats_and_eval_refuse_a_dataset_or_prediction_folder_linked_to_a_device(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    link = _zero_link(tmp_path / "link")
    code, _, err = sensorbox(capsys, "stats", str(link))
    assert (code, err) == (2, [f"error: {link}: is {ZERO}; expected a dataset folder"])
    ds = _dataset(tmp_path / "ds")
    code, _, err = sensorbox(capsys, "eval", "--dataset", str(ds), "--pred", str(link), "--task", "mono")
    assert (code, err) == (2, [f"error: --pred {link}: is {ZERO}; expected a folder of predictions"])


@pytest.mark.parametrize(
    ("ext", "make", "what"),
    [
        (".png", _zero_link, f"is {ZERO}, not a PNG image file"),
        (".npy", _zero_link, f"is {ZERO}, not a .npy prediction file"),
        (".exr", _zero_link, f"is {ZERO}, not a .exr prediction file"),
        (".png", _fifo, "is a FIFO (named pipe), not a PNG image file"),
        (".npy", _fifo, "is a FIFO (named pipe), not a .npy prediction file"),
    ],
)
def test_eval_refuses_a_prediction_that_is_a_device_or_fifo(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], ext: str, make: Callable[[Path], Path], what: str
) -> None:
    ds = _dataset(tmp_path / "ds")
    pred = tmp_path / "pred" / "depth_fisheye"
    pred.mkdir(parents=True)
    np.save(pred / "000000.npy", np.full((8, 8), 2.5, np.float32))
    bad = make(pred / f"000001{ext}")
    code, _, err = sensorbox(
        capsys, "eval", "--dataset", str(ds), "--pred", str(pred.parent), "--task", "mono"
    )
    assert (code, err) == (2, [f"error: {bad}: {what}"])


def test_a_sample_name_with_a_newline_stays_on_the_warning_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 3: meta/'00000\\n5.json' split stats' missing-depth warning into two lines."""
    root = _dataset(tmp_path / "ds")
    (root / "meta").mkdir()
    (root / "meta" / "000000.json").write_text("{}")
    (root / "meta" / "00000\n5.json").write_text("{}")
    code, _, err = sensorbox(capsys, "stats", str(root), "--out", str(tmp_path / "st"))
    assert (code, err) == (
        0,
        [
            f"warning: {root}: 1 finished sample(s) (meta/<id>.json) have no depth map (depth_fisheye/<id>.png), "
            "left out of these statistics: '00000\\n5'"
        ],
    )
