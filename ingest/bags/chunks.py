"""Corrupt chunks: found while reading, reported with their bag and time range, never decoded.

Public API:

- `LostChunk`: one chunk whose messages could not be read (CRC mismatch, data
  that does not decompress, a header that does not parse): file, byte offset,
  the log-time range of its messages, how many it held per topic, and why.
  `describe()` is the one line that reports it.
- `CorruptChunkError(BagError)`: raised at a corrupt chunk unless the reader
  was told to skip them (`--salvage`); it carries the `LostChunk`.
- `ChunkGuard`: what a reader does at a corrupt chunk: raise, or (skip=True)
  log one warning line and record the chunk in `lost`.
- `ingest.bags.checked_readers.guard_readers(readers, guard)`: make rosbags'
  readers of an `AnyReader` (before `open()`) check chunk by chunk and report to `guard`.
- `decompress_checked(data, compression, size, crc)`: an MCAP chunk's records,
  size- and CRC-checked (`ChunkDataError` when they do not match).
- `chunk_messages(bio, chunk, channels, start, stop, ...)`: one MCAP chunk's
  messages in time order, walked in place, and whether later reads may take
  the chunk in part. Both readers hand out a message of `COPY_BELOW_BYTES` or
  more as a read-only memoryview into its decompressed chunk (no copy of an
  image), a smaller one as bytes.
- Each MCAP chunk is decompressed whole and checked the first time a bag
  set reads it; when its MessageIndex records (which the CRC does not
  cover) list exactly its message records, it is `ChunkGuard.checked`. A
  later read of a checked chunk decompresses it only as far as its wanted
  messages reach, found through that index: the ingest's later passes read
  a sweep or an IMU sample without the raw image that shares its chunk.
  Such a read does not check the CRC again, so it relies on the file not
  changing while the bag set is open (as the ingest's passes do).
- `DeferredData`: a message still in its compressed MCAP chunk. Asked for
  (`ChunkGuard.defer_topics`), the last wanted message of a checked chunk,
  when it is at least `DEFER_MIN_BYTES` and no smaller than the chunk's
  compressed bytes, comes this way: the reader decompresses only the records
  before it and the first bytes of its data (its header stamp), and whoever
  calls `data()` decompresses and checks the whole chunk. The ingest's
  stream pass hands camera images to its workers so (`ingest.train.run.stream`).

What can be checked depends on the format. An MCAP chunk carries the CRC-32
of its records (every mcap SensorBox writes sets it; 0 means "not computed")
and its compressed data fails to decompress when damaged; the chunk index in
the summary gives each chunk's log-time range and its message count per
channel. A ROS 1 bag's chunks have no checksum: a bz2 chunk (block CRCs) or an
lz4 chunk with a content checksum (as `sensorbox.live.interop.Ros1Writer`
writes them) fails to decompress when damaged, but an uncompressed chunk's
damage cannot be told from data. rosbag2 `.db3` files have no chunks: SQLite
keeps rows in pages without checksums.
"""

from __future__ import annotations

import heapq
import logging
import struct
import sys
import threading
from collections import deque
from collections.abc import Callable, Collection, Generator, Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lz4.frame
import zstandard
from isal import isal_zlib
from rosbags.rosbag2.storage_mcap import DECOMPRESSORS, ChunkInfo, McapReader, Msg, read_exact

from ingest.errors import MessageDecodeError

if sys.version_info >= (3, 14):
    from compression.zstd import ZstdDecompressor
else:
    from backports.zstd import ZstdDecompressor

__all__ = [
    "COPY_BELOW_BYTES",
    "DEFER_MIN_BYTES",
    "ChunkDataError",
    "ChunkGuard",
    "CorruptChunkError",
    "DeferredData",
    "LostChunk",
    "chunk_messages",
    "decompress_checked",
]

from ingest.bags.chunk_guard import ChunkGuard, CorruptChunkError, LostChunk, reason_of

log = logging.getLogger(__name__)

# ---------------------------------------------------------------- MCAP (rosbag2)


