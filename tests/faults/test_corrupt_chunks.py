"""Fault injection, integrity: 64 KiB zeroed in the middle of a recorded bag.

A corrupt chunk must be named (bag, log-time range, messages per topic) and
either stop the run before anything is written, or, with --salvage, be skipped
with its messages counted exactly (against the chunk index of the undamaged
file) and no sample made from what it held. The expected values come from the
undamaged file, read by rosbags itself, never from the code under test.
"""

from __future__ import annotations

import filecmp
import json
import shutil
import sys
from collections import Counter
from itertools import pairwise
from pathlib import Path

import pytest
import yaml
from rosbags.rosbag1 import Reader as Ros1Reader
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2.storage_mcap import McapReader

from ingest.bags.chunks import LostChunk
from ingest.bags.decode import Sweep, decode, header_stamp_ns
from ingest.bags.reader import CorruptChunkError, open_bags, salvage_mcap
from ingest.bags.rostypes import typestore
from ingest.inspect import inspect_bags
from ingest.train.run.pipeline import ingest
from ingest.train.run.plan import LOST_REASON
from ingest.train.run.settings import IngestConfig
from sensorbox.cli.main import main
from sensorbox.live.interop import Ros2Writer
from sensorbox.sim.fixtures import fixture_bag
from sensorbox.sim.truth import truth_dir
from tests.paths import FIXTURES_DIR

ZEROED = 64 * 1024
WINDOW_NS = 50_000_000  # ingest's default LiDAR window
IMU_MARGIN_NS = 20_000_000  # IMU readings beyond it (motion compensation)
FILES = (
    "left_fisheye",
    "right_fisheye",
    "equirect_up",
    "equirect_down_virt",
    "disp_equirect",
    "depth_fisheye",
)


def zero_middle(path: Path) -> tuple[int, int]:
    """Overwrite 64 KiB in the middle of `path` with zeros; the byte range [a, b)."""
    a = path.stat().st_size // 2
    with path.open("r+b") as f:
        f.seek(a)
        f.write(bytes(ZEROED))
    return a, a + ZEROED


def mcap_chunks_hit(clean: Path, hit: tuple[int, int]) -> list[tuple[int, int, int, Counter[str]]]:
    """(offset, first log ns, last log ns, messages per topic) of the undamaged file's chunks in `hit`."""
    reader = McapReader(clean)
    reader.open()
    try:
        topics = {c.id: c.topic for c in reader.connections}
        return [
            (c.chunk_start_offset, c.message_start_time, c.message_end_time,
             Counter({topics[cid]: n for cid, n in c.channel_count.items()}))
            for c in reader.chunks
            if c.chunk_start_offset < hit[1] and hit[0] < c.chunk_start_offset + c.chunk_length
        ]  # fmt: skip
    finally:
        reader.close()


def ros_time(ns: int) -> str:
    return f"{ns // 10**9}.{ns % 10**9:09d}"


@pytest.fixture(scope="module")
def damaged(
    tmp_path_factory: pytest.TempPathFactory,
) -> tuple[Path, Path, tuple[int, int, int, Counter[str]]]:
    """(undamaged bag, damaged copy, the one chunk the zeros hit) of the indoor mcap fixture."""
    clean = fixture_bag("indoor_static_mcap", FIXTURES_DIR)
    bag = tmp_path_factory.mktemp("faults") / clean.name
    shutil.copytree(clean, bag)
    mcap = next(bag.glob("*.mcap"))
    hit = zero_middle(mcap)
    chunks = mcap_chunks_hit(next(clean.glob("*.mcap")), hit)
    assert len(chunks) == 1 and sum(chunks[0][3].values()) > 0  # one chunk, with messages
    return clean, bag, chunks[0]


