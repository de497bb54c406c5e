"""The ``sensorbox`` command line: one module per command, each parses, calls one library function, prints.

A command line click cannot parse (an unknown option or command, "abc"
for a number, a missing argument) is one line too, "error: MESSAGE (see
'sensorbox CMD --help')", exit code 2, instead of click's boxed usage.
Every `SensorboxError` (a user mistake: a file, key, topic or value named)
becomes one plain line on stderr and exit code 2; a write the operating
system refused (disk full, permissions, a missing folder), as an
`ingest.errors.OutputError` or an OSError that reaches the top, one line
naming the path and exit code 3. Messages are printed as text, never as rich markup, so paths and
values with brackets arrive as they are.
"""

from __future__ import annotations

import functools
import logging
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import ParamSpec

import typer

from calibration.errors import SensorboxError, WriteError
from sensorbox.cli.bench import bench_cmd
from sensorbox.cli.calib import calib_check, calib_refine
from sensorbox.cli.capture import capture_cmd, launch_cmd
from sensorbox.cli.common import ctrl_c, err_console, print_error, print_warning
from sensorbox.cli.eval import eval_cmd, stats_cmd
from sensorbox.cli.ingest import ingest_cmd
from sensorbox.cli.inspect import inspect_cmd
from sensorbox.cli.render import render_benchmark_cmd
from sensorbox.cli.simulate import simulate_cmd
from sensorbox.cli.view import view_cmd

P = ParamSpec("P")

app = typer.Typer(
    name="sensorbox",
    help="SensorBox: fisheye stereo + Livox LiDAR rig tools (WideDepth pipeline).",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
calib_app = typer.Typer(
    help="Inspect, check and refine calibrations (Kalibr camchains, rig files).", no_args_is_help=True
)
app.add_typer(calib_app, name="calib")


def _interruptible(command: Callable[P, None]) -> Callable[P, None]:
    """`command` with Ctrl-C as one line, "interrupted", and exit code 130 (typer's own is silent).

    Every writer of a command writes atomically, so nothing half-written
    stays; a command with more to say (ingest: what its output holds)
    catches KeyboardInterrupt itself first.
    """

    @functools.wraps(command)
    def run(*args: P.args, **kwargs: P.kwargs) -> None:
        try:
            with ctrl_c():
                command(*args, **kwargs)
        except KeyboardInterrupt:
            err_console.print("interrupted", markup=False, highlight=False)
            raise typer.Exit(130) from None

    return run


calib_app.command("check")(_interruptible(calib_check))
calib_app.command("refine")(_interruptible(calib_refine))
for name, command in (
    ("simulate", simulate_cmd), ("inspect", inspect_cmd), ("ingest", ingest_cmd), ("eval", eval_cmd),
    ("stats", stats_cmd), ("bench", bench_cmd), ("launch", launch_cmd), ("capture", capture_cmd),
    ("render-benchmark", render_benchmark_cmd), ("view", view_cmd),
):  # fmt: skip
    app.command(name)(_interruptible(command))


class _WarningLines(logging.Handler):
    """Library log records, WARNING and up, as the CLI's own lines: "warning: LINE" or "error: LINE".

    A record that carries an exception gets its type and message appended
    (one line, no traceback).
    """

    def emit(self, record: logging.LogRecord) -> None:
        line = record.getMessage()
        if record.exc_info and record.exc_info[1] is not None:
            exc = record.exc_info[1]
            line = f"{line}: {type(exc).__name__}: {exc}"
        if record.levelno >= logging.ERROR:
            print_error(line)
        else:
            print_warning(line)


@app.callback()
def _root() -> None:
    """SensorBox command line."""
    root = logging.getLogger()
    if not root.handlers:  # `capture` sets up its own (rich) logging
        root.addHandler(_WarningLines(logging.WARNING))


def _usage_line(err: typer.TyperException) -> str:
    """Click's refusal of a command line as one line: its message and where the help is.

    Typer prints it as the usage, a hint and the message in a box (five
    lines and more); a user mistake is one "error: ..." line here as
    everywhere else.
    """
    command_path = getattr(getattr(err, "ctx", None), "command_path", None)
    where = f" (see '{command_path} --help')" if command_path else ""
    return f"{err.format_message()}{where}"


def main() -> None:
    """Console-script entry point: run the app, mapping SensorboxError and click's usage errors to exit
    code 2, a refused write to 3 (one line each)."""
    try:
        done = app(prog_name="sensorbox", standalone_mode=False)
    except typer.TyperException as err:
        # `sensorbox`, `sensorbox calib`: typer has printed the help (its class is in typer's private
        # copy of click, hence the name)
        if type(err).__name__ != "NoArgsIsHelpError":
            print_error(_usage_line(err))
        sys.exit(err.exit_code)
    except typer.Abort:  # end of input where a prompt waited
        print_error("aborted: no input")
        sys.exit(1)
    except WriteError as err:  # the operating system refused a write (an OutputError too): as an OSError
        print_error(str(err))
        sys.exit(3)
    except SensorboxError as err:
        print_error(str(err))
        sys.exit(2)
    except OSError as err:
        where = f"{err.filename}: " if err.filename else "standard output: " if _stdout_fails() else ""
        print_error(f"{where}{err.strerror or err}")
        sys.exit(3)
    sys.exit(done if isinstance(done, int) else 0)  # a typer.Exit's code, else the command's return value


def _stdout_fails() -> bool:
    """Whether standard output refuses writes (`> /dev/full`, a full disk); then it is left for
    /dev/null, so that the interpreter's last flush does not print a traceback-like line."""
    try:
        sys.stdout.write("\n")  # a probe: an OSError without a file name is most often stdout's
        sys.stdout.flush()
    except OSError:
        sys.stdout = Path(os.devnull).open("w")  # noqa: SIM115 - stands in for stdout until the process ends
        return True
    return False


if __name__ == "__main__":
    main()
