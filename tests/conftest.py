"""Session-wide test settings."""

from __future__ import annotations

import os
import sys
from pathlib import Path

# One OpenBLAS thread per process, as the command line sets it (`sensorbox.cli`), before numpy loads: the
# tests that call the library run its small matrix products, whose BLAS threads only spin on the other
# core, beside the other xdist worker (a dense ingest test: 32-35 -> 27-29 CPU s, the same wall time).
NUMPY_LOADED_FIRST = "numpy" in sys.modules
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# OpenMP threads (numba's parallel kernels) sleep when idle instead of spinning for a while after each kernel:
# beside the other xdist worker a spinning thread takes its core (the dense and fault tests, run
# interleaved: 3-4 % less wall and CPU time). libgomp reads the policy when it loads, at the first kernel.
MAPS = Path("/proc/self/maps")  # the shared libraries this process has loaded (Linux)
GOMP_LOADED_FIRST = MAPS.exists() and "libgomp" in MAPS.read_text()
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pytest  # noqa: E402

from calibration.warp import MAP_CACHE_ENV  # noqa: E402


@pytest.fixture(autouse=True, scope="session")
def _map_cache_in_a_temporary_folder(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Remap maps cached on disk go to the run's temporary folder, never the user's ~/.cache.

    Under xdist the workers share one folder (the run's, above each worker's
    own): a full-resolution pair of maps is about 190 MB, and the cache
    writes atomically (a temporary file, then a rename).
    """
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent
    folder = root / "map_cache"
    folder.mkdir(exist_ok=True)
    os.environ[MAP_CACHE_ENV] = str(folder)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tests of an xdist group first, in collection order otherwise.

    `--dist loadgroup` runs a group on one worker, so that its module fixtures
    (the dense walks, the benchmark scenes, the viewer's datasets) are built once;
    it hands work out in collection order, and a heavy group handed out last ran
    alone at the end while the other worker idled. First, the two workers share
    the groups and the single tests fill in behind them.
    """
    grouped = [item for item in items if item.get_closest_marker("xdist_group") is not None]
    items[:] = grouped + [item for item in items if item.get_closest_marker("xdist_group") is None]
