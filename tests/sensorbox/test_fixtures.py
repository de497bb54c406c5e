"""The bundled fixture bags are exactly what the simulator makes today (`make fixtures`)."""

from __future__ import annotations

from pathlib import Path

import pytest
from rosbags.highlevel import AnyReader

from sensorbox.sim.fixtures import FIXTURES, fixture_bag, make_fixture
from sensorbox.sim.truth import truth_dir
from tests.paths import FIXTURES_DIR


def _messages(bag: Path) -> list[tuple[str, int, bytes]]:
    with AnyReader([bag]) as reader:
        return [(conn.topic, log_ns, bytes(raw)) for conn, log_ns, raw in reader.messages()]


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
def test_fixture_regenerates_to_identical_bytes(tmp_path: Path, name: str) -> None:
    stored = fixture_bag(name, FIXTURES_DIR)
    assert stored.exists(), f"{stored} missing: run `make fixtures`"
    fresh = make_fixture(name, tmp_path)
    assert _messages(fresh.bag) == _messages(stored)
    for file in ("sim.yaml", "scene.ply", "trajectory.tum", "rig.yaml", "camchain.yaml"):
        assert (fresh.truth / file).read_bytes() == (truth_dir(stored) / file).read_bytes(), file
    assert stored.parent == FIXTURES_DIR
