"""The local worker pool: each worker's compiled-kernel, Open3D and OpenCV threads are its share of the cores."""

from functools import partial

import cv2
import numba
import numpy as np
import open3d as o3d

from ingest.runtime.executor import Executor, share_cores, usable_cpus


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
