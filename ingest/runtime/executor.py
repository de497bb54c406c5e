"""One executor for the independent jobs of train (samples) and render (views): inline, a fork pool, or Dask.

- Backend: a Dask cluster when an address is given; a pool of forked worker
  processes when `workers` > 1 and the platform forks (workers inherit this
  process's memory: remap maps, scan indexes); otherwise inline, in this process.
- `shared`: what every job needs and no job should carry. A forked worker
  inherits it, a Dask worker receives it once (scattered to every worker),
  inline calls get it as it is. `fn(shared, job)` does one job. On Dask each
  job is scattered straight to a worker (`direct=True`) and the task refers
  to it by key, so a job's bytes never travel in the task graph through the
  scheduler (no "Sending large graph"); the client must reach the workers.
- `worker_init` runs once in every worker process before its first job, and
  once in this process when running inline: process-wide settings (allocator,
  thread counts) belong there, not in a job. Pool workers also end with this
  process (`ingest.runtime.lifetime`), even when it is SIGKILLed.
- `handoff` moves a job's large arrays (camera images) through one shared
  anonymous mapping instead of the task pipe (fork pool only): `take(job)`
  splits a job into a light job and its arrays, `give(job, arrays)` joins them
  again in the worker. A slot is reused once its job's result came back; a job
  whose arrays do not fit, or that finds no free slot, goes the ordinary way.
- `run(jobs)` keeps at most `max_in_flight` jobs submitted and yields the
  results in submission order; it pulls the next job only when there is room,
  so a generator of jobs streams.
- A job may be a `Task` (`ingest.runtime.kept`): one that keeps a value on
  the workers under a key (only its report comes back), or one that uses
  earlier tasks' values, each reaching a worker once; a `Release` drops keys.
  Pool workers keep values in files of a folder in `keep_in` (the system's
  temporary folder by default), removed when the run ends.

One `run` at a time per process: the shared state of a fork pool is this
module's, inherited by the children it forks.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
from collections import deque
from collections.abc import Callable, Generator, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Generic, Literal, TypeVar

import cv2
import numpy as np

from ingest.runtime.kept import FileStore, Kept, Release, Task, check_needs, dask_call, pool_call, report_of
from ingest.runtime.lifetime import die_with_parent
from ingest.runtime.transport import ArraySlots, SlotRef, slot_views

if TYPE_CHECKING:
    from distributed import Client

J = TypeVar("J")
R = TypeVar("R")
Arrays = tuple[np.ndarray[Any, Any], ...]
Backend = Literal["inline", "fork", "spawn", "dask"]

_WORKER: dict[
    str, Any
] = {}  # "shared", "fn", "give", "store": set before the pool forks, inherited by its workers


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask on Linux, else the machine's count)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def share_cores(workers: int) -> None:
    """Worker init: numba's threads (the compiled renderer's) and Open3D's (its k-NN) are this worker's
    share of the usable cores.

    With one worker per core, more threads per worker only add switches.
    OpenCV's share is set before the fork instead (`_share_cv2_threads`).
    Open3D's TBB pool knows no environment variable; `set_max_threads`
    (Open3D 0.20) bounds it, where Open3D is loaded (the GPU machines have none).
    """
    import numba

    from calibration.kernels import fork_safe_numba_threads

    fork_safe_numba_threads()

    cores = max(1, usable_cpus() // workers)
    numba.set_num_threads(min(cores, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]
    o3d = sys.modules.get("open3d")
    if o3d is not None and hasattr(o3d.utility, "set_max_threads"):
        o3d.utility.set_max_threads(cores)


def _share_cv2_threads(workers: int) -> int:
    """OpenCV's threads set to one worker's share of the usable cores in this process, which forked workers
    inherit; returns the previous setting, for this process to take back when its pool is done.

    OpenCV runs a large cvtColor, remap or erode on every core by default, so
    two workers on two cores ran four threads. Set here, before the fork,
    because reconfiguring OpenCV's thread pool inside a forked child can
    deadlock.
    """
    previous = cv2.getNumThreads()
    cv2.setNumThreads(min(previous, max(1, usable_cpus() // workers)))
    return previous


@dataclass(frozen=True)
class Handoff(Generic[J]):
    """How a job's large arrays leave it (`take`, in this process) and come back (`give`, in a worker)."""

    take: Callable[[J], tuple[J, Arrays]]
    give: Callable[[J, Arrays], J]
    slot_bytes: int


def _forked_call(job: Any, ref: SlotRef | None) -> Any:
    """One job in a forked worker: shared state and the job function come from the parent's memory."""
    if isinstance(job, Task):
        if ref is not None:
            job = Task(_WORKER["give"](job.job, slot_views(ref)), job.key, job.needs)
        return pool_call(_WORKER["fn"], _WORKER["shared"], job, _WORKER["store"])
    if ref is not None:
        job = _WORKER["give"](job, slot_views(ref))
    return _WORKER["fn"](_WORKER["shared"], job)


