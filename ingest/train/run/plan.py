"""The ingest's first pass: every camera stamp, sweep span and IMU stamp, the stereo pairs and the samples.

It reads every message the stream pass will read (cameras, LiDARs, IMU), so
a corrupt chunk is found before anything is written; undecodable messages
are counted by `BadMessages`, each LiDAR's point rate is measured (thin
windows), and samples whose windows overlap messages lost in a corrupt chunk
are not planned.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from calibration.types import I64
from ingest.bags.decode import ImuSample, Sweep
from ingest.bags.reader import READAHEAD_THREADS, BagSet, Progress
from ingest.errors import BagError
from ingest.runtime.executor import usable_cpus
from ingest.train.bad_messages import BadMessages
from ingest.train.plausible import NOISE_TAG, POINT_FAR
from ingest.train.repeats import FirstCopies, fingerprint
from ingest.train.run.lidar_rate import LidarRates
from ingest.train.run.lost import lost_intervals, untouched
from ingest.train.sync import (
    IMU_MARGIN_NS,
    lidar_clock_spread,
    lidar_covered,
    median_period_ns,
    pair_stereo,
    pair_tolerance_ns,
    select_samples,
    unpaired_line,
)
from ingest.train.trajectory.estimate import GyroReadings

if TYPE_CHECKING:
    from ingest.train.run.resolved import ResolvedRun
    from ingest.train.run.settings import Topics


@dataclass(frozen=True)
class Plan:
    """The samples of a run: their upper/lower stamps and the sweeps each needs."""

    upper_ns: I64
    lower_ns: I64
    spans: dict[str, list[tuple[int, int]]]  # per lidar topic: (first, last) point stamp per sweep
    frames: int
    pairs: int
    rates: LidarRates = field(default_factory=LidarRates)  # each LiDAR's point rate (thin windows)
    duplicates: dict[str, int] = field(default_factory=dict)  # per topic: repeated messages, read once
    uncovered: int = 0  # stereo pairs with no LiDAR point within the window (never eligible)
    lost_samples: int = 0  # eligible, but their LiDAR/IMU window overlaps a corrupt chunk's messages
    crossed_samples: int = 0  # eligible, but their LiDAR window holds a sweep another LiDAR's repeats
    imu_last_ns: int | None = None  # the IMU's latest reading in the bags (None without an IMU)
    upper_shift_ns: int = 0  # added to a camera's header stamps: its exposure times on the LiDAR clock
    lower_shift_ns: int = 0
    repeated: dict[str, set[int]] = field(default_factory=dict)  # per camera topic: stamps of frames that
    # repeat the frame before them to the byte (`FirstCopies.same_as_before`)
    unpaired: str | None = None  # `unpaired_line` when no frame found a partner

    @property
    def upper_exposure_ns(self) -> I64:
        """Each sample's time: the upper camera's mid-exposure on the LiDAR clock (stamp + timeshift)."""
        out: I64 = self.upper_ns + self.upper_shift_ns
        return out

    @property
    def stereo_dt_ns(self) -> I64:
        """Each sample's lower minus upper camera exposure time (ns, on the LiDAR clock)."""
        out: I64 = (self.lower_ns + self.lower_shift_ns) - self.upper_exposure_ns
        return out


LOST_REASON = "LiDAR/IMU window overlaps a corrupt chunk (not planned)"
CROSSED_REASON = "LiDAR window holds a sweep whose points another LiDAR's repeats (not planned)"


def _seen(
    bags: BagSet, topics: Topics, bad: BadMessages, progress: Progress | None = None
) -> tuple[dict[str, I64], LidarRates, FirstCopies, GyroReadings]:
    """Per camera, LiDAR and IMU topic: (log_ns, first stamp, last stamp) of each message, as (N, 3).

    A sweep's stamps are its first and last point's (empty sweeps are left
    out), a frame's or IMU sample's its header stamp twice. Reading the IMU
    here too means every chunk the stream pass will read has been checked
    before anything is written. Undecodable messages are left out and
    counted by `bad`; each LiDAR's point rate is measured on the way.
    A message seen before (the same sweep, or a frame or IMU reading with the
    same stamp) is left out and counted per topic (the third value's
    `repeats`; its `restamped` lists those whose bytes differ). The fourth:
    the IMU's readings, decoded (`read_gyro` integrates them).
    """
    where = bags.label
    imu = [topics.imu] if topics.imu else []
    seen: dict[str, list[tuple[int, int, int]]] = {
        t: [] for t in (topics.upper, topics.lower, *topics.lidars, *imu)
    }
    rates = LidarRates()
    copies = FirstCopies()
    gyro = GyroReadings()
    readahead = min(READAHEAD_THREADS, usable_cpus())
    for msg in bags.messages(topics=list(seen), readahead=readahead, progress=progress):
        if msg.topic not in topics.lidars:
            stamp = bad.stamp(msg, where)
            if stamp is not None and copies.stamped(msg.topic, stamp, fingerprint(msg.raw)):
                seen[msg.topic].append((msg.log_ns, stamp, stamp))
                if msg.topic == topics.imu and isinstance(reading := bad.decoded(msg, where), ImuSample):
                    gyro.add(reading)  # the trajectory pass's gyro, without reading the bags again
            continue
        sweep = bad.decoded(msg, where)
        if not isinstance(sweep, Sweep) or not len(sweep.stamps_ns):
            continue
        rates.add_print(msg.topic, sweep.points_print)  # every sweep: a topic repeating another's is refused
        if copies.sweep(msg.topic, sweep):
            seen[msg.topic].append((msg.log_ns, *sweep.span_ns))
            rates.add(msg.topic, sweep.stamps_ns)
            rates.add_ranges(msg.topic, sweep.xyz_m)
    return {t: np.array(v, np.int64).reshape(-1, 3) for t, v in seen.items()}, rates, copies, gyro


