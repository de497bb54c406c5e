"""Per-point times of a PointCloud2, whichever LiDAR driver wrote them.

Drivers store a point's time in different fields, types, units and bases:

| driver                          | field         | type    | unit | base               |
|---------------------------------|---------------|---------|------|--------------------|
| Livox livox_ros_driver2         | `timestamp`   | float64 | ns   | absolute           |
| Livox-style converted clouds    | `offset_time` | uint32  | ns   | from header stamp  |
| Velodyne velodyne_pointcloud    | `time`        | float32 | s    | from header stamp  |
| Ouster ouster-ros               | `t`           | uint32  | ns   | from header stamp  |
| Hesai HesaiLidar_ROS_2.0        | `timestamp`   | float64 | s    | absolute           |
| RoboSense rslidar_sdk           | `timestamp`   | float64 | s    | absolute           |

The field name does not settle unit and base (Livox and Hesai share
`timestamp`), so they are read off the values against the header stamp:
every reading the field's type allows (floats: s or ns, absolute or
relative; integers: ns, absolute only for 64-bit) is tried, and one fits
when every point lands within `MAX_OFFSET_NS` of the header stamp (a relative
float read as ns must also hold whole, larger-than-second values, as
nanosecond counts do). Among readings that fit, the one that puts a point
nearest the header stamp wins (drivers stamp a sweep at its first or last
point), which also tells a relative time from an absolute one when the clock
is near zero (simulation). A field no reading fits raises
`MessageDecodeError` naming it and its value range: a guessed time would
silently skew the deskew.

Public API: `TIME_FIELDS`, `MAX_OFFSET_NS`, `PointTimeLayout`,
`point_times_ns(points, stamp_ns) -> (stamps_ns, layout | None)`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ingest.errors import MessageDecodeError

I64 = np.ndarray[Any, np.dtype[np.int64]]
F64 = np.ndarray[Any, np.dtype[np.float64]]

TIME_FIELDS = ("timestamp", "offset_time", "time", "t")
"""Point-time field names, in order of preference when a cloud has several."""
MAX_OFFSET_NS = 3_000_000_000
"""How far a point's time may lie from its header stamp: a sweep lasts up to 2 s (Livox at 0.5 Hz)."""

_SCALE_NS = {"s": 1_000_000_000, "ns": 1}
_DRIVERS = {
    ("timestamp", "float64", "ns", False): "Livox livox_ros_driver2",
    ("offset_time", "uint32", "ns", True): "Livox-style offset_time",
    ("time", "float32", "s", True): "Velodyne",
    ("t", "uint32", "ns", True): "Ouster",
    ("timestamp", "float64", "s", False): "Hesai / RoboSense",
}


@dataclass(frozen=True)
class PointTimeLayout:
    """How a cloud's per-point time was read: field, its type, unit and base."""

    field: str
    dtype: str  # numpy name of the field's type, e.g. "float64"
    unit: str  # "s" or "ns"
    relative: bool  # True: offset from the header stamp; False: absolute time

    @property
    def driver(self) -> str:
        """The driver known to write this layout, or "unrecognised layout"."""
        return _DRIVERS.get((self.field, self.dtype, self.unit, self.relative), "unrecognised layout")

    def __str__(self) -> str:
        base = "from the header stamp" if self.relative else "absolute"
        return f"{self.field} {self.dtype} {self.unit} {base} ({self.driver})"


def _as_ns(values: F64, unit: str) -> I64:
    """Float times in `unit` to int64 ns, rounding the float's exact value to the nearest ns."""
    if unit == "ns":
        return np.rint(values).astype(np.int64)
    whole = np.floor(values)
    frac_ns = np.rint((values - whole) * 1e9).astype(np.int64)  # values - whole is exact
    return whole.astype(np.int64) * _SCALE_NS["s"] + frac_ns


def _readings(dtype: np.dtype[Any]) -> list[tuple[str, bool]]:
    """(unit, relative) readings a field of this type may hold, in order of preference."""
    if dtype.kind == "f":
        return [("s", False), ("ns", False), ("s", True), ("ns", True)]
    if dtype.itemsize == 8:
        return [("ns", False), ("ns", True)]
    return [("ns", True)]


