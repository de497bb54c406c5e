"""A Ctrl-C that arrives inside llvmlite (numba compiling or loading its cache, in a ctypes callback) is
not lost: ctypes prints and drops an exception raised in a callback, so the CLI notes it there and raises
it at the next progress update."""

from __future__ import annotations

import ctypes
import signal
import sys
from typing import Any

import pytest

from sensorbox.cli.common import ctrl_c, progress_bar

# a ctypes callback whose Python code lives in a file named like llvmlite's (as numba's cache callback does)
_SOURCE = "import signal\ndef pressed():\n    signal.raise_signal(signal.SIGINT)\n"
_NAMESPACE: dict[str, Any] = {}
exec(compile(_SOURCE, "/site-packages/llvmlite/binding/executionengine.py", "exec"), _NAMESPACE)
CALLBACK = ctypes.CFUNCTYPE(None)(_NAMESPACE["pressed"])


@pytest.fixture(autouse=True)
def _python_handler():
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


def test_python_alone_loses_a_ctrl_c_raised_in_a_ctypes_callback(monkeypatch):
    dropped = []
    monkeypatch.setattr(sys, "unraisablehook", lambda info: dropped.append(info.exc_type))
    CALLBACK()  # no raise here: ctypes hands the KeyboardInterrupt to sys.unraisablehook
    assert dropped == [KeyboardInterrupt]


def test_the_cli_notes_it_instead(monkeypatch):
    dropped = []
    monkeypatch.setattr(sys, "unraisablehook", lambda info: dropped.append(info.exc_type))
    with ctrl_c():
        CALLBACK()
    assert dropped == []


def test_the_cli_raises_it_at_the_next_progress_update():
    with ctrl_c(), progress_bar("ingesting", "samples") as update:
        CALLBACK()  # noted, not raised
        with pytest.raises(KeyboardInterrupt):
            update(1, 10)
        update(2, 10)  # raised once


def test_elsewhere_a_ctrl_c_raises_at_once():
    with ctrl_c(), pytest.raises(KeyboardInterrupt):
        signal.raise_signal(signal.SIGINT)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_an_ignored_sigint_stays_ignored():
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with ctrl_c():
        signal.raise_signal(signal.SIGINT)
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
