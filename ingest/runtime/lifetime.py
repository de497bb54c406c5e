"""Worker processes end with the process that started them.

A forked pool worker whose parent is SIGKILLed is re-parented to init and
would live on (holding ~300 MB each) until its task pipe breaks, which never
happens while it waits. On Linux the kernel can send the child a signal when
its parent dies (`prctl(PR_SET_PDEATHSIG)`); `die_with_parent` asks for
SIGKILL, and exits at once if the parent is already gone (it may die between
the fork and this call). Elsewhere nothing is set.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys

PR_SET_PDEATHSIG = 1  # linux/prctl.h


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
