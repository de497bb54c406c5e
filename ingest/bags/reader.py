"""Open ROS 1 and ROS 2 bags and iterate their raw messages.

Public API:

- `open_bags(paths, salvage=False) -> BagSet`: one or several ROS 1 `.bag`
  files, or ROS 2 `.mcap`/`.db3` files and rosbag2 directories (not mixed),
  read through rosbags' `AnyReader` with the SensorBox typestore
  (`ingest.bags.rostypes.typestore`) as the fallback for bags without embedded
  definitions. With `salvage=True`, every MCAP file (also those of rosbag2
  directories, whose metadata.yaml may then be missing) is read record by
  record with `salvage_mcap`, so a cut end, damaged bytes or a missing
  summary lose only what they hit.
- `BagSet.topics() -> dict[str, TopicSummary]`: type and message count per topic.
- `BagSet.messages(topics=None, start_ns=None, stop_ns=None) -> Iterator[RawMessage]`:
  lazy, merged in log-time order; `stop_ns` is exclusive.
- `BagSet.lost_chunks`, `BagSet.lost_counts()`: corrupt chunks skipped
  (salvage) and their messages per topic (`ingest.bags.chunks`).
- `BagSet.close()`, or use the `BagSet` as a context manager.
- `salvage_mcap(path, topics=None) -> Iterator[RawMessage]`: every intact
  message of a truncated, unclosed or damaged MCAP file, in file order
  (`ingest.bags.mcap_records`); what was lost is logged, never raised.
- `RawMessage(topic, msgtype, log_ns, raw, ros_version)`: `log_ns` is the bag's
  receive time, *not* the header stamp sync must use; decode `raw` with
  `ingest.bags.decode.decode(msgtype, raw, ros_version)`.

Trust in message layouts: a topic whose embedded definition cannot be parsed
(rosbag2 records service-event topics with the raw `.srv` text) is set aside
in every format with a warning naming it (`BagSet.skipped`); the rest of
the bag reads, and asking for that topic by name raises `BagError`. A
connection whose embedded definition is empty
(rosbag2 writes those when it cannot find a type; rosbags would then decode an
empty struct without complaint) is accepted only when SensorBox's typestore
knows the type, which is what `ingest.bags.decode` uses; otherwise `BagError`.
For the types `ingest.bags.decode` reads with numpy, an embedded definition that
differs from SensorBox's (different hash) is refused the same way. In
salvaged MCAP files, where damage can garble a channel record, every such
refused topic is set aside like an unparsable one rather than stopping the read.

Every failure to open or read a bag raises `BagError` naming the path, with a
hint for the common cases (truncated MCAP: rerun with --salvage; unindexed
ROS 1 bag: rosbag reindex). A corrupt chunk (failed CRC or decompression)
raises `CorruptChunkError` naming the file, the chunk's log-time range and its
messages per topic; with `salvage=True` it is skipped, logged once and listed
in `lost_chunks` (`ingest.bags.chunks` says what each format lets us check).
"""

from __future__ import annotations

import heapq
import logging
from collections.abc import Callable, Collection, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import zstandard

from calibration.errors import SensorboxError
from calibration.files import resolved
from ingest.bags.checked_readers import guard_readers
from ingest.bags.chunks import ChunkGuard, CorruptChunkError, DeferredData, LostChunk
from ingest.bags.decode import RosVersion
from ingest.bags.definitions import TolerantAnyReader, check_definition
from ingest.bags.diagnose import bag_ros_version, check_bare_db3, check_metadata, explain
from ingest.bags.message import RawMessage
from ingest.bags.recordings import indexed, one_recording
from ingest.bags.rostypes import typestore
from ingest.bags.salvage import (
    SalvageChannel,
    channel_problem,
    mcap_channel_messages,
    salvage_mcap,
    salvage_messages,
    salvage_targets,
)
from ingest.errors import BagError

__all__ = [
    "BagError",
    "BagSet",
    "CorruptChunkError",
    "LostChunk",
    "RawMessage",
    "TopicSummary",
    "open_bags",
    "salvage_mcap",
]

log = logging.getLogger(__name__)


READAHEAD_THREADS = 8
"""A whole read of the bags (the ingest's plan pass, inspect; no worker runs beside them) decompresses
chunks in up to this many threads: a bag of raw images is one 9 MB zstd chunk per image, about 20 ms
each on one core."""


