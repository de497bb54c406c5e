"""Bag reading: every format and Livox package round trips; broken bags fail clearly or are salvaged."""

import logging
import struct
from typing import Any

import numpy as np
import pytest
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.rosbag2 import Writer as Writer2

from ingest.bags.decode import ImuSample, Sweep, decode
from ingest.bags.reader import BagError, RawMessage, TopicSummary, open_bags, salvage_mcap
from ingest.bags.rostypes import IMU_TYPE, typestore
from tests.ingest.mcap_layout import chunk_offsets

RNG = np.random.default_rng(11)
T0 = 1_700_000_000_000_000_000
FORMATS = ["mcap", "sqlite3", "ros1"]
PACKAGES = ["livox_ros_driver", "livox_ros_driver2"]
INT32 = "std_msgs/msg/Int32"
BLOB = "std_msgs/msg/ByteMultiArray"


def version(fmt):
    return 1 if fmt == "ros1" else 2


def header(v, stamp_ns, frame_id):
    ts = typestore(v)
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    if v == 1:
        return ts.types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame_id)
    return ts.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def int32_value(raw: bytes | memoryview) -> int:
    msg: Any = typestore(2).deserialize_cdr(memoryview(raw), INT32)
    return int(msg.data)


def serialize(v, msg, msgtype):
    ts = typestore(v)
    return bytes(ts.serialize_ros1(msg, msgtype) if v == 1 else ts.serialize_cdr(msg, msgtype))


def sweep_values(k):
    """The k-th test sweep: (stamp_ns, frame_id, timebase_ns, points as (offset, x, y, z, refl, tag, line) rows)."""
    n = 3 + 4 * k
    rows = [
        (
            1000 * i + k,
            float(np.float32(0.25 * i + k)),
            float(np.float32(-0.5 * i)),
            float(np.float32(k - i)),
            (7 * i) % 256,
            i % 3,
            i % 4,
        )
        for i in range(n)
    ]
    return T0 + 100_000_000 * k + 50, "livox_frame"[: 2 * k + 1], T0 + 100_000_000 * k, rows


def custom_msg_raw(v, pkg, k):
    ts = typestore(v)
    stamp_ns, frame_id, timebase, rows = sweep_values(k)
    point = ts.types[f"{pkg}/msg/CustomPoint"]
    pts = [
        point(offset_time=o, x=x, y=y, z=z, reflectivity=r, tag=t, line=ln) for o, x, y, z, r, t, ln in rows
    ]
    msg = ts.types[f"{pkg}/msg/CustomMsg"](
        header=header(v, stamp_ns, frame_id), timebase=timebase, point_num=len(pts), lidar_id=192,
        rsvd=np.zeros(3, np.uint8), points=pts,
    )  # fmt: skip
    return serialize(v, msg, f"{pkg}/msg/CustomMsg")


