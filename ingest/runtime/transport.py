"""Large arrays to forked workers through shared memory instead of the task pipe.

A sample's two 1920x1200 BGR images are 13.8 MB, and a dense sample's LiDAR
windows (+-0.5 s of two Mid-360s) about 15 MB. Sent with the job through
`ProcessPoolExecutor`'s pipe they are pickled (a copy), written through a
64 KiB pipe, read and unpickled (two more copies): ~7.5 ms of CPU per
sample between the two processes (bench_ingest). Instead the main process
maps one anonymous shared region before the pool forks, so every worker
inherits it; it copies each job's arrays into a free slot and sends only the
slot number, shapes and dtypes. The executor (`ingest.runtime.executor`)
reuses a slot only after its job's result came back.
"""

from __future__ import annotations

import mmap
from dataclasses import dataclass
from typing import Any

import numpy as np

_REGION: tuple[mmap.mmap, int] | None = None  # (region, bytes per slot), inherited by forked workers


@dataclass(frozen=True)
class SlotRef:
    """Where a job's arrays lie in the shared region: slot number, then (shape, dtype) of each array."""

    slot: int
    layout: tuple[tuple[tuple[int, ...], str], ...]


ALIGN = 64
"""Each array of a slot starts at a multiple of this many bytes (a cache line: aligned for any dtype)."""


def _padded(nbytes: int) -> int:
    return -(-nbytes // ALIGN) * ALIGN


def _views(region: mmap.mmap, slot_bytes: int, ref: SlotRef) -> tuple[np.ndarray[Any, Any], ...]:
    out, offset = [], ref.slot * slot_bytes
    for shape, dtype in ref.layout:
        arr: np.ndarray[Any, Any] = np.ndarray(shape, np.dtype(dtype), buffer=region, offset=offset)
        out.append(arr)
        offset += _padded(arr.nbytes)
    return tuple(out)


class ArraySlots:
    """`n` slots of `slot_bytes` in one shared anonymous mapping; create before the pool forks."""

    def __init__(self, n: int, slot_bytes: int) -> None:
        global _REGION
        self.slot_bytes = slot_bytes
        self.region = mmap.mmap(-1, max(1, n * slot_bytes))  # MAP_SHARED | MAP_ANONYMOUS
        self.free = list(range(n - 1, -1, -1))
        _REGION = (self.region, slot_bytes)

    def put(self, arrays: tuple[np.ndarray[Any, Any], ...]) -> SlotRef | None:
        """Copy the arrays into a free slot; None when none is free or they do not fit."""
        if not self.free or sum(_padded(a.nbytes) for a in arrays) > self.slot_bytes:
            return None
        ref = SlotRef(self.free.pop(), tuple((a.shape, a.dtype.str) for a in arrays))
        for view, array in zip(_views(self.region, self.slot_bytes, ref), arrays, strict=True):
            np.copyto(view, array)
        return ref

    def release(self, ref: SlotRef | None) -> None:
        """The job is done with its slot."""
        if ref is not None:
            self.free.append(ref.slot)

    def close(self) -> None:
        """Unmap the region (after the pool has shut down)."""
        global _REGION
        _REGION = None
        self.region.close()


def slot_views(ref: SlotRef) -> tuple[np.ndarray[Any, Any], ...]:
    """In a worker forked after `ArraySlots` was created: the job's arrays, read in place."""
    if _REGION is None:
        raise RuntimeError("slot_views runs only in a worker forked after ArraySlots was created")
    return _views(*_REGION, ref)