def test_inspect_names_the_bag_and_the_time_range(damaged, monkeypatch, capsys) -> None:
    _, bag, (offset, first, last, counts) = damaged
    monkeypatch.setattr(sys, "argv", ["sensorbox", "inspect", str(bag)])
    with pytest.raises(SystemExit) as ended:
        main()
    assert ended.value.code == 2
    err = capsys.readouterr().err.strip()  # the progress bar leaves a blank line
    assert err.startswith("error: ") and "\n" not in err
    mcap = next(bag.glob("*.mcap"))
    assert f"{mcap}: corrupt chunk at byte {offset}" in err
    assert f"log time {ros_time(first)}..{ros_time(last)}" in err and "s from the bag start" in err
    assert f"{sum(counts.values())} messages: " in err and "--salvage" in err
    for topic, n in counts.items():
        assert f"{n} on {topic}" in err


def test_inspect_salvage_counts_the_lost_messages_exactly(damaged) -> None:
    clean, bag, (offset, first, last, counts) = damaged
    report = inspect_bags(bag, salvage=True)
    (chunk,) = report.lost_chunks
    assert (chunk.offset, chunk.start_ns, chunk.end_ns, dict(chunk.counts)) == (offset, first, last, counts)
    with open_bags(clean) as bags:
        total = {t: s.count for t, s in bags.topics().items()}
    for t in report.topics:
        assert (t.lost, t.count) == (counts[t.topic], total[t.topic] - counts[t.topic])


def test_a_lost_chunks_time_range_is_in_seconds_from_the_bag_start() -> None:
    """A chunk logged from 3.5 s to 4.0 s of a bag whose first message was at 1.0 s: 2.5..3.0 s in."""
    chunk = LostChunk(
        Path("a.mcap"), 1234, 3_500_000_000, 4_000_000_000, {"/b": 2, "/a": 1}, "crc", 1_000_000_000
    )
    assert chunk.time_range() == "log time 3.500000000..4.000000000 (2.500..3.000 s from the bag start)"
    assert chunk.describe() == (
        "a.mcap: corrupt chunk at byte 1234 (crc), log time 3.500000000..4.000000000 "
        "(2.500..3.000 s from the bag start), 3 messages: 1 on /a, 2 on /b"
    )


def test_ros1_corrupt_chunk_is_named_or_skipped_and_counted(tmp_path: Path) -> None:
    """A ROS 1 lz4 chunk has no CRC, but its LZ4 frame checksum makes the damage fail to decompress."""
    clean = fixture_bag("outdoor_static_bag", FIXTURES_DIR)
    bag = tmp_path / clean.name
    shutil.copy(clean, bag)
    hit = zero_middle(bag)
    with Ros1Reader(clean) as reader:
        topics = {c.id: c.topic for c in reader.connections}
        infos = sorted(reader.chunk_infos, key=lambda i: i.pos)
        everything = [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]
    nxt = {a.pos: b.pos for a, b in pairwise(infos)}
    hit_infos = [i for i in infos if i.pos < hit[1] and hit[0] < nxt.get(i.pos, 1 << 62)]
    assert len(hit_infos) == 1
    info = hit_infos[0]
    counts = Counter({topics[c]: n for c, n in info.connection_counts.items()})
    with open_bags(bag) as bags, pytest.raises(CorruptChunkError) as raised:
        list(bags.messages())
    assert f"{bag}: corrupt chunk at byte {info.pos}" in str(raised.value)
    assert f"log time {ros_time(info.start_time)}..{ros_time(info.end_time - 1)}" in str(raised.value)
    with open_bags(bag, salvage=True) as bags:
        read = [(m.topic, m.log_ns, bytes(m.raw)) for m in bags.messages()]
        assert bags.lost_counts() == dict(sorted(counts.items()))
    inside = [m for m in everything if info.start_time <= m[1] < info.end_time]
    assert Counter(m[0] for m in inside) == counts  # the chunk held exactly the messages of its time range
    assert read == [m for m in everything if m not in inside]  # the rest, byte for byte, in order


