"""rosbags' readers made to check their chunks: the ROS 1 reader (`CheckedRos1Reader`) and the wiring
that gives an `AnyReader`'s readers, before it opens, checked MCAP or ROS 1 readers reporting to the
run's `ChunkGuard` (`guard_readers`). What each format lets us check: `ingest.bags.chunks`."""

from __future__ import annotations

import heapq
import struct
from collections.abc import Collection, Generator, Mapping, Sequence
from io import BytesIO
from pathlib import Path
from typing import Any, cast

from rosbags.rosbag1 import Reader as Ros1Reader
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag1.reader import Header, RecordType, read_bytes, read_uint32
from rosbags.rosbag2 import Reader as Ros2Reader
from rosbags.rosbag2.reader import DirectoryReader
from rosbags.rosbag2.storage_mcap import McapReader

from ingest.bags.chunk_guard import ChunkGuard, LostChunk, reason_of
from ingest.bags.chunks import COPY_BELOW_BYTES, CheckedMcapReader

# ---------------------------------------------------------------- ROS 1


class CheckedRos1Reader(Ros1Reader):
    """rosbags' ROS 1 reader that reports a chunk that fails to decompress to `guard` and skips it."""

    guard: ChunkGuard = ChunkGuard()  # raises; `guard_readers` gives each reader the run's guard

    def _lost(self, pos: int, err: BaseException) -> LostChunk:
        info = next(i for i in self.chunk_infos if i.pos == pos)
        names = {c.id: c.topic for c in self.connections}
        counts: dict[str, int] = {}
        for cid, n in info.connection_counts.items():
            topic = names.get(cid, f"connection {cid}")
            counts[topic] = counts.get(topic, 0) + n
        end = info.end_time - 1  # rosbags stores the end exclusive
        return LostChunk(
            Path(str(self.path)), pos, info.start_time, end, counts, reason_of(err), self.start_time
        )

    def _records(self, pos: int) -> tuple[BytesIO, memoryview] | None:
        """The decompressed records of the chunk at `pos` (as a stream, and a view of the same bytes);
        None (after `guard.report`) when corrupt."""
        if self.guard.is_lost(Path(str(self.path)), pos):
            return None
        assert self.bio is not None
        chunk = self.chunks[pos]
        self.bio.seek(chunk.datapos)
        try:
            raw = chunk.decompressor(read_bytes(self.bio, chunk.datasize))
        except Exception as err:  # bz2 / lz4 errors of damaged bytes, a chunk cut short
            self.guard.report(self._lost(pos, err))
            return None
        return BytesIO(raw), memoryview(raw)

    def messages(
        self, connections: Collection[Any] = (), start: int | None = None, stop: int | None = None
    ) -> Generator[tuple[Any, int, bytes], None, None]:
        """Messages of `connections` (empty: all) in log-time order, `stop` exclusive.

        Walks the merged per-connection indexes like rosbags' reader; a chunk
        that fails to decompress goes to `guard` and its entries are passed over.
        """
        self._check_open()
        by_id = {c.id: c for c in self.connections}
        entries = heapq.merge(
            *([(e, c) for e in self.indexes[c.id]] for c in (connections or self.connections)),
            key=lambda ec: ec[0].time,
        )
        pos, records = -1, None
        for entry, indexed in entries:
            if start is not None and entry.time < start:
                continue
            if stop is not None and entry.time >= stop:
                return
            if entry.chunk_pos != pos:
                pos, records = entry.chunk_pos, self._records(entry.chunk_pos)
            if records is not None:
                stream, view = records
                try:
                    connection = _message_at(stream, entry.offset, by_id)  # leaves the stream at the data
                    data = _data(stream, view)
                except (Ros1ReaderError, UnicodeDecodeError, struct.error, KeyError) as err:
                    raise _damaged_record(indexed.topic, entry, err) from err
                # rosbags' reader protocol says bytes; a large message is a memoryview, which every
                # consumer here takes (`ingest.bags.decode.Raw`, `RawMessage.raw`)
                yield connection, entry.time, cast(bytes, data)


def _damaged_record(topic: str, entry: Any, err: BaseException) -> Ros1ReaderError:
    """The error of a message record its chunk's index points at but that does not parse (a zeroed or
    overwritten record header in an uncompressed chunk), naming its topic, log time and place."""
    sec, nsec = divmod(int(entry.time), 1_000_000_000)
    return Ros1ReaderError(
        f"the message record of {topic} at log time {sec}.{nsec:09d} s (chunk at byte {entry.chunk_pos}, "
        f"record at chunk offset {entry.offset}) is damaged: {type(err).__name__}: {err}"
    )


def _message_at(records: BytesIO, offset: int, by_id: Mapping[int, Any]) -> Any:
    """The connection of the message record at `offset` (connection records before it are skipped).

    Leaves `records` at the record's data length field, for `_data`.
    """
    records.seek(offset)
    header = Header.read(records)
    while header.get_uint8("op") == RecordType.CONNECTION:
        records.seek(read_uint32(records), 1)
        header = Header.read(records)
    if header.get_uint8("op") != RecordType.MSGDATA:
        raise Ros1ReaderError(f"expected a message record at chunk offset {offset}")
    return by_id[header.get_uint32("conn")]


def _data(records: BytesIO, view: memoryview) -> bytes | memoryview:
    """The message data at the record's length field: a view of the chunk when large (`chunk_messages`)."""
    n = read_uint32(records)
    if n < COPY_BELOW_BYTES:
        return read_bytes(records, n)
    start = records.tell()
    if start + n > len(view):
        raise Ros1ReaderError(f"message data of {n} bytes overruns its chunk at offset {start}")
    records.seek(start + n)
    return view[start : start + n]


# ---------------------------------------------------------------- wiring


def guard_readers(readers: Sequence[Any], guard: ChunkGuard) -> list[Any]:
    """`readers` (an AnyReader's, not yet open) with checked MCAP / ROS 1 readers reporting to `guard`.

    A rosbag2 directory's storage files are created when it opens; its plugin
    table is pointed at `CheckedMcapReader` for that.
    """
    checked: list[Any] = []
    for reader in readers:
        if isinstance(reader, Ros1Reader):
            reader = CheckedRos1Reader(reader.path)
            reader.guard = guard
        elif isinstance(reader, Ros2Reader) and isinstance(reader.storage, McapReader):
            storage = CheckedMcapReader(reader.storage.path)
            storage.guard = guard
            reader.storage = storage
        elif isinstance(reader, Ros2Reader) and isinstance(reader.storage, DirectoryReader):
            reader.storage.STORAGE_PLUGINS = {
                **DirectoryReader.STORAGE_PLUGINS,
                "mcap": _guarded_mcap(guard),
            }
        checked.append(reader)
    return checked


def _guarded_mcap(guard: ChunkGuard) -> type[CheckedMcapReader]:
    """A `CheckedMcapReader` class whose instances report to `guard` (storage plugins are classes)."""
    return type("GuardedMcapReader", (CheckedMcapReader,), {"guard": guard})