def _untouched(bags: BagSet, topics: Topics, seen: dict[str, I64], tc_ns: I64, run: ResolvedRun) -> Any:
    """Mask of samples whose LiDAR and (when motion uses it) IMU windows overlap no message lost
    in a corrupt chunk."""
    chunks = bags.lost_chunks
    if not chunks:
        return np.ones(len(tc_ns), bool)
    w = run.window_ns
    margins = {t: w for t in topics.lidars}
    if topics.imu and run.sample.motion != "off":
        margins[topics.imu] = w + IMU_MARGIN_NS
    intervals = {t: lost_intervals(chunks, t, *seen[t].T) for t in margins}
    return untouched(tc_ns, intervals, margins)


def _seconds(ns: int) -> str:
    return f"{ns / 1e9:.3f} s"


def _same_clock(
    bags: BagSet, topics: Topics, seen: dict[str, I64], duplicates: dict[str, int], up: I64, window_ns: int
) -> None:
    """Every LiDAR's point times and the IMU's stamps overlap the upper camera's stamps (+- the window).

    A LiDAR on its own clock (a CustomMsg timebase counted from the sensor's
    boot, no PTP/gPTP sync) or an IMU whose header stamps are all zero would
    otherwise plan no sample, or no motion compensation, without a word.
    """
    first, last = int(up[0]) - window_ns, int(up[-1]) + window_ns
    camera = f"the upper camera's stamps {_seconds(int(up[0]))}..{_seconds(int(up[-1]))}"
    for topic in (*topics.lidars, *([topics.imu] if topics.imu else [])):
        times = seen[topic]
        if not len(times):
            continue
        a, b = int(times[:, 1].min()), int(times[:, 2].max())
        what = "point times" if topic in topics.lidars else "header stamps"
        if b < first or a > last:
            raise BagError(
                f"{bags.paths[0]}: {topic}: {what} {_seconds(a)}..{_seconds(b)} do not overlap {camera}; "
                "the sensor's clock is not the cameras' (sync it: PTP/gPTP or the host's time)"
            )
        if len(times) == 1 and duplicates.get(topic, 0):
            raise BagError(
                f"{bags.paths[0]}: {topic}: {1 + duplicates[topic]} messages, all with the {what} "
                f"{_seconds(a)}..{_seconds(b)}; a sensor clock that is not running?"
            )


@dataclass(frozen=True)
class Survey:
    """What the first pass read: per topic (log_ns, first stamp, last stamp) of each message, checked."""

    seen: dict[str, I64]
    rates: LidarRates
    duplicates: dict[str, int]
    upper_ns: I64  # the upper camera's distinct header stamps, ascending
    lower_ns: I64
    imu_gaps_ns: I64 = field(default_factory=lambda: np.zeros(0, np.int64))  # `imu_gaps` of the IMU
    warnings: list[str] = field(default_factory=list)  # one line each (`lidar_clock_spread`, `thin_lines`)
    crossed: dict[str, list[tuple[int, int]]] = field(default_factory=dict)  # `FirstCopies.crossed`
    same_as_before: dict[str, set[int]] = field(default_factory=dict)  # `FirstCopies.same_as_before`
    clock_spread: str | None = None  # `lidar_clock_spread`'s line (also among `warnings`): the LiDARs' clocks
    gyro: GyroReadings | None = None  # the IMU's readings (None without one), for `read_gyro`

    @property
    def span_ns(self) -> tuple[int, int]:
        """The upper camera's first and last stamp."""
        return int(self.upper_ns[0]), int(self.upper_ns[-1])