def imu_raw(v, stamp_ns, gz):
    ts = typestore(v).types
    vec = ts["geometry_msgs/msg/Vector3"]
    msg = ts[IMU_TYPE](
        header=header(v, stamp_ns, "livox_imu"), orientation=ts["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9), angular_velocity=vec(x=0.0, y=0.0, z=gz), angular_velocity_covariance=np.zeros(9),
        linear_acceleration=vec(x=0.0, y=0.0, z=1.0), linear_acceleration_covariance=np.zeros(9),
    )  # fmt: skip
    return serialize(v, msg, IMU_TYPE)


def write_bag(path, fmt, topics, compress=False):
    """Write `topics` = {topic: (msgtype, [(log_ns, raw), ...])} in `fmt`; return the path to open."""
    v = version(fmt)
    if fmt == "ros1":
        writer1 = Writer1(path)
        if compress:
            writer1.set_compression(Writer1.CompressionFormat.LZ4)
        with writer1:
            for topic, (msgtype, msgs) in topics.items():
                conn = writer1.add_connection(topic, msgtype, typestore=typestore(1))
                for log_ns, raw in msgs:
                    writer1.write(conn, log_ns, raw)
        return path
    plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
    writer = Writer2(path, version=9, storage_plugin=plugin)
    if compress:
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        for topic, (msgtype, msgs) in topics.items():
            conn = writer.add_connection(topic, msgtype, typestore=typestore(v))
            for log_ns, raw in msgs:
                writer.write(conn, log_ns, raw)
    return path


def livox_bag(tmp_path, fmt, pkg, n=4):
    v = version(fmt)
    lidar = [(T0 + 100_000_000 * k + 3_000_000, custom_msg_raw(v, pkg, k)) for k in range(n)]
    imu = [(T0 + 5_000_000 * k + 1_000_000, imu_raw(v, T0 + 5_000_000 * k, 0.1 * k)) for k in range(3 * n)]
    topics = {"/livox/lidar": (f"{pkg}/msg/CustomMsg", lidar), "/livox/imu": (IMU_TYPE, imu)}
    return write_bag(tmp_path / ("bag.bag" if fmt == "ros1" else "bag"), fmt, topics)


def imu_of(m: RawMessage) -> ImuSample:
    out = decode(m.msgtype, m.raw, m.ros_version)
    assert isinstance(out, ImuSample)
    return out


def assert_sweep(sweep, k):
    assert isinstance(sweep, Sweep)
    stamp_ns, frame_id, timebase, rows = sweep_values(k)
    cols = np.array(rows, dtype=object).T
    assert (sweep.stamp_ns, sweep.frame_id) == (stamp_ns, frame_id)
    np.testing.assert_array_equal(sweep.xyz_m, np.array(rows)[:, 1:4].astype(np.float32))
    np.testing.assert_array_equal(sweep.stamps_ns, timebase + cols[0].astype(np.int64))
    np.testing.assert_array_equal(sweep.reflectivity, cols[4].astype(np.uint8))
    np.testing.assert_array_equal(sweep.tag, cols[5].astype(np.uint8))
    np.testing.assert_array_equal(sweep.line, cols[6].astype(np.uint8))


# ---------------------------------------------------------------- round trips


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("pkg", PACKAGES)
def test_livox_custom_msg_round_trip(tmp_path, fmt, pkg):
    path = livox_bag(tmp_path, fmt, pkg)
    v = version(fmt)
    with open_bags(path) as bags:
        assert bags.ros_version == v
        assert bags.topics() == {
            "/livox/imu": TopicSummary(IMU_TYPE, 12),
            "/livox/lidar": TopicSummary(f"{pkg}/msg/CustomMsg", 4),
        }
        msgs = list(bags.messages(["/livox/lidar"]))
        assert [(m.topic, m.msgtype, m.ros_version) for m in msgs] == [
            ("/livox/lidar", f"{pkg}/msg/CustomMsg", v)
        ] * 4
        assert [m.log_ns for m in msgs] == [T0 + 100_000_000 * k + 3_000_000 for k in range(4)]
        for k, m in enumerate(msgs):
            assert_sweep(decode(m.msgtype, m.raw, m.ros_version), k)
        imu = [imu_of(m) for m in bags.messages(["/livox/imu"])]
        assert [s.stamp_ns for s in imu] == [T0 + 5_000_000 * k for k in range(12)]
        assert [s.gyro_rad_s[2] for s in imu] == pytest.approx([0.1 * k for k in range(12)])


@pytest.mark.parametrize("fmt", FORMATS)
def test_anyreader_reads_embedded_definitions_without_registration(tmp_path, fmt):
    """No typestore given: the definitions embedded by the writer are enough to deserialise CustomMsg."""
    path = livox_bag(tmp_path, fmt, "livox_ros_driver2")
    with AnyReader([path]) as reader:
        conn = next(c for c in reader.connections if c.topic == "/livox/lidar")
        msgs = [reader.deserialize(raw, conn.msgtype) for _, _, raw in reader.messages([conn])]
    _, frame_id, timebase, rows = sweep_values(2)
    msg: Any = msgs[2]
    assert (msg.header.frame_id, msg.timebase, msg.point_num) == (frame_id, timebase, len(rows))
    assert [(p.offset_time, p.x, p.y, p.z, p.reflectivity, p.tag, p.line) for p in msg.points] == rows


def test_several_bags_merge_by_log_time_and_window(tmp_path):
    a = write_bag(
        tmp_path / "a",
        "mcap",
        {
            "/x": (
                INT32,
                [(T0 + 2 * i, serialize(2, typestore(2).types[INT32](data=2 * i), INT32)) for i in range(5)],
            )
        },
    )
    b = write_bag(
        tmp_path / "b",
        "mcap",
        {
            "/y": (
                INT32,
                [
                    (T0 + 2 * i + 1, serialize(2, typestore(2).types[INT32](data=2 * i + 1), INT32))
                    for i in range(5)
                ],
            )
        },
    )
    with open_bags([a, b]) as bags:
        assert bags.topics() == {"/x": TopicSummary(INT32, 5), "/y": TopicSummary(INT32, 5)}
        msgs = list(bags.messages())
        assert [m.log_ns - T0 for m in msgs] == list(range(10))
        assert [m.topic for m in msgs[:2]] == ["/x", "/y"]
        assert [m.log_ns - T0 for m in bags.messages(["/y"], start_ns=T0 + 3, stop_ns=T0 + 7)] == [3, 5]
        data = [int32_value(m.raw) for m in msgs]
        assert data == list(range(10))


@pytest.mark.parametrize("fmt", FORMATS)
def test_missing_topic_lists_the_bags_topics(tmp_path, fmt):
    path = livox_bag(tmp_path, fmt, "livox_ros_driver2", n=1)
    with open_bags(path) as bags, pytest.raises(BagError) as err:
        bags.messages(["/zed/left"])
    text = str(err.value)
    assert "'/zed/left' is not in" in text and str(path) in text
    assert (
        "/livox/imu (sensor_msgs/msg/Imu, 3)" in text
        and "/livox/lidar (livox_ros_driver2/msg/CustomMsg, 1)" in text
    )


def test_path_errors(tmp_path):
    with pytest.raises(BagError, match=r"nope\.mcap: no such file or directory"):
        open_bags(tmp_path / "nope.mcap")
    ros1 = livox_bag(tmp_path, "ros1", "livox_ros_driver", n=1)
    (tmp_path / "x.mcap").write_bytes(b"")
    with pytest.raises(BagError, match="cannot read ROS 1 and ROS 2 bags together"):
        open_bags([ros1, tmp_path / "x.mcap"])
    (tmp_path / "notes.txt").write_text("hi")
    with pytest.raises(BagError, match=r"notes\.txt: expected a ROS 1 \.bag"):
        open_bags(str(tmp_path / "notes.txt"))
    (tmp_path / "r.bag.active").write_bytes(b"#ROSBAG V2.0\n")
    with pytest.raises(BagError, match=r"r\.bag\.active: unfinished ROS 1 recording"):
        open_bags(tmp_path / "r.bag.active")
    (tmp_path / "emptydir").mkdir()
    with pytest.raises(BagError, match=r"emptydir: not a rosbag2 directory \(no metadata\.yaml\)"):
        open_bags(tmp_path / "emptydir")
    with pytest.raises(BagError, match="no bag paths given"):
        open_bags([])


# ---------------------------------------------------------------- empty or foreign definitions

IMU_GZ = [0.25, -0.5]


def mcap_with_schema(
    path, msgtype, schema_data, raws, topic="/t", encoding="ros2msg", schema=True, channel_metadata=None
):
    """A ROS 2 mcap written with the mcap library, so the schema (e.g. empty) and the channel's metadata
    can be anything."""
    with path.open("wb") as f:
        writer = McapWriter(f, compression=CompressionType.NONE)
        writer.start(profile="ros2", library="test")
        schema_id = writer.register_schema(msgtype, encoding, schema_data) if schema else 0
        channel = writer.register_channel(topic, "cdr", schema_id, channel_metadata or {})
        for i, raw in enumerate(raws):
            writer.add_message(channel, log_time=T0 + i, data=raw, publish_time=T0 + i)
        writer.finish()
    return path


def test_empty_definition_of_a_known_type_decodes_with_our_typestore(tmp_path):
    path = mcap_with_schema(
        tmp_path / "e.mcap",
        IMU_TYPE,
        b"",
        [imu_raw(2, T0 + i, gz) for i, gz in enumerate(IMU_GZ)],
        topic="/imu",
    )
    with open_bags(path) as bags:
        msgs = list(bags.messages(["/imu"]))
    assert [imu_of(m).gyro_rad_s[2] for m in msgs] == IMU_GZ
    assert [imu_of(m).gyro_rad_s[2] for m in salvage_mcap(path)] == IMU_GZ


def test_empty_definition_written_by_rosbags_bare_mcap(tmp_path):
    """rosbags can write an empty msgdef too; read as a bare .mcap (metadata.yaml would carry the real hash)."""
    ts = typestore(2)
    with Writer2(tmp_path / "r", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/n", INT32, msgdef="", rihs01=ts.hash_rihs01(INT32))
        writer.write(conn, T0, serialize(2, ts.types[INT32](data=70000), INT32))
    bare = tmp_path / "r" / "r.mcap"
    with AnyReader([bare], default_typestore=ts) as reader:  # the pitfall: an empty struct, no complaint
        assert reader.connections[0].msgdef.data == ""
        wrong = reader.deserialize(next(iter(reader.messages()))[2], INT32)
        assert not hasattr(wrong, "data")
    with open_bags(bare) as bags:
        (msg,) = bags.messages(["/n"])
    assert int32_value(msg.raw) == 70000
    with pytest.raises(BagError, match=r"r: cannot read bag: .*hash mismatch"):
        open_bags(tmp_path / "r")  # the directory's metadata.yaml hash disagrees with the empty definition


def test_empty_definition_of_an_unknown_type_is_refused(tmp_path):
    path = mcap_with_schema(
        tmp_path / "u.mcap", "my_pkg/msg/Thing", b"", [b"\x00\x01\x00\x00\x70\x11\x01\x00"], topic="/thing"
    )
    with open_bags(path) as bags:
        assert bags.topics() == {"/thing": TopicSummary("my_pkg/msg/Thing", 1)}
        with pytest.raises(
            BagError,
            match=r"u\.mcap: topic '/thing' has no embedded message definition for type 'my_pkg/msg/Thing'",
        ):
            bags.messages(["/thing"])
    with pytest.raises(BagError, match="topic '/thing' has no embedded message definition"):
        list(salvage_mcap(path, ["/thing"]))
    assert list(salvage_mcap(path)) == []  # all topics: skipped with a warning


def test_schemaless_channel_is_refused_by_salvage(tmp_path):
    path = mcap_with_schema(tmp_path / "s.mcap", "", b"", [b"\x00\x01\x00\x00"], topic="/raw", schema=False)
    with pytest.raises(BagError, match="topic '/raw' has no schema"):
        list(salvage_mcap(path, ["/raw"]))
    assert list(salvage_mcap(path)) == []


def test_foreign_definition_of_a_decoded_type_is_refused(tmp_path):
    """A bag whose sensor_msgs/msg/Imu is not the real Imu must not be decoded as one."""
    path = mcap_with_schema(
        tmp_path / "f.mcap", IMU_TYPE, b"int32 data\n", [b"\x00\x01\x00\x00\x70\x11\x01\x00"], topic="/imu"
    )
    with (
        open_bags(path) as bags,
        pytest.raises(
            BagError, match=r"f\.mcap: topic '/imu': the bag's definition of sensor_msgs/msg/Imu differs"
        ),
    ):
        bags.messages()
    with pytest.raises(BagError, match="differs from the one SensorBox decodes"):
        list(salvage_mcap(path, ["/imu"]))
    with open_bags(path, salvage=True) as bags:
        assert list(bags.messages()) == [] and list(bags.skipped) == ["/imu"]


# ---------------------------------------------------------------- truncated, unclosed, unindexed


def blob_raw(i, size=120_000):
    ts = typestore(2)
    layout = ts.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=i)
    data = np.random.default_rng(i).integers(0, 256, size, dtype=np.uint8)  # incompressible
    return serialize(2, ts.types[BLOB](layout=layout, data=data), BLOB)


N_BLOBS = 40


@pytest.fixture(params=[False, True], ids=["plain", "zstd"])
def blob_bag(request, tmp_path):
    """A rosbag2 mcap directory of 40 x 120 kB messages (about 5 chunks of 1 MiB)."""
    msgs = [(T0 + i, blob_raw(i)) for i in range(N_BLOBS)]
    return write_bag(tmp_path / "blobs", "mcap", {"/blob": (BLOB, msgs)}, compress=request.param)


def assert_blobs(msgs):
    assert [m.log_ns - T0 for m in msgs] == list(range(len(msgs)))
    for i, m in enumerate(msgs):
        assert (m.topic, m.msgtype, m.ros_version) == ("/blob", BLOB, 2)
        assert m.raw == blob_raw(i)


def test_truncated_mcap_fails_clearly_and_salvages_complete_chunks(blob_bag, tmp_path, caplog):
    data = next(blob_bag.glob("*.mcap")).read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])  # mid-chunk: the recorder was killed
    with pytest.raises(
        BagError, match=r"cut\.mcap: MCAP file is truncated or still being written.*rerun with --salvage"
    ):
        open_bags(cut)

    with caplog.at_level(logging.INFO, logger="ingest.bags.salvage"):
        salvaged = list(salvage_mcap(cut))
    assert 0 < len(salvaged) < N_BLOBS
    assert_blobs(salvaged)
    assert "stopped at byte" in caplog.text

    with open_bags(cut, salvage=True) as bags:
        assert bags.salvaged == (cut,)
        assert bags.topics() == {"/blob": TopicSummary(BLOB, len(salvaged))}
        assert_blobs(list(bags.messages(["/blob"])))
        assert [m.log_ns - T0 for m in bags.messages(start_ns=T0 + 2, stop_ns=T0 + 4)] == [2, 3]


