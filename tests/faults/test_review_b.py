"""Fault-injection review B: each finding as a user meets it, one line and the files left behind.

Full disks are injected as in test_output_errors (`_fill_disk_at`: half the
bytes land, then ENOSPC); sqlite3's "database or disk is full" by the
writer's own exception. Nothing here needs root.
"""

from __future__ import annotations

import errno
import sqlite3
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Writer

from ingest.errors import OutputError
from sensorbox.cli.main import main
from tests.faults.cli import sensorbox
from tests.faults.test_output_errors import ENOSPC, RIG, _files, _fill_disk_at
from tests.ingest.test_evaluate import make_benchmark, write_predictions

SIM = ["--duration", "0.2", "--scale", "0.1"]


CAPTURE = ["capture", "--rig", str(RIG), "--emulate", "--scale", "0.25"]


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--jpeg-quality", "0"], "--jpeg-quality 0: expected 1..100"),
        (["--duration", "-1"], "--duration -1: expected a finite number >= 0, in seconds (0 = until Ctrl-C)"),
        (["--split-size", "-5"], "--split-size -5: expected a finite number >= 0, in MiB (0 = never split)"),
        (["--min-free", "nan"], "--min-free nan: expected a finite number >= 0, in MiB"),
        (["--name", "a/b"], "--name 'a/b': use letters, digits and _ . + - only (a folder name)"),
        (["--scale", "0"], "--scale 0: expected a number > 0 (0.25 -> 480x300)"),
    ],
)
def test_capture_options_are_checked_before_anything_is_written(
    option: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The rig was copied into --out first, and the error blamed the rig file or named split_bytes."""
    out = tmp_path / "c2"
    code, _, err = sensorbox(capsys, *CAPTURE, "--out", str(out), *option)
    assert (code, err) == (2, [f"error: {message}"])
    assert not out.exists()


def _sensorbox_fd(capfd: pytest.CaptureFixture[str], *args: str) -> tuple[int, list[str]]:
    """`sensorbox ARGS` in this process with file descriptors 1 and 2 captured: what C libraries print too."""
    argv, sys.argv = sys.argv, ["sensorbox", *args]
    try:
        main()
        code = 0
    except SystemExit as done:
        code = int(done.code or 0)
    finally:
        sys.argv = argv
    return code, capfd.readouterr().err.splitlines()


@pytest.mark.parametrize("damage", ["cut", "flip"])
def test_a_damaged_ground_truth_png_is_our_one_line_only(
    damage: str, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """OpenCV's `[ WARN:0@0.8] ... PNG input buffer is incomplete` or `libpng error: ...` came first."""
    bench = make_benchmark(tmp_path / "bench")
    gt = sorted(bench.rglob("depth/*.png"))[0]
    data = bytearray(gt.read_bytes())
    if damage == "cut":
        data = data[: len(data) // 2]
    else:
        idat = data.index(b"IDAT") + 4
        data[idat + 2] ^= 0x10  # inside the zlib stream: libpng reads bad rows before it checks the CRC
    pred = tmp_path / "pred"
    write_predictions(bench, pred, "mono", view="fisheye")  # from the GT while it is whole
    gt.write_bytes(bytes(data))
    capfd.readouterr()
    for args in (
        ["stats", str(bench), "--out", str(tmp_path / "s")],
        [
            "eval",
            "--dataset",
            str(bench),
            "--pred",
            str(pred),
            "--task",
            "mono",
            "--json",
            str(tmp_path / "e.json"),
        ],
    ):
        code, err = _sensorbox_fd(capfd, *args)
        assert (code, err) == (
            2,
            [
                f"error: {gt}: cannot be decoded ({len(data)} bytes: empty, cut short or not an image)"
                + "; ground truth must be a 16-bit single-channel PNG"
            ],
        ), err
