"""A chunk of a bag that could not be read (`LostChunk`), the error that names it
(`CorruptChunkError`), and what the readers of one bag set do at one (`ChunkGuard`: raise, or log it
once, record it and go on, with `--salvage`)."""

from __future__ import annotations

import logging
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from ingest.errors import BagError

if sys.version_info >= (3, 14):
    pass
else:
    pass

__all__ = ["SALVAGE_SKIP_HINT", "ChunkGuard", "CorruptChunkError", "LostChunk", "reason_of", "ros_time"]

log = logging.getLogger(__name__)

SALVAGE_SKIP_HINT = "rerun with --salvage to skip it and count its messages as lost"


def ros_time(ns: int) -> str:
    """`sec.nanosec` of a ROS time in ns."""
    sec, nsec = divmod(ns, 1_000_000_000)
    return f"{sec}.{nsec:09d}"


@dataclass(frozen=True)
class LostChunk:
    """A chunk whose messages could not be read. Times are log times in ns, `end_ns` inclusive.

    `start_ns`/`end_ns` are None when the chunk's own header was damaged and
    no index recorded them; `counts` (topic -> messages) is empty when no
    index recorded them. `file_start_ns` is the log time of the file's first
    message, for times relative to the bag start.
    """

    path: Path
    offset: int
    start_ns: int | None
    end_ns: int | None
    counts: Mapping[str, int]
    reason: str
    file_start_ns: int | None = None

    @property
    def messages(self) -> int | None:
        """Messages the chunk held (None: unknown)."""
        return sum(self.counts.values()) if self.counts else None

    def time_range(self) -> str:
        """The log-time range as ROS time and as seconds from the bag start."""
        if self.start_ns is None or self.end_ns is None:
            return "log-time range unknown"
        text = f"log time {ros_time(self.start_ns)}..{ros_time(self.end_ns)}"
        if self.file_start_ns is not None:
            rel = ((t - self.file_start_ns) / 1e9 for t in (self.start_ns, self.end_ns))
            text += " ({:.3f}..{:.3f} s from the bag start)".format(*rel)
        return text

    def describe(self) -> str:
        """One line: file, offset, why, time range and the messages lost per topic."""
        held = ", ".join(f"{n} on {t}" for t, n in sorted(self.counts.items()))
        noun = "message" if self.messages == 1 else "messages"
        what = f"{self.messages} {noun}: {held}" if self.counts else "message count unknown"
        return (
            f"{self.path}: corrupt chunk at byte {self.offset} ({self.reason}), {self.time_range()}, {what}"
        )


class CorruptChunkError(BagError):
    """A chunk of a bag is corrupt and the reader was not asked to skip it."""

    def __init__(self, chunk: LostChunk) -> None:
        super().__init__(f"{chunk.describe()}; {SALVAGE_SKIP_HINT}")
        self.chunk = chunk


def reason_of(err: BaseException) -> str:
    text = " ".join(str(err).split()).rstrip(".")
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


@dataclass
class ChunkGuard:
    """What the readers of one bag set share: what to do at a corrupt chunk (raise
    `CorruptChunkError`, or record it and go on), and which topics' messages may stay compressed."""

    skip: bool = False
    lost: dict[tuple[Path, int], LostChunk] = field(default_factory=dict)
    """Chunks skipped so far, by (file, byte offset)."""
    defer_topics: frozenset[str] = frozenset()
    """Topics whose large messages an MCAP reader may hand out as `DeferredData` (set for one read by
    `BagSet.messages(defer=...)`)."""
    checked: set[tuple[Path, int]] = field(default_factory=set)
    """MCAP chunks read whole and found intact, by (file, byte offset): later reads may read part."""
    readahead: int = 0
    """Threads that decompress the chunks an MCAP read will read whole ahead of it (0: none; set for
    one read by `BagSet.messages(readahead=...)`)."""

    def report(self, chunk: LostChunk) -> None:
        """Raise, or (skip) log one warning line the first time and record the chunk."""
        if not self.skip:
            raise CorruptChunkError(chunk)
        key = (chunk.path, chunk.offset)
        if key not in self.lost:
            log.warning("%s; skipped, its messages are counted as lost", chunk.describe())
            self.lost[key] = chunk

    def is_lost(self, path: Path, offset: int) -> bool:
        return (path, offset) in self.lost