def _offsets_ns(column: Any, unit: str, relative: bool, stamp_ns: int) -> I64 | None:
    """Point times minus `stamp_ns` under one reading, or None when they do not fit it."""
    scale = _SCALE_NS[unit]
    values = column.astype(np.float64)
    lo, hi = float(values.min()), float(values.max())
    if column.dtype.kind == "f" and relative and unit == "ns":
        if max(abs(lo), abs(hi)) <= MAX_OFFSET_NS / 1e9:
            return None  # small enough to be seconds: read as seconds, never as a few ns
        if not np.array_equal(values, np.floor(values)):
            return None  # nanosecond counts are whole numbers
    base = 0.0 if relative else stamp_ns / scale
    if max(abs(lo - base), abs(hi - base)) * scale > 2 * MAX_OFFSET_NS:
        return None  # far off (checked in float first: the exact conversion could overflow)
    times = _as_ns(values, unit) if column.dtype.kind == "f" else column.astype(np.int64)
    offsets = times if relative else times - np.int64(stamp_ns)
    if int(np.abs(offsets).max()) > MAX_OFFSET_NS:
        return None
    return offsets


BIG_ENDIAN_HINT = (
    " (read big-endian, as the message's is_bigendian says: a driver that sets it on little-endian data?)"
)


def _no_fit(name: str, column: Any, stamp_ns: int) -> MessageDecodeError:
    values = column.astype(np.float64)
    lo, hi = float(np.nanmin(values)), float(np.nanmax(values))
    return MessageDecodeError(
        f"PointCloud2 point-time field {name!r} ({column.dtype.name}) holds {lo:.15g}..{hi:.15g}, which fits"
        f" no known layout: neither absolute s/ns nor s/ns from the header stamp ({stamp_ns} ns)"
        f" keeps every point within {MAX_OFFSET_NS / 1e9:g} s of it"
    )


def point_times_ns(
    points: np.ndarray[Any, np.dtype[np.void]], stamp_ns: int
) -> tuple[I64, PointTimeLayout | None]:
    """Absolute int64 ns time of every point of a decoded PointCloud2, and how it was read.

    `points` is the cloud's structured array, `stamp_ns` its header stamp.
    Without a field of `TIME_FIELDS` every point gets the header stamp and
    the layout is None. Raises `MessageDecodeError` for a time field that is
    not a scalar number, holds non-finite values or fits no reading.
    """
    names = points.dtype.names or ()
    name = next((n for n in TIME_FIELDS if n in names), None)
    if name is None:
        return np.full(len(points), stamp_ns, np.int64), None
    dtype = points.dtype.fields[name][0] if points.dtype.fields else np.dtype("V")
    if dtype.shape or dtype.kind not in "uif":
        raise MessageDecodeError(
            f"PointCloud2 point-time field {name!r} is {dtype}; expected one number per point"
        )
    column = np.ascontiguousarray(points[name], dtype=dtype.newbyteorder("="))
    if len(column) == 0:
        return np.zeros(0, np.int64), None
    big = BIG_ENDIAN_HINT if dtype.byteorder == ">" else ""
    if dtype.kind == "f" and not np.isfinite(column).all():
        bad = int(np.count_nonzero(~np.isfinite(column)))
        raise MessageDecodeError(f"PointCloud2 point-time field {name!r} has {bad} non-finite values{big}")
    fits = []
    for rank, (unit, relative) in enumerate(_readings(column.dtype)):
        offsets = _offsets_ns(column, unit, relative, stamp_ns)
        if offsets is not None:
            fits.append((int(np.abs(offsets).min()), rank, unit, relative, offsets))
    if not fits:
        raise MessageDecodeError(f"{_no_fit(name, column, stamp_ns)}{big}")
    _, _, unit, relative, offsets = min(fits, key=lambda f: (f[0], f[1]))
    layout = PointTimeLayout(name, column.dtype.name, unit, relative)
    return offsets + np.int64(stamp_ns), layout
