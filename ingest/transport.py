"""Camera images to forked ingest workers through shared memory instead of the task pipe.

A sample's two 1920x1200 BGR images are 13.8 MB. Sent with the job through
`ProcessPoolExecutor`'s pipe they are pickled (a copy), written through a
64 KiB pipe, read and unpickled (two more copies): ~7.5 ms of CPU per
sample between the two processes (bench_ingest). Instead the main process
maps one anonymous shared region before the pool forks, so every worker
inherits it; it copies each job's images into a free slot and sends only
the slot number, shapes and dtypes. A slot is reused only after its sample's
result came back. Jobs whose images do not fit a slot, or that find no free
slot, go the ordinary way.
"""

from __future__ import annotations

import mmap
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ingest.sample import SampleJob, SampleResult, process_sample

_SHARED: tuple[mmap.mmap, int] | None = None  # (region, bytes per slot), inherited by forked workers


@dataclass(frozen=True)
class SlotImages:
    """Where a job's two images lie in the shared region: slot number, shapes and dtypes."""

    slot: int
    upper: tuple[tuple[int, ...], str]
    lower: tuple[tuple[int, ...], str]


def _views(region: mmap.mmap, slot_bytes: int, ref: SlotImages) -> tuple[np.ndarray[Any, Any], ...]:
    out, offset = [], ref.slot * slot_bytes
    for shape, dtype in (ref.upper, ref.lower):
        arr: np.ndarray[Any, Any] = np.ndarray(shape, np.dtype(dtype), buffer=region, offset=offset)
        out.append(arr)
        offset += arr.nbytes
    return tuple(out)


class ImageSlots:
    """`n` slots of `slot_bytes` in one shared anonymous mapping; create before the pool forks."""

    def __init__(self, n: int, slot_bytes: int) -> None:
        global _SHARED
        self.slot_bytes = slot_bytes
        self.region = mmap.mmap(-1, max(1, n * slot_bytes))  # MAP_SHARED | MAP_ANONYMOUS
        self.free = list(range(n - 1, -1, -1))
        _SHARED = (self.region, slot_bytes)

    def put(self, upper: np.ndarray[Any, Any], lower: np.ndarray[Any, Any]) -> SlotImages | None:
        """Copy both images into a free slot; None when none is free or they do not fit."""
        if not self.free or upper.nbytes + lower.nbytes > self.slot_bytes:
            return None
        ref = SlotImages(self.free.pop(), (upper.shape, upper.dtype.str), (lower.shape, lower.dtype.str))
        for view, image in zip(_views(self.region, self.slot_bytes, ref), (upper, lower), strict=True):
            np.copyto(view, image)
        return ref

    def release(self, ref: SlotImages | None) -> None:
        """The sample is done with its slot."""
        if ref is not None:
            self.free.append(ref.slot)

    def close(self) -> None:
        """Unmap the region (after the pool has shut down)."""
        global _SHARED
        _SHARED = None
        self.region.close()


def process_in_slot(job: SampleJob, ref: SlotImages) -> SampleResult:
    """`process_sample` in a forked worker, with the job's images read from its slot."""
    if _SHARED is None:
        raise RuntimeError("process_in_slot runs only in a worker forked after ImageSlots was created")
    upper, lower = _views(*_SHARED, ref)
    return process_sample(replace(job, upper_bgr=upper, lower_bgr=lower))
