"""Open ROS 1 and ROS 2 bags and iterate their raw messages.

Public API:

- `open_bags(paths, salvage=False) -> BagSet`: one or several ROS 1 `.bag`
  files, or ROS 2 `.mcap`/`.db3` files and rosbag2 directories (not mixed),
  read through rosbags' `AnyReader` with the SensorBox typestore
  (`ingest.bags.rostypes.typestore`) as the fallback for bags without embedded
  definitions. With `salvage=True`, MCAP files that are truncated or still
  being written (and rosbag2 directories holding them or lacking
  metadata.yaml) are read with `salvage_mcap` instead of failing.
- `BagSet.topics() -> dict[str, TopicSummary]`: type and message count per topic.
- `BagSet.messages(topics=None, start_ns=None, stop_ns=None) -> Iterator[RawMessage]`:
  lazy, merged in log-time order; `stop_ns` is exclusive.
- `BagSet.close()`, or use the `BagSet` as a context manager.
- `salvage_mcap(path, topics=None) -> Iterator[RawMessage]`: every message of
  every complete chunk of a truncated or unclosed MCAP file, in file order.
- `RawMessage(topic, msgtype, log_ns, raw, ros_version)`: `log_ns` is the bag's
  receive time, *not* the header stamp sync must use; decode `raw` with
  `ingest.bags.decode.decode(msgtype, raw, ros_version)`.

Trust in message layouts: a connection whose embedded definition is empty
(rosbag2 writes those when it cannot find a type; rosbags would then decode an
empty struct without complaint) is accepted only when SensorBox's typestore
knows the type, which is what `ingest.bags.decode` uses; otherwise `BagError`.
For the types `ingest.bags.decode` reads with numpy, an embedded definition that
differs from SensorBox's (different hash) is refused the same way.

Every failure to open or read a bag raises `BagError` naming the path, with a
hint for the common cases (truncated MCAP: rerun with --salvage; unindexed
ROS 1 bag: rosbag reindex).
"""

from __future__ import annotations

import dataclasses
import heapq
import logging
from collections.abc import Collection, Iterable, Iterator, Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from types import TracebackType
from typing import Any

from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel as McapChannel
from mcap.records import Chunk as McapChunk
from mcap.records import Message as McapMessage
from mcap.records import Schema as McapSchema
from mcap.stream_reader import StreamReader, breakup_chunk
from rosbags.highlevel import AnyReader
from rosbags.interfaces import MessageDefinition, MessageDefinitionFormat
from rosbags.rosbag2.storage_mcap import decompress as decompress_mcap_chunk
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

from calibration.errors import SensorboxError
from ingest.bags.decode import DECODED_TYPES, RosVersion
from ingest.bags.message import RawMessage
from ingest.bags.rostypes import typestore
from ingest.errors import BagError

__all__ = ["BagError", "BagSet", "RawMessage", "TopicSummary", "open_bags", "salvage_mcap"]

log = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"
SALVAGE_HINT = "rerun with --salvage to read its complete chunks"


@dataclass(frozen=True)
class TopicSummary:
    """What a topic holds: its message type and message count."""

    msgtype: str
    count: int


# ---------------------------------------------------------------- definitions


@cache
def _our_hash(msgtype: str, ros_version: RosVersion) -> str:
    """RIHS01 (ROS 2) or MD5 (ROS 1) of SensorBox's own definition of `msgtype`."""
    store = typestore(ros_version)
    return store.hash_rihs01(msgtype) if ros_version == 2 else store.generate_msgdef(msgtype)[1]


@cache
def _embedded_hash(msgtype: str, msgdef: MessageDefinition, ros_version: RosVersion) -> str:
    """The same hash of a bag's embedded definition (parsed like AnyReader does)."""
    store = get_typestore(Stores.EMPTY)
    if msgdef.format == MessageDefinitionFormat.IDL:
        sep = "=" * 80 + "\n"
        if msgdef.data.startswith(f"{sep}IDL: "):
            for part in msgdef.data.split(sep)[1:]:
                store.register(get_types_from_idl(part.split("\n", 1)[1]))
        else:
            store.register(get_types_from_idl(msgdef.data))
    else:
        store.register(get_types_from_msg(msgdef.data, msgtype))
    return store.hash_rihs01(msgtype) if ros_version == 2 else store.generate_msgdef(msgtype)[1]


