"""glibc keeps freed image-sized arrays mapped, so the next sample reuses their pages."""

from __future__ import annotations

import platform
import resource

import numpy as np
import pytest

from ingest.heap import retain_freed_memory


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt thresholds are glibc's")
def test_a_freed_equirect_sized_array_is_reused_without_page_faults():
    assert retain_freed_memory()
    shape = (2048, 4096, 3)  # 25 MB: one RGB equirect
    a = np.ones(shape, np.uint8)  # first touch: faults in the pages
    del a
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    b = np.ones(shape, np.uint8)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
    assert b.sum() == b.size
    assert faults <= 5  # mapped afresh: ~6000 faults with 4 KiB pages, 13 with 2 MiB pages, ~500 mixed