def test_a_footer_pointing_into_the_data_is_named_and_salvaged(blob_bag, tmp_path):
    """Sweep 7 U5: the footer's summary_start moved by 7 bytes read as `cannot read bag: MemoryError: `."""
    data = bytearray(next(blob_bag.glob("*.mcap")).read_bytes())
    footer = (
        len(data) - 8 - 29
    )  # the footer record before the closing magic: opcode, length, then the offsets
    (start,) = struct.unpack_from("<Q", data, footer + 9)
    struct.pack_into("<Q", data, footer + 9, start + 7)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(BagError) as err:
        open_bags(bad)
    assert str(err.value) == (
        f"{bad}: MCAP file: its footer's summary_start {start + 7} points at no summary record (the file is "
        f"{len(data)} bytes): its index is damaged; rerun with --salvage to read its complete chunks"
    )
    with open_bags(bad, salvage=True) as bags:
        assert_blobs(list(bags.messages()))


def test_complete_mcap_salvages_everything(blob_bag):
    mcap = next(blob_bag.glob("*.mcap"))
    assert_blobs(list(salvage_mcap(mcap)))
    with open_bags(blob_bag, salvage=True) as bags:
        assert bags.salvaged == (mcap,)  # --salvage walks every MCAP, so damage anywhere is skipped
        assert_blobs(list(bags.messages()))


