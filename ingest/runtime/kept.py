"""Jobs whose results later jobs use: computed once on a worker, kept there, referred to by key.

A `Task` wraps an executor job. One with a `key` returns `Kept(value,
report)` from its function: the executor keeps `value` under the key
and hands only `report` back to the caller, so a large value never travels
to the client. One with `needs` gets the values of those keys (tasks
submitted before it) as a third argument, `fn(shared, job, values)`. A
`Release` among the jobs drops keys once every job submitted before it has
finished. Each backend keeps a value where its workers reach it once:

- inline: in a dict of this process;
- fork pool: in a file of a folder (`FileStore`, written once by the worker
  that computed it, atomically), read by the workers that need it, each
  keeping the last few it read in memory (`_CACHE`); a task that needs a key
  whose file is not there yet waits for it: its producer was submitted
  before it and the pool hands jobs out in order, so the producer is
  running or done (if it failed, its error reaches the caller first and the
  pool is ended);
- Dask: as the producing task's result on its worker; a task that needs it
  names that future, so Dask copies it once to each worker that needs it,
  from worker to worker, never through the scheduler or the client.
"""

from __future__ import annotations

import os
import pickle
import shutil
import tempfile
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

J = TypeVar("J")

WAIT_S = 0.002
"""How long a worker sleeps between looks for a needed value's file."""
CACHED_VALUES = 8
"""Values a pool worker keeps in memory after reading them (the last read)."""


@dataclass(frozen=True)
class Task(Generic[J]):
    """An executor job that keeps its value under `key` and/or uses the values of `needs`."""

    job: J
    key: str | None = None
    needs: tuple[str, ...] = ()


@dataclass(frozen=True)
class Kept:
    """What a keyed task's function returns: `value` stays with the workers, `report` goes to the caller."""

    value: Any
    report: Any


@dataclass(frozen=True)
class Release:
    """Keys no later task needs: dropped once every job submitted before this one has finished."""

    keys: tuple[str, ...]


class UnknownKeyError(ValueError):
    """A task needs a key that no earlier task keeps (or that was released): a bug of the caller."""


def check_needs(task: Task[Any], known: set[str] | Mapping[str, Any]) -> None:
    """Raise `UnknownKeyError` when `task` needs a key not kept (so no worker ever waits for it)."""
    missing = [k for k in task.needs if k not in known]
    if missing:
        raise UnknownKeyError(f"task needs {missing}, which no earlier task keeps")


def call(fn: Callable[..., Any], shared: Any, task: Task[Any], values: Mapping[str, Any]) -> Any:
    """`fn(shared, job, values)`; a keyed task's result must be `Kept`."""
    result = fn(shared, task.job, dict(values))
    if task.key is not None and not isinstance(result, Kept):
        raise TypeError(f"task {task.key}: a keyed task's function returns Kept, not {type(result).__name__}")
    return result


# ---------------------------------------------------------------- fork pool: files


_CACHE: OrderedDict[tuple[str, str], Any] = OrderedDict()  # (folder, key) -> value, in each pool worker


class FileStore:
    """A folder of kept values, one pickle file per key (`write` in a worker, `read` in any worker)."""

    def __init__(self, parent: Path | None = None) -> None:
        """A fresh folder `.kept.XXXXXXXX.tmp` in `parent` (the system's temporary folder when None): an
        output folder's stale temporaries are removed by the next run that holds it."""
        self.folder = Path(tempfile.mkdtemp(prefix=".kept.", suffix=".tmp", dir=parent))

    def path(self, key: str) -> Path:
        return self.folder / f"{key.replace('/', '_')}.pkl"

    def write(self, key: str, value: Any) -> None:
        """Write `value` under `key` atomically: a reader sees the whole file or none."""
        fd, tmp = tempfile.mkstemp(dir=self.folder, prefix=".writing-")
        with os.fdopen(fd, "wb") as f:
            pickle.dump(value, f, protocol=pickle.HIGHEST_PROTOCOL)
        Path(tmp).replace(self.path(key))

    def read(self, key: str) -> Any:
        """The value kept under `key`, waiting for its file (see the module docstring); cached per process."""
        cache_key = (str(self.folder), key)
        if cache_key in _CACHE:
            _CACHE.move_to_end(cache_key)
            return _CACHE[cache_key]
        path = self.path(key)
        while True:
            try:
                with path.open("rb") as f:
                    value = pickle.load(f)
                break
            except FileNotFoundError:
                time.sleep(WAIT_S)
        _CACHE[cache_key] = value
        while len(_CACHE) > CACHED_VALUES:
            _CACHE.popitem(last=False)
        return value

    def drop(self, keys: tuple[str, ...]) -> None:
        for key in keys:
            self.path(key).unlink(missing_ok=True)

    def close(self) -> None:
        """Remove the folder and every value in it."""
        shutil.rmtree(self.folder, ignore_errors=True)


def pool_call(fn: Callable[..., Any], shared: Any, task: Task[Any], store: FileStore) -> Any:
    """One task in a pool worker: its needed values read from `store`, a keyed value written there."""
    values = {k: store.read(k) for k in task.needs}
    result = call(fn, shared, task, values)
    if task.key is None:
        return result
    store.write(task.key, result.value)
    return result.report


# ---------------------------------------------------------------- Dask: futures


def dask_call(fn: Callable[..., Any], shared: Any, task: Task[Any], kept: Mapping[str, Kept]) -> Any:
    """One task on a Dask worker: `kept` are the producing tasks' results (Dask resolved their futures)."""
    return call(fn, shared, task, {k: v.value for k, v in kept.items()})


def report_of(kept: Kept) -> Any:
    """A keyed task's report (a Dask task of its own, so that only the report reaches the client)."""
    return kept.report
