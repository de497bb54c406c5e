"""Salvage never raises on a cut or damaged MCAP, and topics whose definition cannot be parsed are skipped.

The MCAP files are written with the `mcap` library (chunked plain/zstd/lz4 and
unchunked, with an attachment, a metadata record and the summary section), then
cut at every 1 % of their length or have byte ranges zeroed. Whatever salvage
returns must be exactly messages that were written, in order, without repeats.
"""

import logging
from functools import cache

import pytest
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2

from ingest.bags.reader import BagError, TopicSummary, open_bags, salvage_mcap
from ingest.bags.rostypes import typestore
from ingest.inspect import inspect_bags
from tests.ingest.mcap_layout import chunk_offsets

T0 = 1_700_000_000_000_000_000
INT32 = "std_msgs/msg/Int32"
N = 100
WRITERS = {  # name: (compression, chunk size; 0 = unchunked)
    "plain": (CompressionType.NONE, 512),
    "zstd": (CompressionType.ZSTD, 512),
    "lz4": (CompressionType.LZ4, 1024),
    "flat": (CompressionType.NONE, 0),
}


@cache
def int32_raw(value: int) -> bytes:
    ts = typestore(2)
    return bytes(ts.serialize_cdr(ts.types[INT32](data=value), INT32))


def values_of(msgs) -> list[int]:
    """The Int32 values of salvaged messages, each checked to be byte-identical to what was written."""
    out = []
    for m in msgs:
        value = int.from_bytes(m.raw[4:8], "little", signed=True)
        assert (m.topic, m.msgtype, m.log_ns, m.raw) == ("/n", INT32, T0 + value, int32_raw(value))
        out.append(value)
    return out


def write_mcap(path, compression, chunk_size):
    """N Int32 messages on /n, an attachment after message 30 and a metadata record after 60."""
    schema, _ = typestore(2).generate_msgdef(INT32, ros_version=2)
    with path.open("wb") as f:
        writer = McapWriter(
            f, compression=compression, chunk_size=chunk_size or 1024, use_chunking=chunk_size > 0
        )
        writer.start(profile="ros2", library="test")
        channel = writer.register_channel(
            "/n", "cdr", writer.register_schema(INT32, "ros2msg", schema.encode())
        )
        for i in range(N):
            writer.add_message(channel, log_time=T0 + i, data=int32_raw(i), publish_time=T0 + i)
            if i == 30:
                writer.add_attachment(T0, T0, "calib.yaml", "text/yaml", b"fx: 500\n" * 40)
            if i == 60:
                writer.add_metadata("rig", {"name": "sensorbox"})
        writer.finish()
    return path


@pytest.fixture(scope="module", params=list(WRITERS))
def mcap_bytes(request, tmp_path_factory):
    path = tmp_path_factory.mktemp("mcap") / f"{request.param}.mcap"
    return request.param, write_mcap(path, *WRITERS[request.param]).read_bytes()


