"""Readings and points no sensor can produce: dropped where a message enters ingest, counted by reason.

A decodable message can still carry values no sensor of the rig measures: a
gyro rate of 1e6 rad/s, a NaN acceleration, a Livox point whose `offset_time`
is 0xFFFFFFFF (4.3 s after its sweep began), a point 1e30 m away. Taken as
given they make wrong ground truth without a word (a gyro spike rotates a
whole window of points; a far point's range does not fit the uint16 PNG and
its pixel is written empty). Each is dropped as the message enters the
ingest (`screen`, called by `BadMessages.decoded` in every pass), and
counted once per message by topic and reason (`Dropped`) for the summary
and `dataset.yaml`; a LiDAR whose sweeps carry no point time (a PointCloud2
without a time field: every point at the header stamp) is said once. Points
the Livox itself tags as noise (`NOISE_TAG`) are counted here too, by topic,
once per message: `ingest.train.trajectory.clouds.filter_points` leaves them out of
every window, and a dust storm that empties a run must show in the summary
and `dataset.yaml`, not only in each sample's meta. The
rig's IMU rate is checked against the readings' (`check_imu_rate`), and each
topic's stamps against the bag's log order (`check_time_order`).

Bounds (notes/livox.md): the Mid-360's IMU (ICM-40609) measures at most
+-2000 deg/s and +-32 g (its largest full scales; the driver publishes g,
the sensor_msgs contract m/s^2, so the acceleration bound is 32 g in m/s^2,
which holds in either unit); its LiDAR ranges to 70 m; a Livox driver
publishes 0.5..100 sweeps a second, so a sweep lasts 10 ms..2 s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from calibration.types import F64, I64
from ingest.bags.decode import NO_POINT_TIME, Frame, ImuSample, Sweep
from ingest.bags.point_time import TIME_FIELDS
from ingest.errors import BagError

GYRO_LIMIT_RAD_S = math.radians(2000.0) * 1.1
"""An angular rate beyond this on any axis is no reading: the largest full scale (2000 deg/s) and 10 % for
scale error."""
ACC_LIMIT = 32 * 9.80665 * 1.1
"""An acceleration beyond this on any axis is no reading: 32 g (the largest full scale) in m/s^2, the larger
of the two units drivers publish, and 10 % for scale error."""
RANGE_LIMIT_M = 500.0
"""A LiDAR point farther than this is no return: the Mid-360 ranges to 70 m, other LiDARs to ~300 m."""
SWEEP_MAX_NS = 3_000_000_000
"""A point stamped farther than this from its sweep's header stamp lies beyond any sweep (the slowest
Livox rate, 0.5 Hz, makes 2 s sweeps; `ingest.bags.point_time.MAX_OFFSET_NS` is the same bound)."""
SWEEP_SPREAD_MADS = 8.0
"""A point stamped farther than this many median absolute deviations from its sweep's median point
time lies beyond it: point times spread evenly over a sweep of period P have a MAD of P/4, so this is 2 P."""
SWEEP_SPREAD_MIN_NS = 20_000_000
"""The least that bound may be: two periods of the fastest Livox rate (100 Hz)."""
SPREAD_SAMPLE = 1024
"""Points `beyond_sweep` takes its robust statistics over (about)."""
NOISE_TAG_BITS = 0b0011_1100
"""Livox tag fields rain/fog/dust (bits 2-3) and other (bits 4-5): non-zero means a doubtful echo."""
IMU_RATE_TOLERANCE = 0.2
"""The IMU's measured rate may differ from the rig's `rate_hz` by this fraction."""

GYRO_SPIKE_RAD_S = 5.0
"""A gyro reading that leaves the mean of its two neighbours by more than this (rad/s, vector norm) while
they agree within half of it is a spike no rigid turn makes (a handheld rig's rate changes over tens of
milliseconds): single readings 10 rad/s off, one in 40, bent a walk's motion compensation (8 % outliers
against truth, 2 % clean)."""
IMU_SPIKE = f"IMU gyro spike (over {GYRO_SPIKE_RAD_S:g} rad/s off both neighbours, which agree)"
FROZEN_RUN = 3
FROZEN_TURN_RAD_S = 0.1
"""Readings in a row whose gyro repeats the one before it exactly while reading a turn over
`FROZEN_TURN_RAD_S` (5.7 deg/s), from which a gyro counts as frozen: while the rig turns, its motion and
the gyro's noise change every reading. (At rest a quantised gyro may repeat its bias for a while.)"""
IMU_FROZEN = (
    f"IMU gyro repeating its reading before exactly, {FROZEN_RUN}+ in a row while turning (a frozen IMU)"
)
IMU_NON_FINITE = "IMU reading with NaN or inf"
IMU_GYRO = f"IMU gyro beyond {math.degrees(GYRO_LIMIT_RAD_S):.0f} deg/s"
IMU_ACC = f"IMU acceleration beyond {ACC_LIMIT:.0f} (32 g in m/s^2)"
POINT_TIME = "LiDAR point time beyond its sweep"
POINT_FAR = f"LiDAR point beyond {RANGE_LIMIT_M:g} m"
POINT_REPEATED = "LiDAR point repeated within its sweep (same time and coordinates)"
NOISE_TAG = "point with a Livox noise tag"
"""A point whose Livox tag marks a doubtful echo (`NOISE_TAG_BITS`): the sensor's own verdict, counted but
not warned about (a few per sweep are normal)."""
REASONS = (
    IMU_NON_FINITE,
    IMU_GYRO,
    IMU_ACC,
    IMU_SPIKE,
    IMU_FROZEN,
    POINT_TIME,
    POINT_FAR,
    POINT_REPEATED,
    NOISE_TAG,
)
"""Why a reading or point was dropped, in the order the summary lists them."""


