"""The suite's own settings take effect: `tests/conftest.py` runs before numpy is imported."""

import os

import tests.conftest as suite


def test_openblas_gets_one_thread_before_numpy_loads() -> None:
    """OpenBLAS reads OPENBLAS_NUM_THREADS once, when numpy loads: set later, it changes nothing, and
    its spinning threads take CPU from the other xdist worker."""
    assert not suite.NUMPY_LOADED_FIRST
    assert os.environ["OPENBLAS_NUM_THREADS"] == "1"


def test_openmp_threads_sleep_when_idle_set_before_libgomp_loads() -> None:
    """libgomp reads OMP_WAIT_POLICY once, when it loads (numba's first parallel kernel): set later, its
    idle threads spin and take CPU from the other xdist worker."""
    assert not suite.GOMP_LOADED_FIRST
    assert os.environ["OMP_WAIT_POLICY"] == "PASSIVE"