class CheckedMcapReader(McapReader):
    """rosbags' MCAP storage whose indexed reads report a corrupt chunk to `guard` instead of aborting."""

    guard: ChunkGuard = ChunkGuard()  # raises; `guard_readers` gives each reader the run's guard

    def _lost(self, chunk: ChunkInfo, err: BaseException) -> LostChunk:
        counts: dict[str, int] = {}
        for cid, n in chunk.channel_count.items():
            topic = self.channels[cid].topic if cid in self.channels else f"channel {cid}"
            counts[topic] = counts.get(topic, 0) + n
        return LostChunk(
            Path(str(self.path)), chunk.chunk_start_offset, chunk.message_start_time, chunk.message_end_time,
            counts, reason_of(err), self.metadata.start_time,
        )  # fmt: skip

    def _chunk(
        self, chunk: ChunkInfo, channels: dict[int, Any], start: int, stop: int, defer: Collection[int],
        ahead: _Readahead | None,
    ) -> Iterator[Msg]:  # fmt: skip
        """The chunk's messages in time order, its decompression put off until the merge reaches it."""
        yield Msg(chunk.message_start_time, 0, None, None)  # placeholder: no bytes read yet
        path = Path(str(self.path))
        if self.guard.is_lost(path, chunk.chunk_start_offset):
            return
        assert self.bio is not None
        key = (path, chunk.chunk_start_offset)
        try:  # all or nothing
            found, indexed = chunk_messages(
                self.bio, chunk, channels, start, stop, key in self.guard.checked, defer, str(path),
                ahead.records if ahead is not None else None,
            )  # fmt: skip
        except Exception as err:  # checksum, size, decompressor and record errors of damaged bytes
            self.guard.report(self._lost(chunk, err))
            return
        if indexed:
            self.guard.checked.add(key)
        yield from found

    def messages(
        self, connections: Collection[Any], start: int | None = None, stop: int | None = None
    ) -> Generator[tuple[Any, int, bytes], None, None]:
        """Messages of `connections` in log-time order; a corrupt chunk goes to `guard`.

        A large message on a topic of `guard.defer_topics` may come as `DeferredData`
        (`chunk_messages`). With `guard.readahead` threads, the chunks to be read
        whole are decompressed ahead in them (`_Readahead`), stopped when the read
        ends. A file without a chunk index (unchunked, or no summary) is scanned
        by rosbags as is.
        """
        if not self.chunks:
            yield from super().messages(connections, start, stop)
            return
        channels = {c.id: c for c in connections}
        defer = {i for i, c in channels.items() if c.topic in self.guard.defer_topics}
        lo = 0 if start is None else start
        chunks = [
            c
            for c in self.chunks
            if lo <= c.message_end_time
            and (stop is None or c.message_start_time < stop)
            and any(c.channel_count.get(cid, 0) for cid in channels)
        ]
        ahead = None
        if self.guard.readahead > 0:
            path = Path(str(self.path))
            whole = [c for c in chunks if (path, c.chunk_start_offset) not in self.guard.checked]
            # the merge below opens the chunks in the order of their first log time
            whole.sort(key=lambda c: c.message_start_time)
            ahead = _Readahead(path, whole, self.guard.readahead) if whole else None
        sources = [
            self._chunk(c, channels, lo, c.message_end_time + 1 if stop is None else stop, defer, ahead)
            for c in chunks
        ]
        try:
            for msg in heapq.merge(*sources):
                if msg.connection is not None and msg.data is not None:
                    yield msg.connection, msg.timestamp, msg.data
        finally:
            if ahead is not None:
                ahead.close()


Records = bytes | bytearray
"""A chunk's decompressed records."""


class ChunkDataError(ValueError):
    """A chunk's records do not match its header (size, CRC) or cannot be decompressed."""


def decompress_checked(data: bytes, compression: str, size: int, crc: int) -> Records:
    """A chunk's records: decompressed, checked against the header's size and CRC-32 (0: none).

    The CRC is ISA-L's (`isal`), several times faster than zlib's on the
    MiBs of a raw-image chunk. Raises `ChunkDataError` naming what does not
    match; a decompressor's own error on damaged data passes through.
    """
    if compression not in DECOMPRESSORS:
        raise ChunkDataError(f"Unsupported chunk compression {compression!r}")
    records = _zstd_records(data, size) if compression == "zstd" else DECOMPRESSORS[compression](data, size)
    if len(records) != size:
        raise ChunkDataError(f"Chunk size mismatch: expected {size} bytes, got {len(records)}")
    if crc and (got := isal_zlib.crc32(records)) != crc:
        raise ChunkDataError(f"Chunk checksum mismatch: records' CRC-32 {got:#010x}, header {crc:#010x}")
    return records


_ZSTD_BLOCK = 1 << 22
"""Bytes per read of zstd data that does not state its size up front (`_zstd_records`)."""