@dataclass(frozen=True)
class TopicSummary:
    """What a topic holds: its message type and message count."""

    msgtype: str
    count: int


# ---------------------------------------------------------------- opening


def _decompressed(msg: RawMessage, dctx: zstandard.ZstdDecompressor) -> RawMessage:
    """`msg`, one zstd-compressed message of a rosbag2 .db3 (compression_mode 'message'), decompressed
    with `dctx` (one per read); data that does not decompress is the message's `damage` (counted under
    --max-bad, or one line naming the topic and log time), and the read goes on."""
    frame = dctx.decompressobj()
    try:
        data = frame.decompress(msg.raw)
    except zstandard.ZstdError as err:
        return msg._replace(raw=b"", damage=f"its zstd-compressed data does not decompress ({err})")
    if not frame.eof:
        return msg._replace(raw=b"", damage="its zstd-compressed data is cut short")
    return msg._replace(raw=data)


def _open_reader(paths: list[Path], ros_version: RosVersion, guard: ChunkGuard) -> TolerantAnyReader:
    """An open reader over `paths` checking chunk by chunk, or `BagError` naming the path that fails."""
    for path in paths:
        if path.is_dir():
            check_metadata(path)
        elif path.suffix == ".db3":
            check_bare_db3(path)
    try:
        reader = TolerantAnyReader(paths, default_typestore=typestore(ros_version))
        reader.readers = guard_readers(reader.readers, guard)
        reader.open()
    except Exception as err:  # rosbags raises its own errors, OSError, KeyError, ...
        if len(paths) == 1:
            raise BagError(explain(paths[0], err)) from err
        for path in paths:  # which one is it?
            try:
                with TolerantAnyReader([path], default_typestore=typestore(ros_version)):
                    pass
            except Exception as single:
                raise BagError(explain(path, single)) from err
        names = ", ".join(map(str, paths))
        raise BagError(f"cannot read these bags together ({names}): {type(err).__name__}: {err}") from err
    try:
        indexed(reader.readers)
        one_recording(reader.readers)
    except BagError:
        reader.close()
        raise
    return reader


def _resolved(path: Path) -> Path:
    """`path` with every link followed (`calibration.files.resolved`)."""
    return resolved(path, BagError, "a bag file or rosbag2 folder")


def given_once(bag_paths: Sequence[Path]) -> None:
    """One line when a recording is named twice: it would be read twice, its messages counted twice.

    A rosbag2 folder and a data file inside it (`bag/` and `bag/bag_0.mcap`)
    are the same recording too.
    """
    owner: dict[Path, Path] = {}
    for p in bag_paths:
        path = Path(p)
        files = sorted(path.glob("*.mcap")) + sorted(path.glob("*.db3")) if path.is_dir() else []
        for key in {_resolved(f) for f in files} | {_resolved(path)}:
            if key in owner:
                first = owner[key]
                same = "" if _resolved(first) == _resolved(path) else f" (as {first})"
                raise BagError(f"{p}: the same recording is given twice{same}")
            owner[key] = path


def open_bags(paths: str | Path | Sequence[str | Path], salvage: bool = False) -> BagSet:
    """Open one or several bags of one ROS version for reading (see the module docstring).

    `salvage=True` reads every MCAP file record by record (`salvage_mcap`),
    skipping what is cut or damaged instead of raising, and skips the corrupt
    chunks of the other bags (`BagSet.lost_chunks`). Raises `BagError`
    naming the path at fault (`CorruptChunkError` at a corrupt chunk).
    """
    items = [paths] if isinstance(paths, str | Path) else list(paths)
    if not items:
        raise BagError("no bag paths given")
    bag_paths = [Path(p) for p in items]
    given_once(bag_paths)
    ros_version = bag_ros_version(bag_paths)
    salvaged: list[Path] = []
    direct = bag_paths
    if salvage and ros_version == 2:
        targets = {p: salvage_targets(p) for p in bag_paths}
        salvaged = [m for p in bag_paths for m in targets[p]]
        direct = [p for p in bag_paths if not targets[p]]
    guard = ChunkGuard(skip=salvage)
    reader = _open_reader(direct, ros_version, guard) if direct else None
    try:
        return BagSet(tuple(bag_paths), ros_version, reader, salvaged, guard)
    except BaseException:
        if reader is not None:
            reader.close()
        raise


# ---------------------------------------------------------------- the bag set


