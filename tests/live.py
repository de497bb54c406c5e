"""Helpers for tests of live paths (sockets, threads, clocks): waits that only catch hangs, and a
clock that moves only when the test says so, so that no assertion depends on how busy the machine is."""

from __future__ import annotations

import subprocess
import time
from collections.abc import Callable

import pytest

HANG_S = 600.0
"""Waits end this late only when something hangs: on a busy machine everything is merely slower."""

NO_DISK_GUARD = 0
"""`min_free_bytes` (and `min_free_mb`) of recorders in tests that are not about the disk guard. The guard
has its own tests with an injected free-space reading; anywhere else it would make a test pass or fail
by how full the machine's disk happens to be."""


class ManualClock:
    """A monotonic clock in seconds that moves only by `advance`."""

    def __init__(self, start_s: float = 0.0) -> None:
        self.now_s = start_s

    def __call__(self) -> float:
        return self.now_s

    def advance(self, seconds: float) -> None:
        self.now_s += seconds


def wait_for(
    condition: Callable[[], bool],
    what: str,
    timeout_s: float = HANG_S,
    child: subprocess.Popen[str] | None = None,
) -> None:
    """Poll until `condition()`; the timeout only catches a hang. With `child`, the process that is to
    make `condition()` true: its exit ends the wait at once, with what it printed."""
    end = time.monotonic() + timeout_s
    while not condition():
        if child is not None and child.poll() is not None and not condition():  # it may have just made it
            stdout, stderr = child.communicate()
            pytest.fail(f"the child exited ({child.returncode}) before {what}:\n{stdout}\n{stderr}")
        if time.monotonic() > end:
            pytest.fail(f"still waiting after {timeout_s:.0f} s for {what}")
        time.sleep(0.01)
