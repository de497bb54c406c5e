"""The local worker pool: each worker's compiled-kernel, Open3D and OpenCV threads are its share of the cores."""

from functools import partial

import cv2
import numba
import numpy as np
import pytest

from ingest.runtime import executor as executor_module
from ingest.runtime.executor import Executor, share_cores, usable_cpus
from ingest.runtime.o3d import o3d


def _threads(shared: object, job: int) -> tuple[int, int]:
    return numba.get_num_threads(), o3d.utility.get_max_threads()


def test_each_worker_gets_its_share_of_the_cores_for_numba_and_open3d():
    executor = Executor(2, worker_init=partial(share_cores, 2))
    seen = set(executor.run(_threads, range(6)))
    share = max(1, usable_cpus() // 2)
    assert seen == {(min(share, numba.config.NUMBA_NUM_THREADS), share)}  # type: ignore[attr-defined]


def _cv2_threads(shared: object, job: int) -> tuple[int, int]:
    """OpenCV's thread count in the worker, after a parallel OpenCV call (the pool works once forked)."""
    image = cv2.erode(np.full((512, 512), job, np.float32), np.ones((5, 5), np.uint8))
    return cv2.getNumThreads(), int(image[0, 0])


def test_forked_workers_run_opencv_on_their_share_and_this_process_gets_its_setting_back():
    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(max(2, usable_cpus()))  # more than a share, whatever the machine
        results = list(Executor(2).run(_cv2_threads, range(6)))
        assert results == [(min(max(2, usable_cpus()), max(1, usable_cpus() // 2)), job) for job in range(6)]
        assert cv2.getNumThreads() == max(2, usable_cpus())
        assert list(Executor(1).run(_cv2_threads, range(2))) == [
            (max(2, usable_cpus()), 0),
            (max(2, usable_cpus()), 1),
        ]
    finally:
        cv2.setNumThreads(before)


def test_opencv_threads_are_never_raised_to_a_workers_share(monkeypatch: pytest.MonkeyPatch) -> None:
    """The share only bounds OpenCV's threads: with 8 usable CPUs a worker of two may use 4, but when
    this process runs OpenCV on 2 threads its forked workers keep 2 (min(2, 8 // 2)), not 4."""
    monkeypatch.setattr(executor_module, "usable_cpus", lambda: 8)
    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(2)
        assert [n for n, _ in Executor(2).run(_cv2_threads, range(2))] == [2, 2]
        assert cv2.getNumThreads() == 2
    finally:
        cv2.setNumThreads(before)


def test_default_in_flight_is_two_jobs_per_worker_and_every_core_busy_from_one_worker_per_cpu(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Without `max_in_flight` a pool keeps two jobs per worker submitted (one running, one queued;
    at least 2); `every_core_busy` holds once there are as many local workers as usable CPUs."""
    monkeypatch.setattr(executor_module, "usable_cpus", lambda: 4)
    assert [Executor(w).max_in_flight for w in (1, 2, 3, 5)] == [2, 4, 6, 10]
    assert Executor(3, max_in_flight=7).max_in_flight == 7
    assert [Executor(w).every_core_busy for w in (1, 3, 4, 5)] == [False, False, True, True]
