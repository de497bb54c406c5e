"""Every intact record of a damaged MCAP file: truncated, unclosed, or with overwritten bytes.

Public API:

- `McapChannel`: one channel (topic, schema name/encoding/text, message encoding).
- `SalvageReport`: what a read found (messages, skipped records, damaged byte ranges).
- `mcap_messages(path, report) -> Iterator[(McapChannel, log_ns, data)]`: in file order.

The file is memory-mapped and walked record by record (opcode u8, length u64,
body), each body parsed only within its own length, so no damage can make
one record's parser read into the next. A record that does not fit the file,
has an opcode the MCAP specification does not allow (0x00, 0x10..0x7F) or a
body that does not parse is damage: the walk skips ahead to the next
intact Chunk record (found by its layout: known compression, byte lengths
that add up, and its CRC when the writer set one) and goes on from there.
A chunk that fails to decompress or its CRC is skipped and reported
(`SalvageReport.lost_chunks`) with its log-time range (its own header, or the
summary's chunk index) and its message count per topic (the chunk index, or
the Message Index records that follow it); so is every chunk the intact
summary's index names whose records were not read. Files without chunks
cannot be resynchronised, so damage in one ends the read there.
Nothing here raises for damage; `report` says what was lost.
"""

from __future__ import annotations

import mmap
import struct
from collections.abc import Iterator
from contextlib import suppress
from dataclasses import dataclass, field
from pathlib import Path

from ingest.bags.chunks import LostChunk, decompress_checked

MCAP_MAGIC = b"\x89MCAP0\r\n"

FOOTER, SCHEMA, CHANNEL, MESSAGE, CHUNK, MESSAGE_INDEX, CHUNK_INDEX = 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08
COMPRESSIONS = ("", "zstd", "lz4")
MAX_CHUNK_BYTES = 1 << 30
"""A chunk header claiming more uncompressed bytes than this is damaged (real chunks are MiBs)."""
_HEADER = 9  # opcode u8 + length u64
_CHUNK_FIXED = 8 + 8 + 8 + 4 + 4  # start, end, uncompressed size, crc, compression length


@dataclass(frozen=True)
class McapChannel:
    """One MCAP channel with its schema (`schema_name` empty when it has none)."""

    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    schema_data: str


@dataclass
class SalvageReport:
    """What `mcap_messages` found. Byte ranges are [start, stop) offsets into the file."""

    messages: int = 0
    skipped_records: int = 0
    """Records that did not parse, messages of unknown channels, chunks that failed CRC/decompression."""
    damaged: list[tuple[int, int]] = field(default_factory=list)
    """Byte ranges skipped while looking for the next intact chunk."""
    end: str = "read to the end of the file"
    """How the read ended: at the footer, at the end of the file, or where a cut record began."""
    has_magic: bool = True
    """False when the file neither starts nor ends with the MCAP magic."""
    intact_records: int = 0
    """Schema, channel and message records and chunks read whole (0 and no magic: not MCAP)."""
    lost_chunks: list[LostChunk] = field(default_factory=list)
    """Chunks whose messages were lost (failed CRC/decompression, or inside a damaged byte range
    when the summary's chunk index names them), with their time range and counts when known;
    filled when the read has gone through the whole file."""

    @property
    def intact(self) -> bool:
        return not self.skipped_records and not self.damaged and self.end.startswith("read to")

    def summary(self) -> str:
        lost = ", ".join(f"{a}..{b}" for a, b in self.damaged)
        return (
            f"salvaged {self.messages} messages ({self.skipped_records} unreadable records skipped"
            + (f"; damaged bytes skipped: {lost}" if lost else "")
            + f"); {self.end}"
        )


# ---------------------------------------------------------------- framing


def _opcode_allowed(opcode: int) -> bool:
    """0x01..0x0F are the specification's records, 0x80..0xFF private ones; the rest is damage."""
    return 0x01 <= opcode <= 0x0F or opcode >= 0x80