def imu_problem(sample: ImuSample) -> str | None:
    """Why the IMU reading is no measurement (one of `REASONS`), or None for a plausible one."""
    values = np.concatenate([sample.gyro_rad_s, sample.acc])
    if not np.isfinite(values).all():
        return IMU_NON_FINITE
    if float(np.abs(sample.gyro_rad_s).max()) > GYRO_LIMIT_RAD_S:  # the full scale bounds each axis
        return IMU_GYRO
    if float(np.abs(sample.acc).max()) > ACC_LIMIT:
        return IMU_ACC
    return None


def gyro_spikes(gyro_rad_s: F64) -> np.ndarray[Any, np.dtype[np.bool_]]:
    """Which readings of a gyro series (N, 3) in time order are spikes (`GYRO_SPIKE_RAD_S`); the first
    and last, with one neighbour, are not judged."""
    out = np.zeros(len(gyro_rad_s), bool)
    if len(gyro_rad_s) < 3:
        return out
    before, here, after = gyro_rad_s[:-2], gyro_rad_s[1:-1], gyro_rad_s[2:]
    off = np.linalg.norm(here - 0.5 * (before + after), axis=1) > GYRO_SPIKE_RAD_S
    agree = np.linalg.norm(after - before, axis=1) < 0.5 * GYRO_SPIKE_RAD_S
    out[1:-1] = off & agree
    return out


def gyro_frozen(gyro_rad_s: F64) -> np.ndarray[Any, np.dtype[np.bool_]]:
    """Which readings of a gyro series (N, 3) in time order repeat the reading before them exactly, turning
    (`FROZEN_TURN_RAD_S`), in a run of at least `FROZEN_RUN`; a run's first reading, the last one
    measured, is not."""
    g = np.asarray(gyro_rad_s)
    out = np.zeros(len(g), bool)
    if len(g) < 2:
        return out
    same = (g[1:] == g[:-1]).all(axis=1) & (np.linalg.norm(g[1:], axis=1) > FROZEN_TURN_RAD_S)
    edges = np.diff(np.concatenate([[0], same.astype(np.int8), [0]]))
    for start, stop in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True):
        if stop - start >= FROZEN_RUN:
            out[start + 1 : stop + 1] = True
    return out