def test_rosbag2_directory_of_an_interrupted_recording(blob_bag):
    """A killed recorder leaves the directory without metadata.yaml and its mcap without a summary."""
    mcap = next(blob_bag.glob("*.mcap"))
    (blob_bag / "metadata.yaml").unlink()
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    with pytest.raises(
        BagError, match=r"blobs: rosbag2 directory has no metadata\.yaml.*rerun with --salvage"
    ):
        open_bags(blob_bag)
    with open_bags(blob_bag, salvage=True) as bags:
        assert bags.salvaged == (mcap,)
        msgs = list(bags.messages())
    assert 0 < len(msgs) < N_BLOBS
    assert_blobs(msgs)


def test_salvage_skips_a_corrupt_chunk(tmp_path):
    msgs = [(T0 + i, blob_raw(i)) for i in range(N_BLOBS)]
    bag = write_bag(tmp_path / "z", "mcap", {"/blob": (BLOB, msgs)}, compress=True)
    mcap = next(bag.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    chunks = chunk_offsets(data)
    assert len(chunks) >= 3
    # Chunk record: opcode, length, start/end time, size, crc, "zstd" (4 + 4 bytes), data length, data
    second = chunks[1] + 9 + 8 + 8 + 8 + 4 + 8 + 8
    assert bytes(data[second : second + 4]) == b"\x28\xb5\x2f\xfd"  # zstd frame magic
    data[second : second + 4] = b"oops"
    mcap.write_bytes(bytes(data))
    got = [m.log_ns - T0 for m in salvage_mcap(mcap)]
    assert 0 < len(got) < N_BLOBS
    lost = sorted(set(range(N_BLOBS)) - set(got))
    assert lost == list(range(lost[0], lost[-1] + 1)) and lost[0] > 0  # exactly one chunk's run is missing
    assert got == sorted(got)
    assert all(m.raw == blob_raw(m.log_ns - T0) for m in salvage_mcap(mcap))


def test_salvage_never_yields_a_cut_message_of_an_unchunked_mcap(tmp_path):
    path = tmp_path / "flat.mcap"
    schema, _ = typestore(2).generate_msgdef(BLOB, ros_version=2)
    with path.open("wb") as f:
        writer = McapWriter(f, use_chunking=False, compression=CompressionType.NONE)
        writer.start(profile="ros2", library="test")
        channel = writer.register_channel(
            "/blob", "cdr", writer.register_schema(BLOB, "ros2msg", schema.encode())
        )
        for i in range(5):
            writer.add_message(channel, log_time=T0 + i, data=blob_raw(i), publish_time=T0 + i)
        writer.finish()
    data = path.read_bytes()
    third = data.index(blob_raw(2))
    path.write_bytes(data[: third + 1000])  # cut inside the third message
    assert_blobs(list(salvage_mcap(path)))
    assert len(list(salvage_mcap(path))) == 2


def test_salvage_refuses_a_file_that_is_not_mcap(tmp_path):
    (tmp_path / "x.mcap").write_bytes(b"hello world, not mcap")
    with pytest.raises(BagError, match=r"x\.mcap: not an MCAP file"):
        list(salvage_mcap(tmp_path / "x.mcap"))
    with pytest.raises(BagError, match=r"missing\.mcap: no such MCAP file"):
        salvage_mcap(tmp_path / "missing.mcap")


def int32_ros1_bag(path, n=2000):
    ts = typestore(1)
    msgs = [(T0 + i, serialize(1, ts.types[INT32](data=i), INT32)) for i in range(n)]
    return write_bag(path, "ros1", {"/i": (INT32, msgs)})


def test_unindexed_ros1_bag(tmp_path):
    data = bytearray(int32_ros1_bag(tmp_path / "ok.bag").read_bytes())
    at = data.index(b"index_pos=") + len(b"index_pos=")
    data[at : at + 8] = bytes(8)  # what a killed recorder leaves: no index position
    (tmp_path / "killed.bag").write_bytes(bytes(data))
    with pytest.raises(
        BagError, match=r"killed\.bag: ROS 1 bag is not indexed \(recording was interrupted\)"
    ):
        open_bags(tmp_path / "killed.bag")


def test_truncated_ros1_bag(tmp_path):
    data = int32_ros1_bag(tmp_path / "ok.bag").read_bytes()
    (tmp_path / "cut.bag").write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match=r"cut\.bag: ROS 1 bag is truncated or its index is damaged"):
        open_bags(tmp_path / "cut.bag")


