"""Which planned samples a corrupt chunk touches: those whose inputs could have been in it.

Public API:

- `lost_intervals(chunks, topic, log_ns, first_ns, last_ns) -> list[(lo, hi)]`:
  the header-time intervals where `topic`'s messages lost in corrupt chunks
  can lie.
- `untouched(tc_ns, intervals, margins_ns) -> bool mask`: the samples whose
  input windows overlap none of them.

A chunk is indexed by log (receive) time, but samples are chosen on header
stamps, and a LiDAR sweep's points span ~100 ms after its stamp, so the
chunk's log-time range does not say directly which sample windows lost data.
The intact messages of the same topic bound it: a message lost from a chunk
was logged between the chunk's first and last log time, so (as long as a
topic's stamps follow its log order) its stamps lie after the last stamp of
every intact message logged before the chunk and before the first stamp of
every intact message logged after it. A sample whose LiDAR or IMU window
overlaps such an interval would be made from incomplete data; it is not
planned, and counted.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from calibration.types import I64
from ingest.bags.chunks import LostChunk

__all__ = ["lost_intervals", "untouched"]

_MIN = int(np.iinfo(np.int64).min)
_MAX = int(np.iinfo(np.int64).max)


def _holds(chunk: LostChunk, topic: str) -> bool:
    """True when the chunk held messages of `topic` (or nobody knows what it held)."""
    return not chunk.counts or chunk.counts.get(topic, 0) > 0


def lost_intervals(
    chunks: Sequence[LostChunk], topic: str, log_ns: I64, first_ns: I64, last_ns: I64
) -> list[tuple[int, int]]:
    """Open header-time intervals (lo, hi) in ns where `topic`'s lost messages can lie.

    `log_ns`, `first_ns`, `last_ns`: per intact message of `topic`, its log
    time and its first and last stamp (a sweep's first and last point; a
    frame's or IMU sample's stamp twice). A chunk without a known time range
    could have held anything: its interval is unbounded.
    """
    order = np.argsort(log_ns, kind="stable")
    logs = log_ns[order]
    last_before = np.maximum.accumulate(last_ns[order]) if len(order) else last_ns
    first_after = np.minimum.accumulate(first_ns[order][::-1])[::-1] if len(order) else first_ns
    out = []
    for chunk in chunks:
        if not _holds(chunk, topic):
            continue
        if chunk.start_ns is None or chunk.end_ns is None:
            out.append((_MIN, _MAX))
            continue
        i = int(np.searchsorted(logs, chunk.start_ns, "left"))  # logs[:i] came before the chunk
        j = int(np.searchsorted(logs, chunk.end_ns, "right"))  # logs[j:] came after it
        lo = int(last_before[i - 1]) if i > 0 else _MIN
        hi = int(first_after[j]) if j < len(logs) else _MAX
        out.append((lo, hi))
    return out


def untouched(
    tc_ns: I64, intervals: Mapping[str, list[tuple[int, int]]], margins_ns: Mapping[str, int]
) -> np.ndarray:
    """Mask of samples (frame times `tc_ns`) whose windows overlap no lost interval.

    A sample reads `topic` within tc +- `margins_ns[topic]`; topics without
    a margin (the cameras: a lost frame is simply absent) are not checked.
    """
    keep = np.ones(len(tc_ns), bool)
    for topic, margin in margins_ns.items():
        for lo, hi in intervals.get(topic, []):
            keep &= ~((tc_ns + margin > lo) & (tc_ns - margin < hi))
    return keep