def beyond_sweep(stamps_ns: I64, stamp_ns: int) -> np.ndarray[Any, np.dtype[np.bool_]]:
    """Which point times (int64 ns) lie beyond the sweep stamped `stamp_ns`.

    A point is beyond it when it is more than `SWEEP_SPREAD_MADS` median
    absolute deviations (at least `SWEEP_SPREAD_MIN_NS`) from the sweep's
    median point time, or, when that median lies within `SWEEP_MAX_NS` of the
    header stamp, more than `SWEEP_MAX_NS` from the header stamp. A sweep
    whose points all lie far from its header stamp is left whole: a LiDAR on
    another clock than its header's, which the survey names
    (`ingest.train.run.plan.survey`). The median and the deviation are taken over
    about `SPREAD_SAMPLE` evenly strided points (a 20k-point sweep in a tenth
    of the time; robust statistics of 1000 points move by a few per cent, far
    inside the bound).
    """
    sample = stamps_ns[:: max(1, len(stamps_ns) // SPREAD_SAMPLE)]
    if len(sample) == 0:
        return np.zeros(0, bool)
    median = int(np.median(sample))
    mad = float(np.median(np.abs(sample - np.int64(median))))
    bound = int(max(SWEEP_SPREAD_MADS * mad, SWEEP_SPREAD_MIN_NS))
    out: np.ndarray[Any, np.dtype[np.bool_]] = np.abs(stamps_ns - np.int64(median)) > bound
    if abs(median - stamp_ns) <= SWEEP_MAX_NS:
        out |= np.abs(stamps_ns - np.int64(stamp_ns)) > SWEEP_MAX_NS
    return out


def too_far(xyz_m: np.ndarray[Any, Any]) -> np.ndarray[Any, np.dtype[np.bool_]]:
    """Which points lie beyond `RANGE_LIMIT_M` (NaN coordinates do not: `filter_points` counts those).

    Squared ranges in the points' own float type, per column (an overflow to inf is beyond too).
    """
    x, y, z = xyz_m[:, 0], xyz_m[:, 1], xyz_m[:, 2]
    with np.errstate(over="ignore", invalid="ignore"):
        out: np.ndarray[Any, np.dtype[np.bool_]] = x * x + y * y + z * z > RANGE_LIMIT_M**2
    return out


_MIX = np.array([0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9, 0x27D4EB2F165667C5], np.uint64)
"""Odd 64-bit multipliers that mix a point's time and coordinate bits into one hash (`repeated_points`)."""


def repeated_points(xyz_m: np.ndarray[Any, Any], stamps_ns: I64) -> np.ndarray[Any, np.dtype[np.bool_]]:
    """Which points repeat an earlier point of the same sweep: the same time (ns) and the same coordinates.

    No LiDAR measures one return twice: a driver or a recorder that wrote
    the points twice would weigh their surfaces double in every fit and
    render (a sweep's points doubled moved GT pixels by up to 157 disparity
    units). The first of equal points is kept. Points at the origin (a
    Livox's no-return) and NaN coordinates are not compared: other checks
    drop them. One sort of a 64-bit hash per point finds the candidates; only
    those are compared exactly.
    """
    out = np.zeros(len(stamps_ns), bool)
    if len(stamps_ns) < 2:
        return out
    xyz = np.ascontiguousarray(xyz_m, np.float64)
    bits = xyz.view(np.uint64)
    mixed = np.asarray(stamps_ns, np.int64).view(np.uint64) * _MIX[0]
    for axis in range(3):
        mixed ^= bits[:, axis] * _MIX[axis + 1]
    ascending = np.sort(mixed)  # the common case, no repeat, costs one sort of the hashes
    if not (ascending[1:] == ascending[:-1]).any():
        return out
    order = np.argsort(mixed, kind="stable")
    same = np.flatnonzero(mixed[order][1:] == mixed[order][:-1])
    firsts: set[tuple[int, float, float, float]] = set()
    for i in np.unique(np.concatenate([order[same], order[same + 1]])).tolist():
        x, y, z = xyz[i].tolist()
        if x == y == z == 0.0:
            continue
        key = (int(stamps_ns[i]), x, y, z)
        if key in firsts:
            out[i] = True
        firsts.add(key)
    return out


def noise_tagged(tag: np.ndarray[Any, Any] | None) -> int:
    """How many points a Livox tag array (uint8, or None without tags) marks as noise (`NOISE_TAG_BITS`)."""
    return 0 if tag is None else int(np.count_nonzero(np.asarray(tag) & NOISE_TAG_BITS))


def screened_sweep(sweep: Sweep) -> tuple[Sweep, dict[str, int]]:
    """`sweep` without the points no LiDAR measures, and how many points were dropped by reason (none: {}).

    The points the Livox tagged as noise are counted under `NOISE_TAG` among those kept here, but stay
    in the sweep: `ingest.train.trajectory.clouds.filter_points` leaves them out of each window (and
    counts them in its meta), so every pass and GT method drops the same points.
    """
    late = beyond_sweep(sweep.stamps_ns, sweep.stamp_ns)
    if sweep.late is not None:  # the decoder's own verdict: a time field beyond any sweep
        late |= sweep.late
    far = too_far(sweep.xyz_m) & ~late
    repeated = repeated_points(sweep.xyz_m, sweep.stamps_ns) & ~(late | far)
    drop = late | far | repeated
    if not drop.any():
        tagged = noise_tagged(sweep.tag)
        return sweep, {NOISE_TAG: tagged} if tagged else {}
    keep = ~drop

    def kept(a: np.ndarray[Any, Any] | None) -> np.ndarray[Any, Any] | None:
        return None if a is None else np.ascontiguousarray(a[keep])

    out = replace(
        sweep,
        xyz_m=np.ascontiguousarray(sweep.xyz_m[keep]),
        stamps_ns=np.ascontiguousarray(sweep.stamps_ns[keep]),
        reflectivity=kept(sweep.reflectivity),
        tag=kept(sweep.tag),
        line=kept(sweep.line),
        late=None,
    )
    counts = {
        POINT_TIME: int(late.sum()),
        POINT_FAR: int(far.sum()),
        POINT_REPEATED: int(repeated.sum()),
        NOISE_TAG: noise_tagged(out.tag),
    }
    return out, {k: n for k, n in counts.items() if n}


@dataclass
class Dropped:
    """What `screen` dropped in one run: per (topic, log ns) of a message, the count by reason.

    Every pass reads a message again; keyed by message it counts once.
    """

    by_message: dict[tuple[str, int], dict[str, int]] = field(default_factory=dict)
    untimed: set[tuple[str, int]] = field(default_factory=set)  # sweeps without a point time (kept)

    def screen(
        self, topic: str, log_ns: int, decoded: Sweep | Frame | ImuSample
    ) -> Sweep | Frame | ImuSample | None:
        """`decoded` without what no sensor measures: None for an implausible IMU reading, a sweep
        without its implausible points; a frame as it is."""
        if isinstance(decoded, ImuSample):
            why = imu_problem(decoded)
            if why is None:
                return decoded
            self.by_message[(topic, log_ns)] = {why: 1}
            return None
        if isinstance(decoded, Sweep):
            if decoded.time_layout == NO_POINT_TIME and len(decoded.stamps_ns):
                self.untimed.add((topic, log_ns))
            sweep, counts = screened_sweep(decoded)
            if counts:
                self.by_message[(topic, log_ns)] = counts
            return sweep
        return decoded

    def spikes(self, topic: str, stamps_ns: I64, gyro_rad_s: F64) -> np.ndarray[Any, np.dtype[np.bool_]]:
        """Which readings of a gyro series are spikes (`gyro_spikes`) or frozen (`gyro_frozen`), each
        counted once by its stamp."""
        spiked, frozen = gyro_spikes(gyro_rad_s), gyro_frozen(gyro_rad_s)
        for stamp in stamps_ns[spiked]:
            self.by_message[(topic, int(stamp))] = {IMU_SPIKE: 1}
        for stamp in stamps_ns[frozen & ~spiked]:
            self.by_message[(topic, int(stamp))] = {IMU_FROZEN: 1}
        out: np.ndarray[Any, np.dtype[np.bool_]] = spiked | frozen
        return out

    def by_topic(self) -> dict[str, dict[str, int]]:
        """Per topic (sorted), per reason (in `REASONS` order): readings or points dropped."""
        totals: dict[str, dict[str, int]] = {}
        for (topic, _), counts in sorted(self.by_message.items()):
            mine = totals.setdefault(topic, {})
            for why, n in counts.items():
                mine[why] = mine.get(why, 0) + n
        return {t: {why: c[why] for why in REASONS if why in c} for t, c in totals.items()}

    def lines(self) -> list[str]:
        """One warning line per topic and reason: how many, and the first message's log time; and one per
        topic whose sweeps carry no point time (a PointCloud2 without a time field). Points tagged as noise
        (`NOISE_TAG`) are counted, not warned about."""
        out = []
        for topic in sorted({t for t, _ in self.untimed}):
            n = sum(1 for t, _ in self.untimed if t == topic)
            out.append(
                f"{topic}: {n:,} sweep{'' if n == 1 else 's'} without a point-time field (PointCloud2 fields "
                f"{'/'.join(TIME_FIELDS)}): every point taken at its sweep's header stamp, so no motion "
                "within a sweep is compensated"
            )
        for topic, counts in self.by_topic().items():
            for why, n in counts.items():
                if why == NOISE_TAG:
                    continue
                first = min(log for (t, log), c in self.by_message.items() if t == topic and why in c)
                what = "reading" if why.startswith("IMU") else "point"
                sec, nsec = divmod(first, 1_000_000_000)
                when = "stamp" if why in (IMU_SPIKE, IMU_FROZEN) else "log time"
                out.append(
                    f"{topic}: dropped {n:,} {what}{'' if n == 1 else 's'}: {why} "
                    f"(first at {when} {sec}.{nsec:09d} s)"
                )
        return out


def check_imu_rate(
    where: str, topic: str, name: str, rate_hz: float | None, stamps_ns: I64, repeated: int = 0
) -> None:
    """Raise `BagError` when the IMU's readings come at a rate more than `IMU_RATE_TOLERANCE` from the
    rig's `rate_hz` (`stamps_ns`: its distinct header stamps; no check without a rate or with fewer than 3).

    The median interval measures the rate, so gaps do not move it. `repeated` readings carried the
    stamp of an earlier one and were left out (`ingest.train.repeats`): when all the readings would
    come at the rig's rate, the stamps repeat, not the rate differs, and the error says so.
    """
    stamps = np.unique(stamps_ns)
    if rate_hz is None or len(stamps) < 3:
        return
    period_ns = float(np.median(np.diff(stamps)))
    measured_hz = 1e9 / period_ns
    if abs(measured_hz - rate_hz) <= IMU_RATE_TOLERANCE * rate_hz:
        return
    readings = len(stamps) + repeated
    all_hz = readings * 1e9 / (float(stamps[-1] - stamps[0]) + period_ns)  # the last batch lasts a period
    if repeated and abs(all_hz - rate_hz) <= IMU_RATE_TOLERANCE * rate_hz:
        raise BagError(
            f"{where}: {topic}: {repeated:,} of {readings:,} IMU readings repeat an earlier reading's header"
            f" stamp: {len(stamps):,} distinct stamps, at {measured_hz:.3g} Hz, for readings at"
            f" {all_hz:.3g} Hz (the rig's {name} says rate_hz {rate_hz:g}); readings stamped in batches"
            " cannot be placed in time (a driver or clock that repeats stamps: fix the IMU's header stamps)"
        )
    raise BagError(
        f"{where}: {topic}: IMU readings at {measured_hz:.3g} Hz (median interval"
        f" {period_ns / 1e6:.3g} ms) but the rig's {name} says rate_hz {rate_hz:g};"
        f" more than {IMU_RATE_TOLERANCE:.0%} apart"
        " (the wrong rig file, or the IMU set to another rate: correct rate_hz)"
    )


UNITS_FRACTION = 0.1
"""An IMU more than this fraction of whose readings lie beyond `GYRO_LIMIT_RAD_S` (or `ACC_LIMIT`) is refused:
a knock or a glitch spikes a few readings, a gyro publishing deg/s (57 times rad/s) or an accelerometer
publishing mg most of them, and the readings under the bound are as wrong as those beyond it."""
UNITS_HINT = {
    IMU_GYRO: "a gyro publishing deg/s where sensor_msgs/Imu has rad/s, or a driver scaling its rates wrong",
    IMU_ACC: "an accelerometer publishing mg or cm/s^2, not the m/s^2 of sensor_msgs/Imu or the g of Livox's "
    "driver, or a driver scaling its readings wrong",
}


def check_imu_units(where: str, topic: str, kept: int, dropped: dict[str, int]) -> None:
    """Raise `BagError` when more than `UNITS_FRACTION` of an IMU topic's readings were dropped as beyond
    the gyro's or the accelerometer's bound (`kept`: its readings that passed, `dropped`: its counts by
    reason, `Dropped.by_topic`): the readings are in other units, so those under the bound are wrong too."""
    readings = kept + sum(n for why, n in dropped.items() if why.startswith("IMU"))
    for why, hint in UNITS_HINT.items():
        n = dropped.get(why, 0)
        if n >= 3 and n > UNITS_FRACTION * readings:
            raise BagError(
                f"{where}: {topic}: {n:,} of {readings:,} IMU readings ({n / readings:.0%}) dropped as "
                f"{why}, where a knock spikes a few: {hint}; the readings under the bound are as wrong, so "
                "nothing is written: fix the IMU driver's units"
            )


BACKWARDS_FRACTION = 0.1
"""A topic whose header stamps step back, in log order, in more than this fraction of its steps (and at
least twice) is refused: a message delivered late steps back once, a clock or a bag running backwards
in every step."""


def _seconds(ns: int) -> str:
    return f"{ns / 1e9:.3f} s"


def check_time_order(where: str, topic: str, what: str, seen: I64) -> str | None:
    """Raise `BagError` when `topic`'s stamps run backwards in log order; one line when they step back
    only now and then.

    `seen` is the survey's (N, 3) rows of (log ns, first stamp, last stamp) per
    message, in log order (`ingest.train.run.plan.survey`); `what` names the stamps
    ("header stamps", "first point times"). The passes read the bags in log
    order and take it for time order (a sample is handed on once the
    messages up to its window's end have arrived): with the order reversed, a
    sparse run kept half the points of each window and every drop counter
    read 0. A message or two delivered late are ordered by their stamps, and
    the returned line says so: a camera frame stamped early can lose its
    stereo partner (counted among the unpaired frames) and move the samples
    after it to other frames.
    """
    if len(seen) < 2:
        return None
    stamps = seen[:, 1]
    back = np.flatnonzero(np.diff(stamps) < 0)
    steps = len(stamps) - 1
    if len(back) == 0:
        return None
    k = int(back[0])
    first = (
        f"(the first: {_seconds(int(stamps[k + 1]))} logged at {_seconds(int(seen[k + 1, 0]))}, after "
        f"{_seconds(int(stamps[k]))})"
    )
    if len(back) < 2 or len(back) <= BACKWARDS_FRACTION * steps:
        return (
            f"{topic}: {what} step back in {len(back)} of {steps} steps of the bag's log order "
            f"{first}; those messages are taken in stamp order (a message delivered late, or a sensor "
            "clock that jumped)"
        )
    raise BagError(
        f"{where}: {topic}: {what} run backwards in {len(back)} of {steps} steps of the bag's log order "
        f"{first}; expected stamps that rise with log time (a sensor clock running "
        "backwards, or a bag rewritten out of order)"
    )
