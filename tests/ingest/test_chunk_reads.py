"""MCAP chunks read in part once checked, images handed out still compressed (`DeferredData`), and
chunks decompressed ahead in threads: the same bytes as a plain read, and damage still found.

The bags are written by rosbags (zstd chunks, `BagWriter`: each image closes
its chunk, as a raw image does in a recorded bag) and by the mcap library (lz4,
everything in one chunk); the expected bytes are those written, and a read
without deferral, which decompresses every chunk, gives the same messages.
"""

from __future__ import annotations

import filecmp
import threading
from dataclasses import replace
from types import GeneratorType
from typing import Any

import numpy as np
import pytest
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from ingest.bags import chunks
from ingest.bags.chunks import DEFER_MIN_BYTES, DeferredData
from ingest.bags.decode import Frame, header_stamp_ns
from ingest.bags.reader import CorruptChunkError, open_bags
from ingest.bags.rostypes import IMAGE_TYPE, typestore
from ingest.dataset.layout import GT_DIRS, IMAGE_DIRS
from ingest.errors import MessageDecodeError
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from sensorbox.live.bagwriter import BagWriter
from sensorbox.messages import image_msg
from tests.faults.bags import LIDAR_BOTTOM, LIDAR_TOP, UPPER, raw_image, rewrite
from tests.ingest.mcap_layout import chunk_offsets

T0 = 1_700_000_000_000_000_000
IMAGE = "/cam/image"
INT32 = "std_msgs/msg/Int32"
H, W = 480, 720  # 1.38 MB as bgra8: at least DEFER_MIN_BYTES


def picture(k: int) -> np.ndarray:
    """A compressible BGR image (colour gradients), different for each k."""
    ramp = np.add.outer(np.arange(H), np.arange(W))[..., None] // (3, 5, 7) + 7 * k
    return (ramp % 256).astype(np.uint8)


def int32(k: int) -> bytes:
    ts = typestore(2)
    return bytes(ts.serialize_cdr(ts.types[INT32](data=k), INT32))


def written(n: int = 4) -> list[tuple[str, int, bytes]]:
    """(topic, log ns, bytes): per k an Int32, then an image; the last image is followed by an Int32."""
    out = []
    for k in range(n):
        out.append(("/n", T0 + 10 * k, int32(k)))
        out.append((IMAGE, T0 + 10 * k + 5, image_msg(T0 + k * 33_000_000, "cam", picture(k))))
    out.append(("/n", T0 + 10 * n, int32(n)))  # in the last image's chunk, after it
    return out


def zstd_bag(tmp_path, messages):
    """rosbags' mcap, zstd chunks; each image but the last closes its chunk."""
    path = tmp_path / "z"
    with BagWriter(path, "mcap", compress=True) as out:
        out.add("/n", INT32)
        out.add(IMAGE, IMAGE_TYPE)
        for k, (topic, log_ns, raw) in enumerate(messages):
            out.write(topic, log_ns, raw)
            if topic == IMAGE and k < len(messages) - 2:
                out.flush()
    return path


def lz4_bag(tmp_path, messages):
    """The mcap library's writer, lz4: every message in one chunk."""
    path = tmp_path / "l.mcap"
    with path.open("wb") as f:
        writer = McapWriter(f, compression=CompressionType.LZ4, chunk_size=64 * DEFER_MIN_BYTES)
        writer.start(profile="ros2", library="test")
        ids = {
            topic: writer.register_channel(topic, "cdr", writer.register_schema(msgtype, "ros2msg", b""))
            for topic, msgtype in (("/n", INT32), (IMAGE, IMAGE_TYPE))
        }
        for topic, log_ns, raw in messages:
            writer.add_message(ids[topic], log_time=log_ns, data=raw, publish_time=log_ns)
        writer.finish()
    return path


