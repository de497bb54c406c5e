"""`ingest.runtime.jit.compiling` counts the seconds numba compiles, and nothing for a kernel it has."""

from __future__ import annotations

import numba
import numpy as np

from ingest.runtime.jit import compiling


def test_a_first_call_compiles_and_a_second_does_not() -> None:
    @numba.njit(cache=False)
    def twice(x: np.ndarray) -> float:
        return float(x.sum()) * 2.0

    with compiling() as first:
        assert twice(np.arange(4.0)) == 12.0
    with compiling() as second:
        assert twice(np.arange(5.0)) == 20.0  # the same types: the machine code it has
    with compiling() as third:
        assert twice(np.arange(5, dtype=np.int64)) == 20.0  # new types: compiled again
    assert first[0] > 0.01 and second == [0.0] and third[0] > 0.01
