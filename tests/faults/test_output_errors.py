"""Issue 20, class 6: a write the operating system refuses is one line naming the path, no partial file.

Each case runs the command as a user would (in this process) with the fault
injected where the operating system would raise it: a read-only folder, a
disk that fills up half way through a file, a file where a folder belongs, a
folder where a file belongs, a binary file as the rig, a port past 65535.
"""

from __future__ import annotations

import builtins
import errno
import io
import os
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from ingest.dataset.layout import GT_DIRS, IMAGE_DIRS
from tests.faults.bags import INDOOR
from tests.faults.cli import sensorbox
from tests.paths import ROOT

RIG = INDOOR.parent / "indoor_static_mcap.truth" / "rig.yaml"
INGEST = [
    "ingest",
    str(INDOOR),
    "--rig",
    str(RIG),
    "--workers",
    "1",
    "--every",
    "20",
    "--height-full",
    "96",  # the fewest rows that keep disparity GT (64 is one warning line)
    "--gt",
    "sparse",
]
ENOSPC = os.strerror(errno.ENOSPC)


def _fill_disk_at(monkeypatch: pytest.MonkeyPatch, name: str) -> None:
    """A full disk for files whose path contains `name`: half the bytes land, then ENOSPC.

    Every way a file is opened for writing goes through it: `open` (matplotlib,
    `Path.write_text`) and `os.fdopen` (a temporary file from `mkstemp`).
    """
    real_open, real_fdopen = builtins.open, os.fdopen

    class HalfFile:
        def __init__(self, f: Any) -> None:
            self.f = f

        def __enter__(self) -> HalfFile:
            return self

        def __exit__(self, *exc: object) -> None:
            self.f.close()

        def __getattr__(self, attr: str) -> Any:
            return getattr(self.f, attr)

        def write(self, data: Any) -> int:
            self.f.write(data[: len(data) // 2])
            self.f.flush()
            raise OSError(errno.ENOSPC, ENOSPC)

    def full(f: Any, path: str, mode: str) -> Any:
        return HalfFile(f) if name in path and any(m in mode for m in "wax+") else f

    def open_(file: Any, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
        f = real_open(file, mode, *args, **kwargs)
        return full(f, str(file), mode) if isinstance(file, str | Path) else f

    def fdopen(fd: int, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
        return full(real_fdopen(fd, mode, *args, **kwargs), str(Path(f"/proc/self/fd/{fd}").readlink()), mode)

    monkeypatch.setattr(builtins, "open", open_)
    monkeypatch.setattr(io, "open", open_)
    monkeypatch.setattr(os, "fdopen", fdopen)


def _read_only(monkeypatch: pytest.MonkeyPatch, folder: Path) -> None:
    """`folder` on a read-only file system: creating a file in it fails with EROFS (as root too)."""
    import tempfile

    real: Any = tempfile.mkstemp

    def mkstemp(*args: Any, dir: Any = None, **kwargs: Any) -> tuple[int, str]:
        if dir is not None and Path(dir).resolve() == folder.resolve():
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(Path(dir) / "tmpXXXX"))
        made: tuple[int, str] = real(*args, dir=dir, **kwargs)
        return made

    monkeypatch.setattr(tempfile, "mkstemp", mkstemp)


def _files(folder: Path) -> list[str]:
    return (
        sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())
        if folder.exists()
        else []
    )


Case = Callable[[Path, pytest.MonkeyPatch], tuple[list[str], str, int, Callable[[], None]]]


def _read_only_output(tmp: Path, mp: pytest.MonkeyPatch) -> tuple[list[str], str, int, Callable[[], None]]:
    out = tmp / "ds"
    for name in (*IMAGE_DIRS, *GT_DIRS, "meta"):  # a dataset folder that has become read-only
        (out / name).mkdir(parents=True)
    _read_only(mp, out)
    return (
        [*INGEST, "--out", str(out)],
        f"error: cannot write {out}/dataset.yaml: Read-only file system",
        3,
        (lambda: _check(_files(out) == [], _files(out))),
    )


def _full_disk_copying_the_rig(
    tmp: Path, mp: pytest.MonkeyPatch
) -> tuple[list[str], str, int, Callable[[], None]]:
    out = tmp / "ds"
    _fill_disk_at(mp, "camchain.yaml")
    return (
        [*INGEST, "--out", str(out)],
        f"error: cannot write {out}/rig/camchain.yaml: {ENOSPC}",
        3,
        (
            lambda: _check(_files(out) == ["dataset.yaml"], _files(out))  # whole; no rig/, no staging folder
        ),
    )


def _full_disk_at_the_preview(
    tmp: Path, mp: pytest.MonkeyPatch
) -> tuple[list[str], str, int, Callable[[], None]]:
    out = tmp / "ds"
    _fill_disk_at(mp, "preview.png")
    samples = [f"{d}/{sid}.png" for d in (*GT_DIRS, *IMAGE_DIRS) for sid in ("000000", "000001")]
    whole = sorted(
        [
            "dataset.yaml",
            "rig/camchain.yaml",
            "rig/rig.yaml",
            "meta/000000.json",
            "meta/000001.json",
            *samples,
        ]
    )
    return (
        [*INGEST, "--out", str(out)],
        f"error: cannot write {out}/preview.png: {ENOSPC}",
        3,
        (
            lambda: _check(_files(out) == whole, _files(out))  # every sample kept, no preview, no temp file
        ),
    )


def _stats_out_is_a_file(tmp: Path, mp: pytest.MonkeyPatch) -> tuple[list[str], str, int, Callable[[], None]]:
    f = tmp / "stats.json"
    f.write_text("mine\n")
    msg = f"error: --out {f}: is a file; give a folder for stats.json and stats.png"
    return ["stats", str(tmp), "--out", str(f)], msg, 2, lambda: _check(f.read_text() == "mine\n", f)


def _binary_rig(tmp: Path, mp: pytest.MonkeyPatch) -> tuple[list[str], str, int, Callable[[], None]]:
    rig = tmp / "rig.yaml"
    rig.write_bytes(b"sensorbox_rig: 1\n\x89PNG\r\n")
    out = tmp / "ds"
    msg = f"error: {rig}: not a YAML rig file (byte 17 is 0x89, not UTF-8 text)"
    cmd = ["ingest", str(INDOOR), "--rig", str(rig), "--out", str(out)]
    return cmd, msg, 2, lambda: _check(not out.exists(), out)


def _port_base_capture(tmp: Path, mp: pytest.MonkeyPatch) -> tuple[list[str], str, int, Callable[[], None]]:
    out = tmp / "bags"
    cmd = [
        "capture",
        "--rig",
        str(RIG),
        "--out",
        str(out),
        "--emulate",
        "--port-base",
        "70000",
        "--duration",
        "1",
    ]
    msg = "error: --port-base 70000: expected 1..65527 (the first of nine UDP ports)"
    return cmd, msg, 2, lambda: _check(not out.exists(), out)


def _port_base_launch(tmp: Path, mp: pytest.MonkeyPatch) -> tuple[list[str], str, int, Callable[[], None]]:
    out = tmp / "bags"
    launch = ROOT / "launch" / "sim.launch.yaml"
    cmd = ["launch", str(launch), "port_base:=70000", f"out:={out}", "duration:=1"]
    node_line = 1 + launch.read_text().splitlines().index("  - node:")  # the first emulator's
    msg = (
        "error: node 'lidar_top_emulator' (sensorbox/mid360_emulator) at "
        f"{ROOT}/sensorbox/share/launch/sim.launch.yaml:{node_line}: parameter 'port_base' = 70000: "
        "expected 1..65527 (the first of nine UDP ports, each <= 65535)"
    )
    return cmd, msg, 2, lambda: _check(not out.exists(), out)


def _plot_into_a_folder(tmp: Path, mp: pytest.MonkeyPatch) -> tuple[list[str], str, int, Callable[[], None]]:
    folder = tmp / "plots"
    folder.mkdir()
    cmd = ["calib", "check", str(RIG), "--plot", str(folder)]
    return (
        cmd,
        f"error: --plot {folder}: is a folder; give a file path",
        2,
        (
            lambda: _check(_files(tmp) == [], _files(tmp))  # no plots.png beside it, no temp file in it
        ),
    )


def _check(ok: bool, what: object) -> None:
    assert ok, what


CASES: dict[str, Case] = {
    "read-only output folder": _read_only_output,
    "full disk copying the rig": _full_disk_copying_the_rig,
    "full disk writing preview.png": _full_disk_at_the_preview,
    "stats --out FILE": _stats_out_is_a_file,
    "binary --rig": _binary_rig,
    "capture --port-base 70000": _port_base_capture,
    "launch port_base:=70000": _port_base_launch,
    "calib check --plot DIR": _plot_into_a_folder,
}


@pytest.mark.parametrize("case", list(CASES))
def test_output_side_os_errors_are_one_line_and_leave_no_partial_file(
    case: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    args, message, code, no_partial_file = CASES[case](tmp_path, monkeypatch)
    exit_code, _, err = sensorbox(capsys, *args)
    assert (exit_code, err) == (code, [message])
    no_partial_file()


def _special_target(tmp: Path, kind: str) -> tuple[Path, str]:
    """An output path that is a FIFO, or a symlink to /dev/null (a character device a test can reach
    without root); what the refusal calls it."""
    path = tmp / "out.png"
    if kind == "fifo":
        os.mkfifo(path)
        return path, "a FIFO (named pipe)"
    path.symlink_to("/dev/null")
    return path, "a character device"


@pytest.mark.parametrize("kind", ["fifo", "link to /dev/null"])
def test_an_output_file_that_is_a_device_or_fifo_is_refused_not_replaced(
    kind: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plot, what = _special_target(tmp_path, kind)
    before = os.lstat(plot)
    code, _, err = sensorbox(capsys, "calib", "check", str(RIG), "--plot", str(plot))
    assert (code, err) == (3, [f"error: {plot}: is not a regular file ({what}); give a file path"])
    after = os.lstat(plot)
    assert (after.st_mode, after.st_ino) == (before.st_mode, before.st_ino)  # the node itself, untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.png"]  # no temporary file beside it


@pytest.mark.parametrize("kind", ["fifo", "link to /dev/null"])
def test_atomic_writes_refuse_a_special_target_before_writing_any_file(kind: str, tmp_path: Path) -> None:
    from ingest.dataset.layout import write_atomic, write_atomic_set
    from ingest.errors import OutputError

    target, what = _special_target(tmp_path, kind)
    line = f"{target}: is not a regular file ({what}); give a file path"
    with pytest.raises(OutputError) as single:
        write_atomic(target, b"{}")
    first = tmp_path / "eval.csv"  # `eval --json X` writes its report and CSV as one set
    with pytest.raises(OutputError) as pair:
        write_atomic_set([(first, b"a,b\n"), (target, b"{}")])
    assert (str(single.value), str(pair.value)) == (line, line)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.png"]  # nothing written, not even eval.csv
    assert not stat.S_ISREG(target.stat().st_mode)
