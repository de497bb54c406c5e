"""The suite's own settings take effect: `tests/conftest.py` runs before numpy is imported."""

import os

import tests.conftest as suite


def test_openblas_gets_one_thread_before_numpy_loads() -> None:
    """OpenBLAS reads OPENBLAS_NUM_THREADS once, when numpy loads: set later, it changes nothing, and
    its spinning threads take CPU from the other xdist worker."""
    assert not suite.NUMPY_LOADED_FIRST
    assert os.environ["OPENBLAS_NUM_THREADS"] == "1"
