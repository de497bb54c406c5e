"""What every command shares: the consoles, a progress bar on stderr, byte counts for people, and the
checks of an output path given on the command line (before any long work)."""

from __future__ import annotations

import errno
import os
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path
from types import FrameType
from typing import Annotated, Any, Protocol

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.text import Text

from calibration.errors import SensorboxError
from ingest.errors import DatasetError, OutputError

console = Console(width=None if sys.stdout.isatty() else 140, highlight=False)
err_console = Console(stderr=True, width=None if sys.stderr.isatty() else 200)

LidarMsgOpt = Annotated[str, typer.Option(help="custom (livox CustomMsg) | pointcloud2.")]
"""The LiDAR message type of a written bag (simulate, capture)."""


def _nonempty_path(flag: str) -> Callable[[str], Path]:
    """The parser of the path given to `flag`: an empty one is refused in one line naming `flag`.

    Typer reads "" as Path("."), so `ingest --out ""` wrote the dataset into
    the current folder.
    """

    def parse(value: str) -> Path:
        if not str(value).strip():
            raise SensorboxError(f"{flag} {value!r}: empty path (that is the current folder); give a path")
        return Path(value)

    return parse


def path_param(flag: str, many: bool = False) -> dict[str, Any]:
    """`typer.Option` (`flag` "--out") or `typer.Argument` (`flag` "BAGS") keywords of a path, `many`
    for a list of them: an empty value is refused (`_nonempty_path`), the help shows what it did."""
    if not flag.startswith("-"):  # an argument: its usage name stays the parameter's
        return {"parser": _nonempty_path(flag)}
    return {"parser": _nonempty_path(flag), "metavar": "<list[Path]>" if many else "<path>"}


class Update(Protocol):
    """progress(done, total): the library's progress callback; with `verb` and `unit`, the bar's words
    change to another stage of the work (a bar of its own: its time left restarts); `note` names the
    item at hand after the bar (the bar and its time left go on)."""

    def __call__(
        self, done: int, total: int, verb: str | None = None, unit: str | None = None, note: str | None = None
    ) -> None: ...


_DEFERRED: list[int] = []  # SIGINTs noted but not yet raised (see `ctrl_c`)


def _on_ctrl_c(signum: int, frame: FrameType | None) -> None:
    """SIGINT as KeyboardInterrupt, except inside llvmlite (numba compiling or loading its cache).

    There the handler runs within a ctypes callback, and ctypes prints a
    KeyboardInterrupt raised in a callback and drops it: the Ctrl-C would be
    lost and the run would go on to the end. It is noted instead, and the next
    progress update raises it (`raise_deferred_ctrl_c`).
    """
    if frame is not None and "llvmlite" in frame.f_code.co_filename:
        _DEFERRED.append(signum)
        return
    raise KeyboardInterrupt


def raise_deferred_ctrl_c() -> None:
    """Raise KeyboardInterrupt for a Ctrl-C `_on_ctrl_c` noted and has not raised yet."""
    if _DEFERRED:
        _DEFERRED.clear()
        raise KeyboardInterrupt


@contextmanager
def ctrl_c() -> Iterator[None]:
    """Within the block, Ctrl-C raises KeyboardInterrupt where it can be caught (`_on_ctrl_c`).

    Only where Python's own handler is in place: a SIGINT ignored (a
    background job of a shell) or handled by the caller stays as it is.
    """
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return
    signal.signal(signal.SIGINT, _on_ctrl_c)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        _DEFERRED.clear()


@contextmanager
def progress_bar(verb: str, unit: str) -> Iterator[Update]:
    """A transient progress bar on stderr ("VERB [bar] done/total UNIT, time left"); yields the callback.

    The callback also raises a Ctrl-C that arrived where it could not be
    raised (`raise_deferred_ctrl_c`).

    Only on a terminal: rich leaves an empty line behind in a log or a pipe,
    where a bar cannot be redrawn anyway, so there the callback does nothing.
    """
    if not err_console.is_terminal:

        def quiet(
            done: int, total: int, verb: str | None = None, unit: str | None = None, note: str | None = None
        ) -> None:
            raise_deferred_ctrl_c()

        yield quiet
        return
    columns = (
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
        TextColumn("{task.fields[unit]}"), TimeRemainingColumn(), TextColumn("{task.fields[note]}"),
    )  # fmt: skip
    with Progress(*columns, console=err_console, transient=True) as bar:
        task = bar.add_task(verb, total=None, unit=unit, note="")
        words = (verb, unit)

        def update(
            done: int, total: int, verb: str | None = None, unit: str | None = None, note: str | None = None
        ) -> None:
            nonlocal task, words
            raise_deferred_ctrl_c()
            stage = (verb or words[0], unit or words[1])
            if stage != words:
                bar.remove_task(task)
                task, words = bar.add_task(stage[0], total=None, unit=stage[1], note=""), stage
            if note is not None:
                bar.update(task, note=note)
            bar.update(task, completed=done, total=total)

        yield update


