"""Thin LiDAR windows: a sample whose LiDAR gave far fewer points than a Mid-360 sends.

A sensor that drops packets, loses a sweep to a bad message or stops half
way through a sample's window still gives *some* points, so the sample is
written, but with a hole nobody asked for. The rule (per LiDAR, per sample):

    thin  <=>  0 < n_window < THIN_FRACTION * rate * covered

- `n_window`: the LiDAR's raw points (before any filter) within the sample's
  +-window around the frame time;
- `rate`: what the LiDAR sends per second: a Mid-360 sends a fixed
  `MID360_POINTS_PER_S`, returns or not (the rig's LiDARs are Mid-360s), or
  the median over its sweeps in the recording when that is more. The
  sweeps alone do not set it: a LiDAR thin in every sweep (a driver that
  publishes one point a sweep) would be thin against nothing;
- `covered`: the part of the window inside the recording's LiDAR data (from
  the first to the last point of any LiDAR), so the first and last samples of a
  recording are not thin merely for lying at its ends.

A window with no point at all is "silent" (`PointMeta.silent_lidars`), not
thin. Thin LiDARs go to `PointMeta.thin_lidars` and the run's summary; a
LiDAR thin over the whole recording is one warning line too (`thin_lines`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration.types import I64

THIN_FRACTION = 0.5
"""A window holding fewer than this share of the points the LiDAR's rate promises is thin."""
MID360_POINTS_PER_S = 200_000
"""Points a Livox Mid-360 sends per second, whatever its publish rate (datasheet: 200,000 points/s, first
return), 20,000 a sweep at the driver's 10 Hz."""

MID360_MAX_RANGE_M = 70
"""A Livox Mid-360's farthest return (m, 80 % reflectivity; datasheet)."""
FARTHEST_MEDIAN_RANGE_M = 100.0
"""A LiDAR whose sweeps' median point lies farther (m) than this has coordinates in another unit: half
of a Mid-360's points cannot lie beyond its reach (`LidarRates.too_far`)."""
CROWDED_FACTOR = 20
"""A LiDAR whose sweeps' points come this many times faster than `MID360_POINTS_PER_S` has its point
times squeezed (`LidarRates.crowded`); a Mid-360's sweep spans its whole 100 ms."""


MAX_SWEEP_GAP_NS = 1_000_000_000
"""Sweeps further apart than this (ns) belong to stretches recorded apart: the time between is not the
LiDAR's (`LidarRates.recorded_per_s`)."""


