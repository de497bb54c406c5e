"""Helpers for tests of live paths (sockets, threads, clocks): waits that only catch hangs, and a
clock that moves only when the test says so, so that no assertion depends on how busy the machine is."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest

HANG_S = 600.0
"""Waits end this late only when something hangs: on a busy machine everything is merely slower."""


class ManualClock:
    """A monotonic clock in seconds that moves only by `advance`."""

    def __init__(self, start_s: float = 0.0) -> None:
        self.now_s = start_s

    def __call__(self) -> float:
        return self.now_s

    def advance(self, seconds: float) -> None:
        self.now_s += seconds


def wait_for(condition: Callable[[], bool], what: str, timeout_s: float = HANG_S) -> None:
    """Poll until `condition()`; the timeout only catches a hang."""
    end = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > end:
            pytest.fail(f"still waiting after {timeout_s:.0f} s for {what}")
        time.sleep(0.01)
