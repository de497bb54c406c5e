"""Issue 20, class 4: undecodable messages are skipped and counted up to --max-bad N, an error beyond.

One bag, three bad messages the run needs: a raw Image whose `step` is 4
bytes short (upper camera, frame 4), a CompressedImage whose data sequence
claims more bytes than the message holds (lower camera, frame 16), a Livox
CustomMsg whose `point_num` disagrees with its points (top LiDAR, sweep 2).
Every fourth frame is planned (--every 4), so frames 4 and 16 are samples 1 and 4.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from ingest.bags.reader import open_bags
from ingest.dataset.layout import GT_DIRS, IMAGE_DIRS
from ingest.dataset.meta import read_meta
from ingest.errors import MessageDecodeError
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from ingest.train.run.stream import UNDECODABLE_IMAGE
from sensorbox.sim.truth import truth_dir
from tests.faults.bags import (
    LIDAR_TOP,
    LOWER,
    UPPER,
    cut_compressed,
    raw_image,
    rewrite,
    wrong_point_num,
)
from tests.faults.cli import sensorbox

FAST = {"workers": 1, "every": 4, "height_full": 64}


@pytest.fixture(scope="module")
def bad_bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict[str, int]]:
    """(bag, rig, log time in ns of each bad message by topic)."""

    def keep(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic.startswith("/zed_upper"):
            return [(UPPER, raw_image(raw, short_step=k == 4))]
        if topic == LOWER and k == 16:
            return [(topic, cut_compressed(raw))]
        if topic == LIDAR_TOP and k == 2:
            return [(topic, wrong_point_num(raw))]
        return [(topic, raw)]

    bag, rig = rewrite(tmp_path_factory.mktemp("bad") / "bad", keep)
    at = {UPPER: 4, LOWER: 16, LIDAR_TOP: 2}
    seen: dict[str, int] = {}
    log_ns = {}
    with open_bags([bag]) as bags:
        for msg in bags.messages(topics=list(at)):
            k = seen[msg.topic] = seen.get(msg.topic, -1) + 1
            if k == at[msg.topic]:
                log_ns[msg.topic] = msg.log_ns
    return bag, rig, log_ns


def _at(log_ns: int) -> str:
    sec, nsec = divmod(log_ns, 1_000_000_000)
    return f"{sec}.{nsec:09d} s"


def _complete(out: Path, sid: str) -> bool:
    return all((out / d / f"{sid}.png").is_file() for d in (*IMAGE_DIRS, *GT_DIRS))


def test_max_bad_skips_names_and_counts_each_and_stops_beyond(
    bad_bag: tuple[Path, Path, dict[str, int]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag, rig, log_ns = bad_bag
    expected = {
        LIDAR_TOP: f"{bag}: {LIDAR_TOP} at log time {_at(log_ns[LIDAR_TOP])}: "
        "CustomMsg point_num 19975 != points array length 19968",
        UPPER: f"{bag}: {UPPER} at log time {_at(log_ns[UPPER])}: "
        "Image bgra8 480x300: step 1916 < 1920 bytes per row",
        LOWER: f"{bag}: {LOWER} at log time {_at(log_ns[LOWER])}: 59703 bytes are not a valid ROS 2 "
        "sensor_msgs/msg/CompressedImage: Invalid sequence length 59731 at offset 68.",
    }
    # within the limit: each one a warning, counted per topic; every sample that did not need one is written
    warnings: list[str] = []
    out = tmp_path / "ds"
    summary = ingest([bag], IngestConfig(rig=rig, out=out, max_bad=3, **FAST), warn=warnings.append)  # type: ignore[arg-type]
    assert warnings == [
        f"skipped undecodable message {n}/3: {expected[topic]}"
        for n, topic in enumerate((LIDAR_TOP, UPPER, LOWER), 1)
    ]
    assert summary.undecodable == {LIDAR_TOP: 1, LOWER: 1, UPPER: 1}
    assert (summary.planned, summary.written, summary.skipped) == (6, 4, {UNDECODABLE_IMAGE: 2})
    written = sorted(p.stem for p in (out / "meta").glob("*.json"))
    assert written == [f"{k:06d}" for k in range(6) if k not in (1, 4)]
    assert all(_complete(out, sid) for sid in written)
    source = yaml.safe_load((out / "dataset.yaml").read_text())["sources"][0]
    assert source["undecodable_messages"] == {LIDAR_TOP: 1, LOWER: 1, UPPER: 1}
    # the lost sweep thinned the top LiDAR's points in frame 8's window (sample 2): flagged, not hidden
    assert [sid for sid in written if read_meta(out, sid).points.thin_lidars] == ["000002"]
    assert read_meta(out, "000002").points.thin_lidars == ["lidar_top"]

    # beyond the limit: one line naming the message, exit code 2; what was finished stays, nothing partial
    out1 = tmp_path / "ds1"
    args = [
        "ingest",
        str(bag),
        "--rig",
        str(rig),
        "--out",
        str(out1),
        "--workers",
        "1",
        "--every",
        "4",
        "--gt",
        "sparse",
    ]
    code, _, err = sensorbox(capsys, *args, "--height-full", "64", "--max-bad", "1")
    assert code == 2
    assert err == [
        f"warning: skipped undecodable message 1/1: {expected[LIDAR_TOP]}",
        f"error: {expected[UPPER]} (undecodable message 2, more than --max-bad 1; "
        "--max-bad N skips and counts up to N)",
    ]
    done = sorted(p.stem for p in (out1 / "meta").glob("*.json"))
    assert done == ["000000"] and all(_complete(out1, sid) for sid in done)
    assert not list(out1.rglob("*.tmp"))
    # the default is 0: the first one stops the run
    with pytest.raises(MessageDecodeError, match="undecodable message 1, more than --max-bad 0"):
        ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds0", **FAST))  # type: ignore[arg-type]


def test_images_decoded_in_pool_workers_are_counted_as_in_one_process(
    bad_bag: tuple[Path, Path, dict[str, int]], tmp_path: Path
) -> None:
    """The pool's workers decode the camera images; the main process counts what they could not decode."""
    bag, rig, log_ns = bad_bag
    warnings: list[str] = []
    out = tmp_path / "ds"
    cfg = IngestConfig(rig=rig, out=out, max_bad=3, **{**FAST, "workers": 2})  # type: ignore[arg-type]
    summary = ingest([bag], cfg, warn=warnings.append)
    assert [w.split(": ")[2] for w in warnings] == [
        f"{topic} at log time {_at(log_ns[topic])}" for topic in (LIDAR_TOP, UPPER, LOWER)
    ]
    assert summary.undecodable == {LIDAR_TOP: 1, LOWER: 1, UPPER: 1}
    assert (summary.planned, summary.written, summary.skipped) == (6, 4, {UNDECODABLE_IMAGE: 2})
    assert sorted(p.stem for p in (out / "meta").glob("*.json")) == [f"{k:06d}" for k in (0, 2, 3, 5)]