def _all_dropped(counts: Mapping[str, int], what: str) -> str:
    """The tail of a 'no points' or 'no readings' line when the topic had some, each dropped as implausible:
    how many for each reason (`ingest.train.plausible.REASONS`), or '' when none was."""
    counts = {why: n for why, n in counts.items() if why != NOISE_TAG}  # tagged points are kept
    if not counts:
        return ""
    reasons = "; ".join(f"{n:,} {what}{'' if n == 1 else 's'}: {why}" for why, n in counts.items())
    hint = ", millimetres written as metres?" if POINT_FAR in counts else ""
    return f": every one was dropped as no sensor measures it ({reasons}{hint})"


def survey(
    bags: BagSet, topics: Topics, window_ns: int, bad: BadMessages | None = None,
    progress: Progress | None = None,
) -> Survey:  # fmt: skip
    """The first pass (`_seen`) and its checks: points on every LiDAR, readings on the IMU, frames on
    both cameras (two stamps on the upper), one clock.

    Runs before anything is written, and before the trajectory pass, which
    would otherwise walk a LiDAR on its own clock knot by knot across years.
    It reads (and checks) every chunk of the bags: on a long recording it
    takes minutes: `progress` hears of the messages read (`BagSet.messages`).
    """
    bad = bad or BadMessages()
    seen, rates, copies, gyro = _seen(bags, topics, bad, progress)
    duplicates = copies.repeats
    dropped = bad.dropped.by_topic()
    if odd := rates.same_sweeps(topics.lidars):  # first: the repeated sweeps of such a topic are left out
        raise BagError(f"{bags.paths[0]}: {odd}")
    for topic, name in topics.lidars.items():
        if not len(seen[topic]):
            raise BagError(
                f"{bags.paths[0]}: no points on {topic} (the rig's lidar {name}) in the whole bag"
                + _all_dropped(dropped.get(topic, {}), "point")
            )
    if odd := rates.crowded(topics.lidars) or rates.too_far(topics.lidars):
        raise BagError(f"{bags.paths[0]}: {odd}")
    if topics.imu and not len(seen[topics.imu]):  # the rig names it: motion and odometry rely on it
        raise BagError(
            f"{bags.paths[0]}: no readings on {topics.imu} (the rig's IMU) in the whole bag"
            + _all_dropped(dropped.get(topics.imu, {}), "reading")
        )
    for topic, role in ((topics.upper, "upper"), (topics.lower, "lower")):
        if not len(seen[topic]):  # every sample needs a frame of each
            raise BagError(
                f"{bags.paths[0]}: no frames on {topic} (the rig's {role} camera) in the whole bag"
            )
    up = np.unique(seen[topics.upper][:, 1])  # duplicated stamps count once
    lo = np.unique(seen[topics.lower][:, 1])
    if len(up) < 2:
        n = len(up) + duplicates.get(topics.upper, 0)
        stamps = f" (header stamps: {_seconds(int(up[0]))} for all)" if n > len(up) == 1 else ""
        raise BagError(
            f"{bags.paths[0]}: {n} frame(s) on {topics.upper} but {len(up)} distinct header "
            f"stamp(s){stamps}; need at least 2"
        )
    _same_clock(bags, topics, seen, duplicates, up, window_ns)
    gaps = imu_gaps(np.unique(seen[topics.imu][:, 1])) if topics.imu else np.zeros(0, np.int64)
    offsets_ms = {t: float(np.median(seen[t][:, 0] - seen[t][:, 1])) / 1e6 for t in topics.lidars}
    spread = lidar_clock_spread(offsets_ms)
    warnings = (
        ([spread] if spread else [])
        + [restamped_line(topic, stamps_ns) for topic, stamps_ns in copies.restamped.items()]
        + [overlapping_line(topic, firsts_ns) for topic, firsts_ns in copies.overlapping.items()]
        + [repeated_points_line(topic, found) for topic, found in copies.repeated_points.items()]
    )
    return Survey(
        seen,
        rates,
        duplicates,
        up,
        lo,
        gaps,
        warnings + rates.thin_lines(topics.lidars),
        copies.crossed,
        copies.same_as_before,
        spread,
        gyro if topics.imu else None,
    )


def restamped_line(topic: str, stamps_ns: list[int]) -> str:
    """One line for the messages of `topic` that carry the header stamp of an earlier message with other
    content (`FirstCopies.restamped`): each was left out, as its time is not known."""
    n = len(stamps_ns)
    return (
        f"{topic}: {n} message{'' if n == 1 else 's'} carr{'ies' if n == 1 else 'y'} the header stamp of an "
        f"earlier message with other content (the first: {_seconds(stamps_ns[0])}); left out, as "
        f"{'its' if n == 1 else 'their'} time is not known (a sensor clock that stalled or stepped back)"
    )