def _check_definition(
    where: str, topic: str, msgtype: str, msgdef: MessageDefinition, ros_version: RosVersion
) -> None:
    """Raise `BagError` unless the messages of `topic` can be decoded without guessing."""
    if not msgdef.data.strip():
        if msgtype not in typestore(ros_version).types:
            raise BagError(
                f"{where}: topic {topic!r} has no embedded message definition for type {msgtype!r}"
                " and SensorBox does not know that type; refusing to guess its layout"
            )
        return  # decoded with SensorBox's typestore
    if msgtype not in DECODED_TYPES:
        return
    try:
        theirs = _embedded_hash(msgtype, msgdef, ros_version)
    except Exception as err:  # rosbags' parsers raise several types on bad text
        raise BagError(
            f"{where}: topic {topic!r}: the embedded definition of {msgtype} cannot be parsed: {err}"
        ) from err
    ours = _our_hash(msgtype, ros_version)
    if theirs != ours:
        raise BagError(
            f"{where}: topic {topic!r}: the bag's definition of {msgtype} differs from the one"
            f" SensorBox decodes ({theirs} != {ours}); refusing to decode it"
        )


# ---------------------------------------------------------------- salvage


@dataclass(frozen=True)
class _Channel:
    topic: str
    msgtype: str
    msgdef: MessageDefinition
    ros_version: RosVersion | None  # None: a message encoding SensorBox cannot decode
    encoding: str


_SCHEMA_FORMATS = {
    "ros2msg": MessageDefinitionFormat.MSG,
    "ros1msg": MessageDefinitionFormat.MSG,
    "ros2idl": MessageDefinitionFormat.IDL,
    "omgidl": MessageDefinitionFormat.IDL,
}
_ENCODING_VERSIONS: dict[str, RosVersion] = {"cdr": 2, "ros1": 1}


def _chunk_records(chunk: McapChunk) -> list[Any]:
    """Records inside one chunk, decompressed (zstd, lz4) and size/CRC-checked by rosbags."""
    data = decompress_mcap_chunk(
        chunk.data, chunk.compression, chunk.uncompressed_size, chunk.uncompressed_crc
    )
    return list(breakup_chunk(dataclasses.replace(chunk, compression="", data=data)))


def _mcap_messages(path: Path) -> Iterator[tuple[_Channel, int, bytes]]:
    """(channel, log_ns, data) of every complete message record in an MCAP file."""
    schemas: dict[int, McapSchema] = {}
    channels: dict[int, _Channel] = {}
    count = skipped = 0
    stopped = "end of file"
    with path.open("rb") as f:
        if f.read(8) != MCAP_MAGIC:
            raise BagError(f"{path}: not an MCAP file (no MCAP magic at its start)")
        f.seek(0)
        # a record cut short by the end of the file raises EndOfFile before it is yielded
        records = StreamReader(f, emit_chunks=True).records
        while True:
            try:
                record = next(records)
            except StopIteration:
                break
            except (EndOfFile, McapError, ValueError, OSError, EOFError) as err:
                stopped = f"stopped at byte {f.tell()}: {type(err).__name__} {err}".strip()
                break
            inner: Iterable[Any] = (record,)
            if isinstance(record, McapChunk):
                try:
                    inner = _chunk_records(record)
                except Exception as err:  # corrupt chunk: skip it, keep reading the next ones
                    skipped += 1
                    log.warning("%s: skipping an unreadable chunk: %s", path, err)
                    continue
            for rec in inner:
                if isinstance(rec, McapSchema):
                    schemas[rec.id] = rec
                elif isinstance(rec, McapChannel):
                    schema = schemas.get(rec.schema_id)
                    msgdef = MessageDefinition(MessageDefinitionFormat.NONE, "")
                    if schema is not None:
                        fmt = _SCHEMA_FORMATS.get(schema.encoding, MessageDefinitionFormat.NONE)
                        msgdef = MessageDefinition(fmt, schema.data.decode(errors="replace"))
                    channels[rec.id] = _Channel(
                        rec.topic,
                        schema.name if schema is not None else "",
                        msgdef,
                        _ENCODING_VERSIONS.get(rec.message_encoding),
                        rec.message_encoding,
                    )
                elif isinstance(rec, McapMessage):
                    channel = channels.get(rec.channel_id)
                    if channel is None:
                        skipped += 1
                        continue
                    count += 1
                    yield channel, rec.log_time, rec.data
    level = logging.INFO if not skipped and stopped == "end of file" else logging.WARNING
    log.log(
        level, "%s: salvaged %d messages (%d unreadable records skipped); %s", path, count, skipped, stopped
    )