def test_a_corrupt_message_of_a_compressed_db3_is_that_message_alone(tmp_path: Path) -> None:
    """A rosbag2 .db3 with compression_mode 'message' stores each message as its own zstd frame. One whose
    frame is damaged (zeroed bytes) or cut short is an undecodable message named by topic and log time,
    skipped and counted under --max-bad; every other message of the recording still reads."""
    import shutil
    import sqlite3

    from sensorbox.sim.fixtures import fixture_bag
    from tests.paths import FIXTURES_DIR

    src = fixture_bag("indoor_walk_db3", FIXTURES_DIR)
    bag = tmp_path / "walk"
    shutil.copytree(src, bag)
    imu, upper = "/livox/imu_192_168_1_12", "/zed_upper/zed_node/rgb/color/rect/image/compressed"
    (db3,) = bag.glob("*.db3")
    with sqlite3.connect(db3) as db:
        rows = db.execute(
            "SELECT m.id, t.name, m.timestamp, m.data FROM messages m JOIN topics t ON m.topic_id = t.id "
            "WHERE t.name IN (?, ?) ORDER BY m.timestamp",
            (imu, upper),
        ).fetchall()
        bad_imu = next(r for r in rows if r[1] == imu and r[2] > rows[60][2])
        bad_image = next(r for r in rows if r[1] == upper and r[2] > rows[100][2])
        db.execute(
            "UPDATE messages SET data = ? WHERE id = ?",
            (bad_imu[3][:8] + bytes(32) + bad_imu[3][40:], bad_imu[0]),
        )
        db.execute(
            "UPDATE messages SET data = ? WHERE id = ?",
            (bad_image[3][: len(bad_image[3]) // 2], bad_image[0]),
        )
    with open_bags([bag]) as bags:
        msgs = list(bags.messages())
    assert len(msgs) == 336
    damaged = {(m.topic, m.log_ns): m.damage for m in msgs if m.damage}
    assert damaged == {
        (imu, bad_imu[2]): "its zstd-compressed data does not decompress "
        "(zstd decompressor error: Data corruption detected)",
        (upper, bad_image[2]): "its zstd-compressed data is cut short",
    }
    rig = truth_dir(src) / "rig.yaml"
    with pytest.raises(MessageDecodeError) as err:
        ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds0", **FAST))  # type: ignore[arg-type]
    assert str(err.value) == (
        f"{bag}: {imu} at log time {_at(bad_imu[2])}: {damaged[(imu, bad_imu[2])]} "
        "(undecodable message 1, more than --max-bad 0; --max-bad N skips and counts up to N)"
    )
    summary = ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds", max_bad=2, **FAST))  # type: ignore[arg-type]
    assert summary.undecodable == {imu: 1, upper: 1}
    assert summary.written >= 1
