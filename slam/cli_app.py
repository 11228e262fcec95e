"""The ``slam`` command line's frame: the Typer app, its one error boundary (:func:`command`),
the console, logging and progress bars. The commands live in :mod:`slam.cli` (run, view, synth)
and :mod:`slam.cli_eval` (eval, report, bench)."""

from __future__ import annotations

import functools
import logging
import re
import sys
from collections.abc import Callable
from typing import Annotated

import typer
from rich.console import Console
from rich.logging import RichHandler
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from slam.errors import RunInterrupted, SlamError

# options shared by `slam eval` and `slam report`
TMaxDiff = Annotated[
    float, typer.Option("--t-max-diff", help="Max timestamp difference to associate (s).")
]
CorrectScale = Annotated[
    bool, typer.Option("--correct-scale", help="Sim(3) alignment instead of SE(3).")
]

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Offline RGB-D SLAM: KinectFusion tracking, TSDF mapping, trajectory evaluation.",
    # help as plain text: no rich markup (it swallowed `[viz]`, `[runs/bench/SUITE_NAME]`),
    # flags and counts without a value placeholder (`--overwrite`, not `--overwrite <bool>`)
    rich_markup_mode=None,
)

#: the console's width when it writes to a pipe or a file, where nothing is wrapped (rich's
#: default there, 80 columns, broke paths, messages and the `rerun ...` command mid-line)
_PIPE_WIDTH = 100_000


def _make_console() -> Console:
    """stderr: rich's layout on a terminal; no wrapping to a pipe or a file."""
    con = Console(stderr=True)
    if con.is_terminal:
        return con
    return Console(stderr=True, soft_wrap=True, width=_PIPE_WIDTH)


console = _make_console()  # made again for each command (the stream may differ)


Verbose = Annotated[
    int,
    typer.Option(
        "--verbose",
        "-v",
        count=True,
        show_default=False,
        help="Log every event (lost frames, loops, relocalisations); -vv: debug detail too.",
    ),
]
Quiet = Annotated[
    bool, typer.Option("--quiet", "-q", help="Print only errors: no progress bar, no summary.")
]


def setup_logging(verbose: int = 0, quiet: bool = False) -> None:
    """Console logging: warnings by default (a run shows its progress bar and one summary),
    per-event INFO lines with -v, DEBUG with -vv, errors only with --quiet."""
    if quiet:
        level = logging.ERROR
    else:
        level = {0: logging.WARNING, 1: logging.INFO}.get(verbose, logging.DEBUG)
    handler: logging.Handler
    if console.is_terminal:  # above the progress bar, levels in colour
        handler = RichHandler(console=console, show_path=False, show_time=False)
        fmt = "%(message)s"
    else:  # a pipe or a file: one plain line per record, never wrapped
        handler = logging.StreamHandler(sys.stderr)
        fmt = "%(levelname)-8s %(message)s"
    logging.basicConfig(level=level, format=fmt, handlers=[handler], force=True)


def _version(value: bool) -> None:
    if value:
        from slam.run_folder.provenance import software_line

        typer.echo(software_line())
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool,
        typer.Option(
            "--version",
            callback=_version,
            is_eager=True,
            help="Print the version (and the git commit when run from a checkout) and exit.",
        ),
    ] = False,
) -> None:
    # runs before every command: the console for the stream this invocation writes to; a
    # bug's traceback in rich's layout on a terminal, plain (no colour codes) in a file
    global console
    console = _make_console()
    app.pretty_exceptions_enable = console.is_terminal


#: a terminal's colour codes, as a library's message may carry them (Open3D's errors do)
_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def _fail(exc: Exception) -> None:
    text = escape(_ANSI.sub("", str(exc)))
    if isinstance(exc, RunInterrupted):  # the shell's convention: 128 + the signal's number
        console.print(f"[bold yellow]stopped:[/] {text}")
        raise typer.Exit(code=128 + exc.signal_number)
    console.print(f"[bold red]error:[/] {text}")
    raise typer.Exit(code=2)


def command(*args, **kwargs) -> Callable[[Callable], Callable]:
    """``app.command`` with the command line's one error boundary: a :class:`SlamError` (what
    the library raises for anything the user can fix) is printed as ``error: ...`` and exits
    with code 2 (a run stopped by a signal: ``stopped: ...``, 128 + the signal's number, as a
    shell reports it); anything else is a bug and keeps its traceback."""

    def register(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def guarded(*a, **kw):
            try:
                return fn(*a, **kw)
            except SlamError as exc:
                _fail(exc)
            except KeyboardInterrupt:  # a second Ctrl-C, or one outside a run's frame loop
                console.print(
                    "[bold yellow]stopped:[/] interrupted at once; if the run folder holds a "
                    "checkpoint (RUN_DIR/checkpoint/), `slam run --resume RUN_DIR` continues it"
                )
                raise typer.Exit(code=130) from None

        return app.command(*args, **kwargs)(guarded)

    return register


def progress_bar(*columns) -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        *columns,
        TimeElapsedColumn(),
        console=console,
        transient=False,
    )
