"""The typer application and the helpers every subcommand shares.

The CLI is a thin skin over :mod:`heliocal.pipeline`: a command parses options, calls one
library function, and formats the result. Results go to stdout (``--json`` for machines),
progress and logs to stderr. A :class:`~heliocal.pipeline.errors.HeliocalError` becomes one line
``Error: <message>`` on stderr with exit code 1; usage errors exit with 2 (typer's default).
SIGINT (Ctrl-C) and SIGTERM stop a command cleanly: its worker processes are stopped, no artifact
is half-written (writes are atomic), and it exits with 130 or 143 (128 + the signal number) after
one ``Error: ...`` line.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import signal
import sys
import threading
import traceback
from pathlib import Path
from typing import Annotated, Any, Callable, Optional

import typer
from rich.console import Console
from rich.logging import RichHandler

from heliocal.cli.rerun import UNCHANGED_LINE
from heliocal.pipeline.errors import HeliocalError, resource_error_message
from heliocal.pipeline.vocabulary import Scheduler as SchedulerChoice

__all__ = [
    "app",
    "stderr",
    "stdout",
    "Workdir",
    "JsonFlag",
    "QuietFlag",
    "Seed",
    "Workers",
    "Scheduler",
    "DaskAddress",
    "command",
    "emit",
    "fmt_number",
    "progress_enabled",
    "progress_bar",
    "DEFAULT_WORKDIR",
    "INTERRUPTED",
    "debug_enabled",
    "fail",
]

app = typer.Typer(
    name="heliocal",
    help="Calibrate heliostats from camera-target calibration logs (staged; artifacts in --workdir).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)

# markup=False: text from the data (heliostat ids, target names, paths) is printed as it is,
# never read as rich markup ("[red]", "[/]" would restyle the terminal or raise).
stderr = Console(stderr=True, highlight=False, soft_wrap=True, markup=False)
stdout = Console(highlight=False, soft_wrap=True, markup=False)

DEFAULT_WORKDIR = Path("runs/default")

Workdir = Annotated[Path, typer.Option(
    "--workdir", "-w", help="Work directory holding the stage artifacts.",
    file_okay=False, dir_okay=True)]
JsonFlag = Annotated[bool, typer.Option("--json", help="Print a machine-readable summary on stdout.")]
def incremental_line(summary: dict) -> bool:
    """Print what an ``--incremental`` run computed; True when it kept everything (nothing more
    to print)."""
    inc = summary.get("incremental") or {}
    if inc.get("unchanged"):
        stdout.print(UNCHANGED_LINE, markup=False)
        return True
    if inc.get("reused") or inc.get("removed"):
        stdout.print(f"incremental: computed {inc['computed']} heliostats, kept {inc['reused']} "
                     f"from the previous run, dropped {inc['removed']}.", markup=False)
    elif inc.get("why_all") and inc["why_all"] != "not --incremental":
        stdout.print(f"incremental: computed every heliostat: {inc['why_all']}.", markup=False)
    return False


IncrementalFlag = Annotated[bool, typer.Option(
    "--incremental", help="Compute again only the heliostats whose inputs changed since the "
    "stage's last run (same options and code); take the others' results from its artifacts.")]
QuietFlag = Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars or info logs.")]
Workers = Annotated[Optional[int], typer.Option(
    "--workers", help="Local worker processes for per-heliostat work (default: the machine's cores).")]
Scheduler = Annotated[SchedulerChoice, typer.Option(
    "--scheduler", help="local (processes on this machine) or dask (a Dask cluster).")]
DaskAddress = Annotated[Optional[str], typer.Option(
    "--dask-address", help="Run per-heliostat work on this Dask scheduler (tcp://HOST:PORT).")]
Seed = Annotated[int, typer.Option("--seed", help="Seed of every random step (same seed, same artifacts).")]


def fmt_number(value: float | None, digits: int = 3) -> str:
    """A number of a result table with ``digits`` decimals; ``-`` for a missing one (None, NaN)."""
    return "-" if value is None or value != value else f"{value:.{digits}f}"


def progress_enabled(quiet: bool) -> bool:
    """Progress bars only on an interactive stderr and without ``--quiet``."""
    return not quiet and stderr.is_terminal


def _setup_logging(quiet: bool) -> None:
    level = logging.WARNING if quiet else logging.INFO
    root = logging.getLogger("heliocal")
    root.handlers[:] = [RichHandler(console=stderr, show_time=False, show_path=False,
                                    markup=False, rich_tracebacks=False)]
    root.setLevel(level)
    root.propagate = False


class Terminated(BaseException):
    """Raised in the main thread by SIGTERM while a command runs (a BaseException like
    KeyboardInterrupt, so that cleanup code runs and no ``except Exception`` swallows it)."""


INTERRUPTED = ("nothing of this run was committed unless it had finished (each stage's last "
               "complete run is the one in use), and no worker process is left running")


@contextlib.contextmanager
def _sigterm_raises():
    """While a command runs, SIGTERM raises :class:`Terminated` in the main thread (once: a second
    SIGTERM during the cleanup is ignored so that the workers are still stopped)."""

    def handler(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        raise Terminated()

    try:
        previous = signal.signal(signal.SIGTERM, handler)
        _quiet_multiprocessing_threads()
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _quiet_multiprocessing_threads() -> None:
    """Keep stderr to one line when workers are stopped: multiprocessing's helper thread in this
    process (the resource sharer, which hands file descriptors to workers) can fail with a
    connection error when the worker it serves was just terminated. That error is expected there;
    it is logged at debug level instead of printed as a traceback. Every other thread exception
    goes to Python's default hook. (Installed by the CLI, which owns its process.)"""
    if getattr(threading.excepthook, "_heliocal", False):
        return
    default = threading.excepthook

    def hook(args):
        frames = traceback.extract_tb(args.exc_traceback)
        if (isinstance(args.exc_value, (ConnectionError, EOFError))
                and any("multiprocessing" in Path(f.filename).parts for f in frames)):
            logging.getLogger("heliocal").debug("a stopped worker's connection closed: %r",
                                                args.exc_value)
            return
        default(args)

    hook._heliocal = True
    threading.excepthook = hook


