"""Malformed YAML in any file we read is one line: the file, line and column, and PyYAML's problem.

PyYAML's own message spans five lines (context, a caret, problem, a caret);
every reader here condenses it with `calibration.opencv_yaml.yaml_error_line`.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from calibration.errors import SensorboxError
from ingest.bags.reader import open_bags
from ingest.render.scans import read_site
from ingest.train.describe import _read_dataset_yaml
from sensorbox.sim.fixtures import fixture_bag
from tests.paths import FIXTURES_DIR

BROKEN = "version: [5\n  foo: : bar\n"  # an unclosed flow sequence
PROBLEM = r": line 2, column 6: malformed YAML: expected ',' or '\]', but got ':'$"


def _one_line(err: pytest.ExceptionInfo[SensorboxError]) -> str:
    text = str(err.value)
    assert "\n" not in text
    return text


def test_rosbag2_metadata(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    shutil.copytree(fixture_bag("indoor_static_mcap", FIXTURES_DIR), bag)
    (bag / "metadata.yaml").write_text(BROKEN)
    with pytest.raises(SensorboxError) as err:
        open_bags(bag)
    assert _one_line(err).startswith(f"rosbag2 {bag / 'metadata.yaml'}")
    with pytest.raises(SensorboxError, match=PROBLEM):
        open_bags(bag)


def test_site_manifest_and_dataset_description(tmp_path: Path) -> None:
    path = tmp_path / "site.yaml"
    path.write_text(BROKEN)
    with pytest.raises(SensorboxError, match=PROBLEM) as err:
        read_site(path)
    assert _one_line(err).startswith(f"site manifest {path}: line 2")
    with pytest.raises(SensorboxError, match=PROBLEM) as err:
        _read_dataset_yaml(path)
    assert _one_line(err).startswith(f"existing dataset description {path}: line 2")
