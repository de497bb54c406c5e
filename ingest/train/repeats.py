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
        self.repeated_points: dict[str, list[tuple[int, str]]] = {}  # per topic: (first point time, the
        # topic of the sweep whose points it repeats) of sweeps left out
        self.crossed: dict[str, list[tuple[int, int]]] = {}  # per topic: point-time spans of sweeps whose
        # points another LiDAR's sweep repeats, kept or not: which of the two is the LiDAR's is not known
        self.same_as_before: dict[str, set[int]] = {}  # per topic: times of first copies whose content
        # (a `fingerprint`) is the topic's previous first copy's: a frame that repeats the one before it
        self._previous: dict[str, object] = {}
        self._last_mark: dict[str, int | None] = {}  # per topic: the last kept sweep's `Sweep.points_print`
        self._prints: dict[int, tuple[str, int, int]] = {}  # kept sweeps' points' prints -> (topic, span)
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
        if content is not None:
            if self._previous.get(topic) == content:
                self.same_as_before.setdefault(topic, set()).add(t_ns)
            self._previous[topic] = content
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

        False too, listed in `repeated_points`, for a sweep whose points are its LiDAR's previous sweep's
        or another LiDAR's sweep's, to the bit (`Sweep.points_print`, `_repeats`): a driver
        that sent a stale buffer again, or one unit's points on the other's topic; where they were
        measured is not known.

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
        mark = sweep.points_print
        if mark is not None and self._repeats(mark, topic):
            other, a, b = self._prints[mark]
            self.repeated_points.setdefault(topic, []).append((first, other))
            if other != topic:
                self.crossed.setdefault(other, []).append((a, b))
                self.crossed.setdefault(topic, []).append((first, last))
            return False
        spans.append((first, last))
        if len(spans) > 256:  # the recent ones: bags are read merged in time
            del spans[: len(spans) - 128]
        if mark is not None:
            self._remember(mark, topic, first, last)
        self._last_mark[topic] = mark
        return True

    def _repeats(self, mark: int, topic: str) -> bool:
        """Whether a sweep with `points_print` `mark` repeats a kept one: the LiDAR's previous
        sweep (a driver that sent its buffer again), or any sweep of another LiDAR (one unit's points on the
        other's topic: two units never measure the same points). A sweep equal to an older one of its own
        LiDAR is a replay, as an emulator looping its scan sends (`loop_s`), and is kept."""
        if mark not in self._prints:
            return False
        other = self._prints[mark][0]
        return other != topic or self._last_mark.get(topic) == mark

    def _remember(self, mark: int, topic: str, first_ns: int, last_ns: int) -> None:
        """Keep a sweep's `points_print`; those `horizon_ns` behind the newest are forgotten."""
        self._prints[mark] = (topic, first_ns, last_ns)
        if len(self._prints) > 1024:
            newest = max(t for _, _, t in self._prints.values())
            self._prints = {k: v for k, v in self._prints.items() if v[2] >= newest - self.horizon_ns}