Progress = Callable[[int, int], None]
"""progress(messages read, messages to read) of a read over the bags."""

PROGRESS_EVERY = 256
"""Messages between two `progress` calls of `BagSet.messages`."""


def _counted(messages: Iterator[RawMessage], total: int, progress: Progress) -> Iterator[RawMessage]:
    """`messages`, with `progress(read, total)` every `PROGRESS_EVERY` messages and at their end."""
    read = 0
    for msg in messages:
        yield msg
        read += 1
        if read % PROGRESS_EVERY == 0:
            progress(read, max(total, read))
    if read == 0 or read % PROGRESS_EVERY:
        progress(read, max(total, read))


class BagSet:
    """Open bags of one ROS version; create with `open_bags`."""

    def __init__(
        self,
        paths: tuple[Path, ...],
        ros_version: RosVersion,
        reader: TolerantAnyReader | None,
        salvaged: list[Path],
        guard: ChunkGuard | None = None,
    ) -> None:
        self.paths = paths
        """The paths given to `open_bags`."""
        self.ros_version: RosVersion = ros_version
        self.salvaged: tuple[Path, ...] = tuple(salvaged)
        """MCAP files read record by record (`salvage_mcap`) rather than by rosbags."""
        self._reader = reader
        self._guard = guard or ChunkGuard()
        self._salvage_index: dict[Path, dict[SalvageChannel, int]] = {}
        self._salvage_lost: list[LostChunk] = []
        self.skipped: dict[str, str] = {}
        """Topics left out when reading all topics -> why (one line): an embedded definition
        that cannot be parsed, or, in salvaged files, any reason a topic cannot be decoded safely."""
        if reader is not None and reader.qos_mismatches:
            log.warning(
                "%s: metadata.yaml describes %s otherwise than the storage file; their messages are "
                "read all the same", self._where, ", ".join(reader.qos_mismatches),
            )  # fmt: skip
        if reader is not None:
            for conn, problem in reader.unparsable:
                where = str(getattr(conn.owner, "path", self._where))
                self._skip(conn.topic, f"{where}: topic {conn.topic!r}: {problem}")
        for path in self.salvaged:
            for channel in self._index(path):
                if (reason := channel_problem(path, channel)) is not None:
                    self._skip(channel.topic, reason)

    def _skip(self, topic: str, reason: str) -> None:
        if topic not in self.skipped:
            log.warning("%s; skipping that topic, the others are read", reason)
            self.skipped[topic] = reason

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

    def _index(self, path: Path) -> dict[SalvageChannel, int]:
        """Message count per channel of a salvaged file (one full read, cached)."""
        if path not in self._salvage_index:
            counts: dict[SalvageChannel, int] = {}
            for channel, _, _ in mcap_channel_messages(
                path, lost=self._salvage_lost
            ):  # logs what it lost, once
                counts[channel] = counts.get(channel, 0) + 1
            self._salvage_index[path] = counts
        return self._salvage_index[path]

    @property
    def lost_chunks(self) -> tuple[LostChunk, ...]:
        """Corrupt chunks skipped so far (`salvage=True`), by file and offset.

        Those of salvaged MCAP files are all known once the bags are open;
        those of bags read by rosbags are found while reading, so the list
        is complete only after every topic has been read once.
        """
        found = [*self._salvage_lost, *self._guard.lost.values()]
        return tuple(sorted(found, key=lambda c: (str(c.path), c.offset)))

    def lost_counts(self) -> dict[str, int]:
        """Messages per topic lost in `lost_chunks` (as far as their indexes tell), sorted by topic."""
        counts: dict[str, int] = {}
        for chunk in self.lost_chunks:
            for topic, n in chunk.counts.items():
                counts[topic] = counts.get(topic, 0) + n
        return dict(sorted(counts.items()))

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

    def log_span_ns(self) -> tuple[int, int] | None:
        """First and last log time (ns) of every message in the bags, whatever its type (the readers'
        indexes; salvaged files are not indexed: None when there is no reader)."""
        if self._reader is None or not self._reader.message_count:
            return None
        return int(self._reader.start_time), int(self._reader.end_time) - 1  # rosbags' end is exclusive

    def _missing_topic(self, topic: str) -> BagError:
        have = "; ".join(f"{t} ({s.msgtype}, {s.count})" for t, s in self.topics().items()) or "none"
        return BagError(f"topic {topic!r} is not in {self._where}; its topics are: {have}")

    def messages(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        stop_ns: int | None = None,
        defer: Collection[str] = (),
        readahead: int = 0,
        progress: Progress | None = None,
    ) -> Iterator[RawMessage]:
        """Lazy iterator over the raw messages of `topics` (None: all), merged by log time.

        `start_ns`/`stop_ns` bound the log time (stop exclusive). All topics
        leaves out those in `skipped`. Topics that are not in the bags,
        and topics whose type cannot be decoded safely (asked for by name,
        skipped ones too), raise `BagError` here, before any message is read.
        A large message of a `defer` topic that ends its MCAP chunk may come
        still compressed (`RawMessage.deferred`, `ingest.bags.chunks.chunk_messages`):
        for a read after one that checked every chunk. The readers are told
        when the read starts and until it ends; a read interleaved with it may
        be handed deferred messages too, which it decompresses here, so only a
        read that asked gets `deferred` messages. `readahead` threads decompress
        the MCAP chunks this read reads whole ahead of it (a first read of a
        bag of raw images: each chunk is an image); they end with the read.
        `progress(read, total)` hears every `PROGRESS_EVERY` messages and once
        when the read ends, with `total` the topics' message count in the bags
        (more than a read bounded by `start_ns`/`stop_ns` gets).
        """
        names = self.topics()
        wanted = set(names) - set(self.skipped) if topics is None else set(topics)
        for topic in sorted(wanted):
            if topic not in names:
                raise self._missing_topic(topic)
            if topic in self.skipped:
                raise BagError(f"{self.skipped[topic]}; that topic is skipped")
        sources: list[Iterator[RawMessage]] = []
        if self._reader is not None:
            conns = [c for c in self._reader.connections if c.topic in wanted]
            for conn in conns:
                where = str(getattr(conn.owner, "path", self._where))
                check_definition(where, conn.topic, conn.msgtype, conn.msgdef, self.ros_version)
            if conns:
                sources.append(self._read(conns, start_ns, stop_ns, frozenset(defer), readahead))
        for path in self.salvaged:  # skipped topics are not in `wanted`
            sources.append(_time_window(salvage_messages(path, wanted, quiet=True), start_ns, stop_ns))
        merged = sources[0] if len(sources) == 1 else heapq.merge(*sources, key=lambda m: m.log_ns)
        if progress is None:
            return merged
        return _counted(merged, sum(names[t].count for t in wanted), progress)

    def _read(
        self, conns: list[Any], start_ns: int | None, stop_ns: int | None, defer: frozenset[str],
        readahead: int,
    ) -> Iterator[RawMessage]:  # fmt: skip
        assert self._reader is not None
        if defer:  # the MCAP readers look when they start reading
            self._guard.defer_topics = defer
        if readahead:
            self._guard.readahead = readahead
        compressed = self._reader.message_compressed
        dctx = zstandard.ZstdDecompressor()  # reused by every message of this read
        try:
            for conn, log_ns, raw in self._reader.messages(connections=conns, start=start_ns, stop=stop_ns):
                if compressed and id(conn.owner) in compressed:
                    msg = RawMessage(conn.topic, conn.msgtype, log_ns, raw, self.ros_version)
                    yield _decompressed(msg, dctx)
                elif isinstance(raw, DeferredData) and conn.topic in defer:
                    yield RawMessage(conn.topic, conn.msgtype, log_ns, raw.head, self.ros_version, raw)
                elif isinstance(raw, DeferredData):  # asked for by another read running beside this one
                    yield RawMessage(conn.topic, conn.msgtype, log_ns, raw.data(), self.ros_version)
                else:
                    yield RawMessage(conn.topic, conn.msgtype, log_ns, raw, self.ros_version)
        except SensorboxError:
            raise
        except Exception as err:  # rosbags raises its own errors, OSError, struct.error, ...
            raise BagError(f"{self._where}: reading messages failed: {type(err).__name__}: {err}") from err
        finally:
            if defer:
                self._guard.defer_topics = frozenset()
            if readahead:
                self._guard.readahead = 0


def _time_window(
    messages: Iterator[RawMessage], start_ns: int | None, stop_ns: int | None
) -> Iterator[RawMessage]:
    """Messages with start_ns <= log_ns < stop_ns (None: unbounded)."""
    for msg in messages:
        if (start_ns is None or msg.log_ns >= start_ns) and (stop_ns is None or msg.log_ns < stop_ns):
            yield msg
