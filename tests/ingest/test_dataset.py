"""Dataset files: atomic writes, GT that does not fit its uint16 PNG."""

import json
import stat

import numpy as np
import OpenEXR
import pytest

from ingest.dataset.layout import SampleFiles, prepare_dirs, write_atomic, write_sample
from ingest.dataset.meta import GtMeta, MotionMeta, PointMeta, SampleMeta
from ingest.dataset.png import read_image
from ingest.dataset.sparse import SparseImage


def test_written_files_are_readable_by_others_and_no_temporary_is_left(tmp_path):
    path = tmp_path / "000000.png"
    write_atomic(path, b"abc")
    assert path.read_bytes() == b"abc"
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert sorted(p.name for p in tmp_path.iterdir()) == ["000000.png"]


def _meta() -> SampleMeta:
    return SampleMeta(
        stamp_ns=1, lower_stamp_ns=2, stereo_dt_ms=0.0, source_bag="bag", lidar_skew_ms={},
        motion=MotionMeta(False, "none", 0.0, 0.0, 0.0, None),
        points=PointMeta(0, 0, 0, 0, 0, 0, 0, 0), gt=GtMeta(3, 3, 0, 0.5),
    )  # fmt: skip


def test_gt_beyond_uint16_is_zero_in_the_png_counted_in_the_meta_and_kept_in_the_exr(tmp_path):
    """Ranges over 65.535 m and disparities over 655.35 px do not fit the uint16 PNGs: those pixels
    are 0 there, each is counted in the sample's meta, and the EXRs keep the value."""
    prepare_dirs(tmp_path, exr=True)
    shape = (2, 3)
    range_m = SparseImage(shape, np.array([0, 1, 4]), np.array([1.5, 65.535, 70.25], np.float32))
    disp_px = SparseImage(shape, np.array([2, 3, 5]), np.array([700.0, 655.35, 0.01], np.float32))
    image = np.full((*shape, 3), 7, np.uint8)
    files = SampleFiles(image, image, image, image, disp_px, range_m, _meta())
    drops = write_sample(tmp_path, "000000", files, exr=True)
    assert drops == {"disp_over_uint16": 1, "depth_over_uint16": 1}
    meta = json.loads((tmp_path / "meta" / "000000.json").read_text())
    assert meta["dropped"] == drops
    depth = read_image(tmp_path / "depth_fisheye" / "000000.png")
    disp = read_image(tmp_path / "disp_equirect" / "000000.png")
    assert depth is not None and depth.reshape(-1).tolist() == [1500, 65535, 0, 0, 0, 0]
    assert disp is not None and disp.reshape(-1).tolist() == [0, 0, 0, 65535, 0, 1]
    exr = OpenEXR.File(str(tmp_path / "depth_fisheye_exr" / "000000.exr")).channels()["Y"].pixels
    assert exr.reshape(-1).tolist() == pytest.approx([1.5, 65.535, 0, 0, 70.25, 0])


def test_a_difference_that_prints_alike_names_both_types() -> None:
    """Sweep 11: a hand-edited dataset.yaml with `height_full: '128'` was refused "(value: 128 -> 128)"."""
    from ingest.dataset.compare import first_difference

    assert first_difference({"height_full": "128"}, {"height_full": 128}) == (
        " (height_full: '128' (str) -> 128 (int))"
    )
    assert first_difference({"a": {"every": 5}}, {"a": {"every": 7}}) == " (a.every: 5 -> 7)"
    assert first_difference(128, 128.0) == ""  # equal values are no difference, whatever their types
