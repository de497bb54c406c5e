"""Input files read whole (rig files, camchains, launch and parameter files): checked before reading.

A path given as a calibration or launch file may name anything: a symlink to
``/dev/zero`` or ``/dev/urandom`` (read without end until the process is
killed for memory), a FIFO (a read that waits forever), a folder. `read_text`
follows symlinks, accepts a regular file only and bounds its size before a
byte is read, so each of these is one line naming the file.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from calibration.errors import CalibrationError, SensorboxError

MAX_TEXT_FILE_BYTES = 4 * 1024 * 1024
"""Largest YAML or JSON input file read (4 MiB). The reference camchain is 2 KiB, the rig file 3 KiB,
a launch file a few KiB: a file a thousand times over them is not one of them."""


def file_kind(mode: int) -> str:
    """What a non-regular file is, in words."""
    for test, name in (
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def check_regular_file(
    path: Path, what: str, max_bytes: int, error: type[SensorboxError] = CalibrationError
) -> int:
    """The size in bytes of `path`, after refusing what is not a regular file of at most `max_bytes`.

    Symlinks are followed (a link to a device is the device). Raises `error`
    with one line naming the path and `what` it should be.
    """
    try:
        st = path.stat()
    except FileNotFoundError as err:
        raise error(f"{path}: {what} file not found") from err
    except OSError as err:  # no permission on a folder above, a symlink loop, a name too long
        raise error(f"{path}: cannot read {what} file: {err.strerror or err}") from err
    if not stat.S_ISREG(st.st_mode):
        target = os.path.realpath(path)
        via = f" (a link to {target})" if target != str(path.absolute()) else ""
        raise error(f"{path}: is {file_kind(st.st_mode)}{via}, not a {what} file")
    if st.st_size > max_bytes:
        raise error(
            f"{path}: {st.st_size} bytes; a {what} file is at most {max_bytes // (1024 * 1024)} MiB "
            f"(is this the right file?)"
        )
    return st.st_size


def read_text(
    path: Path,
    what: str,
    syntax: str = "YAML",
    max_bytes: int = MAX_TEXT_FILE_BYTES,
    error: type[SensorboxError] = CalibrationError,
) -> str:
    """The UTF-8 text of `path`, a regular file of at most `max_bytes` (a BOM is dropped).

    `what` names the file in messages ("rig", "launch"), `syntax` its text
    format ("YAML", "JSON"): "not a YAML rig file (byte 17 is 0x89, ...)".

    Every refusal is `error` with one line naming the path: not found, not a
    regular file (a FIFO, a device, a folder; symlinks followed), too big,
    unreadable, not UTF-8. At most `max_bytes` + 1 bytes are read, so a file
    that grows after the check is refused too.
    """
    check_regular_file(path, what, max_bytes, error)
    try:
        with path.open("rb") as f:
            data = f.read(max_bytes + 1)
    except OSError as err:
        raise error(f"{path}: cannot read {what} file: {err.strerror or err}") from err
    if len(data) > max_bytes:
        raise error(f"{path}: over {max_bytes // (1024 * 1024)} MiB; a {what} file is at most that")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise error(
            f"{path}: not a {syntax} {what} file (byte {err.start} is {data[err.start]:#04x}, not UTF-8 text)"
        ) from err