def _inner(job: Any) -> Any:
    """The job a `Task` wraps, or the job itself."""
    return job.job if isinstance(job, Task) else job


def _with_inner(job: Any, inner: Any) -> Any:
    """`job` with `inner` as the job it wraps (a `Task`), or `inner` itself."""
    return Task(inner, job.key, job.needs) if isinstance(job, Task) else inner


def _terminate_workers(pool: ProcessPoolExecutor) -> None:
    """SIGTERM every worker of `pool`, so that its shutdown does not wait for the jobs they are running.

    A Ctrl-C that reaches only this process (`kill -INT`, a supervisor) would
    otherwise wait for every running job to end. The pool keeps its processes
    in a private mapping (Python 3.14 adds `terminate_workers` for this).
    """
    for proc in list(getattr(pool, "_processes", {}).values()):
        if proc.is_alive():
            proc.terminate()


def _init_worker(worker_init: Callable[[], object] | None, parent_pid: int | None = None) -> None:
    if parent_pid is not None:
        die_with_parent(parent_pid)
    if worker_init is not None:
        worker_init()


class Executor:
    """Run `fn(shared, job)` over many jobs on the chosen backend (see the module docstring)."""

    def __init__(
        self,
        workers: int = 1,
        *,
        dask: str | None = None,
        worker_init: Callable[[], object] | None = None,
        max_in_flight: int | None = None,
    ) -> None:
        self.workers = max(1, int(workers))
        self.dask = dask
        self.worker_init = worker_init
        self.max_in_flight = max_in_flight or max(2, 2 * self.workers)
        forks = "fork" in multiprocessing.get_all_start_methods()
        self.backend: Backend = (
            "dask" if dask else "inline" if self.workers == 1 else "fork" if forks else "spawn"
        )
        self._client: Client | None = None  # opened by `connect`

    def connect(self) -> None:
        """Dask: connect to the scheduler now, so that an unreachable one fails before anything is written.

        `run` connects on its own otherwise; `close` ends the connection. Other backends: nothing.
        """
        if self.backend == "dask" and self._client is None:
            from distributed import Client

            self._client = Client(self.dask)  # type: ignore[no-untyped-call]

    def close(self) -> None:
        """End a connection that `connect` opened."""
        if self._client is not None:
            self._client.close()  # type: ignore[no-untyped-call]
            self._client = None

    @property
    def every_core_busy(self) -> bool:
        """Whether local workers already occupy every usable CPU (helper threads would only add switches)."""
        return self.backend in ("fork", "spawn") and self.workers >= usable_cpus()

    def run(
        self,
        fn: Callable[..., R],
        jobs: Iterable[J | Task[J] | Release],
        *,
        shared: Any = None,
        handoff: Handoff[J] | None = None,
        keep_in: Path | None = None,
    ) -> Generator[R, None, None]:
        """Results of `fn(shared, job)` for every job, in the jobs' order (a `Task`: `fn(shared, job,
        values)`, its report when keyed; a `Release` has none)."""
        if self.backend == "inline":
            yield from self._run_inline(fn, jobs, shared)
        elif self.backend == "dask":
            yield from self._run_dask(fn, jobs, shared)
        else:
            yield from self._run_pool(fn, jobs, shared, handoff, keep_in)

    def _run_inline(
        self, fn: Callable[..., R], jobs: Iterable[J | Task[J] | Release], shared: Any
    ) -> Generator[R, None, None]:
        _init_worker(self.worker_init)
        kept: dict[str, Any] = {}
        for job in jobs:
            if isinstance(job, Release):
                for key in job.keys:
                    kept.pop(key, None)
            elif isinstance(job, Task):
                check_needs(job, kept)
                result = fn(shared, job.job, {k: kept[k] for k in job.needs})
                if job.key is not None:
                    assert isinstance(result, Kept), f"task {job.key}: a keyed task's function returns Kept"
                    kept[job.key], result = result.value, result.report
                yield result
            else:
                yield fn(shared, job)

    def _run_pool(
        self,
        fn: Callable[..., R],
        jobs: Iterable[J | Task[J] | Release],
        shared: Any,
        handoff: Handoff[J] | None,
        keep_in: Path | None,
    ) -> Generator[R, None, None]:
        fork = self.backend == "fork"
        slots = ArraySlots(self.max_in_flight + 1, handoff.slot_bytes) if fork and handoff else None
        store = FileStore(keep_in)
        _WORKER.update(shared=shared, fn=fn, give=handoff.give if handoff else None, store=store)
        ctx = multiprocessing.get_context("fork" if fork else "spawn")
        cv2_threads = _share_cv2_threads(self.workers) if fork else None
        pool = ProcessPoolExecutor(
            self.workers, mp_context=ctx, initializer=_init_worker, initargs=(self.worker_init, os.getpid())
        )
        # a Release waits in line (no future) until every job before it has finished
        pending: deque[tuple[Future[R] | Release, SlotRef | None]] = deque()
        kept: set[str] = set()
        finished = False
        try:
            for job in jobs:
                if isinstance(job, Release):
                    kept -= set(job.keys)
                    pending.append((job, None))
                else:
                    if isinstance(job, Task):
                        check_needs(job, kept)
                        kept |= {job.key} if job.key is not None else set()
                    pending.append(self._submit(pool, fn, shared, job, handoff, slots, store))
                while pending and (
                    self._in_flight(pending) >= self.max_in_flight or self._front_done(pending)
                ):
                    yield from self._collect(pending, slots, store)
            while pending:
                yield from self._collect(pending, slots, store)
            finished = True
        finally:
            if not finished:  # an error, Ctrl-C or the consumer stopped: running jobs' results are unwanted
                _terminate_workers(pool)
            pool.shutdown(cancel_futures=True)
            _WORKER.clear()
            store.close()
            if cv2_threads is not None:
                cv2.setNumThreads(cv2_threads)
            if slots is not None:
                slots.close()

    def _submit(
        self,
        pool: ProcessPoolExecutor,
        fn: Callable[..., R],
        shared: Any,
        job: J | Task[J],
        handoff: Handoff[J] | None,
        slots: ArraySlots | None,
        store: FileStore,
    ) -> tuple[Future[R], SlotRef | None]:
        """Submit one job (its arrays through a slot where they fit); spawned workers inherit nothing, so
        the function and shared state travel with the job."""
        if self.backend != "fork":
            if isinstance(job, Task):
                return pool.submit(pool_call, fn, shared, job, store), None
            return pool.submit(fn, shared, job), None
        ref = None
        if slots is not None and handoff is not None:
            light, arrays = handoff.take(_inner(job))
            ref = slots.put(arrays) if arrays else None
            if ref is not None:
                job = _with_inner(job, light)
        return pool.submit(_forked_call, job, ref), ref

    @staticmethod
    def _in_flight(pending: deque[tuple[Any, SlotRef | None]]) -> int:
        return sum(1 for f, _ in pending if not isinstance(f, Release))

    @staticmethod
    def _front_done(pending: deque[tuple[Any, SlotRef | None]]) -> bool:
        front = pending[0][0]
        return isinstance(front, Release) or bool(front.done())

    @staticmethod
    def _collect(
        pending: deque[tuple[Future[R] | Release, SlotRef | None]], slots: ArraySlots | None, store: FileStore
    ) -> Iterator[R]:
        """The front job's result (a Release at the front: its keys dropped, nothing yielded)."""
        fut, ref = pending.popleft()
        if isinstance(fut, Release):
            store.drop(fut.keys)
            return
        try:
            result = fut.result()
        finally:
            if slots is not None:
                slots.release(ref)
        yield result

    def _run_dask(
        self, fn: Callable[..., R], jobs: Iterable[J | Task[J] | Release], shared: Any
    ) -> Generator[R, None, None]:
        self.connect()
        client = self._client
        assert client is not None
        try:
            if self.worker_init is not None:
                client.run(self.worker_init)
            shared_ref = client.scatter(shared, broadcast=True) if shared is not None else None  # type: ignore[no-untyped-call]
            pending: deque[Any] = deque()
            kept: dict[str, Any] = {}  # key -> the future of its task's Kept, on the worker that made it
            for job in jobs:
                if isinstance(job, Release):
                    pending.append(job)
                    for key in job.keys:
                        kept.pop(key, None)  # the tasks that need it hold it until they are done
                else:
                    pending.append(self._submit_dask(client, fn, shared_ref, job, kept))
                while pending and (
                    sum(1 for p in pending if not isinstance(p, Release)) >= self.max_in_flight
                    or isinstance(pending[0], Release)
                    or pending[0].done()
                ):
                    front = pending.popleft()
                    if not isinstance(front, Release):
                        yield front.result()
            while pending:
                front = pending.popleft()
                if not isinstance(front, Release):
                    yield front.result()
        finally:
            self.close()

    @staticmethod
    def _submit_dask(
        client: Client, fn: Callable[..., R], shared_ref: Any, job: J | Task[J], kept: dict[str, Any]
    ) -> Any:
        """Submit one job; its data goes straight to a worker (the scheduler sees only its key), a task's
        needed values as the futures of the tasks that keep them."""
        job_ref = client.scatter(job, direct=True, hash=False)  # type: ignore[no-untyped-call]
        if not isinstance(job, Task):
            return client.submit(fn, shared_ref, job_ref, pure=False)
        check_needs(job, kept)
        needed = {k: kept[k] for k in job.needs}
        future = client.submit(dask_call, fn, shared_ref, job_ref, needed, pure=False)
        if job.key is None:
            return future
        kept[job.key] = future
        return client.submit(report_of, future, pure=False)
