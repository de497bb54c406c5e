"""A streamed job's trip to a worker: its big arrays apart from the rest.

The executor hands jobs to the workers through shared slots
(`ingest.runtime.transport`): `take_arrays` lifts a job's two camera
messages and its LiDAR windows' arrays out of it, or a dense-GT block's
sweeps out of its task (`ingest.train.run.block_jobs`), `give_arrays` puts
them back in the worker, and `handoff_bytes_bound` sizes the slots.
Pickling ~15 MB of points per dense sample, or a free-space test's 3 s of
sweeps (~26 MB at half resolution), through the task pipe cost more than
the sample's own work in the main process.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from ingest.bags.message import RawMessage
from ingest.runtime.transport import ALIGN
from ingest.train.run.block_jobs import ClearJob, FitJob
from ingest.train.run.lidar_rate import LidarRates
from ingest.train.run.sample_job import Geometry, LidarPoints
from ingest.train.run.stream import StreamedJob

Array = np.ndarray[Any, Any]


def _payload(msg: RawMessage) -> Array:
    """The bytes a message's trip to a worker carries: its data, or its chunk's compressed records."""
    return np.frombuffer(msg.raw if msg.deferred is None else msg.deferred.compressed, np.uint8)


def _with_payload(msg: RawMessage, payload: bytes) -> RawMessage:
    """`msg` with `payload` (`_payload`'s bytes, or b"") in their place."""
    if msg.deferred is None:
        return msg._replace(raw=payload)
    return msg._replace(deferred=replace(msg.deferred, compressed=payload))


_LIDAR_FIELDS = ("xyz_m", "stamps_ns", "tag", "normal_world", "clear_bits", "reflectivity")


def _lidar_arrays(points: LidarPoints) -> list[Array]:
    """A window's arrays in `_LIDAR_FIELDS` order, those it has (tags, normals, bits and reflectivity may
    be None)."""
    return [a for a in (getattr(points, f) for f in _LIDAR_FIELDS) if a is not None]


def _refilled(points: LidarPoints, arrays: list[Array]) -> LidarPoints:
    """`points` with the arrays it has replaced by `arrays`, in `_LIDAR_FIELDS` order (None stays None)."""
    it = iter(arrays)
    xyz, stamps, tag, normal, bits, refl = (
        None if getattr(points, f) is None else next(it) for f in _LIDAR_FIELDS
    )
    assert xyz is not None and stamps is not None  # never None
    return LidarPoints(points.name, xyz, stamps, tag, normal, bits, refl)


def take_arrays(job: Any) -> tuple[Any, tuple[Array, ...]]:
    """The job without its two messages' bytes and its LiDAR windows' arrays, or a block's task without its
    sweeps' arrays, and those as arrays (the executor's shared slots, instead of pickling them through the
    task pipe). The light job keeps each array cut to no rows: its dtype and columns, and which are None.
    Any other job is left whole, with no arrays."""
    if isinstance(job, FitJob):
        parts, arrays = _lift(job.parts)
        return replace(job, parts=parts), arrays
    if isinstance(job, ClearJob):
        sweeps, arrays = _lift(job.sweeps)
        return replace(job, sweeps=sweeps), arrays
    if not isinstance(job, StreamedJob):
        return job, ()
    per_lidar = [_lidar_arrays(p) for p in job.lidars]
    emptied = [_refilled(p, [a[:0] for a in own]) for p, own in zip(job.lidars, per_lidar, strict=True)]
    light = replace(
        job, upper=_with_payload(job.upper, b""), lower=_with_payload(job.lower, b""), lidars=tuple(emptied)
    )
    return light, (_payload(job.upper), _payload(job.lower), *(a for arrays in per_lidar for a in arrays))


def give_arrays(job: Any, arrays: tuple[Array, ...]) -> Any:
    """`take_arrays` undone in the worker, each array copied out of its slot (which the next job reuses)."""
    if isinstance(job, FitJob):
        return replace(job, parts=_put_back(job.parts, arrays))
    if isinstance(job, ClearJob):
        return replace(job, sweeps=_put_back(job.sweeps, arrays))
    upper, lower, *points = arrays
    lidars, i = [], 0
    for p in job.lidars:
        n = len(_lidar_arrays(p))
        lidars.append(_refilled(p, [np.array(a) for a in points[i : i + n]]))
        i += n
    return replace(
        job, upper=_with_payload(job.upper, upper.tobytes()), lower=_with_payload(job.lower, lower.tobytes()),
        lidars=tuple(lidars),
    )  # fmt: skip


_BLOCK_FIELDS = ("rows", "xyz_m", "stamps_ns", "tag")
"""The array fields of a block's parts (`FitPart`) and sweeps (`ClearSweep`, which has no rows)."""


def _arrays_of(item: Any) -> dict[str, Array]:
    """A block part's or sweep's arrays by field, those it has (a sweep may have no tags)."""
    return {f: a for f in _BLOCK_FIELDS if (a := getattr(item, f, None)) is not None}


def _lift(items: tuple[Any, ...]) -> tuple[tuple[Any, ...], tuple[Array, ...]]:
    """The items with their arrays cut to no rows, and those arrays in order."""
    light: list[Any] = []
    arrays: list[Array] = []
    for item in items:
        own = _arrays_of(item)
        light.append(replace(item, **{f: a[:0] for f, a in own.items()}))
        arrays += own.values()
    return tuple(light), tuple(arrays)


def _put_back(items: tuple[Any, ...], arrays: tuple[Array, ...]) -> tuple[Any, ...]:
    """`_lift` undone: each item's arrays, in order, copied out of `arrays`."""
    it = iter(arrays)
    return tuple(replace(item, **{f: np.array(next(it)) for f in _arrays_of(item)}) for item in items)


def handoff_bytes_bound(
    geometry: Geometry, job: StreamedJob, rates: LidarRates, window_ns: int, task_span_ns: int = 0
) -> int:
    """An upper bound of any job's `take_arrays` bytes, with `job`'s LiDAR arrays' bytes per point.

    A sample: its two camera messages (4 bytes a pixel (bgra8) and a header
    each) and each LiDAR's window of +-`window_ns`. A block's task (dense GT):
    each LiDAR's sweeps over `task_span_ns` (`PlaneSettings.task_span_ns`;
    0: none), with a row index per point. Points: at the fastest sweep rate
    of any LiDAR, plus 10 % and a sweep's end (a job over this bound, a
    burst of points, travels pickled: slower, never wrong).
    """
    cams = (geometry.rig.upper, geometry.rig.lower)
    images = sum(cam.model.width * cam.model.height * 4 + 65536 for cam in cams)
    fastest = max((max(r) for r in rates.per_sweep.values() if r), default=0.0)
    per_point = sum(a.itemsize * int(np.prod(a.shape[1:])) for p in job.lidars for a in _lidar_arrays(p))

    def points(span_ns: int) -> int:
        return int(fastest * span_ns / 1e9 * 1.1) + 1000

    sample = images + points(2 * window_ns) * per_point + ALIGN * (2 + len(_LIDAR_FIELDS) * len(job.lidars))
    if not task_span_ns:
        return sample
    rows_bytes = np.dtype(np.int64).itemsize * len(job.lidars)
    return max(sample, points(task_span_ns) * (per_point + rows_bytes) + TASK_PADDING)


TASK_PADDING = 1 << 20
"""Bytes a block's task may need for its arrays' alignment: each of a sweep's arrays starts at a multiple
of `ALIGN`, 4 x 64 bytes per sweep, so 4,096 sweeps in `task_span_ns` (a Mid-360 sends 10 a second)."""
