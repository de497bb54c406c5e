"""Bags given together checked before they are read as one recording: each ROS 1 bag's index counts its
messages (`indexed`), and no two files are two recordings of the same stretch (`one_recording`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ingest.errors import BagError

UNINDEXED_BYTES = 64 * 1024
"""A ROS 1 bag larger than this whose header counts no message holds messages its index does not list."""


def indexed(readers: Sequence[Any]) -> None:
    """`BagError` for a ROS 1 bag whose header and index count no message though the file is larger than
    `UNINDEXED_BYTES`: its chunks are there, its index (header chunk_count, index records) is not."""
    for r in readers:
        path = Path(str(r.path))
        if path.suffix != ".bag" or int(r.message_count) or not path.is_file():
            continue
        size = path.stat().st_size
        if size > UNINDEXED_BYTES:
            raise BagError(
                f"{path}: ROS 1 bag whose header and index count no message though the file holds {size:,} "
                "bytes: its index is damaged; run `rosbag reindex` on it first"
            )


def one_recording(readers: Sequence[Any]) -> None:
    """`BagError` when two of the bags given together overlap in time on a topic they share and the later
    one's first message there is not in the earlier one: two recordings of the same sensors, whose
    messages would interleave, not the files of one (a split recording's files follow each other or
    repeat each other's messages, which are read once; recorders of other topics are welcome)."""
    spans = sorted(readers, key=lambda r: (int(r.start_time), str(r.path)))
    for k, a in enumerate(spans):
        for b in spans[k + 1 :]:
            if int(b.start_time) >= int(a.end_time):
                break
            overlap_ns = min(int(a.end_time), int(b.end_time)) - int(b.start_time)
            shorter_ns = min(int(a.end_time) - int(a.start_time), int(b.end_time) - int(b.start_time))
            if overlap_ns <= max(SPLIT_OVERLAP_NS, SPLIT_OVERLAP_SHARE * shorter_ns):
                continue  # files cut by header stamp overlap a little in log time
            shared = _recorded(a) & _recorded(b)
            if shared and not _repeats(a, b, shared):
                raise BagError(
                    f"{a.path} and {b.path} overlap in time ({_span(a)} and {_span(b)}) on {len(shared)} "
                    f"topics such as {sorted(shared)[0]} with other messages: two recordings, not the files "
                    "of one (a split recording's files follow each other); give them in two calls"
                )


SPLIT_OVERLAP_NS = 100_000_000
SPLIT_OVERLAP_SHARE = 0.25
"""Files of one recording may overlap in log time by up to this (ns), or this share of the shorter one's
span: a recording cut by header stamp, not log time (a fixture cut at 0.35 s: 51 ms); two recordings
of the same stretch overlap by most of it."""


def _recorded(reader: Any) -> set[str]:
    """The topics a file holds messages of (a file may declare every channel and fill some)."""
    return {c.topic for c in reader.connections if getattr(c, "msgcount", 1)}


def _repeats(a: Any, b: Any, topics: set[str]) -> bool:
    """Whether `b`'s first message on each of `topics` is in `a` too (same topic, log time and bytes):
    one topic may match by chance (a still rig's IMU readings), every topic's first message does not."""
    for topic in sorted(topics):
        mine = [c for c in b.connections if c.topic == topic]
        first = next(iter(b.messages(connections=mine)), None)
        if first is None:
            continue
        _, t_ns, raw = first
        theirs = [c for c in a.connections if c.topic == topic]
        same_time = a.messages(connections=theirs, start=t_ns, stop=t_ns + 1)
        if not any(bytes(r) == bytes(raw) for _, _, r in same_time):
            return False
    return True


def _span(reader: Any) -> str:
    """A reader's log-time span, in seconds."""
    return f"{int(reader.start_time) / 1e9:.3f}-{(int(reader.end_time) - 1) / 1e9:.3f} s"