def _frame(buf: memoryview, pos: int) -> tuple[int, memoryview] | None:
    """(opcode, body) of the record at `pos`, or None when it is not a record that fits `buf`."""
    if pos + _HEADER > len(buf):
        return None
    opcode = buf[pos]
    (length,) = struct.unpack_from("<Q", buf, pos + 1)
    if not _opcode_allowed(opcode) or length > len(buf) - pos - _HEADER:
        return None
    return opcode, buf[pos + _HEADER : pos + _HEADER + length]


def _damaged_at(buf: memoryview, pos: int) -> bool:
    """True when the bytes at `pos` are neither a record, nor the end, nor a record cut by the end.

    The record before such bytes may be damaged too (its framing held, its
    content need not), so it is not trusted.
    """
    if pos >= len(buf) or _frame(buf, pos) is not None or pos + _HEADER > len(buf):
        return False
    return not _opcode_allowed(buf[pos])  # an allowed opcode whose length runs past the end: a cut


def _string(body: memoryview, pos: int) -> tuple[str, int]:
    """A u32-length-prefixed UTF-8 string at `pos` and the offset after it."""
    (n,) = struct.unpack_from("<I", body, pos)
    end = pos + 4 + n
    if end > len(body):
        raise ValueError("string runs past its record")
    return bytes(body[pos + 4 : end]).decode(), end


def _chunk_payload(body: memoryview) -> tuple[str, int, int, memoryview]:
    """(compression, uncompressed size, crc, records) of a Chunk body whose lengths add up."""
    size, crc, _ = struct.unpack_from("<QII", body, 16)
    compression, pos = _string(body, 28)
    (n,) = struct.unpack_from("<Q", body, pos)
    if compression not in COMPRESSIONS or pos + 8 + n != len(body) or size > MAX_CHUNK_BYTES:
        raise ValueError("not a chunk layout")
    return compression, size, crc, body[pos + 8 :]


def _chunk_records(body: memoryview) -> memoryview:
    """The decompressed, size- and CRC-checked records of one chunk."""
    compression, size, crc, data = _chunk_payload(body)
    return memoryview(decompress_checked(bytes(data), compression, size, crc))


def _resync(buf: memoryview, data: mmap.mmap, pos: int) -> int | None:
    """Offset of the next intact chunk after `pos` whose records decompress, or None."""
    while (pos := data.find(bytes([CHUNK]), pos + 1)) != -1:
        frame = _frame(buf, pos)
        if frame is None or len(frame[1]) < _CHUNK_FIXED + 8:
            continue
        try:
            _chunk_records(frame[1])
        except Exception:  # not a chunk here; look further
            continue
        return pos
    return None


# ---------------------------------------------------------------- records


@dataclass
class _ChunkEntry:
    """What is known of one chunk without its records: log-time range (ns) and messages per channel."""

    start_ns: int | None
    end_ns: int | None
    counts: dict[int, int] = field(default_factory=dict)


@dataclass
class _State:
    schemas: dict[int, tuple[str, str, str]] = field(default_factory=dict)
    channels: dict[int, McapChannel] = field(default_factory=dict)
    index: dict[int, _ChunkEntry] = field(default_factory=dict)
    """The summary's chunk index, by chunk offset (empty without an intact summary)."""
    read: set[int] = field(default_factory=set)
    """Offsets of the chunks whose records were read."""
    failed: dict[int, tuple[_ChunkEntry, str]] = field(default_factory=dict)
    """Chunks that failed (CRC, decompression): what their header and message indexes say, and why."""
    last_chunk: int = -1
    first_ns: int | None = None
    """The earliest log time seen, for times relative to the bag start."""


def _add_schema(state: _State, body: memoryview) -> None:
    (schema_id,) = struct.unpack_from("<H", body, 0)
    name, pos = _string(body, 2)
    encoding, pos = _string(body, pos)
    (n,) = struct.unpack_from("<I", body, pos)
    if pos + 4 + n > len(body):
        raise ValueError("schema data runs past its record")
    text = bytes(body[pos + 4 : pos + 4 + n]).decode(errors="replace")
    state.schemas[schema_id] = (name, encoding, text)


def _add_channel(state: _State, body: memoryview) -> None:
    channel_id, schema_id = struct.unpack_from("<HH", body, 0)
    topic, pos = _string(body, 4)
    encoding, _ = _string(body, pos)
    name, schema_encoding, text = state.schemas.get(schema_id, ("", "", ""))
    state.channels[channel_id] = McapChannel(topic, encoding, name, schema_encoding, text)