def command(name: str, *, writes: bool = False, **kwargs) -> Callable:
    """Register a subcommand that turns :class:`HeliocalError` into one stderr line and exit 1,
    and SIGINT / SIGTERM into one line and exit 130 / 143. A command that ``writes`` its
    ``--workdir`` is refused at once while another stage writes there, before it imports its
    stage (the stage's own lock still decides)."""

    def decorator(func: Callable) -> Callable:
        @functools.wraps(func)
        def wrapper(*args, **kw):
            _setup_logging(bool(kw.get("quiet", False)))
            try:
                with _sigterm_raises():
                    if writes:
                        from heliocal.pipeline.artifacts.workdir_lock import refuse_if_busy

                        refuse_if_busy(kw["workdir"])
                    return func(*args, **kw)
            except HeliocalError as exc:
                fail(str(exc))
            except OSError as exc:
                message = resource_error_message(exc)
                if message is None:
                    raise
                fail(message)
            except KeyboardInterrupt:
                fail(f"interrupted (SIGINT); {INTERRUPTED}", code=130)
            except Terminated:
                fail(f"terminated (SIGTERM); {INTERRUPTED}", code=128 + signal.SIGTERM)

        return app.command(name, **kwargs)(wrapper)

    return decorator


def fail(message: str, code: int = 1) -> None:
    """Print ``Error: message`` (one line) on stderr and exit with ``code``."""
    print(f"Error: {' '.join(str(message).split())}", file=sys.stderr)
    raise typer.Exit(code)


def emit(summary: dict[str, Any], as_json: bool, human: Callable[[dict], None] | None = None) -> None:
    """Print a stage's result: JSON on stdout with ``--json``, else a short human summary."""
    if as_json:
        sys.stdout.write(json.dumps(summary, indent=2, sort_keys=False, default=str) + "\n")
    elif human is not None:
        human(summary)
    else:
        for key, value in summary.items():
            stdout.print(f"{key}: {value}")


@contextlib.contextmanager
def progress_bar(description: str, quiet: bool):
    """A rich progress bar with ETA on stderr; yields ``advance(done, total, label)``.

    Disabled (a no-op callable) with ``--quiet`` or when stderr is not a terminal.
    """
    if not progress_enabled(quiet):
        yield lambda done, total, label=None: None
        return
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                               TimeElapsedColumn, TimeRemainingColumn)

    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                  TextColumn("{task.fields[label]}"), console=stderr, transient=True) as bar:
        task = bar.add_task(description, total=None, label="")

        def advance(done: int, total: int, label=None) -> None:
            bar.update(task, completed=done, total=total, label=str(label or ""))

        yield advance


def debug_enabled() -> bool:
    return os.environ.get("HELIOCAL_DEBUG", "") not in ("", "0")


@app.callback()
def _root(
    version: Annotated[bool, typer.Option("--version", help="Print the version and exit.")] = False,
) -> None:
    """Calibrate heliostats from camera-target calibration logs.

    Stages read and write Parquet artifacts in --workdir (default runs/default):
    ingest -> split-knn -> fit-coarse -> fit-hybrid -> sweep -> report.
    """
    if version:
        from heliocal.pipeline import __version__

        stdout.print(f"heliocal {__version__}")
        raise typer.Exit(0)
