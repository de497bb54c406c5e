"""libjpeg's warnings about corrupt data, which OpenCV's decoder prints and decodes on.

`cv2.imdecode` reads a JPEG whose entropy-coded data is damaged (flipped
bytes in a chunk whose CRC was written over them, a cut transfer) into an
image with grey or smeared blocks, and the only trace is libjpeg's bare line
on the process's stderr (`Corrupt JPEG data: premature end of data segment`),
naming no bag, topic or time. OpenCV offers no hook for it, so
`jpeg_warnings` catches what C code writes to file descriptor 2 during the
block: libjpeg's corrupt-data warnings (`WARNING_PREFIXES`) are handed back,
anything else (another thread's log line) is written on to stderr after the
block. One block at a time per process (a lock): the descriptor is the
process's. Without a descriptor 2 to borrow (a daemon closed it) nothing is
caught.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading
from collections.abc import Iterator

WARNING_PREFIXES = (
    "Corrupt JPEG data",  # JWRN_EXTRANEOUS_DATA, JWRN_HIT_MARKER, JWRN_HUFF_BAD_CODE, JWRN_MUST_RESYNC, ...
    "Premature end of JPEG file",  # JWRN_JPEG_EOF
    "Invalid SOS parameters",  # JWRN_NOT_SEQUENTIAL
    "Inconsistent progression sequence",  # JWRN_BOGUS_PROGRESSION
)
"""How libjpeg(-turbo)'s warnings about damaged data begin (jerror.h)."""

_FD2 = threading.Lock()


@contextlib.contextmanager
def jpeg_warnings() -> Iterator[list[str]]:
    """Yield a list that, after the block, holds libjpeg's corrupt-data warnings written during it."""
    found: list[str] = []
    with _FD2, tempfile.TemporaryFile() as caught:
        sys.stderr.flush()
        try:
            saved = os.dup(2)
        except OSError:  # no stderr to borrow
            yield found
            return
        os.dup2(caught.fileno(), 2)
        try:
            yield found
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            caught.seek(0)
            others = []
            for line in caught.read().decode(errors="replace").splitlines(keepends=True):
                if line.startswith(WARNING_PREFIXES):
                    found.append(line.strip())
                else:
                    others.append(line)
            if others:
                os.write(2, "".join(others).encode())