def _zstd_records(data: bytes | memoryview, size: int) -> Records:
    """zstd data (one or more frames) decompressed, at most `size` + 1 bytes (`decompress_checked`
    compares the length with `size`).

    A chunk whose one frame states `size` as its content size (as the mcap
    writers' do) is decompressed by python-zstandard into one buffer of that
    size: about twice as fast on a 9 MB raw-image chunk as rosbags'
    decompressor (`backports.zstd`, which grows its output as it goes), 11-15
    ms against 27, a cost the ingest pays twice per image. Other data (frames
    without a content size, several frames, a size that disagrees) streams
    in blocks, so a damaged header never sizes an allocation.
    """
    decompressor = zstandard.ZstdDecompressor()
    if zstandard.frame_content_size(data) == size:
        try:
            return decompressor.decompress(data, max_output_size=size, allow_extra_data=False)
        except zstandard.ZstdError:  # damaged, or more frames after the first: streamed below
            pass
    records = bytearray()
    with decompressor.stream_reader(data, read_across_frames=True) as reader:
        while len(records) <= size and (block := reader.read(min(_ZSTD_BLOCK, size + 1 - len(records)))):
            records += block
    return records


COPY_BELOW_BYTES = 1 << 18
"""Messages smaller than this are copied out of their chunk; larger ones are views into it."""
_CHUNK_CRC_AT = 9 + 24  # opcode u8, length u64, then start u64, end u64, uncompressed size u64
_MESSAGE = 0x05
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time


def _walk(
    records: bytes | bytearray, end: int, chunk: ChunkInfo, channels: Mapping[int, Any], start: int,
    stop: int, every: list[tuple[int, int, int]] | None = None,
) -> list[Msg]:  # fmt: skip
    """The messages of `channels` with log time in [start, stop) among the records in [0, end).

    A large message is a read-only memoryview into `records`, a small one a
    copy. A record that overruns `end` raises `ChunkDataError`. `every`, when
    given, gets (offset, channel, log ns) of every message record, wanted or not.
    """
    view = memoryview(records).toreadonly()
    found: list[Msg] = []
    pos = 0
    while pos < end:
        if pos + 9 > end:
            raise ChunkDataError(f"record header cut at chunk offset {pos}")
        op, length = records[pos], int.from_bytes(records[pos + 1 : pos + 9], "little")
        body, pos = pos + 9, pos + 9 + length
        if pos > end:
            raise ChunkDataError(f"record of {length} bytes overruns the chunk at offset {body - 9}")
        if op != _MESSAGE:
            continue
        if length < _MESSAGE_HEAD.size:
            raise ChunkDataError(f"message record of {length} bytes at chunk offset {body - 9}")
        channel_id, _, log_ns, _ = _MESSAGE_HEAD.unpack_from(records, body)
        if every is not None:
            every.append((body - 9, channel_id, log_ns))
        if start <= log_ns < stop and channel_id in channels:
            data = view[body + _MESSAGE_HEAD.size : pos]
            found.append(Msg(log_ns, chunk.chunk_start_offset, channels[channel_id],
                             bytes(data) if len(data) < COPY_BELOW_BYTES else data))  # type: ignore[arg-type]  # fmt: skip
    return found


def _compressed(bio: Any, chunk: ChunkInfo) -> tuple[bytes, int]:
    """A chunk's compressed records and the CRC-32 of the uncompressed ones (0: not computed)."""
    bio.seek(chunk.chunk_start_offset + _CHUNK_CRC_AT)
    (crc,) = struct.unpack("<I", read_exact(bio, 4))
    # after the crc: compression (u32 length + text), then the records' length (u64), then the records
    bio.seek(chunk.chunk_start_offset + _CHUNK_CRC_AT + 4 + 4 + len(chunk.compression) + 8)
    return read_exact(bio, chunk.compressed_size), crc


def _read_whole(bio: Any, chunk: ChunkInfo) -> Records:
    """A chunk's records, read from `bio`, decompressed and checked (`decompress_checked`)."""
    compressed, crc = _compressed(bio, chunk)
    return decompress_checked(compressed, chunk.compression, chunk.uncompressed_size, crc)


