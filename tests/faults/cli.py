"""Run `sensorbox ...` in this process as a user would: exit code, stdout and stderr lines."""

from __future__ import annotations

import subprocess
import sys

import pytest

from sensorbox.cli.main import main


def sensorbox(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, list[str]]:
    """(exit code, stdout, the stderr lines) of `sensorbox ARGS` (a blank line counts: errors are one line)."""
    argv = sys.argv
    sys.argv = ["sensorbox", *args]
    try:
        main()
        code = 0
    except SystemExit as done:
        code = int(done.code or 0)
    finally:
        sys.argv = argv
    out, err = capsys.readouterr()
    return code, out, err.splitlines()


def run_here(capsys: pytest.CaptureFixture[str], *args: str) -> subprocess.CompletedProcess[str]:
    """`sensorbox ARGS` in this process, shaped as `subprocess.run`'s result (for tests written against
    one): a subprocess per case costs seconds of imports (torch among them) and checks nothing more."""
    code, out, err = sensorbox(capsys, *args)
    return subprocess.CompletedProcess(
        ["sensorbox", *args], code, out, "\n".join(err) + ("\n" if err else "")
    )
