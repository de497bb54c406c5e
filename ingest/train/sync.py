"""Time alignment on header stamps (int64 ns): stereo pairs, sample selection, point windows.

Bag log times are never used here: they are receive times, shifted by driver
latency (18 ms for ZED images, a whole sweep for Livox messages).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.types import I64, Bool

DEFAULT_LIDAR_WINDOW_NS = 50_000_000
IMU_MARGIN_NS = 20_000_000
"""IMU readings are taken this far beyond a sample's LiDAR window (motion compensation)."""


@dataclass(frozen=True)
class StereoPairs:
    """Indices into the upper and lower stamp arrays of matched frames, and what was dropped."""

    upper: I64
    lower: I64
    dt_ns: I64  # lower - upper stamp of each pair
    dropped_upper: int
    dropped_lower: int


def pair_tolerance_ns(period_ns: float) -> int:
    """The stereo pairing tolerance of cameras running at `period_ns`: half a frame period.

    Within it a frame of a steady camera has at most one candidate partner, so
    pairing in arrival order (the live node) and pairing a whole recording
    (`pair_stereo`) give the same pairs.
    """
    return int(period_ns // 2)


def median_period_ns(stamps_ns: I64) -> float:
    """Median interval of sorted frame stamps (ns); 0 with fewer than two frames."""
    return float(np.median(np.diff(stamps_ns))) if len(stamps_ns) >= 2 else 0.0


def pair_stereo(upper_ns: I64, lower_ns: I64, tolerance_ns: int) -> StereoPairs:
    """Match each upper frame to the nearest lower frame within `tolerance_ns`, each used once.

    The stereo pairing rule of SensorBox: `inspect` and `ingest` use it on a
    whole recording. Greedy by increasing |dt|, so a duplicated or jittered
    frame never steals a better partner's match; unmatched frames on either
    side are counted drops. The live camera node
    (`sensorbox.live.cameras.StereoPairer`) pairs in arrival order instead,
    which gives the same pairs wherever each frame has at most one candidate
    partner within the tolerance (steady cameras, `pair_tolerance_ns`); a
    duplicated frame can pair differently live.
    """
    up = np.asarray(upper_ns, np.int64)
    lo = np.asarray(lower_ns, np.int64)
    if len(up) == 0 or len(lo) == 0:
        empty = np.zeros(0, np.int64)
        return StereoPairs(empty, empty, empty, len(up), len(lo))
    order = np.argsort(lo, kind="stable")
    lo_sorted = lo[order]
    pos = np.searchsorted(lo_sorted, up)
    cand_i: list[int] = []
    cand_j: list[int] = []
    for k in (pos - 1, pos):  # the neighbours on each side of every upper stamp
        ok = (k >= 0) & (k < len(lo_sorted))
        cand_i += np.nonzero(ok)[0].tolist()
        cand_j += k[ok].tolist()
    i = np.array(cand_i, np.int64)
    j = np.array(cand_j, np.int64)
    dt = np.abs(lo_sorted[j] - up[i])
    keep = dt <= tolerance_ns
    i, j, dt = i[keep], j[keep], dt[keep]
    used_i: set[int] = set()
    used_j: set[int] = set()
    pairs: list[tuple[int, int]] = []
    for idx in np.lexsort((i, dt)):
        a, b = int(i[idx]), int(j[idx])
        if a not in used_i and b not in used_j:
            used_i.add(a)
            used_j.add(b)
            pairs.append((a, b))
    pairs.sort()
    pu = np.array([a for a, _ in pairs], np.int64)
    pl = order[np.array([b for _, b in pairs], np.int64)] if pairs else np.zeros(0, np.int64)
    return StereoPairs(pu, pl, lo[pl] - up[pu], len(up) - len(pu), len(lo) - len(pl))


STEREO_SYNC_MS = 2.0
"""Stereo exposures further apart than this (ms) are said: the disparity GT is made for the upper
camera's time, and the lower camera moves 2 mm in 2 ms at a walker's 1 m/s, twice the GT's error
budget. Hardware-synchronised cameras expose within a millisecond of each other (the simulator: each
within +-0.5 ms of its frame time)."""


def unsynced_line(stereo_dt_ns: I64, upper_ns: I64) -> str | None:
    """One line when some planned stereo pairs (`stereo_dt_ns`: lower minus upper exposure, per sample at
    upper stamp `upper_ns`) are more than `STEREO_SYNC_MS` apart, else None. Each sample's meta records
    its own `stereo_dt_ms`, so a dataset's user can leave them out."""
    dt_ms = np.abs(np.asarray(stereo_dt_ns, np.int64)) / 1e6
    apart = np.flatnonzero(dt_ms > STEREO_SYNC_MS)
    if len(apart) == 0:
        return None
    k = int(apart[np.argmax(dt_ms[apart])])
    return (
        f"{len(apart)} of {len(dt_ms)} stereo pairs are exposed more than {STEREO_SYNC_MS:g} ms apart (the "
        f"most: {dt_ms[k]:.1f} ms, at upper stamp {int(upper_ns[k]) / 1e9:.3f} s): with the rig moving, the "
        "lower image shows another moment than the disparity GT (hardware-sync the cameras, or leave out "
        "the samples by their meta's stereo_dt_ms)"
    )


def unpaired_line(upper_ns: I64, lower_ns: I64, tolerance_ns: int, pairs: int) -> str | None:
    """One line when no upper frame found a lower one within `tolerance_ns` (`pairs` 0 of some frames on
    both cameras; exposure times, the rig's camera clock offsets applied), naming how far apart the two
    cameras' nearest frames lie; else None. Without it the run writes nothing and says only '0 pairs'."""
    up, lo = np.sort(np.asarray(upper_ns, np.int64)), np.sort(np.asarray(lower_ns, np.int64))
    if pairs or not len(up) or not len(lo):
        return None
    k = np.clip(np.searchsorted(lo, up), 1, max(len(lo) - 1, 1))
    nearest = np.where(
        np.abs(lo[k - 1] - up) <= np.abs(lo[np.minimum(k, len(lo) - 1)] - up), lo[k - 1], lo[k]
    )
    apart_ms = float(np.median(nearest - up)) / 1e6
    return (
        f"no upper frame has a lower frame within {tolerance_ns / 1e6:.1f} ms of its exposure (of {len(up)} "
        f"upper and {len(lo)} lower frames; the nearest lie {apart_ms:+.1f} ms apart, median): nothing can "
        "be written; check the camchain's timeshift_cam_imu of each camera and that both topics are the same "
        "recording's"
    )


def lidar_covered(frame_ns: I64, lidar_spans_ns: list[tuple[int, int]], window_ns: int) -> Bool:
    """Which frames have LiDAR points within +-`window_ns`: some sweep overlaps [t - window, t + window].

    `lidar_spans_ns` are (first, last) point stamps of each sweep of any LiDAR.
    A frame is covered when the latest end among the windows starting at or
    before it reaches it: one sort and one search, not a pass over the frames
    per sweep (an hour holds 72,000 sweeps).
    """
    t = np.asarray(frame_ns, np.int64)
    if not lidar_spans_ns:
        return np.zeros(len(t), bool)
    spans = np.array(lidar_spans_ns, np.int64).reshape(-1, 2)
    order = np.argsort(spans[:, 0], kind="stable")
    starts = spans[order, 0] - window_ns
    reach = np.maximum.accumulate(spans[order, 1] + window_ns)
    k = np.searchsorted(starts, t, side="right") - 1
    out: Bool = (k >= 0) & (reach[np.maximum(k, 0)] >= t)
    return out


def select_samples(
    frame_ns: I64,
    lidar_spans_ns: list[tuple[int, int]],
    window_ns: int = DEFAULT_LIDAR_WINDOW_NS,
    every: int = 1,
) -> I64:
    """Indices of frames that have LiDAR points within +-`window_ns` (`lidar_covered`), thinned to every
    `every`-th."""
    t = np.asarray(frame_ns, np.int64)
    if not lidar_spans_ns or len(t) == 0:
        return np.zeros(0, np.int64)
    idx = np.nonzero(lidar_covered(t, lidar_spans_ns, window_ns))[0].astype(np.int64)
    return idx[:: max(1, every)]


LIDAR_CLOCK_SPREAD_MS = 10.0
"""LiDARs whose bag-time-minus-stamp medians differ by more than this (ms) likely run on clocks that
disagree: both are published by one driver over one network, a millisecond or two apart."""


def lidar_clock_spread(offsets_ms: dict[str, float]) -> str | None:
    """One line when the LiDAR topics' median (bag log time - stamp) `offsets_ms` differ by more than
    `LIDAR_CLOCK_SPREAD_MS`, else None.

    A clock offset between two LiDARs (no PTP/gPTP between them) places one
    LiDAR's points at the wrong times: dense GT's free-space test then
    removes much of the scene as "movers" (30 ms: density 48 % -> 22 %)
    without a word, and sparse GT's motion compensation is off by the
    offset.
    """
    if len(offsets_ms) < 2:
        return None
    lo = min(offsets_ms, key=lambda t: offsets_ms[t])
    hi = max(offsets_ms, key=lambda t: offsets_ms[t])
    spread = offsets_ms[hi] - offsets_ms[lo]
    if spread <= LIDAR_CLOCK_SPREAD_MS:
        return None
    return (
        f"{hi} and {lo}: bag time minus stamp differs by {spread:.1f} ms (median); their clocks may "
        "disagree by that much (sync the LiDARs: PTP/gPTP)"
    )