def count_whole_reads(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The size of each chunk read whole from now on (`decompress_checked` calls), in order."""
    whole: list[int] = []
    real = chunks.decompress_checked

    def counting(data: bytes, compression: str, size: int, crc: int) -> chunks.Records:
        whole.append(size)
        return real(data, compression, size, crc)

    monkeypatch.setattr(chunks, "decompress_checked", counting)
    return whole


@pytest.mark.parametrize("write", [zstd_bag, lz4_bag], ids=["zstd", "lz4"])
def test_deferred_images_are_the_written_bytes(tmp_path, write):
    messages = written()
    path = write(tmp_path, messages)
    with open_bags(path) as bags:
        first = list(bags.messages(defer=[IMAGE]))  # no chunk is checked yet: all are read whole
        plain = list(bags.messages())
        deferring = list(bags.messages(defer=[IMAGE]))
        images_only = list(bags.messages(topics=[IMAGE], defer=[IMAGE]))
    for read in (first, plain):
        assert [(m.topic, m.log_ns, bytes(m.raw)) for m in read] == messages
        assert not any(m.deferred for m in read)
    assert [(m.topic, m.log_ns, bytes(m.data())) for m in deferring] == messages
    deferred = [m.deferred is not None for m in deferring if m.topic == IMAGE]
    deferred_alone = [m.deferred is not None for m in images_only]
    if write is zstd_bag:  # each image ends its chunk
        assert deferred == deferred_alone == [True] * 4
    else:  # one chunk: only its last wanted message can stay compressed
        assert deferred == [False] * 4  # an Int32 follows the last image
        assert deferred_alone == [False, False, False, True]
    assert [(m.log_ns, bytes(m.data())) for m in images_only] == [
        (t, r) for c, t, r in messages if c == IMAGE
    ]
    for m in images_only:
        assert m.stamp("bag") == header_stamp_ns(m.data(), 2)
        frame = m.decoded("bag")
        assert isinstance(frame, Frame)
        assert np.array_equal(frame.image, picture((m.log_ns - T0) // 10))


def test_a_deferred_chunk_that_no_longer_checks_is_an_undecodable_message(tmp_path):
    """Bytes that changed after the chunk was checked: one error naming the file, chunk, topic and time."""
    path = zstd_bag(tmp_path, written(2))
    with open_bags(path) as bags:
        list(bags.messages())  # checks every chunk
        msg = next(m for m in bags.messages(topics=[IMAGE], defer=[IMAGE]))
    assert msg.deferred is not None and len(msg.raw) < 100 < len(msg.data())  # raw: the header only
    data = bytearray(msg.deferred.compressed)
    data[len(data) // 2] ^= 0xFF
    damaged = msg._replace(deferred=replace(msg.deferred, compressed=bytes(data)))
    with pytest.raises(MessageDecodeError) as err:
        damaged.decoded("the bag")
    text = str(err.value)
    assert text.startswith(f"the bag: {IMAGE} at log time ")
    assert f"{path}" in text and "chunk at byte " in text


def test_ingest_writes_the_same_files_with_its_images_left_in_their_chunks(tmp_path, monkeypatch):
    """The fixture with raw upper images, each closing its zstd chunk (sweeps in chunks of their own):
    read whole, and left compressed for the workers (`DEFER_MIN_BYTES` lowered to take the fixture's
    576 kB images)."""

    def keep(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        return [(UPPER, raw_image(raw))] if topic.startswith("/zed_upper") else [(topic, raw)]

    bag, rig = rewrite(tmp_path / "raw", keep, flush_after=[UPPER, LIDAR_TOP, LIDAR_BOTTOM])
    real = chunks._partial
    deferred: dict[str, list[int]] = {}
    for name, min_bytes, workers in (("whole", DEFER_MIN_BYTES, 1), ("deferred", 1024, 2)):
        times = deferred[name] = []

        def counting(*args: Any, **kwargs: Any) -> Any:
            found = real(*args, **kwargs)
            times.extend(m.timestamp for m in found or () if isinstance(m.data, DeferredData))  # noqa: B023
            return found

        monkeypatch.setattr(chunks, "DEFER_MIN_BYTES", min_bytes)
        monkeypatch.setattr(chunks, "_partial", counting)
        cfg = IngestConfig(rig=rig, out=tmp_path / name, workers=workers, every=4, height_full=64)
        assert ingest([bag], cfg).written == 6
    with open_bags(bag) as bags:
        uppers = [m.log_ns for m in bags.messages(topics=[UPPER])]
    assert deferred["whole"] == []
    assert deferred["deferred"] == uppers  # every upper image, in the stream pass only
    a, b = tmp_path / "whole", tmp_path / "deferred"
    for sub in (*IMAGE_DIRS, *GT_DIRS, "meta"):
        names = sorted(p.name for p in (a / sub).iterdir())
        match, mismatch, errs = filecmp.cmpfiles(a / sub, b / sub, names, shallow=False)
        assert not mismatch and not errs and len(match) == 6, (sub, mismatch)


def test_a_read_beside_a_deferring_one_gets_whole_messages(tmp_path):
    """The readers share what to defer: an interleaved read that did not ask still gets every byte."""
    messages = written()
    with open_bags(zstd_bag(tmp_path, messages)) as bags:
        list(bags.messages())  # checks every chunk
        deferring = bags.messages(topics=[IMAGE], defer=[IMAGE])
        first = next(deferring)  # this read has told the readers to defer
        beside = list(bags.messages(topics=[IMAGE]))
        rest = list(deferring)
    assert first.deferred is not None and all(m.deferred is not None for m in rest)
    assert not any(m.deferred for m in beside)
    images = [(t, r) for c, t, r in messages if c == IMAGE]
    assert [(m.log_ns, bytes(m.raw)) for m in beside] == images
    assert [(m.log_ns, bytes(m.data())) for m in [first, *rest]] == images


def test_a_checked_chunk_is_read_only_as_far_as_its_wanted_messages(tmp_path, monkeypatch):
    """Chunks [Int32, image] x 4 and [Int32]: the first read of the Int32s decompresses and checks each
    chunk whole, a second one only the one whose Int32 ends it."""
    messages = written()
    path = zstd_bag(tmp_path, messages)
    whole = count_whole_reads(monkeypatch)
    with open_bags(path) as bags:
        first = list(bags.messages(topics=["/n"]))
        checked = len(whole)
        again = list(bags.messages(topics=["/n"]))
    ints = [(t, r) for c, t, r in messages if c == "/n"]
    assert [(m.log_ns, bytes(m.raw)) for m in first] == [(m.log_ns, bytes(m.raw)) for m in again] == ints
    assert checked == 5 and min(whole[:4]) > DEFER_MIN_BYTES  # the four image chunks, read whole once
    assert len(whole) == 6 and whole[5] < 100  # again: the last chunk, a lone Int32


def test_the_first_read_finds_damage_past_its_wanted_messages(tmp_path):
    """Damage in an image's bytes is found by a read that wants only the Int32 before it in the chunk."""
    path = zstd_bag(tmp_path, written())
    mcap = path / f"{path.name}.mcap"
    data = bytearray(mcap.read_bytes())
    first = chunk_offsets(data)[0]
    records = first + 9 + 8 + 8 + 8 + 4 + 4 + len("zstd") + 8  # the first chunk's compressed records
    size = int.from_bytes(data[records - 8 : records], "little")
    data[records + 3 * size // 4] ^= 0xFF  # well past the Int32 at its start
    mcap.write_bytes(bytes(data))
    with open_bags(path) as bags, pytest.raises(CorruptChunkError, match=f"corrupt chunk at byte {first} "):
        list(bags.messages(topics=["/n"]))


def test_a_chunk_whose_message_index_disagrees_is_always_read_whole(tmp_path, monkeypatch):
    """MessageIndex records lie outside the chunk's CRC: one whose log time was damaged must not make
    a later read stop early and lose the message it misplaces."""
    path = tmp_path / "i.mcap"
    ints = [(T0 + 100, int32(1)), (T0 + 200, int32(2))]
    with path.open("wb") as f:
        writer = McapWriter(f, compression=CompressionType.ZSTD, chunk_size=64 * DEFER_MIN_BYTES)
        writer.start(profile="ros2", library="test")
        n = writer.register_channel("/n", "cdr", writer.register_schema(INT32, "ros2msg", b""))
        image = writer.register_channel(
            "/cam/image", "cdr", writer.register_schema(IMAGE_TYPE, "ros2msg", b"")
        )
        for log_ns, raw in ints:
            writer.add_message(n, log_time=log_ns, data=raw, publish_time=log_ns)
        picture_raw = image_msg(T0, "cam", picture(0))
        writer.add_message(image, log_time=T0 + 300, data=picture_raw, publish_time=T0 + 300)
        writer.finish()
    data = bytearray(path.read_bytes())
    pos = 8
    while data[pos] != 0x02:  # up to the Footer: the MessageIndex (0x07) of channel /n
        length = int.from_bytes(data[pos + 1 : pos + 9], "little")
        if data[pos] == 0x07 and int.from_bytes(data[pos + 9 : pos + 11], "little") == n:
            second = pos + 15 + 16  # its entries (log time u64, offset u64) start after 15 bytes
            assert int.from_bytes(data[second : second + 8], "little") == T0 + 200
            data[second + 5] ^= 0x01  # + 2^40 ns: the log time lies 18 minutes on, past the chunk's end
        pos += 9 + length
    path.write_bytes(bytes(data))
    whole = count_whole_reads(monkeypatch)
    with open_bags(path) as bags:
        reads = [[(m.log_ns, bytes(m.raw)) for m in bags.messages(topics=["/n"])] for _ in range(2)]
    assert reads == [ints, ints]
    assert len(whole) == 2  # the second read too


def chunk_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith("chunk-readahead")]


@pytest.mark.parametrize("write", [zstd_bag, lz4_bag], ids=["zstd", "lz4"])
def test_a_read_ahead_gives_the_same_messages_and_leaves_no_thread(tmp_path, write):
    messages = written(6)
    path = write(tmp_path, messages)
    with open_bags(path) as bags:
        ahead = [(m.topic, m.log_ns, bytes(m.raw)) for m in bags.messages(readahead=3)]
    assert ahead == messages
    assert chunk_threads() == []
    with open_bags(path) as bags:  # stopped part way: the threads end with the read
        read = bags.messages(readahead=3)
        assert isinstance(read, GeneratorType)
        assert (next(read).log_ns, chunk_threads() != []) == (T0, True)
        read.close()
    assert chunk_threads() == []


def test_a_read_ahead_names_a_corrupt_chunk_as_a_plain_read_does(tmp_path):
    path = zstd_bag(tmp_path, written(6))
    mcap = path / f"{path.name}.mcap"
    data = bytearray(mcap.read_bytes())
    third = chunk_offsets(data)[2]
    records = third + 9 + 8 + 8 + 8 + 4 + 4 + len("zstd") + 8
    size = int.from_bytes(data[records - 8 : records], "little")
    data[records + size // 2] ^= 0xFF
    mcap.write_bytes(bytes(data))
    errors = []
    for readahead in (0, 4):
        with open_bags(path) as bags, pytest.raises(CorruptChunkError) as err:
            list(bags.messages(readahead=readahead))
        errors.append(str(err.value))
    assert errors[0] == errors[1] and f"corrupt chunk at byte {third} " in errors[0]
    assert chunk_threads() == []


def test_zstd_records_of_one_or_more_frames_are_the_bytes_compressed() -> None:
    """decompress_checked's zstd path: frames from the reference compressor (with and without the content
    size in their header), one or several, give the bytes back; a size or CRC that differs is named, and
    a size far beyond the data is not allocated."""
    import zstandard
    from backports import zstd as reference
    from isal import isal_zlib

    records = picture(3).tobytes() + bytes(range(256)) * 7
    half = len(records) // 2
    with_size = reference.compress(records)
    streamed = reference.ZstdCompressor()
    no_size = streamed.compress(records) + streamed.flush()  # a streamed frame: no content size
    two = reference.compress(records[:half]) + reference.compress(records[half:])
    empty_after = with_size + reference.compress(b"")  # a second frame with nothing in it
    crc = isal_zlib.crc32(records)
    for data in (with_size, no_size, two, empty_after):
        got = chunks.decompress_checked(data, "zstd", len(records), crc)
        assert got == records
    with pytest.raises(chunks.ChunkDataError, match=f"expected {1 << 50} bytes, got {len(records)}"):
        chunks.decompress_checked(with_size, "zstd", 1 << 50, 0)  # a damaged header sizes no allocation
    with pytest.raises(chunks.ChunkDataError, match=f"expected {len(records)} bytes, got {len(records) + 1}"):
        chunks.decompress_checked(with_size + with_size, "zstd", len(records), 0)  # read one byte past
    with pytest.raises(chunks.ChunkDataError, match=f"expected {len(records) - 1} bytes, got {len(records)}"):
        chunks.decompress_checked(with_size, "zstd", len(records) - 1, 0)
    with pytest.raises(chunks.ChunkDataError, match=f"expected {len(records) + 1} bytes, got {len(records)}"):
        chunks.decompress_checked(two, "zstd", len(records) + 1, 0)
    with pytest.raises(chunks.ChunkDataError, match="checksum mismatch"):
        chunks.decompress_checked(two, "zstd", len(records), crc ^ 1)
    damaged = bytearray(with_size)
    damaged[len(damaged) // 2 : len(damaged) // 2 + 64] = bytes(64)
    with pytest.raises((zstandard.ZstdError, chunks.ChunkDataError)):  # the decompressor's, or the CRC's
        chunks.decompress_checked(bytes(damaged), "zstd", len(records), crc)


def test_raw_bgra_images_are_warped_and_written_as_recorded_into_the_same_files(tmp_path, monkeypatch):
    """Raw bgra8 upper images reach the sample as BGRA (no conversion to BGR) and give the files a BGR
    conversion first gives, byte for byte; the lower camera's JPEGs come as BGR."""
    from ingest.bags.message import RawMessage
    from ingest.train.run import stream
    from ingest.train.run.sample import process_sample

    def keep(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        return [(UPPER, raw_image(raw))] if topic.startswith("/zed_upper") else [(topic, raw)]

    bag, rig = rewrite(tmp_path / "raw", keep, flush_after=[UPPER])
    real_decoded = RawMessage.decoded
    for name in ("bgr", "bgra"):
        channels: list[tuple[int, int]] = []

        def recording(job: Any) -> Any:
            channels.append((job.upper_bgr.shape[2], job.lower_bgr.shape[2]))  # noqa: B023
            return process_sample(job)

        monkeypatch.setattr(stream, "process_sample", recording)
        if name == "bgr":  # the decode before: every image converted to BGR
            monkeypatch.setattr(
                RawMessage, "decoded", lambda m, where, keep_bgra=False: real_decoded(m, where)
            )
        else:
            monkeypatch.setattr(RawMessage, "decoded", real_decoded)
        cfg = IngestConfig(rig=rig, out=tmp_path / name, workers=1, every=4, height_full=64)
        assert ingest([bag], cfg).written == 6
        assert channels == [(3 if name == "bgr" else 4, 3)] * 6
    a, b = tmp_path / "bgr", tmp_path / "bgra"
    for sub in (*IMAGE_DIRS, *GT_DIRS, "meta"):
        names = sorted(p.name for p in (a / sub).iterdir())
        match, mismatch, errs = filecmp.cmpfiles(a / sub, b / sub, names, shallow=False)
        assert not mismatch and not errs and len(match) == 6, (sub, mismatch)