def overlapping_line(topic: str, firsts_ns: list[int]) -> str:
    """One line for the sweeps of `topic` whose point times cover an earlier sweep's
    (`FirstCopies.overlapping`): each was left out, as its time is not known."""
    n = len(firsts_ns)
    return (
        f"{topic}: {n} sweep{'' if n == 1 else 's'} with point times that cover an earlier sweep's (the "
        f"first: {_seconds(firsts_ns[0])}); left out, as {'its' if n == 1 else 'their'} time is not known "
        "(a driver that repeated a sweep's timebase, or a clock that stepped back)"
    )


def _few(stamps: set[int], frames: int) -> set[int]:
    """`stamps` of a camera's frames that repeat the frame before them, when they are under half of its
    `frames`; none when most are (a still rig in a simulator that adds no image noise repeats them all)."""
    return stamps if 2 * len(stamps) < frames else set()


def repeated_points_line(topic: str, found: list[tuple[int, str]]) -> str:
    """One line for the sweeps of `topic` whose points repeat an earlier sweep's to the bit
    (`FirstCopies.repeated_points`): each was left out, as where its points were measured is not known."""
    n, (first_ns, other) = len(found), found[0]
    whose = "its own earlier sweep's" if other == topic else f"a sweep's of {other}"
    return (
        f"{topic}: {n} sweep{'' if n == 1 else 's'} with the points of an earlier sweep to the bit (the "
        f"first: {_seconds(first_ns)}, {whose}); left out, as where {'it was' if n == 1 else 'they were'} "
        "measured is not known (a driver that sent a stale buffer again, or one unit's points on the other's "
        "topic)"
    )


IMU_GAP_PERIODS = 5
"""An IMU interval longer than this many median periods is a gap (25 ms at the Mid-360's 200 Hz)."""


def imu_gaps(stamps_ns: I64) -> I64:
    """Lengths (ns) of the intervals between sorted IMU stamps longer than `IMU_GAP_PERIODS` median periods.

    The gyro is integrated across such a gap as if the rate stayed what it
    was: motion compensation and the trajectory lose the rotation there (a
    1 s gap left a 0.24 deg error), so the summary shows them.
    """
    if len(stamps_ns) < 3:
        return np.zeros(0, np.int64)
    dt = np.diff(stamps_ns)
    out: I64 = dt[dt > IMU_GAP_PERIODS * np.median(dt)]
    return out


def plan(
    bags: BagSet, topics: Topics, run: ResolvedRun, bad: BadMessages | None = None,
    surveyed: Survey | None = None,
) -> Plan:  # fmt: skip
    """Pairs and samples on header stamps, from the first pass (`survey`; run here when not given)."""
    sv = surveyed or survey(bags, topics, run.window_ns, bad)
    spans = {t: [(int(a), int(b)) for _, a, b in sv.seen[t]] for t in topics.lidars}
    up, lo = sv.upper_ns, sv.lower_ns
    # pairs and windows on exposure times (the rig's camera clock offsets applied), frames kept by stamp
    up_t, lo_t = up + topics.upper_shift_ns, lo + topics.lower_shift_ns
    tol = run.stereo_tolerance_ns or pair_tolerance_ns(median_period_ns(up))
    pairs = pair_stereo(up_t, lo_t, tol)
    all_spans = [s for v in spans.values() for s in v]
    chosen = select_samples(up_t[pairs.upper], all_spans, run.window_ns, run.every)
    uncovered = int((~lidar_covered(up_t[pairs.upper], all_spans, run.window_ns)).sum())
    upper, lower = up[pairs.upper][chosen], lo[pairs.lower][chosen]
    keep = _untouched(bags, topics, sv.seen, upper + topics.upper_shift_ns, run)
    lost = int(len(keep) - keep.sum())
    clear = untouched(upper + topics.upper_shift_ns, sv.crossed, dict.fromkeys(topics.lidars, run.window_ns))
    crossed = int((keep & ~clear).sum())
    keep &= clear
    return Plan(
        upper[keep],
        lower[keep],
        spans,
        len(up),
        len(pairs.upper),
        sv.rates,
        duplicates=sv.duplicates,
        lost_samples=lost,
        crossed_samples=crossed,
        uncovered=uncovered,
        imu_last_ns=int(sv.seen[topics.imu][:, 1].max()) if topics.imu else None,
        upper_shift_ns=topics.upper_shift_ns,
        lower_shift_ns=topics.lower_shift_ns,
        repeated={
            t: _few(sv.same_as_before.get(t, set()), len(n))
            for t, n in ((topics.upper, up), (topics.lower, lo))
        },
        unpaired=unpaired_line(up_t, lo_t, tol, len(pairs.upper)),
    )
