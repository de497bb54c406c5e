"""Messages read twice: the same file under two names, split bags that overlap, a recorder that wrote
a message twice. Every pass over the bags keeps the first copy only, so that the plan, the gyro,
the trajectory and the samples all see the recording once.

A sweep is known by `sweep_key` (its first and last point time and its point
count: two different sweeps of one LiDAR never share all three), a frame or
an IMU reading by its header stamp. The plan pass also compares a repeat's
bytes with its first copy's (`fingerprint`): a message with other content
under an earlier stamp is a sensor clock that stalled or stepped back, left
out like a copy but listed apart (`FirstCopies.restamped`) so that the run
says so.
"""

from __future__ import annotations

import zlib

from ingest.bags.decode import Sweep

HORIZON_NS = 10_000_000_000
"""A copy is recognised up to this long (message time) after its first: bags are read merged in time,
so a copy arrives beside its first."""


FINGERPRINT_TAIL = 4096
"""Bytes at a message's end that `fingerprint` hashes: the whole of an IMU reading, the last of an
image's data (JPEG entropy data or raw pixels, which differ between any two exposures)."""


def fingerprint(raw: bytes | memoryview) -> tuple[int, int]:
    """What tells two messages with one header stamp apart without hashing megabytes: the length and the
    CRC-32 of the last `FINGERPRINT_TAIL` bytes."""
    return len(raw), zlib.crc32(raw[-FINGERPRINT_TAIL:])


def sweep_key(sweep: Sweep) -> tuple[int, int, int]:
    """What makes a sweep the same as another: its first and last point time and its point count."""
    return int(sweep.span_ns[0]), int(sweep.span_ns[1]), len(sweep.stamps_ns)


class FirstCopies:
    """Which messages are first copies; keys older than `HORIZON_NS` behind their topic's newest are
    forgotten (per topic: sensors on other clocks do not prune each other)."""

    def __init__(self, horizon_ns: int = HORIZON_NS) -> None:
        self.horizon_ns = horizon_ns
        self.repeats: dict[str, int] = {}  # per topic: copies seen after the first
        self.restamped: dict[str, list[int]] = {}  # per topic: stamps of repeats whose bytes differ
        self.overlapping: dict[str, list[int]] = {}  # per topic: first point times of sweeps left out
        self._seen: dict[tuple[str, object], tuple[int, object]] = {}
        self._spans: dict[str, list[tuple[int, int]]] = {}  # per topic: the kept sweeps' point-time spans
        self._newest: dict[str, int] = {}
        self._bound = 4096  # entries before the next pruning

    def first(self, topic: str, key: object, t_ns: int, content: object = None) -> bool:
        """True for the first copy of (`topic`, `key`) at message time `t_ns`; a repeat is counted, and
        listed in `restamped` when its `content` (a `fingerprint`, or None: not compared) differs."""
        known = self._seen.get((topic, key))
        if known is not None:
            self.repeats[topic] = self.repeats.get(topic, 0) + 1
            if content is not None and known[1] is not None and content != known[1]:
                self.restamped.setdefault(topic, []).append(t_ns)
            return False
        self._seen[(topic, key)] = (t_ns, content)
        self._newest[topic] = max(self._newest.get(topic, t_ns), t_ns)
        if len(self._seen) > self._bound:
            self._seen = {k: v for k, v in self._seen.items() if v[0] >= self._newest[k[0]] - self.horizon_ns}
            self._bound = max(4096, 2 * len(self._seen))
        return True

    def stamped(self, topic: str, stamp_ns: int, content: object = None) -> bool:
        """`first` for a frame or IMU reading, known by its header stamp (`content`: its `fingerprint`)."""
        return self.first(topic, stamp_ns, stamp_ns, content)

    def sweep(self, topic: str, sweep: Sweep) -> bool:
        """`first` for a sweep with points; False too, listed in `overlapping`, for a sweep whose point
        times lie mostly within a kept sweep's of the same LiDAR.

        A LiDAR measures each moment once: its sweeps abut in time, whatever
        order they are logged in. A sweep whose points cover an earlier one's
        carries a stamp that is not its own (a driver that repeated the
        previous sweep's timebase): placed there, its points stand where the
        rig was not, and its own moment has none.
        """
        first, last = int(sweep.span_ns[0]), int(sweep.span_ns[1])
        if not self.first(topic, sweep_key(sweep), last):
            return False
        spans = self._spans.setdefault(topic, [])
        length = max(last - first, 1)
        if any(min(last, b) - max(first, a) > length // 2 for a, b in spans):
            self.overlapping.setdefault(topic, []).append(first)
            return False
        spans.append((first, last))
        if len(spans) > 256:  # the recent ones: bags are read merged in time
            del spans[: len(spans) - 128]
        return True