def test_every_cut_point_salvages_a_prefix(mcap_bytes, tmp_path):
    name, data = mcap_bytes
    cut = tmp_path / "cut.mcap"
    previous = 0
    for percent in range(1, 101):
        cut.write_bytes(data[: len(data) * percent // 100])
        got = values_of(salvage_mcap(cut))
        assert got == list(range(len(got))), (name, percent)
        assert len(got) >= previous, (name, percent)  # more file never gives fewer messages
        previous = len(got)
        if percent % 25 == 0:
            with open_bags(cut, salvage=True) as bags:
                assert values_of(bags.messages()) == got
    assert previous == N


def test_zeroed_bytes_lose_only_what_they_hit(mcap_bytes, tmp_path):
    name, data = mcap_bytes
    chunks = chunk_offsets(data)
    damaged = tmp_path / "zeroed.mcap"
    width = max(len(data) // 50, 16)
    for start in [0, 3, 8, *range(17, len(data), len(data) // 37)]:
        buf = bytearray(data)
        buf[start : start + width] = bytes(min(width, len(data) - start))
        damaged.write_bytes(bytes(buf))
        got = values_of(salvage_mcap(damaged))
        assert got == sorted(set(got)), (name, start)
        if chunks and start + width <= chunks[-1]:
            assert got[-1] == N - 1, (name, start)  # resynchronised on a later intact chunk
        with open_bags(damaged, salvage=True) as bags:
            assert values_of(bags.messages()) == got


def test_damage_is_logged_with_its_byte_range(tmp_path, caplog):
    data = bytearray(write_mcap(tmp_path / "a.mcap", CompressionType.ZSTD, 1024).read_bytes())
    first, second = chunk_offsets(bytes(data))[:2]
    data[first : first + 20] = bytes(20)  # the first chunk's header
    (tmp_path / "b.mcap").write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING, logger="ingest.bags.salvage"):
        got = values_of(salvage_mcap(tmp_path / "b.mcap"))
    assert got[0] > 0 and got[-1] == N - 1
    assert f"damaged bytes skipped: {first}..{second}" in caplog.text


def test_lost_messages_of_several_damaged_chunks_of_one_topic_add_up(tmp_path):
    """Two damaged chunks, both of /n: the messages lost on /n are those of both, every message the
    salvage did not return (not only the last chunk's)."""
    data = bytearray(write_mcap(tmp_path / "a.mcap", CompressionType.ZSTD, 512).read_bytes())
    offsets = chunk_offsets(bytes(data))
    for at in (offsets[1], offsets[3]):
        data[at + 60 : at + 80] = bytes(20)  # inside the compressed records: zstd refuses them
    (tmp_path / "b.mcap").write_bytes(bytes(data))
    with open_bags(tmp_path / "b.mcap", salvage=True) as bags:
        got = values_of(bags.messages())
        assert [c.offset for c in bags.lost_chunks] == [offsets[1], offsets[3]]
        assert all(c.counts["/n"] > 0 for c in bags.lost_chunks)
        assert bags.lost_counts() == {"/n": N - len(got)}


def test_a_cut_between_chunks_is_logged_as_a_cut(tmp_path, caplog):
    """A file that ends where a chunk ends has no footer: it was cut, and salvage says so (a warning)."""
    data = write_mcap(tmp_path / "a.mcap", CompressionType.ZSTD, 512).read_bytes()
    third = chunk_offsets(data)[2]
    (tmp_path / "b.mcap").write_bytes(data[:third])  # two whole chunks, nothing after
    with caplog.at_level(logging.WARNING, logger="ingest.bags.salvage"):
        got = values_of(salvage_mcap(tmp_path / "b.mcap"))
    assert 0 < len(got) < N and got == list(range(len(got)))
    assert f"b.mcap: salvaged {len(got)} messages" in caplog.text
    assert f"stopped at byte {third}, the end of the file, before the footer" in caplog.text


def test_a_cut_magic_is_an_empty_file_and_garbage_is_not_mcap(tmp_path, caplog):
    (tmp_path / "m.mcap").write_bytes(b"\x89MC")
    with pytest.raises(BagError, match=r"m\.mcap: not an MCAP file"):
        list(salvage_mcap(tmp_path / "m.mcap"))
    (tmp_path / "e.mcap").write_bytes(b"")
    with caplog.at_level(logging.WARNING, logger="ingest.bags.salvage"):
        assert list(salvage_mcap(tmp_path / "e.mcap")) == []
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warned == [
        f"{tmp_path / 'e.mcap'}: salvaged 0 messages (0 unreadable records skipped); the file is empty (0 bytes)"
    ]


# ---------------------------------------------------------------- unparsable definitions

EVENT = "rosbag2_test_msgdefs/srv/AddTwoInts_Event"
EVENT_TOPIC = "/add_two_ints/_service_event"
SRV_TEXT = "=" * 80 + "\nSRV: rosbag2_test_msgdefs/srv/AddTwoInts\nint64 a\nint64 b\n---\nint64 sum\n"
"""What rosbag2 stores as the schema of a service-event topic (ros2/rosbag2 #2365)."""
EVENT_RAW = b"\x00\x01\x00\x00" + bytes(44)


def event_mcap(path):
    schema, _ = typestore(2).generate_msgdef(INT32, ros_version=2)
    with path.open("wb") as f:
        writer = McapWriter(f, compression=CompressionType.NONE)
        writer.start(profile="ros2", library="test")
        n = writer.register_channel("/n", "cdr", writer.register_schema(INT32, "ros2msg", schema.encode()))
        ev = writer.register_channel(
            EVENT_TOPIC, "cdr", writer.register_schema(EVENT, "ros2msg", SRV_TEXT.encode())
        )
        for i in range(5):
            writer.add_message(n, log_time=T0 + i, data=int32_raw(i), publish_time=T0 + i)
            writer.add_message(ev, log_time=T0 + i, data=EVENT_RAW, publish_time=T0 + i)
        writer.finish()
    return path


def event_db3(path):
    with Writer2(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        n = writer.add_connection("/n", INT32, typestore=typestore(2))
        ev = writer.add_connection(EVENT_TOPIC, EVENT, msgdef=SRV_TEXT, rihs01="RIHS01_" + "0" * 64)
        for i in range(5):
            writer.write(n, T0 + i, int32_raw(i))
            writer.write(ev, T0 + i, EVENT_RAW)
    return path


def malformed_ros1(path):
    ts = typestore(1)
    with Writer1(path) as writer:
        n = writer.add_connection("/n", INT32, typestore=ts)
        bad = writer.add_connection(
            EVENT_TOPIC, "my_pkg/msg/Bad", msgdef="int64 a\nfoo bar baz\n", md5sum="0" * 32
        )
        for i in range(5):
            writer.write(n, T0 + i, bytes(ts.serialize_ros1(ts.types[INT32](data=i), INT32)))
            writer.write(bad, T0 + i, bytes(8))
    return path


UNPARSABLE = {
    "mcap": (lambda d: event_mcap(d / "ev.mcap"), False, "service's .srv text"),
    "mcap-salvage": (lambda d: event_mcap(d / "ev.mcap"), True, "service's .srv text"),
    "db3": (lambda d: event_db3(d / "ev"), False, "service's .srv text"),
    "ros1": (lambda d: malformed_ros1(d / "ev.bag"), False, "my_pkg/msg/foo' is unknown"),
}


@pytest.mark.parametrize("kind", list(UNPARSABLE))
def test_unparsable_topic_is_skipped_and_the_rest_reads(kind, tmp_path, caplog):
    make, salvage, why = UNPARSABLE[kind]
    path = make(tmp_path)
    with (
        caplog.at_level(logging.WARNING, logger="ingest.bags.salvage"),
        open_bags(path, salvage=salvage) as bags,
    ):
        assert bags.topics()["/n"] == TopicSummary(INT32, 5)
        assert bags.topics()[EVENT_TOPIC].count == 5
        assert list(bags.skipped) == [EVENT_TOPIC]
        msgs = list(bags.messages())
        with pytest.raises(
            BagError,
            match=rf"topic '{EVENT_TOPIC}': its embedded definition .*{why}.*; that topic is skipped",
        ):
            bags.messages([EVENT_TOPIC])
    if kind == "ros1":
        assert [int.from_bytes(m.raw, "little") for m in msgs] == list(range(5))
    else:
        assert values_of(msgs) == list(range(5))
    (warning,) = [r.getMessage() for r in caplog.records if "skipping that topic" in r.getMessage()]
    assert f"topic '{EVENT_TOPIC}': its embedded definition" in warning and why in warning
    assert "\n" not in warning


def test_inspect_reports_the_skipped_topic_and_reads_the_rest(tmp_path):
    report = inspect_bags(event_mcap(tmp_path / "ev.mcap"))
    assert report.topic("/n").count == 5 and report.topic("/n").error is None
    event = report.topic(EVENT_TOPIC)
    assert event.count == 5
    assert event.error is not None and "service's .srv text" in event.error


def test_salvage_mcap_skips_an_unparsable_topic(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="ingest.bags.salvage"):
        got = values_of(salvage_mcap(event_mcap(tmp_path / "ev.mcap")))
    assert got == list(range(5))
    assert f"topic '{EVENT_TOPIC}': its embedded definition" in caplog.text
    assert "skipping that topic" in caplog.text