@dataclass
class LidarRates:
    """Per LiDAR topic the points-per-second of each sweep, and the span of all LiDAR points (ns)."""

    per_sweep: dict[str, list[float]] = field(default_factory=dict)
    first_ns: int | None = None
    last_ns: int | None = None
    points: dict[str, int] = field(default_factory=dict)  # per topic: every point of its sweeps
    sweeps: dict[str, int] = field(default_factory=dict)  # per topic: sweeps with a point
    span_ns: dict[str, tuple[int, int]] = field(default_factory=dict)  # per topic: first and last point
    sweep_spans_ns: dict[str, list[tuple[int, int]]] = field(default_factory=dict)  # per topic, per sweep
    median_range_m: dict[str, list[float]] = field(default_factory=dict)  # per topic: each sweep's median
    prints: dict[str, set[int]] = field(default_factory=dict)  # per topic: its sweeps' points, hashed

    def add_print(self, topic: str, mark: int | None) -> None:
        """Record one sweep's measured points (its `Sweep.points_print`; None: too few) for `same_sweeps`."""
        if mark is not None:
            self.prints.setdefault(topic, set()).add(mark)

    def same_sweeps(self, names: dict[str, str]) -> str | None:
        """The first two LiDARs (topic -> rig name) over half of whose sweeps are the same points (to the
        bit), in one line: one sensor's data sent to both topics; None when there are none."""
        topics = list(names)
        for k, a in enumerate(topics):
            for b in topics[k + 1 :]:
                mine, theirs = self.prints.get(a, set()), self.prints.get(b, set())
                shared = len(mine & theirs)
                if mine and theirs and shared > 0.5 * min(len(mine), len(theirs)):
                    return (
                        f"{b} (the rig's lidar {names[b]}) carries the same sweeps as {a} ({names[a]}): "
                        f"{shared:,} of {len(theirs):,} point for point; one LiDAR's points were sent to "
                        "both topics (a remap, or a driver or recorder that copied them): check the recording"
                    )
        return None

    def add_ranges(self, topic: str, xyz_m: np.ndarray[Any, Any]) -> None:
        """Record one sweep's median point range (m; points at the origin, a Livox "no return", left out)."""
        r = np.linalg.norm(np.asarray(xyz_m, np.float64), axis=1)
        r = r[np.isfinite(r) & (r > 0)]
        if len(r):
            self.median_range_m.setdefault(topic, []).append(float(np.median(r)))

    def too_far(self, names: dict[str, str]) -> str | None:
        """The first LiDAR (topic -> rig name) whose sweeps' median point range exceeds
        `FARTHEST_MEDIAN_RANGE_M`, in one line: coordinates in centimetres or millimetres read as metres;
        None when there is none."""
        for topic, name in names.items():
            ranges = self.median_range_m.get(topic)
            if not ranges or float(np.median(ranges)) <= FARTHEST_MEDIAN_RANGE_M:
                continue
            return (
                f"{topic} (the rig's lidar {name}): its points lie {float(np.median(ranges)):,.0f} m away "
                f"(median over {len(ranges)} sweeps), beyond the {MID360_MAX_RANGE_M} m a Mid-360 reaches: "
                "coordinates in centimetres or millimetres read as metres? Fix the driver's unit"
            )
        return None

    def add(self, topic: str, stamps_ns: I64) -> None:
        """Record one sweep's point stamps (absolute ns); an empty sweep only counts for nothing."""
        if not len(stamps_ns):
            return
        lo, hi = int(stamps_ns.min()), int(stamps_ns.max())
        self.first_ns = lo if self.first_ns is None else min(self.first_ns, lo)
        self.last_ns = hi if self.last_ns is None else max(self.last_ns, hi)
        self.points[topic] = self.points.get(topic, 0) + len(stamps_ns)
        self.sweeps[topic] = self.sweeps.get(topic, 0) + 1
        first, last = self.span_ns.get(topic, (lo, hi))
        self.span_ns[topic] = (min(first, lo), max(last, hi))
        self.sweep_spans_ns.setdefault(topic, []).append((lo, hi))
        if hi > lo:
            self.per_sweep.setdefault(topic, []).append((len(stamps_ns) - 1) * 1e9 / (hi - lo))

    def rate_per_s(self, topic: str) -> float:
        """What the LiDAR sends (points/s): `MID360_POINTS_PER_S`, or the median of its sweeps when more."""
        rates = self.per_sweep.get(topic)
        return max(float(np.median(rates)) if rates else 0.0, float(MID360_POINTS_PER_S))

    def recorded_per_s(self, topic: str) -> float | None:
        """The points per second the LiDAR gave over the recording (None with less than 1 ms of points).

        Its points over the time its sweeps cover, from first to last point less the gaps over
        `MAX_SWEEP_GAP_NS` between sweeps (bags recorded an hour apart), plus one point spacing of the
        rate (so a sweep of one point each 100 ms gives 10 points/s).
        """
        n = self.points.get(topic, 0)
        spans = sorted(self.sweep_spans_ns.get(topic, []))
        if not spans:
            return None
        covered_ns, (start, end) = 0, spans[0]
        for lo, hi in spans[1:]:
            if lo - end > MAX_SWEEP_GAP_NS:
                covered_ns += end - start
                start = lo
            end = max(end, hi)
        covered_ns += end - start
        span_ns = covered_ns + covered_ns / max(n - 1, 1)
        return n * 1e9 / span_ns if span_ns >= 1_000_000 else None

    def thin_lines(self, names: dict[str, str]) -> list[str]:
        """One warning line per LiDAR (topic -> rig name) whose recording holds fewer than `THIN_FRACTION`
        of the points a Mid-360 sends: its every window is thin, its GT (nearly) empty."""
        out = []
        for topic, name in names.items():
            got = self.recorded_per_s(topic)
            if got is None or got >= THIN_FRACTION * MID360_POINTS_PER_S:
                continue
            n, sweeps = self.points[topic], self.sweeps[topic]
            out.append(
                f"{topic} (the rig's lidar {name}): {n:,} points in {sweeps:,} sweeps "
                f"({n / sweeps:,.0f} a sweep, {got:,.0f} points/s) but a Mid-360 sends "
                f"{MID360_POINTS_PER_S:,} points/s; every window of it is thin and its GT sparse "
                "(a driver set to drop points, or lost packets?)"
            )
        return out

    def crowded(self, names: dict[str, str]) -> str | None:
        """The first LiDAR (topic -> rig name) whose sweeps' points come `CROWDED_FACTOR` times faster than
        a Mid-360 sends them, in one line: point times squeezed into a sliver of each sweep (offsets in
        microseconds read as nanoseconds), which no Mid-360 gives and which would misplace every moving
        point; None when there is none."""
        for topic, name in names.items():
            rates = self.per_sweep.get(topic)
            if not rates or float(np.median(rates)) < CROWDED_FACTOR * MID360_POINTS_PER_S:
                continue
            rate = float(np.median(rates))
            span_ms = 1e3 * (self.points[topic] / self.sweeps[topic]) / rate
            return (
                f"{topic} (the rig's lidar {name}): each sweep's point times span {span_ms:.3g} ms (median), "
                f"{rate:,.0f} points/s against the {MID360_POINTS_PER_S:,} a Mid-360 sends: its point times "
                "look scaled (offset_time in microseconds, not nanoseconds?); fix the driver's time unit"
            )
        return None

    def expected(self, topic: str, t_ns: int, window_ns: int) -> float:
        """Points the LiDAR's rate promises in [t - window, t + window] within the recording."""
        if self.first_ns is None or self.last_ns is None:
            return 0.0
        covered_ns = min(t_ns + window_ns, self.last_ns) - max(t_ns - window_ns, self.first_ns)
        return self.rate_per_s(topic) * max(covered_ns, 0) / 1e9

    def is_thin(self, topic: str, n_window: int, t_ns: int, window_ns: int) -> bool:
        """`0 < n_window < THIN_FRACTION * expected` (see the module's rule)."""
        return 0 < n_window < THIN_FRACTION * self.expected(topic, t_ns, window_ns)
