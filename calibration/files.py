"""Files read whole and files written whole: inputs checked before reading, outputs renamed into place.

A path given as a calibration or launch file may name anything: a symlink to
``/dev/zero`` or ``/dev/urandom`` (read without end until the process is
killed for memory), a FIFO (a read that waits forever), a folder. `read_text`
follows symlinks, accepts a regular file only and bounds its size before a
byte is read, so each of these is one line naming the file.

Every file SensorBox writes goes through `write_atomic` or `write_atomic_set`
(a temporary file beside the target, then a rename), so a failed write leaves
no empty or cut file; an output path that is a device, FIFO or socket is
refused before anything is written (a rename would replace the node itself).
They live here, at the bottom of the package tree, so that calibration's own
writers (rig files, camchains, the remap cache) use them as ingest does.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import tempfile
from collections.abc import Sequence
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


def resolved(path: Path, error: type[SensorboxError], expected: str = "") -> Path:
    """`path` with every link followed; `error` in one line when its links lead round in a loop (pathlib
    raises RuntimeError for that before Python 3.13, OSError after), `expected` saying what to give."""
    try:
        return path.resolve()
    except (OSError, RuntimeError) as err:
        raise error(
            f"{path}: is a symbolic link that leads nowhere (a loop of links)"
            + (f"; give {expected}" if expected else "")
        ) from err


def refuse_special_target(path: Path, error: type[SensorboxError]) -> None:
    """Refuse an output `path` that exists as a device, FIFO or socket (symlinks followed).

    The rename of an atomic write would replace the node itself (`--plot
    /dev/full` made /dev/full a PNG), and writing into it instead would send a
    whole output to a device. One line naming the path and what it is, as
    `error`. A missing path, a regular file and a folder pass (a folder is
    refused by the write, "Is a directory").
    """
    try:
        mode = path.stat().st_mode
    except OSError:  # missing, or a dangling link: the write itself decides
        return
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise error(f"{path}: is not a regular file ({file_kind(mode)}); give a file path")


def staged_file(path: Path, data: bytes) -> str:
    """`data` written to a new temporary file beside `path`, readable by all; its name. On an `OSError` no
    temporary file is left."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            os.fchmod(fd, 0o644)  # mkstemp makes 0600; a dataset must be readable by its users
            f.write(data)
    except OSError:
        Path(tmp).unlink(missing_ok=True)
        raise
    return tmp


def write_atomic(path: Path, data: bytes, error: type[SensorboxError]) -> None:
    """Write `data` to `path` via a temporary file in the same folder and an atomic rename.

    Any failure (a read-only or missing folder, a full disk, `path` a folder)
    is `error` naming `path`, and leaves neither `path` changed nor the
    temporary file behind. An existing `path` that is neither a regular file
    nor a folder (a device, a FIFO, a socket, or a symlink to one) is refused
    before anything is written (`refuse_special_target`).
    """
    refuse_special_target(path, error)
    try:
        tmp = staged_file(path, data)
        try:
            Path(tmp).replace(path)
        except OSError:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as err:
        raise error(f"cannot write {path}: {err.strerror or err}") from err


def write_atomic_set(files: Sequence[tuple[Path, bytes]], error: type[SensorboxError]) -> None:
    """Write several files as one set: all of them, or (after any failure) none changed.

    Each file's bytes go to a temporary file beside it first; only when every
    one is written are they renamed into place (a rename takes no room). A
    failure (a full disk, a read-only or missing folder, a folder where a file
    belongs) is `error` naming the file, leaves every target as it was, no
    temporary file, and no folder this call made. Folders are made as needed.
    A target that is a device, FIFO or socket is refused before any file is
    written (`refuse_special_target`).
    """
    for target, _ in files:
        refuse_special_target(target, error)
    made: list[Path] = []
    staged: list[tuple[str, Path]] = []
    path = files[0][0] if files else Path()
    try:
        for path, _ in files:
            for folder in reversed([path.parent, *path.parent.parents]):
                if not folder.exists():
                    folder.mkdir()
                    made.append(folder)
        for path, _ in files:
            if path.is_dir():  # a rename over it would fail only after others were renamed
                raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(path))
        for path, data in files:
            staged.append((staged_file(path, data), path))
        for tmp, path in staged:
            Path(tmp).replace(path)
    except OSError as err:
        for tmp, _ in staged:
            Path(tmp).unlink(missing_ok=True)
        for folder in reversed(made):
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise error(f"cannot write {path}: {err.strerror or err}") from err