def _inner(buf: memoryview, state: _State, report: SalvageReport) -> Iterator[tuple[McapChannel, int, bytes]]:
    """Messages of the records in `buf` (one chunk's, or a whole unchunked stretch)."""
    pos = 0
    while pos < len(buf):
        frame = _frame(buf, pos)
        if frame is None:
            report.skipped_records += 1  # the rest of a damaged chunk
            return
        opcode, body = frame
        pos += _HEADER + len(body)
        if _damaged_at(buf, pos):
            report.skipped_records += 1
            continue
        got = _record(opcode, body, state, report)
        if got is not None:
            yield got


def _record(
    opcode: int, body: memoryview, state: _State, report: SalvageReport
) -> tuple[McapChannel, int, bytes] | None:
    """Apply one schema/channel record, or return a message's (channel, log_ns, data)."""
    try:
        if opcode == SCHEMA:
            _add_schema(state, body)
        elif opcode == CHANNEL:
            _add_channel(state, body)
        elif opcode == MESSAGE:
            channel_id, _, log_ns = struct.unpack_from("<HIQ", body, 0)
            channel = state.channels.get(channel_id)
            if channel is None:
                report.skipped_records += 1
                return None
            report.messages += 1
            report.intact_records += 1
            state.first_ns = log_ns if state.first_ns is None else min(state.first_ns, log_ns)
            return channel, int(log_ns), bytes(body[22:])
        else:
            return None
        report.intact_records += 1
    except (struct.error, ValueError):  # UnicodeDecodeError is a ValueError
        report.skipped_records += 1
    return None