def salvage_mcap(path: str | Path, topics: Collection[str] | None = None) -> Iterator[RawMessage]:
    """Messages of every complete chunk of a truncated or unclosed MCAP file, in file order.

    Reads records with `mcap`'s `StreamReader` until the file ends or a record
    is cut short; a chunk that fails to decompress or its CRC is skipped. A
    complete file yields all its messages. `topics` limits the output (None: all).
    Raises `BagError` for a missing or non-MCAP file and, when reached, for a
    topic whose type cannot be decoded safely (see the module docstring).
    """
    path = Path(path)
    if not path.is_file():
        raise BagError(f"{path}: no such MCAP file")
    wanted = None if topics is None else set(topics)
    return _salvage(path, wanted)


def _salvage(path: Path, wanted: set[str] | None) -> Iterator[RawMessage]:
    checked: set[_Channel] = set()
    for channel, log_ns, data in _mcap_messages(path):
        if wanted is not None and channel.topic not in wanted:
            continue
        if channel not in checked:
            _check_salvaged(path, channel)
            checked.add(channel)
        assert channel.ros_version is not None  # _check_salvaged
        yield RawMessage(channel.topic, channel.msgtype, log_ns, data, channel.ros_version)


def _check_salvaged(path: Path, channel: _Channel) -> None:
    if channel.ros_version is None:
        raise BagError(
            f"{path}: topic {channel.topic!r} uses message encoding {channel.encoding!r};"
            " expected 'cdr' (ROS 2) or 'ros1'"
        )
    if not channel.msgtype:
        raise BagError(f"{path}: topic {channel.topic!r} has no schema, so its message type is unknown")
    _check_definition(str(path), channel.topic, channel.msgtype, channel.msgdef, channel.ros_version)


def _mcap_is_complete(path: Path) -> bool:
    """True when an MCAP file ends with the closing magic (it was closed properly)."""
    try:
        with path.open("rb") as f:
            if f.seek(0, 2) < 2 * len(MCAP_MAGIC):
                return False
            f.seek(-len(MCAP_MAGIC), 2)
            return f.read() == MCAP_MAGIC
    except OSError:
        return False


def _salvage_targets(path: Path) -> list[Path]:
    """MCAP files of `path` that only salvage can read (empty when AnyReader can)."""
    if path.is_file():
        return [path] if path.suffix == ".mcap" and not _mcap_is_complete(path) else []
    mcaps = sorted(path.glob("*.mcap"))
    if mcaps and (not (path / "metadata.yaml").exists() or not all(map(_mcap_is_complete, mcaps))):
        return mcaps
    return []


# ---------------------------------------------------------------- opening


def _ros_version(paths: Sequence[Path]) -> RosVersion:
    """1 for `.bag` files, 2 for `.mcap`/`.db3` files and directories; mixing is an error."""
    kinds: set[RosVersion] = set()
    for path in paths:
        if not path.exists():
            raise BagError(f"{path}: no such file or directory")
        if path.name.endswith(".bag.active"):
            raise BagError(
                f"{path}: unfinished ROS 1 recording (.bag.active, the recorder was interrupted);"
                " run `rosbag reindex` on it and rename it to .bag"
            )
        if path.is_dir() or path.suffix in (".mcap", ".db3"):
            kinds.add(2)
        elif path.suffix == ".bag":
            kinds.add(1)
        else:
            raise BagError(f"{path}: expected a ROS 1 .bag, a ROS 2 .mcap/.db3 file or a rosbag2 directory")
    if len(kinds) > 1:
        raise BagError(f"cannot read ROS 1 and ROS 2 bags together: {', '.join(map(str, paths))}")
    return kinds.pop() if kinds else 2


