"""The `sensorbox` command line (see `sensorbox.cli.main`).

numpy's OpenBLAS gets one thread per process unless the user says otherwise
(`OPENBLAS_NUM_THREADS`): this package is imported before numpy is, so the
setting takes. Our matrix products are small (points times 3x3, 12x12 normal
equations) and the parallelism is worker processes; BLAS threads only spun on
the other core (dense ingest of a full-resolution walk, 2 workers: 87.1 s ->
78.8 s; the odometry used 12.5 s of CPU for 4 s of data with them, 9.0 without).
"""

import contextlib
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


INTERRUPTED = 130  # the shell's code for a command stopped by SIGINT
USAGE = 2  # a user mistake (`sensorbox.cli.main`)


def _streams_open() -> None:
    """Exit 2 with one line when standard output is closed (`>&-`) or the current directory is gone
    (deleted while the shell stood in it): every command prints its progress
    and summary there, and coreutils refuse a closed stdout the same way ("write error: Bad file
    descriptor"); `>/dev/null` discards it. A closed standard error (Python leaves it None) is
    /dev/null's: the exit code still tells."""
    if sys.stderr is None:
        sys.stderr = Path(os.devnull).open("w")  # noqa: SIM115 (for the life of the process)
    if sys.stdout is None:
        sys.stderr.write("error: standard output is closed; give it a file, or >/dev/null to discard it\n")
        raise SystemExit(USAGE)
    try:  # relative paths mean nothing without it, and Open3D's oneMKL dies loading its library
        Path.cwd()
    except FileNotFoundError:
        gone = "the current directory no longer exists (deleted since the shell entered it)"
        sys.stderr.write(f"error: {gone}; cd to a folder that exists\n")
        raise SystemExit(USAGE) from None


def run() -> None:
    """The `sensorbox` console script: `sensorbox.cli.main.main`, and Ctrl-C while its modules are still
    being imported (numpy, OpenCV, Open3D: about 2 s) as the same one line and exit code 130.

    After a Ctrl-C the process ends at once (`os._exit`) once the command has
    said its line and unwound: a helper thread may still be inside OpenCV or
    numba then, and the interpreter's normal shutdown would run C++ static
    destructors under it and abort ("terminate called without an active
    exception", SIGABRT instead of 130). Nothing is lost: every file a command
    writes is whole when written (atomic renames), and the streams are flushed.
    """
    _streams_open()
    try:
        try:
            from sensorbox.cli.main import main
        except KeyboardInterrupt:
            sys.stderr.write("interrupted\n")
            raise SystemExit(INTERRUPTED) from None
        main()
    except SystemExit as done:
        if done.code != INTERRUPTED:
            raise
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError, ValueError):  # a closed pipe or stream: nothing can reach it
                stream.flush()
        os._exit(INTERRUPTED)