def _add_chunk_index(state: _State, body: memoryview) -> None:
    """A Chunk Index record: the chunk's time range, and its messages per channel.

    The count comes from the byte length of each channel's Message Index
    record (opcode, length, channel id, array length: 15 bytes, then 16 per
    message), the distance between successive offsets.
    """
    start, end, offset, length, n = struct.unpack_from("<QQQQI", body, 0)
    pairs = sorted((o, c) for c, o in struct.iter_unpack("<HQ", body[36 : 36 + n]))
    (index_length,) = struct.unpack_from("<Q", body, 36 + n)
    stops = [o for o, _ in pairs[1:]] + [offset + length + index_length]
    counts = {c: (stop - o - 15) // 16 for (o, c), stop in zip(pairs, stops, strict=True)}
    state.index[offset] = _ChunkEntry(start, end, {c: k for c, k in counts.items() if k > 0})


def _chunk_failed(state: _State, pos: int, body: memoryview, err: Exception) -> None:
    """Note a chunk whose records cannot be read; its header's time range when that parses."""
    times = struct.unpack_from("<QQ", body, 0) if len(body) >= 16 else (None, None)
    text = " ".join(str(err).split()).rstrip(".")
    state.failed[pos] = (_ChunkEntry(*times), f"{type(err).__name__}: {text}" if text else type(err).__name__)


def _note_message_index(state: _State, body: memoryview) -> None:
    """A Message Index record after a failed chunk: how many messages of one channel it held."""
    if state.last_chunk in state.failed and len(body) >= 6:
        channel_id, n = struct.unpack_from("<HI", body, 0)
        state.failed[state.last_chunk][0].counts[channel_id] = n // 16


def _lost_chunks(path: Path, state: _State, report: SalvageReport) -> list[LostChunk]:
    """Every chunk whose messages were not read: failed ones, and those the chunk index names that
    lay in damaged bytes or after where the read stopped."""
    lost = dict(state.failed)
    for off, entry in state.index.items():
        if off not in state.read and off not in lost:
            where = [f"inside damaged bytes {a}..{b}" for a, b in report.damaged if a <= off < b]
            lost[off] = (entry, where[0] if where else "not reached: " + report.end)
    starts = [e.start_ns for e, _ in lost.values() if e.start_ns is not None]
    first = min([*starts, *([state.first_ns] if state.first_ns is not None else [])], default=None)
    out = []
    for off, (entry, reason) in sorted(lost.items()):
        known = state.index.get(off, entry)
        counts: dict[str, int] = {}
        for cid, n in known.counts.items():
            topic = state.channels[cid].topic if cid in state.channels else f"channel {cid}"
            counts[topic] = counts.get(topic, 0) + n
        out.append(LostChunk(path, off, known.start_ns, known.end_ns, counts, reason, first))
    return out


def _summary_channels(buf: memoryview, state: _State) -> None:
    """Schemas, channels and the chunk index from the summary section, when the file ends with an
    intact footer.

    Lets messages be read whose channel record sat in a damaged part of the
    data section, and names the chunks that damage made unreadable.
    """
    footer = len(buf) - len(MCAP_MAGIC) - _HEADER - 20
    if footer <= len(MCAP_MAGIC) or bytes(buf[-len(MCAP_MAGIC) :]) != MCAP_MAGIC:
        return
    frame = _frame(buf, footer)
    if frame is None or frame[0] != FOOTER or len(frame[1]) != 20:
        return
    (pos,) = struct.unpack_from("<Q", frame[1], 0)
    scratch = SalvageReport()
    while 0 < pos < footer and (frame := _frame(buf, pos)) is not None:
        if frame[0] in (SCHEMA, CHANNEL):
            _record(frame[0], frame[1], state, scratch)
        elif frame[0] == CHUNK_INDEX:
            with suppress(struct.error, ValueError):
                _add_chunk_index(state, frame[1])
        pos += _HEADER + len(frame[1])


def _walk(
    buf: memoryview, data: mmap.mmap, report: SalvageReport, state: _State
) -> Iterator[tuple[McapChannel, int, bytes]]:
    _summary_channels(buf, state)
    pos = len(MCAP_MAGIC) if bytes(buf[: len(MCAP_MAGIC)]) == MCAP_MAGIC else 0
    if pos == 0:
        report.has_magic = bytes(buf[-len(MCAP_MAGIC) :]) == MCAP_MAGIC
    while pos < len(buf):
        frame = _frame(buf, pos)
        if frame is not None and frame[0] == CHUNK:
            state.last_chunk = pos
            try:
                records = _chunk_records(frame[1])
            except Exception as err:  # rosbags' decompressors raise several types on bad data
                report.skipped_records += 1
                _chunk_failed(state, pos, frame[1], err)
            else:
                report.intact_records += 1
                state.read.add(pos)
                yield from _inner(records, state, report)
        elif frame is not None and frame[0] == FOOTER:
            report.end = "read to the footer"
            return
        elif frame is not None and _damaged_at(buf, pos + _HEADER + len(frame[1])):
            report.skipped_records += 1
        elif frame is not None and frame[0] == MESSAGE_INDEX:
            _note_message_index(state, frame[1])
        elif frame is not None:
            got = _record(frame[0], frame[1], state, report)
            if got is not None:
                yield got
        else:
            found = _resync(buf, data, pos)
            if found is None:
                report.end = (
                    f"stopped at byte {pos}: the record there runs past the end of the file"
                    " or is damaged, and no intact chunk follows"
                )
                return
            report.damaged.append((pos, found))
            pos = found
            continue
        pos += _HEADER + len(frame[1])
    if report.has_magic or report.intact_records:  # an MCAP file ends with its footer: this one was cut
        report.end = (
            f"stopped at byte {len(buf)}, the end of the file, before the footer: the recording was cut "
            "there or is still being written"
        )


def mcap_messages(path: Path, report: SalvageReport) -> Iterator[tuple[McapChannel, int, bytes]]:
    """(channel, log_ns, data) of every intact message record of an MCAP file, in file order.

    `report` is filled while iterating (see the module docstring). The file
    must exist; an empty file yields nothing and its report is not intact.
    """
    with path.open("rb") as f:
        if f.seek(0, 2) == 0:
            report.end = "the file is empty (0 bytes)"  # not intact: nothing of a recording was saved
            return
        data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    buf = memoryview(data)
    state = _State()
    try:
        yield from _walk(buf, data, report, state)
        report.lost_chunks = _lost_chunks(path, state, report)
    finally:
        buf.release()
        with suppress(BufferError):  # a caller's traceback may still pin a view; then GC closes it
            data.close()
