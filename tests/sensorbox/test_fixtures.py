"""The bundled fixture bags are what the simulator makes today (`make fixtures`).

Byte for byte on the CPU that made them. Another CPU renders through other
SIMD paths (numpy's and Embree's), which move a LiDAR coordinate by a float32
step (up to 7.6 um measured between an AMD EPYC and an Intel Xeon), a raw
pixel or a point's reflectivity by one level, and JPEG can turn the one level
into up to 14 in a few pixels. So points, reflectivities and pixels are
compared within those bounds, everything else (topics, types, log times,
stamps, per-point times, tags and lines, IMU messages, the truth files)
exactly: a change to the simulator moves far more.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ingest.bags.decode import Frame, Sweep, decode
from ingest.bags.message import RawMessage
from ingest.bags.reader import open_bags
from sensorbox.sim.fixtures import FIXTURES, fixture_bag, make_fixture
from sensorbox.sim.truth import truth_dir
from tests.cpu_bounds import JPEG_MEAN_LEVELS, JPEG_OFF_BY_3_SHARE, RAW_PIXEL_LEVELS, XYZ_TOLERANCE_M
from tests.paths import FIXTURES_DIR


def _decoded(m: RawMessage) -> object:
    return decode(m.msgtype, m.data(), m.ros_version)


def _assert_same_sweep(fresh: Sweep, stored: Sweep, where: str) -> None:
    assert (fresh.stamp_ns, fresh.frame_id, fresh.time_layout) == (
        stored.stamp_ns,
        stored.frame_id,
        stored.time_layout,
    ), where
    np.testing.assert_array_equal(fresh.stamps_ns, stored.stamps_ns, err_msg=where)
    for name, levels in (("reflectivity", RAW_PIXEL_LEVELS), ("tag", 0), ("line", 0)):
        a, b = getattr(fresh, name), getattr(stored, name)
        assert (a is None) == (b is None), (where, name)
        if a is not None:
            np.testing.assert_allclose(a.astype(np.int16), b, rtol=0, atol=levels, err_msg=f"{where} {name}")
    assert fresh.xyz_m.shape == stored.xyz_m.shape, where
    np.testing.assert_allclose(fresh.xyz_m, stored.xyz_m, rtol=0, atol=XYZ_TOLERANCE_M, err_msg=where)


def _assert_same_frame(fresh: Frame, stored: Frame, jpeg: bool, where: str) -> None:
    assert (fresh.stamp_ns, fresh.frame_id, fresh.image.shape) == (
        stored.stamp_ns,
        stored.frame_id,
        stored.image.shape,
    ), where
    diff = np.abs(fresh.image.astype(np.int16) - stored.image.astype(np.int16))
    if jpeg:
        assert diff.mean() <= JPEG_MEAN_LEVELS, (where, float(diff.mean()))
        assert (diff > 2).mean() <= JPEG_OFF_BY_3_SHARE, (where, float((diff > 2).mean()))
    else:
        assert diff.max() <= RAW_PIXEL_LEVELS, (where, int(diff.max()))


def assert_same_recording(fresh_bag: Path, stored_bag: Path) -> None:
    """The same messages in the same order; points and pixels within the CPU bounds above."""
    with open_bags(fresh_bag) as fresh, open_bags(stored_bag) as stored:
        a, b = list(fresh.messages()), list(stored.messages())
        assert [(m.topic, m.msgtype, m.log_ns) for m in a] == [(m.topic, m.msgtype, m.log_ns) for m in b]
        for x, y in zip(a, b, strict=True):
            raw_x, raw_y = bytes(x.data()), bytes(y.data())
            if raw_x == raw_y:
                continue
            where = f"{x.topic} at {x.log_ns}"
            dx, dy = _decoded(x), _decoded(y)
            if isinstance(dx, Sweep) and isinstance(dy, Sweep):
                _assert_same_sweep(dx, dy, where)
            elif isinstance(dx, Frame) and isinstance(dy, Frame):
                _assert_same_frame(dx, dy, x.msgtype.endswith("CompressedImage"), where)
            else:
                raise AssertionError(f"{where}: {x.msgtype} differs in bytes")


def test_fixtures_cover_scenes_formats_and_message_kinds() -> None:
    cfgs = FIXTURES.values()
    assert {c.scene for c in cfgs} == {"indoor", "outdoor"}
    assert {c.format for c in cfgs} == {"mcap", "db3", "bag"}
    assert {c.lidar_msg for c in cfgs} == {"custom", "pointcloud2"}
    for name in FIXTURES:
        bag = fixture_bag(name, FIXTURES_DIR)
        files = [bag] if bag.is_file() else list(bag.rglob("*"))
        size = sum(f.stat().st_size for f in [*files, *truth_dir(bag).iterdir()] if f.is_file())
        assert 0 < size < 8_000_000, (name, size)


@pytest.mark.parametrize("name", sorted(FIXTURES))
def test_fixture_regenerates_within_cpu_bounds(tmp_path: Path, name: str) -> None:
    stored = fixture_bag(name, FIXTURES_DIR)
    assert stored.exists(), f"{stored} missing: run `make fixtures`"
    fresh = make_fixture(name, tmp_path)
    assert_same_recording(fresh.bag, stored)
    for file in ("sim.yaml", "scene.ply", "trajectory.tum", "rig.yaml", "camchain.yaml"):
        assert (fresh.truth / file).read_bytes() == (truth_dir(stored) / file).read_bytes(), file
    assert stored.parent == FIXTURES_DIR
