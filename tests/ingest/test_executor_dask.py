"""The executor's Dask backend: shared state sent once, jobs' bytes never in the task graph."""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import pytest

from ingest.runtime.executor import Executor

distributed = pytest.importorskip("distributed")


def _checksum(shared: dict[str, Any], job: tuple[int, bytes]) -> tuple[int, int, int]:
    k, data = job
    return k, int(np.frombuffer(data, np.uint8).sum(dtype=np.int64)), shared["calls"]


def test_large_jobs_reach_the_workers_without_a_large_graph() -> None:
    rng = np.random.default_rng(0)
    jobs = [(k, rng.integers(0, 256, 12_000_000, np.uint8).tobytes()) for k in range(3)]  # over 10 MB each
    expected = [(k, int(np.frombuffer(d, np.uint8).sum(dtype=np.int64)), 7) for k, d in jobs]
    with (
        distributed.LocalCluster(
            n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
        ) as cluster,
        warnings.catch_warnings(record=True) as caught,
    ):
        warnings.simplefilter("always")
        results = list(Executor(dask=cluster.scheduler_address).run(_checksum, jobs, shared={"calls": 7}))
    assert results == expected
    assert not [w for w in caught if "large graph" in str(w.message)]