def test_a_ros1_bag_whose_header_counts_no_chunk_is_named(tmp_path):
    """Sweep 7: a 6 MB ROS 1 bag whose header said chunk_count 0 (its chunks and index whole) was 'no messages
    at all (an empty bag, or cut before its first message)'; `rosbag reindex` was not suggested."""
    from tests.paths import FIXTURES_DIR

    data = bytearray((FIXTURES_DIR / "outdoor_static_bag.bag").read_bytes())
    field = data.index(b"chunk_count=") + len(b"chunk_count=")
    struct.pack_into("<I", data, field, 0)
    bag = tmp_path / "lies.bag"
    bag.write_bytes(bytes(data))
    with pytest.raises(BagError) as err:
        open_bags(bag)
    assert str(err.value) == (
        f"{bag}: ROS 1 bag whose header and index count no message though the file holds {len(data):,} bytes: "
        "its index is damaged; run `rosbag reindex` on it first"
    )


def test_the_failing_bag_among_several_is_named(tmp_path, blob_bag):
    data = next(blob_bag.glob("*.mcap")).read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    good = next(blob_bag.glob("*.mcap"))
    with pytest.raises(BagError, match=r"^\S*cut\.mcap: MCAP file is truncated"):
        open_bags([good, tmp_path / "cut.mcap"])
    with open_bags([good, tmp_path / "cut.mcap"], salvage=True) as bags:
        msgs = list(bags.messages())
    assert len(msgs) > N_BLOBS and isinstance(msgs[0], RawMessage)
    assert [m.log_ns for m in msgs] == sorted(m.log_ns for m in msgs)


