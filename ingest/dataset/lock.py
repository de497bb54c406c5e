"""One run at a time per output folder, and no temporary file left from an interrupted one.

Every file goes through `layout.write_atomic`: a temporary `.NAME.XXXXXXXX.tmp`
beside it, renamed into place. A run killed by SIGKILL (or a power cut)
leaves that temporary behind, which a rerun never touches because it writes
under a new random name. `hold_folder` takes an exclusive lock on the
folder itself (`flock` on its directory descriptor: no lock file, released by
the kernel when the process dies, however it dies) and, once it holds it,
removes such temporaries: no other run can be writing them. A second run into
the same folder meanwhile is refused in one line instead of racing the first
for the same sample files.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ingest.errors import DatasetError, OutputError

log = logging.getLogger(__name__)

# write_atomic's temporaries (mkstemp's 8 random characters) and describe's staging folders for rig/
TEMPORARY = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp$")


@contextmanager
def hold_folder(out: Path) -> Iterator[int]:
    """Hold `out` (an existing folder) for this run; yields how many stale temporaries were removed.

    Raises DatasetError when another process holds it. Without `fcntl`
    (Windows), or on a file system that refuses locks (a warning), there is
    no lock and nothing is removed: no temporary can be told from a running
    run's.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not on Linux or macOS
        yield 0
        return
    try:
        fd = os.open(out, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError as err:
        raise OutputError(f"cannot open {out}: {err.strerror or err}") from err
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as err:
            raise DatasetError(
                f"{out}: another SensorBox run is writing into this folder; wait for it to end or choose "
                "another --out"
            ) from err
        except OSError as err:  # a file system without locks (some network mounts): run, but say so
            log.warning("cannot lock %s (%s): a second run into it would not be refused", out, err.strerror)
            yield 0
            return
        yield remove_temporaries(out)
    finally:
        os.close(fd)  # releases the lock


def remove_temporaries(out: Path) -> int:
    """Remove `write_atomic`'s leftover temporaries (files, and staging folders) under `out`; how many."""
    removed = 0
    for root, dirs, files in os.walk(out):
        for name in [*files, *dirs]:
            if not TEMPORARY.match(name):
                continue
            path = Path(root) / name
            try:
                if path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path)
                    dirs.remove(name)
                else:
                    path.unlink()
            except OSError as err:
                raise OutputError(f"cannot remove the stale temporary {path}: {err.strerror or err}") from err
            removed += 1
    return removed