def _explain(path: Path, err: BaseException) -> str:
    """A one-line diagnosis of why rosbags could not open `path`."""
    text = str(err)
    if path.suffix == ".mcap" and path.is_file() and not _mcap_is_complete(path):
        return f"{path}: MCAP file is truncated or still being written (no closing magic); {SALVAGE_HINT}"
    if path.is_dir():
        mcaps = sorted(path.glob("*.mcap"))
        if not (path / "metadata.yaml").exists():
            if mcaps:
                return (
                    f"{path}: rosbag2 directory has no metadata.yaml (the recording was interrupted"
                    f" or is still running); {SALVAGE_HINT}"
                )
            return f"{path}: not a rosbag2 directory (no metadata.yaml)"
        cut = [m.name for m in mcaps if not _mcap_is_complete(m)]
        if cut:
            return f"{path}: {', '.join(cut)} truncated or still being written; {SALVAGE_HINT}"
    if "not indexed" in text:
        return (
            f"{path}: ROS 1 bag is not indexed (recording was interrupted); run `rosbag reindex` on it first"
        )
    if "index looks damaged" in text:
        return (
            f"{path}: ROS 1 bag is truncated or its index is damaged ({text});"
            " run `rosbag reindex` on it first"
        )
    return f"{path}: cannot read bag: {type(err).__name__}: {text}"


def _open_reader(paths: list[Path], ros_version: RosVersion) -> AnyReader:
    """An open AnyReader over `paths`, or `BagError` naming the path that fails."""
    try:
        reader = AnyReader(paths, default_typestore=typestore(ros_version))
        reader.open()
    except Exception as err:  # rosbags raises its own errors, OSError, KeyError, ...
        if len(paths) == 1:
            raise BagError(_explain(paths[0], err)) from err
        for path in paths:  # which one is it?
            try:
                with AnyReader([path], default_typestore=typestore(ros_version)):
                    pass
            except Exception as single:
                raise BagError(_explain(path, single)) from err
        names = ", ".join(map(str, paths))
        raise BagError(f"cannot read these bags together ({names}): {type(err).__name__}: {err}") from err
    return reader


def open_bags(paths: str | Path | Sequence[str | Path], salvage: bool = False) -> BagSet:
    """Open one or several bags of one ROS version for reading (see the module docstring).

    `salvage=True` reads truncated or unclosed MCAP files chunk by chunk
    instead of raising. Raises `BagError` naming the path at fault.
    """
    items = [paths] if isinstance(paths, str | Path) else list(paths)
    if not items:
        raise BagError("no bag paths given")
    bag_paths = [Path(p) for p in items]
    ros_version = _ros_version(bag_paths)
    salvaged: list[Path] = []
    direct = bag_paths
    if salvage and ros_version == 2:
        targets = {p: _salvage_targets(p) for p in bag_paths}
        salvaged = [m for p in bag_paths for m in targets[p]]
        direct = [p for p in bag_paths if not targets[p]]
    reader = _open_reader(direct, ros_version) if direct else None
    return BagSet(tuple(bag_paths), ros_version, reader, salvaged)


# ---------------------------------------------------------------- the bag set