def test_a_message_viewing_its_chunk_pickles_as_bytes() -> None:
    """Large messages are memoryviews into their decompressed chunk; a Dask job or a pipe pickles them."""
    import pickle

    chunk = bytes(range(256)) * 4
    msg = RawMessage("/cam", "sensor_msgs/msg/Image", 7, memoryview(chunk)[16:48], 2)
    back = pickle.loads(pickle.dumps(msg))
    assert back == RawMessage("/cam", "sensor_msgs/msg/Image", 7, chunk[16:48], 2)
    assert type(back.raw) is bytes


@pytest.mark.parametrize("fmt", ["mcap", "ros1"])
@pytest.mark.parametrize("compress", [False, True], ids=["plain", "compressed"])
def test_large_messages_are_views_of_their_chunk_with_the_written_bytes(tmp_path, fmt, compress):
    """Messages of at least `COPY_BELOW_BYTES` come as memoryviews into the decompressed chunk (no copy),
    smaller ones as bytes; either way the bytes written, in log-time order, beside small messages."""
    from ingest.bags.chunks import COPY_BELOW_BYTES

    v = version(fmt)
    ts = typestore(v)
    sizes = [COPY_BELOW_BYTES + 5, 10, COPY_BELOW_BYTES - 40, 2 * COPY_BELOW_BYTES, 3]

    def blob(i, size):
        layout = ts.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=i)
        data = np.random.default_rng(i).integers(0, 256, size, dtype=np.uint8)
        return serialize(v, ts.types[BLOB](layout=layout, data=data), BLOB)

    written = [(T0 + 10 * i, blob(i, n)) for i, n in enumerate(sizes)]
    ints = [(T0 + 10 * i + 5, serialize(v, ts.types[INT32](data=i), INT32)) for i in range(len(sizes))]
    path = write_bag(tmp_path / f"big.{'bag' if fmt == 'ros1' else 'd'}", fmt,
                     {"/blob": (BLOB, written), "/int": (INT32, ints)}, compress=compress)  # fmt: skip
    with open_bags(path) as bags:
        msgs = list(bags.messages())
    assert [m.log_ns for m in msgs] == sorted(t for t, _ in written + ints)
    blobs = [m for m in msgs if m.topic == "/blob"]
    assert [bytes(m.raw) for m in blobs] == [raw for _, raw in written]
    views = [isinstance(m.raw, memoryview) for m in blobs]
    assert views == [len(raw) >= COPY_BELOW_BYTES for _, raw in written]
    assert [bytes(m.raw) for m in msgs if m.topic == "/int"] == [raw for _, raw in ints]