def test_crc_mismatch_in_an_uncompressed_chunk(tmp_path: Path) -> None:
    """A flipped byte in an uncompressed chunk decompresses fine; only the CRC that SensorBox writes
    catches it, in rosbags' read and in the record-by-record salvage alike."""
    ts = typestore(2)
    path = tmp_path / "crc"
    writer = Ros2Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    with writer:
        conns = {t: writer.add_connection(t, "std_msgs/msg/Int32", typestore=ts) for t in ("/a", "/b")}
        for i in range(30):
            raw = ts.serialize_cdr(ts.types["std_msgs/msg/Int32"](data=i), "std_msgs/msg/Int32")
            writer.write(conns["/a" if i % 3 else "/b"], 10**18 + i, raw)
    mcap = next(path.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    at = data.index(ts.serialize_cdr(ts.types["std_msgs/msg/Int32"](data=17), "std_msgs/msg/Int32"))
    data[at + 4] ^= 0xFF  # the value 17 becomes 238: a plausible, wrong message
    mcap.write_bytes(bytes(data))
    with open_bags(path) as bags, pytest.raises(CorruptChunkError, match="Chunk checksum mismatch"):
        list(bags.messages())
    assert list(salvage_mcap(mcap)) == []  # the whole chunk is refused, no message decoded from it
    report = inspect_bags(path, salvage=True)
    (chunk,) = report.lost_chunks
    assert dict(chunk.counts) == {"/a": 20, "/b": 10}
    assert (chunk.start_ns, chunk.end_ns) == (10**18, 10**18 + 29)


def _samples(out: Path) -> dict[int, str]:
    """Upper-camera stamp -> sample id of every written sample."""
    metas = (json.loads(p.read_text()) for p in (out / "meta").glob("*.json"))
    return {m["stamp_ns"]: m["id"] for m in metas}


def _lost_inputs(clean: Path, chunk: tuple[int, int, int, Counter[str]]) -> dict[str, list[tuple[int, int]]]:
    """Per topic, the stamp span of each message the damaged chunk held (read from the undamaged file)."""
    _, first, last, counts = chunk
    spans: dict[str, list[tuple[int, int]]] = {}
    with open_bags(clean) as bags:
        for m in bags.messages(start_ns=first, stop_ns=last + 1):
            got = decode(m.msgtype, m.raw, 2) if "lidar" in m.topic else None
            span = (int(got.stamps_ns.min()), int(got.stamps_ns.max())) if isinstance(got, Sweep) else None
            stamp = header_stamp_ns(m.raw, 2)
            spans.setdefault(m.topic, []).append(span or (stamp, stamp))
    assert Counter({t: len(v) for t, v in spans.items()}) == counts  # the chunk is its time range
    return spans


def test_ingest_stops_before_writing_or_salvages_only_intact_samples(damaged, tmp_path: Path) -> None:
    clean, bag, chunk = damaged
    rig = truth_dir(clean) / "rig.yaml"
    with pytest.raises(CorruptChunkError, match=f"corrupt chunk at byte {chunk[0]}.*--salvage"):
        ingest([bag], IngestConfig(rig=rig, out=tmp_path / "default", workers=1, height_full=128))
    assert not (tmp_path / "default").exists()  # nothing written: no meta, no images, no dataset.yaml

    whole = ingest([clean], IngestConfig(rig=rig, out=tmp_path / "clean", workers=1, height_full=128))
    cfg = IngestConfig(rig=rig, out=tmp_path / "salvaged", workers=1, height_full=128, salvage=True)
    part = ingest([bag], cfg)
    assert part.lost == dict(sorted(chunk[3].items()))  # exactly what the chunk index says
    assert part.skipped == {LOST_REASON: part.skipped[LOST_REASON]} and part.written == part.planned
    clean_ids, kept = _samples(tmp_path / "clean"), _samples(tmp_path / "salvaged")
    assert whole.written == len(clean_ids) and part.written == len(kept) > 0
    assert set(kept) < set(clean_ids)
    for stamp, sid in kept.items():  # every salvaged sample is the undamaged run's, byte for byte
        for folder in FILES:
            a = tmp_path / "clean" / folder / f"{clean_ids[stamp]}.png"
            assert filecmp.cmp(a, tmp_path / "salvaged" / folder / f"{sid}.png", shallow=False), (
                folder,
                stamp,
            )
    lost = _lost_inputs(clean, chunk)
    for stamp in kept:  # no kept sample's LiDAR or IMU window held a lost message
        for topic, spans in lost.items():
            margin = WINDOW_NS + (IMU_MARGIN_NS if "imu" in topic else 0)
            if "image" not in topic:
                assert all(b < stamp - margin or a > stamp + margin for a, b in spans), (topic, stamp)
    # parsed, not searched: YAML folds the long chunk line where the bag's path length puts the break
    (source,) = yaml.safe_load((tmp_path / "salvaged" / "dataset.yaml").read_text())["sources"]
    lost_doc = source["lost_in_corrupt_chunks"]
    assert lost_doc["messages"] == part.lost
    assert len(lost_doc["chunks"]) == 1 and f"corrupt chunk at byte {chunk[0]} " in lost_doc["chunks"][0]


@pytest.mark.parametrize(
    ("damage", "why"),
    [
        ("zeroed", "ReaderError: Header field could not be parsed."),
        (
            "not utf-8",
            "UnicodeDecodeError: 'utf-8' codec can't decode byte 0xff in position 0: invalid start byte",
        ),
    ],
)
def test_a_damaged_ros1_message_record_is_named_by_topic_and_time(
    tmp_path: Path, damage: str, why: str
) -> None:
    """An uncompressed ROS 1 chunk has no checksum: a message record whose header was zeroed or overwritten
    stopped the run with rosbags' words alone (`UnicodeDecodeError ... position 4149`), naming no topic."""
    import struct

    from ingest.errors import BagError
    from sensorbox.live.bagwriter import BagWriter

    src = FIXTURES_DIR / "outdoor_static_bag.bag"
    with open_bags([src]) as bags:
        messages = [(m.topic, m.msgtype, m.log_ns, bytes(m.raw)) for m in bags.messages()]
    bag = tmp_path / "plain.bag"
    with BagWriter(bag, "bag", compress=False) as out:
        for topic, msgtype in {t: ty for t, ty, _, _ in messages}.items():
            out.add(topic, msgtype)
        for topic, _, log_ns, raw in messages:
            out.write(topic, log_ns, raw)
    imu = "/livox/imu_192_168_1_12"
    _, _, log_ns, raw = [m for m in messages if m[0] == imu][50]
    data = bytearray(bag.read_bytes())
    at = data.find(raw)  # the record: header length, header (op, conn, time: 38 bytes), data length, data
    header = at - 4 - 38
    assert data.find(raw, at + 1) == -1 and struct.unpack_from("<I", data, header - 4) == (38,)
    if damage == "zeroed":
        data[header : header + 38] = bytes(38)
    else:  # one field whose name is not UTF-8
        data[header : header + 38] = struct.pack("<I", 34) + b"\xff" * 10 + b"=" + bytes(23)
    bag.write_bytes(bytes(data))
    shutil.copytree(truth_dir(src), truth_dir(bag))
    with pytest.raises(BagError) as err:
        ingest([bag], IngestConfig(rig=truth_dir(bag) / "rig.yaml", out=tmp_path / "ds", workers=1))
    sec, nsec = divmod(log_ns, 1_000_000_000)
    assert str(err.value).startswith(
        f"{bag}: reading messages failed: ReaderError: the message record of {imu} at log time {sec}.{nsec:09d} s "
        "(chunk at byte "
    )
    assert str(err.value).endswith(f") is damaged: {why}")
    assert not (tmp_path / "ds").exists()
