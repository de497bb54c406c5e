"""Run one call in a helper thread beside the caller's own work.

A sample's two equirect warps (cv2, which releases the GIL) do not depend on
its points, so they run while the calling thread does the numpy and Open3D
point work: one worker then uses its second core for them (bench_ingest).
A plain thread per call, not a pool: a thread pool created before a fork
would be dead in the forked ingest workers, and starting a thread costs
~0.1 ms against the ~14 ms it runs. When every core already runs an ingest
worker the helper only adds thread switches (~1-2 ms per sample measured),
so the caller can ask for the same call inline.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")


class Background(Generic[T]):
    """`fn()` started in a helper thread now; `result()` waits for it and returns its value.

    An exception `fn` raised is re-raised by `result()` in the calling thread.
    `wait()` only waits: callers that leave early (an error, a skipped
    sample) call it so the helper never outlives the buffers it writes.
    """

    def __init__(self, fn: Callable[[], T], name: str = "sensorbox-background", inline: bool = False) -> None:
        """Start `fn`; with `inline` run it to the end here instead (no helper thread, same interface)."""
        self._fn = fn
        self._value: list[T] = []  # [return value] once fn returned
        self._error: BaseException | None = None
        self.ms = 0.0  # the helper's own wall time (ms), set when it finishes
        self._thread: threading.Thread | None = None
        if inline:
            self._run()
        else:
            self._thread = threading.Thread(target=self._run, name=name, daemon=True)
            self._thread.start()

    def _run(self) -> None:
        t0 = time.perf_counter()
        try:
            self._value.append(self._fn())
        except BaseException as exc:  # handed to the caller by result()
            self._error = exc
        finally:
            self.ms = (time.perf_counter() - t0) * 1e3

    def wait(self) -> None:
        """Block until the helper has finished (at once if it has or ran inline)."""
        if self._thread is not None:
            self._thread.join()

    def result(self) -> T:
        """Wait, then the helper's return value, or raise what it raised."""
        self.wait()
        if self._error is not None:
            raise self._error
        return self._value[0]
