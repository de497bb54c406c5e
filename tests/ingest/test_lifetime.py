"""Pool workers end with their parent, even when it is SIGKILLed (issue 20, class 8)."""

import contextlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.live import HANG_S, wait_for
from tests.paths import ROOT

pytestmark = [
    pytest.mark.realtime,
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl(PR_SET_PDEATHSIG) is Linux's"),
]

PARENT = """
import time
from ingest.runtime.executor import Executor

def job(_shared, k):
    time.sleep(3600)

for _ in Executor(2).run(job, range(4)):
    pass
"""


def _children(pid: int) -> list[int]:
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        with contextlib.suppress(OSError):  # a thread that ended meanwhile
            out += [int(c) for c in (task / "children").read_text().split()]
    return out


def _running(pid: int) -> bool:
    """The process exists and is not a zombie waiting to be reaped."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_pool_workers_die_when_their_parent_is_killed(tmp_path):
    script = tmp_path / "parent.py"
    script.write_text(PARENT)
    parent = subprocess.Popen([sys.executable, str(script)], cwd=ROOT)
    try:
        wait_for(lambda: len(_children(parent.pid)) >= 2, "two pool workers started")
        workers = _children(parent.pid)
        assert all(_running(w) for w in workers)
    finally:
        parent.kill()
        parent.wait()
    wait_for(lambda: not any(_running(w) for w in workers), "the workers ended with their parent")


def _sleep_or_return(_shared, k):
    import time

    if k > 0:
        time.sleep(3 * HANG_S)  # far beyond the wait below: a pool that waits for it fails the test
    return k


def test_a_run_left_early_ends_its_workers_instead_of_waiting_for_their_jobs():
    """A consumer that stops (an error, or Ctrl-C reaching only this process) gets the pool shut down
    at once: the workers running long jobs are terminated, not waited for."""
    import threading

    from ingest.runtime.executor import Executor

    before = set(_children(os.getpid()))  # a resource tracker, say
    results = Executor(3).run(_sleep_or_return, range(4))
    assert next(results) == 0
    workers = [c for c in _children(os.getpid()) if c not in before]
    assert len(workers) >= 2 and all(_running(w) for w in workers)
    closing = threading.Thread(target=results.close, daemon=True)  # returns once the pool is shut down
    closing.start()
    closing.join(HANG_S)
    assert not closing.is_alive(), "the pool waited for its running jobs"
    assert not any(_running(w) for w in workers)