def check_out_folder(flag: str, folder: Path, holds: str) -> None:
    """Refuse, before any work, an output folder that is a file, lies under a file or a symbolic link
    that leads nowhere (a loop), or cannot be written.

    One line naming the option and the path ("--out X: is a file; give a folder
    for HOLDS"), where mkdir would fail only after the work with a bare
    "File exists" or "Not a directory". A folder the operating system will not
    let this process write into (a read-only file system, no permission: the
    nearest existing one decides) is an `OutputError`, exit code 3, as the
    write itself would be: `bench` found out only after its 25 s run.
    Nothing is created.
    """
    if folder.exists() and not folder.is_dir():
        raise DatasetError(f"{flag} {folder}: is a file; give a folder for {holds}")
    _check_parents(flag, folder, (folder,))


def _unresolved_link(path: Path) -> str | None:
    """Why `path`, a symbolic link, leads to no file (a loop, a missing target), or None when it is
    none or leads somewhere: mkdir would then fail with "File exists" or "Too many levels of symbolic
    links" only after the work."""
    if not path.is_symlink():
        return None
    try:
        path.stat()
    except OSError as err:
        return f"is a symbolic link that leads nowhere ({err.strerror or err})"
    return None


def refuse_link_loop(flag: str, path: Path, expected: str) -> None:
    """Refuse an output `path` that is a symbolic link leading nowhere (a loop), before any work: the
    write would fail after it with "File exists" or "Not a directory" naming a temporary."""
    if (why := _unresolved_link(path)) is not None:
        raise DatasetError(f"{flag} {path}: {why}; give {expected}")


def check_out_file(flag: str, path: Path) -> None:
    """Refuse, before any work, an output file whose folder would have to be made where a file is,
    or cannot be written into, or that exists as a folder, device, FIFO or socket (the write would refuse
    it only after the work, `ingest.dataset.layout.refuse_special_target`)."""
    from ingest.dataset.layout import refuse_special_target

    if path.is_dir():  # the write would fail after the work with a bare "Is a directory"
        raise DatasetError(f"{flag} {path}: is a folder; give a file path")
    refuse_link_loop(flag, path, "a file path")
    refuse_special_target(path)
    _check_parents(flag, path)


def check_not_an_input(flag: str, path: Path, inputs: Sequence[Path], what: str) -> None:
    """Refuse an output file that is one of the command's inputs or lies in an input folder: the write
    would replace what the command read (`what` names the inputs in the message)."""
    from calibration.files import resolved
    from ingest.errors import DatasetError

    where = resolved(path, DatasetError)
    for given in inputs:
        source = resolved(given, DatasetError)
        if where == source:
            raise DatasetError(f"{flag} {path}: is {given}, {what}; give another path")
        if source.is_dir() and where.is_relative_to(source):
            raise DatasetError(f"{flag} {path}: lies in {given}, {what}; give a path outside it")


def _write_refused(folder: Path) -> str | None:
    """Why this process may not create files in `folder` (an existing one), or None when it may."""
    if os.access(folder, os.W_OK | os.X_OK):
        return None
    try:
        read_only = bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
    except OSError:
        read_only = False
    return os.strerror(errno.EROFS if read_only else errno.EACCES)


def _check_parents(flag: str, path: Path, also: tuple[Path, ...] = ()) -> None:
    for parent in (*also, *path.parents):  # the nearest one that exists decides
        if (why := _unresolved_link(parent)) is not None:
            where = "" if parent == path else f" {parent}"
            raise DatasetError(f"{flag} {path}:{where} {why}; give a folder")
        if parent.exists():
            if not parent.is_dir():
                raise DatasetError(f"{flag} {path}: {parent} is a file, not a folder")
            if (why := _write_refused(parent)) is not None:
                where = "" if parent == path else f" (in {parent})"
                raise OutputError(f"{flag} {path}: cannot write{where}: {why}")
            return


def human_bytes(n: float) -> str:
    """1536 -> '1.5 KiB' (binary units, B to TiB)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


def print_warning(line: str, target: Console = err_console) -> None:
    """One plain "warning: LINE" (no markup: paths and values print as they are), on stderr by default."""
    target.print(Text.assemble(("warning:", "bold yellow"), " ", line), highlight=False, soft_wrap=True)


def print_error(line: str) -> None:
    """One plain "error: LINE" on stderr (no markup), as `sensorbox.cli.main` prints a SensorboxError;
    when stderr itself refuses it (`2> /dev/full`), nothing more can be said and the exit code speaks."""
    with suppress(OSError):
        err_console.print(Text.assemble(("error:", "bold red"), " ", line), highlight=False, soft_wrap=True)