class BagSet:
    """Open bags of one ROS version; create with `open_bags`."""

    def __init__(
        self, paths: tuple[Path, ...], ros_version: RosVersion, reader: AnyReader | None, salvaged: list[Path]
    ) -> None:
        self.paths = paths
        """The paths given to `open_bags`."""
        self.ros_version: RosVersion = ros_version
        self.salvaged: tuple[Path, ...] = tuple(salvaged)
        """MCAP files read by salvage rather than by rosbags."""
        self._reader = reader
        self._salvage_index: dict[Path, dict[_Channel, int]] = {}

    @property
    def label(self) -> str:
        """The bags' paths, for messages."""
        return ", ".join(str(p) for p in self.paths)

    def __enter__(self) -> BagSet:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close the underlying readers (idempotent)."""
        if self._reader is not None and self._reader.stack is not None:
            self._reader.close()

    @property
    def _where(self) -> str:
        return ", ".join(map(str, self.paths))

    def _index(self, path: Path) -> dict[_Channel, int]:
        """Message count per channel of a salvaged file (one full read, cached)."""
        if path not in self._salvage_index:
            counts: dict[_Channel, int] = {}
            for channel, _, _ in _mcap_messages(path):
                counts[channel] = counts.get(channel, 0) + 1
            self._salvage_index[path] = counts
        return self._salvage_index[path]

    def topics(self) -> dict[str, TopicSummary]:
        """Message type and count of every topic, sorted by name."""
        types: dict[str, set[str]] = {}
        counts: dict[str, int] = {}
        if self._reader is not None:
            for name, info in self._reader.topics.items():
                types.setdefault(name, set()).update(c.msgtype for c in info.connections)
                counts[name] = counts.get(name, 0) + info.msgcount
        for path in self.salvaged:
            for channel, n in self._index(path).items():
                types.setdefault(channel.topic, set()).add(channel.msgtype)
                counts[channel.topic] = counts.get(channel.topic, 0) + n
        return {t: TopicSummary(" | ".join(sorted(types[t])), counts[t]) for t in sorted(types)}

    def _missing_topic(self, topic: str) -> BagError:
        have = "; ".join(f"{t} ({s.msgtype}, {s.count})" for t, s in self.topics().items()) or "none"
        return BagError(f"topic {topic!r} is not in {self._where}; its topics are: {have}")

    def messages(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        stop_ns: int | None = None,
    ) -> Iterator[RawMessage]:
        """Lazy iterator over the raw messages of `topics` (None: all), merged by log time.

        `start_ns`/`stop_ns` bound the log time (stop exclusive). Topics that
        are not in the bags, and topics whose type cannot be decoded safely,
        raise `BagError` here, before any message is read.
        """
        names = self.topics()
        wanted = set(names) if topics is None else set(topics)
        for topic in sorted(wanted):
            if topic not in names:
                raise self._missing_topic(topic)
        sources: list[Iterator[RawMessage]] = []
        if self._reader is not None:
            conns = [c for c in self._reader.connections if c.topic in wanted]
            for conn in conns:
                where = str(getattr(conn.owner, "path", self._where))
                _check_definition(where, conn.topic, conn.msgtype, conn.msgdef, self.ros_version)
            if conns:
                sources.append(self._read(conns, start_ns, stop_ns))
        for path in self.salvaged:
            for channel in self._index(path):
                if channel.topic in wanted:
                    _check_salvaged(path, channel)
            sources.append(_time_window(_salvage(path, wanted), start_ns, stop_ns))
        if len(sources) == 1:
            return sources[0]
        return heapq.merge(*sources, key=lambda m: m.log_ns)

    def _read(self, conns: list[Any], start_ns: int | None, stop_ns: int | None) -> Iterator[RawMessage]:
        assert self._reader is not None
        try:
            for conn, log_ns, raw in self._reader.messages(connections=conns, start=start_ns, stop=stop_ns):
                yield RawMessage(conn.topic, conn.msgtype, log_ns, raw, self.ros_version)
        except SensorboxError:
            raise
        except Exception as err:  # rosbags raises its own errors, OSError, struct.error, ...
            raise BagError(f"{self._where}: reading messages failed: {type(err).__name__}: {err}") from err


def _time_window(
    messages: Iterator[RawMessage], start_ns: int | None, stop_ns: int | None
) -> Iterator[RawMessage]:
    """Messages with start_ns <= log_ns < stop_ns (None: unbounded)."""
    for msg in messages:
        if (start_ns is None or msg.log_ns >= start_ns) and (stop_ns is None or msg.log_ns < stop_ns):
            yield msg
