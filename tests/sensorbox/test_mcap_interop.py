"""ROS 2 interop: every mcap SensorBox writes decodes with Foxglove's `mcap` + `mcap-ros2-support`.

Those readers are independent of rosbags (our writer): they parse the records,
check each chunk's CRC-32 (which our writer fills in, sensorbox/live/interop.py)
and decode CDR from the schemas embedded in the file. Covered: BagWriter as the
simulator uses it (zstd and uncompressed chunks), the live recorder (in-place
writes, flushes), and the bundled simulator fixtures.
"""

from __future__ import annotations

import errno
import itertools
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import CRCValidationError, StreamReader
from mcap_ros2.decoder import DecoderFactory

from ingest.bags.decode import decode_pointcloud2, header_stamp_ns
from ingest.bags.livox_msg import POINT_DTYPE, Points
from ingest.bags.reader import BagError, open_bags
from ingest.bags.rostypes import (
    COMPRESSED_IMAGE_TYPE,
    CUSTOM_MSG_TYPE,
    IMAGE_TYPE,
    IMU_TYPE,
    POINTCLOUD2_TYPE,
    typestore,
)
from sensorbox import messages
from sensorbox.live.bagwriter import BagWriteError, BagWriter, bag_path
from sensorbox.live.recorder import Recorder
from sensorbox.live.recorder_config import RecorderConfig
from sensorbox.sim.fixtures import FIXTURES, fixture_bag
from tests.live import NO_DISK_GUARD
from tests.paths import FIXTURES_DIR

LOG0_NS = 1_700_000_000_000_000_000


def _points(n: int) -> Points:
    rng = np.random.default_rng(7)
    pts = np.zeros(n, POINT_DTYPE)
    pts["offset_time"] = np.arange(n) * 1000
    for axis in "xyz":
        pts[axis] = rng.normal(0, 5, n).astype(np.float32)
    pts["reflectivity"], pts["line"] = np.arange(n) % 256, np.arange(n) % 4
    return pts


BIG = (np.add.outer(np.arange(400), np.arange(700)) % 251).astype(np.uint8)[:, :, None].repeat(3, axis=2)
"""1.1 MB as bgra8: each such message closes a ~1 MiB chunk, so every file has several."""
SMALL = BIG[:60, :80].copy()
POINTS = _points(300)
GYRO, ACC = np.array([0.1, -0.2, 0.3]), np.array([0.01, 0.02, 1.0])
WRITTEN = [  # (topic, msgtype, header stamp ns, raw): every kind of message SensorBox writes
    ("/zed/image", IMAGE_TYPE, 1_000, messages.image_msg(1_000, "cam0", BIG)),
    ("/zed/image/compressed", COMPRESSED_IMAGE_TYPE, 2_000, messages.compressed_image_msg(2_000, "cam0", SMALL)),
    ("/livox/lidar", CUSTOM_MSG_TYPE, 3_000, messages.custom_msg(3_000, POINTS)),
    ("/livox/points", POINTCLOUD2_TYPE, 4_000, messages.pointcloud2_msg(4_000, POINTS)),
    ("/livox/imu", IMU_TYPE, 5_000, messages.imu_msg(5_000, GYRO, ACC)),
    ("/zed/image", IMAGE_TYPE, 6_000, messages.image_msg(6_000, "cam0", BIG[::-1].copy())),
    ("/livox/imu", IMU_TYPE, 7_000, messages.imu_msg(7_000, -GYRO, -ACC)),
]  # fmt: skip


def mcap_file(bag: Path) -> Path:
    """The .mcap inside a rosbag2 folder."""
    (path,) = bag.glob("*.mcap")
    return path


def chunk_crcs(path: Path) -> list[int]:
    """Each chunk's stored CRC-32 of its uncompressed records (0 = not computed)."""
    with path.open("rb") as f:
        return [r.uncompressed_crc for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]


def foxglove_decode(path: Path, decode: bool = True) -> list[tuple[str, str, int, bytes, Any]]:
    """(topic, schema, log ns, raw, decoded or None) of every message, chunk CRCs checked.

    With `decode=False` only the first message of each topic is decoded, and
    no Livox CustomMsg: mcap_ros2 decodes in pure Python, ~0.5 s per 20k-point
    sweep (`check_decoded` covers CustomMsg point by point).
    """
    out, seen, factory = [], set(), DecoderFactory()
    with path.open("rb") as f:
        for schema, channel, message in make_reader(f, validate_crcs=True).iter_messages(
            log_time_order=False
        ):
            assert schema is not None
            value = None
            if decode or (channel.topic not in seen and not schema.name.endswith("/CustomMsg")):
                seen.add(channel.topic)
                decoder = factory.decoder_for(channel.message_encoding, schema)
                assert decoder is not None, schema.name
                value = decoder(message.data)
            out.append((channel.topic, schema.name, message.log_time, message.data, value))
    return out


def stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def check_decoded(got: list[tuple[str, str, int, bytes, Any]], log_ns: list[int]) -> None:
    """`got` holds exactly WRITTEN, decoded to the values we serialised."""
    assert [(t, s, ln) for t, s, ln, _, _ in got] == [
        (t, m, ln) for (t, m, _, _), ln in zip(WRITTEN, log_ns, strict=True)
    ]
    assert [raw for *_, raw, _ in got] == [raw for *_, raw in WRITTEN]
    values = [v for *_, v in got]
    assert [stamp_ns(v) for v in values] == [s for _, _, s, _ in WRITTEN]
    image, jpeg, custom, cloud, imu, flipped, imu2 = values
    assert (image.height, image.width, image.encoding, image.step) == (400, 700, "bgra8", 2800)
    assert bytes(image.data) == cv2.cvtColor(BIG, cv2.COLOR_BGR2BGRA).tobytes()
    assert bytes(flipped.data) == cv2.cvtColor(BIG[::-1], cv2.COLOR_BGR2BGRA).tobytes()
    ok, buf = cv2.imencode(".jpg", SMALL, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok and bytes(jpeg.data) == buf.tobytes() and jpeg.format == "bgra8; jpeg compressed bgr8"
    assert (custom.timebase, custom.point_num, len(custom.points)) == (3_000, 300, 300)
    fields = ("offset_time", "x", "y", "z", "reflectivity", "tag", "line")
    assert [tuple(getattr(p, f) for f in fields) for p in custom.points] == POINTS.tolist()
    assert [(f.name, f.offset, f.datatype) for f in cloud.fields] == list(messages.PC2_FIELDS)
    assert bytes(cloud.data) == decode_pointcloud2(WRITTEN[3][3]).points.tobytes()
    for msg, sign in ((imu, 1), (imu2, -1)):
        v, a = msg.angular_velocity, msg.linear_acceleration
        assert [v.x, v.y, v.z, a.x, a.y, a.z] == [*(sign * GYRO), *(sign * ACC)]


def write_bag(bag: Path, compress: bool, in_place: bool = False) -> list[int]:
    """WRITTEN through BagWriter; in place with a flush after each message, as the recorder does."""
    log_ns = [LOG0_NS + 1000 * k for k in range(len(WRITTEN))]
    with BagWriter(bag, "mcap", compress=compress, in_place=in_place) as out:
        for topic, msgtype, _, _ in WRITTEN:
            if topic not in out.counts:
                out.add(topic, msgtype)
        for (topic, _, _, raw), ns in zip(WRITTEN, log_ns, strict=True):
            out.write(topic, ns, raw)
            if in_place:
                out.flush()
    return log_ns


@pytest.mark.parametrize(
    ("compress", "in_place"), [(True, False), (False, False), (True, True)], ids=["zstd", "plain", "flushed"]
)
def test_foxglove_mcap_decodes_every_message_we_write(tmp_path: Path, compress: bool, in_place: bool) -> None:
    log_ns = write_bag(tmp_path / "bag", compress, in_place)
    path = mcap_file(tmp_path / "bag")
    crcs = chunk_crcs(path)
    assert len(crcs) >= (len(WRITTEN) if in_place else 2) and all(crcs), crcs
    check_decoded(foxglove_decode(path), log_ns)


def test_a_damaged_chunk_fails_its_crc(tmp_path: Path) -> None:
    write_bag(tmp_path / "bag", compress=False)
    path = mcap_file(tmp_path / "bag")
    data = bytearray(path.read_bytes())
    image_at = data.find(cv2.cvtColor(BIG, cv2.COLOR_BGR2BGRA).tobytes()[:4096])  # uncompressed chunk
    assert image_at > 0
    data[image_at + 5000] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(CRCValidationError):
        foxglove_decode(path)
    with (
        pytest.raises(
            BagError,
            match=r"bag\.mcap: corrupt chunk at byte \d+ \(ChunkDataError: Chunk checksum mismatch: records. CRC-32 0x[0-9a-f]{8}, header 0x[0-9a-f]{8}\)",
        ),
        open_bags(tmp_path / "bag") as ours,
    ):
        list(ours.messages())  # our reader (rosbags) checks the CRC too: no silently wrong pixels


class FakeClock:
    """Receive times 1 ms apart from LOG0_NS."""

    def __init__(self) -> None:
        self.counter = itertools.count()

    def __call__(self) -> int:
        return LOG0_NS + next(self.counter) * 1_000_000


@pytest.mark.realtime  # the recorder's writer thread
def test_foxglove_mcap_decodes_the_recorders_bags(tmp_path: Path) -> None:
    rec = Recorder(RecorderConfig(tmp_path, name="rec", min_free_bytes=NO_DISK_GUARD), clock_ns=FakeClock())
    rec.start()
    for topic, msgtype, _, raw in WRITTEN:
        assert rec.enqueue(topic, msgtype, 0, raw)
    rec.stop()
    (bag,) = rec.files
    path = mcap_file(bag)
    assert all(chunk_crcs(path))
    check_decoded(foxglove_decode(path), [LOG0_NS + k * 1_000_000 for k in range(len(WRITTEN))])


@pytest.mark.parametrize("name", sorted(n for n, cfg in FIXTURES.items() if cfg.format == "mcap"))
def test_foxglove_mcap_reads_the_simulators_fixtures(name: str) -> None:
    """Every message's bytes as ours reads them; the first of each camera and IMU topic decoded."""
    bag = fixture_bag(name, FIXTURES_DIR)
    path = mcap_file(bag)
    assert all(chunk_crcs(path))
    got = foxglove_decode(path, decode=False)
    with open_bags(bag) as ours:
        msgs = list(ours.messages())
    assert sorted((t, ln, raw) for t, _, ln, raw, _ in got) == sorted(
        (m.topic, m.log_ns, m.raw) for m in msgs
    )
    firsts = [(raw, v) for _, _, _, raw, v in got if v is not None]
    assert len(firsts) == 4  # one per camera and IMU topic
    for raw, value in firsts:
        assert stamp_ns(value) == header_stamp_ns(raw, 2)


def test_bag_path_appends_bag_to_a_dotted_name() -> None:
    """`--out run.2024-05-01 --format bag` writes `run.2024-05-01.bag` (the name's dot is no suffix to
    replace); a name already ending in .bag is kept, and rosbag2 formats use the folder as given."""
    assert bag_path(Path("out/run.2024-05-01"), "bag") == Path("out/run.2024-05-01.bag")
    assert bag_path(Path("out/run.bag"), "bag") == Path("out/run.bag")
    assert bag_path(Path("out/run.2024-05-01"), "mcap") == Path("out/run.2024-05-01")


@pytest.mark.parametrize(
    ("code", "no_space"), [(errno.ENOSPC, True), (errno.EDQUOT, True), (errno.EIO, False)]
)
def test_a_refused_write_takes_back_exactly_the_messages_of_the_open_chunk(
    tmp_path: Path, code: int, no_space: bool
) -> None:
    """In place, two messages flushed into a complete chunk stay; the three written after the flush and
    the one refused are lost: counts go back to 2 and `lost` holds (4 messages, 10 + 20 + 30 + 40 bytes).
    A full disk or an exhausted quota (EDQUOT) is "no space"; another I/O error is not."""
    bag = tmp_path / "bag"
    with BagWriter(bag, "mcap", compress=False, in_place=True) as out:
        out.add("/s", "std_msgs/msg/String")
        for k in range(2):
            out.write("/s", LOG0_NS + k, _string_msg(f"{k}"))
        out.flush()
        raws = [_string_msg("x" * (n - 9)) for n in (10, 20, 30, 40)]
        assert [len(r) for r in raws] == [10, 20, 30, 40]
        for k, raw in enumerate(raws[:3]):
            out.write("/s", LOG0_NS + 10 + k, raw)
        writer: Any = out._writer

        def refuse(*_args: Any) -> None:
            raise OSError(code, os.strerror(code))

        writer.write = refuse
        with pytest.raises(BagWriteError) as info:
            out.write("/s", LOG0_NS + 20, raws[3])
        assert info.value.lost == {"/s": (4, 100)} and info.value.no_space is no_space
        assert out.counts == {"/s": 2}
        assert "4 messages of the open chunk not in it" in str(info.value)
    assert [m.raw for m in read_all_messages(bag)] == [_string_msg("0"), _string_msg("1")]


def read_all_messages(bag: Path) -> list[Any]:
    with open_bags([bag]) as reader:
        return list(reader.messages())


def _string_msg(text: str) -> bytes:
    """A std_msgs/String in CDR: 4 bytes of encapsulation, a 4-byte length, the text and its NUL."""
    ts = typestore(2)
    return bytes(ts.serialize_cdr(ts.types["std_msgs/msg/String"](data=text), "std_msgs/msg/String"))
