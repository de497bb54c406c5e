"""glibc keeps freed image-sized arrays in the process heap, so the next sample reuses their pages.

Checked on the allocator's own books (mallinfo2), not on page-fault counts, which depend on the
host's transparent huge pages and on what else the process did.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform

import numpy as np
import pytest

from ingest.runtime.heap import retain_freed_memory


class MallInfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
                     "fordblks", "keepcost")
    ]  # fmt: skip


def _mallinfo2():
    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    fn = getattr(libc, "mallinfo2", None)
    if fn is None:
        pytest.skip("mallinfo2 needs glibc 2.33 or newer")
    fn.restype = MallInfo2
    return fn


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt thresholds are glibc's")
def test_a_freed_equirect_sized_array_stays_in_the_heap():
    mallinfo2 = _mallinfo2()
    assert retain_freed_memory()
    shape = (2048, 4096, 3)  # 25 MB: one RGB equirect
    nbytes = int(np.prod(shape))
    before = mallinfo2()
    a = np.ones(shape, np.uint8)
    held = mallinfo2()
    assert a.sum() == a.size
    del a
    after = mallinfo2()
    # served from the heap, not from a fresh mmap (glibc's default above its mmap threshold) ...
    assert held.hblkhd - before.hblkhd < nbytes
    # ... and on free kept there as free heap memory, not unmapped or trimmed back to the kernel
    assert after.arena == held.arena and after.fordblks - held.fordblks >= nbytes
