"""Ctrl-C during `sensorbox ingest`: exit 130 with one line saying what the output holds, no partial file,
and the same command resumes from there."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from sensorbox.sim.truth import truth_dir
from tests.live import HANG_S, wait_for
from tests.paths import FIXTURES_DIR, ROOT

pytestmark = pytest.mark.realtime  # a signal to a subprocess at a moment of its run: run serially

BAG = FIXTURES_DIR / "indoor_static_mcap"

# the console script's entry point with Python's own Ctrl-C handler, whatever the disposition this test runs under (a shell's background job
# inherits SIGINT ignored)
RUN = (
    "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "from sensorbox.cli import run; sys.argv[0] = 'sensorbox'; run()"
)


def _ingest(out: Path) -> subprocess.Popen[str]:
    args = ["ingest", str(BAG), "--rig", str(truth_dir(BAG) / "rig.yaml"), "--out", str(out)]
    return subprocess.Popen(
        [sys.executable, "-c", RUN, *args, "--workers", "1", "--no-preview"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def _written_resumed(stdout: str) -> tuple[int, int]:
    """The 'written / already done (resumed)' counts of an ingest summary table."""
    row = next(line for line in stdout.splitlines() if "already done (resumed)" in line)
    written, resumed = row.split("│")[2].split("/")
    return int(written), int(resumed)


def test_ctrl_c_stops_ingest_and_the_same_command_resumes(tmp_path: Path) -> None:
    out = tmp_path / "out"
    proc = _ingest(out)
    wait_for(lambda: any((out / "meta").glob("*.json")), "the first sample written", child=proc)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=HANG_S)
    held = len(list((out / "meta").glob("*.json")))
    assert proc.returncode == 130, (stdout, stderr)
    samples = f"{held} sample{'' if held == 1 else 's'}"
    assert stderr.strip() == f"interrupted: {out} holds {samples}; the same command resumes"
    assert not list(out.rglob("*.tmp"))  # every file there is whole
    again = _ingest(out)
    stdout, stderr = again.communicate(timeout=HANG_S)
    assert again.returncode == 0, stderr
    written, resumed = _written_resumed(stdout)
    assert resumed == held >= 1 and written >= 1  # stopped between the first sample and the last
    assert len(list((out / "meta").glob("*.json"))) == written + resumed