class _Readahead:
    """Whole reads of a read's chunks, in the order it opens them, decompressed in `threads` threads up
    to `threads` + 1 chunks ahead of it (zstd, lz4 and the CRC release the GIL). The threads read
    through a file object of their own, one at a time; they decompress side by side."""

    def __init__(self, path: Path, chunks: Sequence[ChunkInfo], threads: int) -> None:
        self._file = path.open("rb")
        self._lock = threading.Lock()
        self._todo = deque(chunks)
        self._depth = threads + 1
        self._running: dict[int, Future[Records]] = {}
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="chunk-readahead")
        self._fill()

    def _read(self, chunk: ChunkInfo) -> Records:
        with self._lock:
            compressed, crc = _compressed(self._file, chunk)
        return decompress_checked(compressed, chunk.compression, chunk.uncompressed_size, crc)

    def _fill(self) -> None:
        while self._todo and len(self._running) < self._depth:
            chunk = self._todo.popleft()
            self._running[chunk.chunk_start_offset] = self._pool.submit(self._read, chunk)

    def records(self, chunk: ChunkInfo) -> Records:
        """The chunk's records: read ahead, or now when it was not (its errors are raised here)."""
        future = self._running.pop(chunk.chunk_start_offset, None)
        if future is None:
            self._todo = deque(c for c in self._todo if c.chunk_start_offset != chunk.chunk_start_offset)
        self._fill()
        return future.result() if future is not None else self._read(chunk)

    def close(self) -> None:
        """Stop: what was not started is dropped, what runs is waited for (no thread outlives the read)."""
        self._todo.clear()
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._file.close()


def chunk_messages(
    bio: Any, chunk: ChunkInfo, channels: Mapping[int, Any], start: int, stop: int, checked: bool = False,
    defer: Collection[int] = (), where: str = "", whole: Callable[[ChunkInfo], Records] | None = None,
) -> tuple[list[Msg], bool]:  # fmt: skip
    """The messages of `channels` in one MCAP chunk with log time in [start, stop), in time order, and
    whether a later read may take the chunk in part.

    The records are decompressed and CRC-checked once (`decompress_checked`)
    and walked in place: a large message (an image) is a memoryview into the
    chunk's records rather than a copy, and a small one (a sweep, an IMU
    sample) is copied, so a buffered sweep never keeps a whole chunk of
    images alive. A record that overruns the chunk raises `ChunkDataError`.

    A later read may take a chunk in part when this whole read found it
    intact, its compression can stop part way, and its MessageIndex records
    (outside the CRC) list exactly its message records. A chunk already
    `checked` so is decompressed only up to its last wanted message
    (`_partial`). That message, when on a channel of `defer` and large
    enough, comes as `DeferredData` (`where` names the file in its errors):
    only the records before it and its header are decompressed, and
    `DeferredData.data` decompresses and checks the rest. `whole(chunk)`,
    when given, reads the records whole instead (`_Readahead.records`).
    """
    if checked and (found := _partial(bio, chunk, channels, start, stop, defer, where)) is not None:
        return found, True
    records = whole(chunk) if whole is not None else _read_whole(bio, chunk)
    every: list[tuple[int, int, int]] = []
    found = _walk(records, len(records), chunk, channels, start, stop, every)
    found.sort(key=lambda m: m.timestamp)
    if checked or chunk.compression not in _STREAMING:  # its index was compared when it was checked
        return found, checked
    try:
        index = _message_index(bio, chunk, chunk.message_index_offsets)
    except Exception:  # an index that does not parse: this chunk is always read whole
        index = None
    return found, index is not None and sorted(index) == sorted(every)


DEFER_MIN_BYTES = 1 << 20
"""A message at least this large may be handed out still compressed (`DeferredData`)."""
PARTIAL_AT_MOST = 0.9
"""A checked chunk is decompressed in part only when its wanted messages end before this fraction of it
(beyond, one whole decompression is as fast as a streamed one)."""
_HEAD_BYTES = 64  # of a deferred message's data, decompressed: its header stamp (`header_stamp_ns`)
_MESSAGE_INDEX = 0x07
_STREAMING: dict[str, Any] = {  # decompressors that stop at a given output length and go on from there
    "zstd": ZstdDecompressor,
    "lz4": lz4.frame.LZ4FrameDecompressor,
}


class _Prefix:
    """A compressed chunk's records, decompressed only as far as asked."""

    def __init__(self, compression: str, data: bytes) -> None:
        self._decompressor = _STREAMING[compression]()
        self._data = data
        self.records = bytearray()

    def upto(self, n: int) -> bytearray:
        """The first n bytes of the records (fewer when the compressed frame ends before)."""
        while len(self.records) < n and not self._decompressor.eof:
            more = self._decompressor.decompress(self._data, max_length=n - len(self.records))
            self._data = b""  # fed once; later calls take what the decompressor still holds
            if not more:
                break
            self.records += more
        return self.records


