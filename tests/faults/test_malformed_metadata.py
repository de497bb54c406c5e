"""Malformed metadata is one line naming the file: YAML (file, line, column, PyYAML's problem), a
rosbag2 metadata.yaml's counts and times that are not integers (the key and value), and a rosbag2
.db3's message definitions that rosbags cannot open.

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
from ingest.train.run.describe import _read_dataset_yaml
from sensorbox.sim.fixtures import fixture_bag
from tests.faults.cli import sensorbox
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


def test_rosbag2_metadata_with_an_integer_of_5000_digits(tmp_path: Path) -> None:
    """A traceback (ValueError: Exceeds the limit (4300 digits) for integer string conversion) in inspect
    and ingest: PyYAML converts a count of 5000 digits with int()."""
    bag = tmp_path / "bag"
    shutil.copytree(fixture_bag("indoor_walk_db3", FIXTURES_DIR), bag)
    text = (bag / "metadata.yaml").read_text()
    old = "    message_count: 336\n"
    assert text.count(old) == 1
    (bag / "metadata.yaml").write_text(text.replace(old, "    message_count: 336" + "0" * 5000 + "\n"))
    with pytest.raises(SensorboxError) as err:
        open_bags(bag)
    assert _one_line(err) == (
        f"rosbag2 {bag / 'metadata.yaml'}: line 10, column 20: malformed YAML: an integer of 5003 digits; "
        "at most 4300 are read"
    )


def test_site_manifest_and_dataset_description(tmp_path: Path) -> None:
    path = tmp_path / "site.yaml"
    path.write_text(BROKEN)
    with pytest.raises(SensorboxError, match=PROBLEM) as err:
        read_site(path)
    assert _one_line(err).startswith(f"site manifest {path}: line 2")
    with pytest.raises(SensorboxError, match=PROBLEM) as err:
        _read_dataset_yaml(path)
    assert _one_line(err).startswith(f"existing dataset description {path}: line 2")


def test_a_db3_definition_rosbags_cannot_open_is_named(tmp_path: Path) -> None:
    """rosbag2 stores encoding 'unknown' for a type it could not find while recording; rosbags then fails
    with a bare KeyError for the whole bag. The error names the file, the type and the way out."""
    import sqlite3

    bag = tmp_path / "bag"
    shutil.copytree(fixture_bag("indoor_walk_db3", FIXTURES_DIR), bag)
    (db3,) = bag.glob("*.db3")
    with sqlite3.connect(db3) as db:
        db.execute("INSERT INTO topics VALUES (99, '/my/foo', 'my_pkg/msg/Foo', 'cdr', '', '')")
        db.execute("INSERT INTO message_definitions VALUES (99, 'my_pkg/msg/Foo', 'unknown', '', '')")
    with pytest.raises(SensorboxError) as err:
        open_bags(bag)
    assert _one_line(err) == (
        f"{bag}: {db3.name}: the definition of my_pkg/msg/Foo is stored with encoding 'unknown' (rosbag2 writes "
        "that for a type it could not find while recording), which rosbags cannot open; record with that "
        "type's package sourced, or leave its topic out (ros2 bag convert, exclude_topics)"
    )


@pytest.mark.parametrize(
    ("old", "new", "key"),
    [
        ("- message_count: 7\n    topic_metadata:\n      name: /livox/lidar_192_168_1_13",
         "- message_count: lots\n    topic_metadata:\n      name: /livox/lidar_192_168_1_13",
         "topics_with_message_count[4].message_count is 'lots'"),
        ("nanoseconds_since_epoch: 1700000000001012932\n  storage", "nanoseconds_since_epoch: soon\n  storage",
         "starting_time.nanoseconds_since_epoch is 'soon'"),
        ("  message_count: 336\n  relative", "  message_count: 3.5\n  relative", "message_count is 3.5"),
        ("    message_count: 336\n", "    message_count: true\n", "files[0].message_count is True"),
    ],
)  # fmt: skip
def test_rosbag2_metadata_values_that_are_not_integers(tmp_path: Path, old: str, new: str, key: str) -> None:
    """rosbags reads a non-integer count or time and fails later with a bare TypeError; the reader names
    the file, the key and the value first."""
    bag = tmp_path / "bag"
    shutil.copytree(fixture_bag("indoor_static_mcap", FIXTURES_DIR), bag)
    text = (bag / "metadata.yaml").read_text()
    assert text.count(old) == 1
    (bag / "metadata.yaml").write_text(text.replace(old, new))
    with pytest.raises(SensorboxError) as err:
        open_bags(bag)
    expected = f"{bag / 'metadata.yaml'}: rosbag2_bagfile_information.{key}, expected an integer"
    assert _one_line(err) == expected


def test_a_bare_db3_of_compressed_messages_asks_for_its_folder(tmp_path: Path) -> None:
    """Message-compressed .db3 data is zstd frames, which only metadata.yaml declares: given the bare file,
    every message would fail to decode as CDR. One line names the file and the folder to pass instead."""
    bag = fixture_bag("indoor_walk_db3", FIXTURES_DIR)
    (db3,) = bag.glob("*.db3")
    with pytest.raises(SensorboxError) as err:
        open_bags(db3)
    assert _one_line(err) == (
        f"{db3}: its messages are zstd-compressed, which only the rosbag2 folder's metadata.yaml declares "
        f"(compression_mode 'message'); pass the folder {bag}, not the .db3 file"
    )
    alone = tmp_path / db3.name
    shutil.copy(db3, alone)
    with pytest.raises(SensorboxError, match=r"; pass its rosbag2 folder, not the .db3 file$"):
        open_bags(alone)
    with open_bags(bag) as bags:  # the folder reads
        assert sum(t.count for t in bags.topics().values()) == 336


ROS1_EXPECTED = "not a ROS 1 bag: a .bag file starts with '#ROSBAG V2.0', this one"


@pytest.mark.parametrize(
    ("head", "size", "problem"),
    [
        (b"", 5 * 1024**3, ROS1_EXPECTED + " starts with " + repr(b"\0" * 13)),  # sparse: read whole, 5 GB
        (b"", 0, ROS1_EXPECTED + " is empty"),
        (b"\x89MCAP0\r\n", 4096, "not a ROS 1 bag: it starts like an MCAP file (renamed?); give it the .mcap suffix"),
        (b"SQLite format 3\0", 4096, "not a ROS 1 bag: it starts like a SQLite database (a rosbag2 .db3) "
         "(renamed?); give it that suffix"),
    ],
    ids=["5 GB of zeros", "empty", "an MCAP file", "a db3 file"],
)  # fmt: skip
def test_a_bag_file_without_the_ros1_header_is_refused_from_its_first_bytes(
    head: bytes, size: int, problem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = tmp_path / "x.bag"
    with bag.open("wb") as f:
        f.write(head)
        f.truncate(size)
    code, _, err = sensorbox(capsys, "inspect", str(bag))
    assert (code, err) == (2, [f"error: {bag}: {problem}"])