@pytest.mark.parametrize("name", ["empty.mcap", "empty.db3"])
def test_an_empty_bag_file_is_called_empty(tmp_path, name):
    """A 0-byte .mcap was called truncated ("rerun with --salvage"), a .db3 "missing tables"; with
    --salvage an empty .mcap salvages 0 messages, said in its warning line."""
    path = tmp_path / name
    path.write_bytes(b"")
    with pytest.raises(BagError) as err:
        open_bags(path)
    assert str(err.value) == (
        f"{path}: the file is empty (0 bytes): nothing was recorded into it, or it was cut to nothing"
    )


def test_a_metadata_yaml_naming_another_storage_than_its_files_is_said(tmp_path):
    """Sweep 5: a .db3 recording whose metadata.yaml says storage_identifier mcap was 'cannot read bag:
    AnyReaderError: File magic is invalid.', naming neither the file nor the key."""
    import shutil

    import yaml

    from tests.paths import FIXTURES_DIR

    bag = tmp_path / "rec"
    shutil.copytree(FIXTURES_DIR / "indoor_walk_db3", bag)
    meta = bag / "metadata.yaml"
    doc = yaml.safe_load(meta.read_text())
    info = doc["rosbag2_bagfile_information"]
    assert info["storage_identifier"] == "sqlite3"
    info["storage_identifier"] = "mcap"
    meta.write_text(yaml.safe_dump(doc))
    name = info["relative_file_paths"][0]
    with pytest.raises(BagError) as err:
        open_bags(bag)
    assert str(err.value) == (
        f"{meta}: storage_identifier 'mcap' (files .mcap) but it lists {name}; expected the storage of its "
        "files (a metadata.yaml of another recording?)"
    )