@dataclass(frozen=True)
class DeferredData:
    """A message's data still in its compressed MCAP chunk: the chunk's compressed records, their
    size and CRC-32, where the data lies in them, and the data's first bytes (its header stamp)."""

    chunk: str  # "<file>: chunk at byte <offset>", for errors
    compression: str
    compressed: bytes
    size: int
    crc: int
    start: int
    length: int
    head: bytes

    def data(self) -> memoryview:
        """The message's bytes: the chunk decompressed and checked; `MessageDecodeError` if it is not."""
        try:
            records = decompress_checked(self.compressed, self.compression, self.size, self.crc)
        except Exception as err:  # checksum, size and decompressor errors of bytes that changed
            raise MessageDecodeError(f"{self.chunk}: {reason_of(err)}") from err
        return memoryview(records).toreadonly()[self.start : self.start + self.length]


def _message_index(
    bio: Any, chunk: ChunkInfo, channels: Collection[int]
) -> list[tuple[int, int, int]] | None:
    """(offset in the records, channel, log ns) of the chunk's messages on `channels`, from its
    MessageIndex records (a channel without one has none); None when they do not parse."""
    out: list[tuple[int, int, int]] = []
    for channel_id in channels:
        at = chunk.message_index_offsets.get(channel_id)
        if at is None:
            continue
        bio.seek(at)
        op, length, got, n = struct.unpack("<BQHI", read_exact(bio, 15))
        if op != _MESSAGE_INDEX or got != channel_id or n % 16 or length != 6 + n:
            return None
        if n > chunk.message_index_length:
            return None
        entries = struct.iter_unpack("<QQ", read_exact(bio, n))  # (log time, offset)
        out += [(offset, channel_id, log_ns) for log_ns, offset in entries]
    return out


def _partial(
    bio: Any, chunk: ChunkInfo, channels: Mapping[int, Any], start: int, stop: int, defer: Collection[int],
    where: str,
) -> list[Msg] | None:  # fmt: skip
    """`chunk_messages` of a checked chunk, decompressed up to its last wanted message (that message as
    `DeferredData` when on a `defer` channel, at least `DEFER_MIN_BYTES` and no smaller than the
    compressed chunk); None when it is better or only possible read whole: a compression that cannot
    stop part way, no usable index, or wanted messages reaching past `PARTIAL_AT_MOST` of the chunk."""
    if chunk.compression not in _STREAMING:
        return None
    try:
        index = _message_index(bio, chunk, channels)
        if index is None:
            return None
        wanted = sorted(e for e in index if start <= e[2] < stop)
        if not wanted:
            return []
        at, channel_id, log_ns = wanted[-1]
        data_at = at + 9 + _MESSAGE_HEAD.size
        compressed, crc = _compressed(bio, chunk)
        prefix = _Prefix(chunk.compression, compressed)
        records = prefix.upto(data_at + _HEAD_BYTES)
        if len(records) < data_at:
            return None
        op, length = records[at], int.from_bytes(records[at + 1 : at + 9], "little")
        got, _, got_ns, _ = _MESSAGE_HEAD.unpack_from(records, at + 9)
        end, size = at + 9 + length, length - _MESSAGE_HEAD.size
        if (op, got, got_ns) != (_MESSAGE, channel_id, log_ns) or end > chunk.uncompressed_size:
            return None
        if channel_id in defer and size >= DEFER_MIN_BYTES and len(compressed) <= size:
            found = _walk(records, at, chunk, channels, start, stop)
            head = bytes(records[data_at : data_at + _HEAD_BYTES])
            data = DeferredData(f"{where}: chunk at byte {chunk.chunk_start_offset}", chunk.compression,
                                compressed, chunk.uncompressed_size, crc, data_at, size, head)  # fmt: skip
            found.append(Msg(log_ns, chunk.chunk_start_offset, channels[channel_id], data))  # type: ignore[arg-type]
        elif end <= PARTIAL_AT_MOST * chunk.uncompressed_size and len(prefix.upto(end)) >= end:
            found = _walk(prefix.records, end, chunk, channels, start, stop)
        else:
            return None
    except Exception:  # a damaged index or prefix: the whole chunk is read and checked instead
        return None
    found.sort(key=lambda m: m.timestamp)
    return found
