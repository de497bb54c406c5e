"""Remap maps cached on disk: keyed by the calibration and size, written atomically, rebuilt when damaged."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import calibration.warp as warp_mod
from calibration import DoubleSphere
from calibration.spherical import Equirectangular
from calibration.warp import MAP_CACHE_ENV, RemapMaps, build_maps, clear_map_cache, maps_file

FISHEYE = DoubleSphere(fx=120.0, fy=120.0, cx=95.5, cy=59.5, xi=-0.18, alpha=0.59, width=192, height=120)
SPHERE = Equirectangular(64)
R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """An empty cache folder; every target size is cached on disk; the memory cache starts empty."""
    monkeypatch.setenv(MAP_CACHE_ENV, str(tmp_path / "maps"))
    monkeypatch.setattr(warp_mod, "DISK_CACHE_MIN_PX", 0)
    clear_map_cache()
    yield tmp_path / "maps"
    clear_map_cache()


def _same(a: RemapMaps, b: RemapMaps) -> bool:
    return (
        np.array_equal(a.map_x, b.map_x)
        and np.array_equal(a.map_y, b.map_y)
        and np.array_equal(a.valid, b.valid)
        and a.spans == b.spans
    )


def _no_building(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*_: object) -> RemapMaps:
        raise AssertionError("the maps were built, not loaded")

    monkeypatch.setattr(warp_mod, "_compute_maps", refuse)


def test_a_new_process_loads_the_maps_instead_of_building_them(
    cache: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    built = build_maps(FISHEYE, SPHERE, R)
    path = maps_file(FISHEYE, SPHERE, R)
    assert path is not None and path.parent == cache and path.is_file()
    assert [p.name for p in cache.iterdir()] == [path.name]  # no temporary file left beside it
    clear_map_cache()  # what a fresh process has
    _no_building(monkeypatch)
    loaded = build_maps(FISHEYE, SPHERE, R)
    assert loaded is not built and _same(loaded, built) and len(built.spans) > 0


def test_the_key_is_every_parameter_the_rotation_and_the_size(cache: Path) -> None:
    path = maps_file(FISHEYE, SPHERE, R)
    others = [
        maps_file(replace(FISHEYE, xi=FISHEYE.xi + 1e-12), SPHERE, R),
        maps_file(replace(FISHEYE, width=193), SPHERE, R),
        maps_file(FISHEYE, Equirectangular(128), R),
        maps_file(FISHEYE, SPHERE, np.eye(3)),
    ]
    assert path not in others and len(set(others)) == len(others)
    assert maps_file(replace(FISHEYE), SPHERE, R.copy()) == path  # equal values, equal key


@pytest.mark.parametrize("damage", ["truncated", "garbage", "wrong size"])
def test_a_damaged_file_is_rebuilt_with_one_warning(
    cache: Path, damage: str, caplog: pytest.LogCaptureFixture
) -> None:
    good = build_maps(FISHEYE, SPHERE, R)
    path = maps_file(FISHEYE, SPHERE, R)
    assert path is not None
    data = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        path.write_bytes(b"\0" * 1000)
    else:  # a readable file of other maps under this name
        small = build_maps(FISHEYE, Equirectangular(32), R)
        np.savez(path, map_x=small.map_x, map_y=small.map_y, valid=small.valid, spans=np.zeros((0, 4)))
    clear_map_cache()
    with caplog.at_level(logging.WARNING, logger="calibration.warp"):
        again = build_maps(FISHEYE, SPHERE, R)
    assert _same(again, good)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and lines[0].startswith(f"{path}: unreadable remap map cache file (")
    assert lines[0].endswith("); building the maps again")
    clear_map_cache()
    assert _same(build_maps(FISHEYE, SPHERE, R), good)  # and the file was written again, whole
    assert len(caplog.records) == 1


def test_off_keeps_maps_in_memory_only(cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(MAP_CACHE_ENV, "off")
    assert maps_file(FISHEYE, SPHERE, R) is None
    build_maps(FISHEYE, SPHERE, R)
    assert not cache.exists()


def test_an_unwritable_cache_is_a_warning_not_an_error(cache: Path, caplog: pytest.LogCaptureFixture) -> None:
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text("a file where the folder should be")
    with caplog.at_level(logging.WARNING, logger="calibration.warp"):
        maps = build_maps(FISHEYE, SPHERE, R)
    assert maps.valid.any()
    path = maps_file(FISHEYE, SPHERE, R)
    [line] = [r.getMessage() for r in caplog.records]
    assert line.startswith(f"{path}: cannot store the remap maps ([Errno 17] File exists")
    assert line.endswith("; they will be built again next time")
