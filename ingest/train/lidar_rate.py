"""Thin LiDAR windows: a sample whose LiDAR gave far fewer points than the LiDAR's own rate promises.

A sensor that drops packets, loses a sweep to a bad message or stops half
way through a sample's window still gives *some* points, so the sample is
written, but with a hole nobody asked for. The rule (per LiDAR, per sample):

    thin  <=>  0 < n_window < THIN_FRACTION * rate * covered

- `n_window`: the LiDAR's raw points (before any filter) within the sample's
  +-window around the frame time;
- `rate`: the LiDAR's nominal rate, the median over its sweeps in the
  recording of points per second (the Mid-360 sends a fixed number of points
  per second, returns or not, so the median of the sweeps is the rate the
  sensor runs at);
- `covered`: the part of the window inside the recording's LiDAR data (from
  the first to the last point of any LiDAR), so the first and last samples of a
  recording are not thin merely for lying at its ends.

A window with no point at all is "silent" (`PointMeta.silent_lidars`), not
thin. Thin LiDARs go to `PointMeta.thin_lidars` and the run's summary.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibration.types import I64

THIN_FRACTION = 0.5
"""A window holding fewer than this share of the points the LiDAR's rate promises is thin."""


@dataclass
class LidarRates:
    """Per LiDAR topic the points-per-second of each sweep, and the span of all LiDAR points (ns)."""

    per_sweep: dict[str, list[float]] = field(default_factory=dict)
    first_ns: int | None = None
    last_ns: int | None = None

    def add(self, topic: str, stamps_ns: I64) -> None:
        """Record one sweep's point stamps (absolute ns); an empty sweep only counts for nothing."""
        if not len(stamps_ns):
            return
        lo, hi = int(stamps_ns.min()), int(stamps_ns.max())
        self.first_ns = lo if self.first_ns is None else min(self.first_ns, lo)
        self.last_ns = hi if self.last_ns is None else max(self.last_ns, hi)
        if hi > lo:
            self.per_sweep.setdefault(topic, []).append((len(stamps_ns) - 1) * 1e9 / (hi - lo))

    def rate_per_s(self, topic: str) -> float:
        """The LiDAR's nominal rate (points/s): the median of its sweeps; 0 without a sweep."""
        rates = self.per_sweep.get(topic)
        return float(np.median(rates)) if rates else 0.0

    def expected(self, topic: str, t_ns: int, window_ns: int) -> float:
        """Points the LiDAR's rate promises in [t - window, t + window] within the recording."""
        if self.first_ns is None or self.last_ns is None:
            return 0.0
        covered_ns = min(t_ns + window_ns, self.last_ns) - max(t_ns - window_ns, self.first_ns)
        return self.rate_per_s(topic) * max(covered_ns, 0) / 1e9

    def is_thin(self, topic: str, n_window: int, t_ns: int, window_ns: int) -> bool:
        """`0 < n_window < THIN_FRACTION * expected` (see the module's rule)."""
        return 0 < n_window < THIN_FRACTION * self.expected(topic, t_ns, window_ns)
