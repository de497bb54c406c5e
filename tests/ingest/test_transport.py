"""Images reach forked workers through the shared slots, byte for byte; slots are reused only when released."""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

from ingest.runtime.transport import ArraySlots, SlotRef, slot_views

pytestmark = pytest.mark.skipif(
    "fork" not in multiprocessing.get_all_start_methods(), reason="the slots are inherited by fork"
)


def _read_back(ref: SlotRef) -> tuple[bytes, bytes]:
    upper, lower = slot_views(ref)
    return upper.tobytes(), lower.tobytes()


def test_images_round_trip_through_a_forked_pool_and_slots_are_recycled():
    rng = np.random.default_rng(5)
    slots = ArraySlots(3, 2 * 12 * 16 * 3)
    try:
        with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("fork")) as pool:
            for _ in range(3):  # more images than slots: each batch releases its slots
                batch = [(rng.integers(0, 256, (12, 16, 3), np.uint8), rng.integers(0, 256, (12, 16), np.uint8))
                         for _ in range(3)]  # fmt: skip
                refs = [r for r in (slots.put((u, lo)) for u, lo in batch) if r is not None]
                assert len(refs) == 3 and slots.put(batch[0]) is None  # all three taken
                got = [f.result() for f in [pool.submit(_read_back, r) for r in refs]]
                assert got == [(u.tobytes(), lo.tobytes()) for u, lo in batch]
                for r in refs:
                    slots.release(r)
        big = np.zeros((13, 16, 3), np.uint8)
        assert slots.put((big, big)) is None  # does not fit: the caller sends it the ordinary way
        assert slots.put((np.zeros((12, 16), np.uint16), np.zeros((12, 16), np.uint16))) is not None
    finally:
        slots.close()
    with pytest.raises(RuntimeError, match="forked after ArraySlots"):
        slot_views(SlotRef(0, ()))


def test_arrays_that_fill_a_slot_exactly_fit():
    """A slot takes arrays whose sizes, each rounded up to 64 bytes (a cache line), sum to at most its size: 50 + 64
    bytes round to 64 + 64 = 128 and fill a 128-byte slot; 65 bytes round to 128 and do not fit beside 64."""
    slots = ArraySlots(2, 128)
    try:
        a, b = np.arange(50, dtype=np.uint8), np.arange(64, dtype=np.uint8)
        ref = slots.put((a, b))
        assert ref is not None and ref.slot == 0
        assert slots.put((np.zeros(65, np.uint8), b)) is None
        assert slots.free == [1]  # the refused put took no slot
    finally:
        slots.close()
