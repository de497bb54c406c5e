"""Worker processes end with the process that started them.

A forked pool worker whose parent is SIGKILLed is re-parented to init and
would live on (holding ~300 MB each) until its task pipe breaks, which never
happens while it waits. On Linux the kernel can send the child a signal when
its parent dies (`prctl(PR_SET_PDEATHSIG)`); `die_with_parent` asks for
SIGKILL, and exits at once if the parent is already gone (it may die between
the fork and this call). Elsewhere nothing is set.

`sigint_blocked` starts spawned children with SIGINT blocked, for children
that their parent stops through a pipe: Ctrl-C reaches the whole process
group, and a child still importing (a second or more) would otherwise die
there with a KeyboardInterrupt traceback on the terminal. Such a child whose
parent was killed (SIGKILL) finds out when its next report meets the closed
pipe (`BrokenPipeError`): it stops and says so in one line, `orphaned`,
instead of a traceback.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from multiprocessing import resource_tracker

PR_SET_PDEATHSIG = 1  # linux/prctl.h


@contextmanager
def sigint_blocked() -> Iterator[None]:
    """SIGINT held back inside: a process spawned here starts with it blocked, and this one gets it after.

    Ctrl-C goes to the whole process group. A spawned child needs a second or
    more to import before its own code can ignore SIGINT, and a
    KeyboardInterrupt in that time would be a traceback on the terminal. The
    thread's signal mask survives fork and exec, so the child never sees
    SIGINT (its parent must stop it some other way, such as a control pipe).
    A Ctrl-C is directed at the process, and the kernel hands it to any
    thread that has SIGINT unblocked (a reader thread, say); Python then runs
    its handler in the main thread, which would raise KeyboardInterrupt in
    the middle of the spawn. So, in the main thread, the handler only notes
    it inside the block. Either way the SIGINT is delivered when the block
    ends, and the parent's own Ctrl-C is not lost.
    """
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    # spawning starts multiprocessing's resource tracker once, and that start unblocks SIGINT on its way
    # out (CPython's resource_tracker.ensure_running): it runs before the block, not inside it
    resource_tracker.ensure_running()
    noted: list[int] = []
    handler = signal.getsignal(signal.SIGINT)  # None: not set from Python, left alone
    defer = threading.current_thread() is threading.main_thread() and handler is not None
    if defer:
        signal.signal(signal.SIGINT, lambda signum, frame: noted.append(signum))
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        # unblocked first, while the noting handler is still in place: a SIGINT pending or arriving now
        # is noted, never raised between the two restores
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
        if defer:
            signal.signal(signal.SIGINT, handler)
        if noted:
            signal.raise_signal(signal.SIGINT)  # to this thread, now unblocked: the handler of before


def die_with_parent(parent_pid: int) -> bool:
    """Have the kernel SIGKILL this process when `parent_pid` (its parent) dies; True when it was set."""
    if not sys.platform.startswith("linux"):
        return False
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name, use_errno=True)
        ok = libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False
    if os.getppid() != parent_pid:  # the parent died before the request took effect
        os._exit(1)
    return bool(ok)


def orphaned(what: str) -> None:
    """Say on stderr, in one line, that `what` (a spawned child) stopped because its parent is gone."""
    try:
        sys.stderr.write(f"{what}: stopped; the process that started it is gone (killed)\n")
        sys.stderr.flush()
    except (OSError, ValueError):  # a closed stderr: nothing left to tell
        pass
