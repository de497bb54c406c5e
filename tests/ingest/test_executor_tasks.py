"""The executor's tasks: values kept on the workers under a key, used by later tasks, released."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ingest.runtime.executor import Executor
from ingest.runtime.kept import Kept, Release, Task, UnknownKeyError


def _fn(shared: int, job: tuple[str, int], values: dict[str, Any] | None = None) -> Any:
    """("make", n): keeps an array of n values, reports its pid; ("sum", _): the sum of every value it needs
    plus `shared`; ("fail", _): raises."""
    kind, n = job
    if kind == "make":
        return Kept(np.arange(n, dtype=np.int64), ("made", n, os.getpid()))
    if kind == "fail":
        raise ValueError(f"block {n} failed")
    return shared + sum(int(v.sum()) for v in (values or {}).values())


def _jobs() -> list[Any]:
    return [
        Task(("make", 10), key="a"),
        Task(("make", 100), key="b"),
        Task(("sum", 0), needs=("a",)),
        Task(("sum", 0), needs=("a", "b")),
        Release(("a",)),
        Task(("sum", 0), needs=("b",)),
        ("sum", 0),  # a plain job: fn(shared, job)
    ]


WANT = [("made", 10), ("made", 100), 7 + 45, 7 + 45 + 4950, 7 + 4950, 7]
"""`_jobs`' results (without the pids), shared = 7: a Release yields none."""


def _without_pids(results: list[Any]) -> list[Any]:
    return [r[:2] if isinstance(r, tuple) else r for r in results]


@pytest.mark.parametrize("workers", [1, 2])
def test_tasks_get_the_values_they_need_and_only_reports_come_back(workers: int, tmp_path: Path) -> None:
    results = list(Executor(workers).run(_fn, _jobs(), shared=7, keep_in=tmp_path))
    assert _without_pids(results) == WANT
    assert list(tmp_path.iterdir()) == []  # the pool's folder of kept values is gone with the run


def test_a_pool_keeps_values_in_a_stale_temporary_folder_of_keep_in_until_released(tmp_path: Path) -> None:
    """The values are files of `.kept.XXXXXXXX.tmp` in keep_in (which a killed run leaves for the next run
    of the output folder to remove); a Release removes its keys' files once the jobs before it are done."""
    from ingest.dataset.lock import TEMPORARY

    seen: list[list[str]] = []

    def jobs() -> Iterator[Any]:
        yield Task(("make", 10), key="a")
        yield Task(("make", 100), key="b")
        yield Task(("sum", 0), needs=("a", "b"))
        yield Release(("a",))
        yield Task(("sum", 0), needs=("b",))
        (folder,) = tmp_path.iterdir()
        assert TEMPORARY.match(folder.name)
        seen.append(sorted(p.name for p in folder.iterdir()))

    results = list(Executor(2, max_in_flight=1).run(_fn, jobs(), shared=0, keep_in=tmp_path))
    assert _without_pids(results) == [("made", 10), ("made", 100), 45 + 4950, 4950]
    assert seen == [["b.pkl"]]  # a released once the job that needed it was done; b still needed
    assert list(tmp_path.iterdir()) == []


def test_a_task_needing_a_key_no_earlier_task_keeps_is_refused_before_it_runs(tmp_path: Path) -> None:
    for workers in (1, 2):
        jobs = [Task(("make", 10), key="a"), Release(("a",)), Task(("sum", 0), needs=("a",))]
        with pytest.raises(UnknownKeyError, match=r"^task needs \['a'\], which no earlier task keeps$"):
            list(Executor(workers).run(_fn, jobs, shared=0, keep_in=tmp_path))


def test_a_failing_keyed_task_stops_the_run_with_its_error_and_no_task_waits_for_it(tmp_path: Path) -> None:
    """The producer's error reaches the caller (in job order, before any task that needs its value), and
    the workers waiting for its value are ended with the pool: the run does not hang."""
    jobs: list[Any] = [
        Task(("fail", 3), key="a"),
        Task(("sum", 0), needs=("a",)),
        Task(("sum", 0), needs=("a",)),
    ]
    for workers in (1, 2):
        with pytest.raises(ValueError, match=r"^block 3 failed$"):
            list(Executor(workers).run(_fn, jobs, shared=0, keep_in=tmp_path))
    assert list(tmp_path.iterdir()) == []


def test_dask_keeps_values_on_the_workers_and_hands_back_only_reports() -> None:
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        results = list(Executor(dask=cluster.scheduler_address).run(_fn, _jobs(), shared=7))
        pids = {r[2] for r in results if isinstance(r, tuple)}
        assert os.getpid() not in pids  # made on the workers
    assert _without_pids(results) == WANT