def test_a_channel_whose_qos_metadata_rosbags_cannot_parse_is_named(tmp_path):
    """Sweep 6: garbage in an .mcap channel's offered_qos_profiles was 'cannot read bag: TypeError: string
    indices must be integers, not 'str''."""
    path = mcap_with_schema(
        tmp_path / "q.mcap", IMU_TYPE, b"", [imu_raw(2, T0, 0.0)], topic="/imu",
        channel_metadata={"offered_qos_profiles": "::: not yaml [[["},
    )  # fmt: skip
    with pytest.raises(BagError) as err:
        open_bags(path)
    assert str(err.value) == (
        f"{path}: /imu: its channel's offered_qos_profiles metadata is not a list of ROS 2 QoS profiles "
        "('::: not yaml [[['), which rosbags cannot read; rewrite the bag without it (ros2 bag convert) or "
        "drop the channel's metadata"
    )


def test_a_topic_whose_schema_rosbags_cannot_open_is_named(tmp_path):
    """Sweep 5: an .mcap with a JSON topic beside the ROS ones was 'cannot read bag: KeyError:
    'jsonschema'', naming neither the topic nor the encoding."""
    path = mcap_with_schema(
        tmp_path / "j.mcap", "Status", b"{}", [b"{}"], topic="/status", encoding="jsonschema"
    )
    with pytest.raises(BagError) as err:
        open_bags(path)
    assert str(err.value) == (
        f"{path}: /status: its schema is stored with encoding 'jsonschema', which rosbags cannot open (it "
        "reads ros2msg and ros2idl); leave the topic out of the recording (ros2 bag convert, exclude_topics) "
        "or record it in a bag of its own"
    )
