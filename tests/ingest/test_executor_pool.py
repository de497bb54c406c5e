"""The local worker pool: each worker's compiled-kernel and Open3D threads are its share of the cores."""

from functools import partial

import numba
import open3d as o3d

from ingest.runtime.executor import Executor, share_cores, usable_cpus


def _threads(shared: object, job: int) -> tuple[int, int]:
    return numba.get_num_threads(), o3d.utility.get_max_threads()


def test_each_worker_gets_its_share_of_the_cores_for_numba_and_open3d():
    executor = Executor(2, worker_init=partial(share_cores, 2))
    seen = set(executor.run(_threads, range(6)))
    share = max(1, usable_cpus() // 2)
    assert seen == {(min(share, numba.config.NUMBA_NUM_THREADS), share)}  # type: ignore[attr-defined]
