"""The ``slam`` command line: a thin layer over the library."""

from __future__ import annotations

import functools
import json
import logging
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.logging import RichHandler
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from slam.cli_eval import echo_result, echo_run
from slam.data.layouts import formats_text
from slam.errors import RunInterrupted, SlamError
from slam.run_folder import (
    CHECKPOINT_DIR,
    CHUNKS_FILE,
    ODOMETRY_FILE,
    RECORDING_FILE,
    REPORT_FILE,
    TRAJECTORY_FILE,
)

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


def _setup_logging(verbose: int = 0, quiet: bool = False) -> None:
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
    # runs before every command: the console for the stream this invocation writes to
    global console
    console = _make_console()


def _fail(exc: Exception) -> None:
    if isinstance(exc, RunInterrupted):  # the shell's convention: 128 + the signal's number
        console.print(f"[bold yellow]stopped:[/] {escape(str(exc))}")
        raise typer.Exit(code=128 + exc.signal_number)
    console.print(f"[bold red]error:[/] {escape(str(exc))}")
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
                    "[bold yellow]stopped:[/] interrupted; a run folder holding a checkpoint "
                    "continues with `slam run --resume OUT`"
                )
                raise typer.Exit(code=130) from None

        return app.command(*args, **kwargs)(guarded)

    return register


def _progress(*columns) -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        *columns,
        TimeElapsedColumn(),
        console=console,
        transient=False,
    )


def _generate_demo(quiet: bool) -> Path:
    """The built-in demo sequence, generated (once) as its own step with its own progress bar."""
    from slam.demo import builtin_path, demo_sequence_path, is_generated

    if is_generated() or quiet:
        return demo_sequence_path()
    console.print(
        f"first run: generating the synthetic demo sequence into {escape(str(builtin_path()))} "
        "(once, about a minute)"
    )
    with _progress() as bar:
        task = bar.add_task("generating", total=None)
        return demo_sequence_path(
            progress=lambda done, total: bar.update(task, completed=done, total=total)
        )


class _RunProgress:
    """The progress bar of `slam run`: it appears at the first frame (not while the sequence is
    checked), shows fps and the tracking state; nothing with --quiet."""

    def __init__(self, quiet: bool, parallel: bool = False) -> None:
        self.quiet = quiet
        self.parallel = parallel  # frames stepped by worker processes: no status of their own
        self.bar = _progress(
            TextColumn("{task.fields[fps]:>5.1f} fps"), TextColumn("{task.fields[state]}")
        )
        self.task = self.bar.add_task("tracking", total=None, fps=0.0, state="")
        self.t0: float | None = None  # set at the first frame
        self.first = 0

    def on_frame(self, done: int, total: int, status) -> None:
        if self.quiet:
            return
        if self.t0 is None:
            self.bar.start()
            self.t0 = time.perf_counter()
            self.first = done
        fps = (done - self.first) / max(time.perf_counter() - self.t0, 1e-9)
        if done == total:
            join = "joining the chunks, " if self.parallel else ""
            state = f"{join}finishing: pose graph, map, mesh, files"
        elif self.parallel:
            state = "workers tracking their chunks"
        elif status is None:
            state = "[yellow]skipped (unreadable)[/]"
        elif status.ok:
            state = f"{status.path} overlap {status.overlap:.2f}"
        else:
            state = "[red]lost[/]"
        self.bar.update(self.task, completed=done, total=total, fps=fps, state=state)

    def stop(self) -> None:
        if self.t0 is not None:  # started at the first frame
            self.bar.stop()


def _chunked_run(run_dir: Path | None) -> bool:
    """Whether ``--resume`` continues a parallel run (``--workers N``)."""
    if run_dir is None:
        return False
    from slam.chunked.runner import is_chunked

    return is_chunked(run_dir)


@command(short_help="Track a sequence into a run folder: trajectory, mesh, metrics.")
def run(
    sequence: Annotated[
        Optional[Path],
        typer.Argument(help=f"Sequence folder ({formats_text()}). Omit for the built-in demo."),
    ] = None,
    out: Annotated[Path, typer.Option("--out", "-o", help="Run folder for the results.")] = Path(
        "runs/latest"
    ),
    config: Annotated[
        Optional[Path], typer.Option("--config", "-c", help="YAML file overriding defaults.")
    ] = None,
    max_frames: Annotated[
        Optional[int], typer.Option("--max-frames", min=1, help="Process at most N frames.")
    ] = None,
    checkpoint_every: Annotated[
        Optional[int],
        typer.Option(
            "--checkpoint-every",
            min=0,
            help=f"Write the run's state to OUT/{CHECKPOINT_DIR}/ every N frames (0: never), so "
            "`--resume` can continue it after a crash or kill. Default: automatically, at most "
            "2% of the run time (and always on Ctrl-C or SIGTERM, which stop after the current "
            "frame).",
        ),
    ] = None,
    resume: Annotated[
        Optional[Path],
        typer.Option(
            "--resume",
            help="Continue the interrupted run in this folder from its last checkpoint (same "
            "sequence and config).",
        ),
    ] = None,
    overwrite: Annotated[
        bool,
        typer.Option("--overwrite", help="Replace the run already in --out (deletes its outputs)."),
    ] = False,
    rerun: Annotated[
        Optional[Path],
        typer.Option(
            "--rerun",
            help="Also record the run for the rerun 3D viewer into this .rrd file (needs the "
            "viz extra, installed from the checkout with `pip install -e '.[viz]'`; open it "
            "with `rerun FILE.rrd`).",
        ),
    ] = None,
    workers: Annotated[
        int,
        typer.Option(
            "--workers",
            min=1,
            help="Cut the sequence into N overlapping chunks tracked at once in N worker "
            "processes (Ray tasks where Ray is installed, else local processes), then join "
            f"them: one pose graph, loops between chunks, one mesh. Writes {CHUNKS_FILE}.",
        ),
    ] = 1,
    ray: Annotated[
        Optional[str],
        typer.Option(
            "--ray",
            help="With --workers: run the chunks on the Ray cluster at this address (e.g. "
            "auto, or ray://host:10001) instead of a local Ray instance.",
        ),
    ] = None,
    verbose: Verbose = 0,
    quiet: Quiet = False,
) -> None:
    """Track a sequence, fuse a TSDF map and write trajectory, mesh and metrics to the run folder."""
    from slam.api import resume_run, run_sequence
    from slam.pipeline import summary_line

    _setup_logging(verbose, quiet)
    if resume is not None and (sequence is not None or config is not None or max_frames):
        raise SlamError(
            "--resume continues a run with its own sequence and config: give no SEQUENCE, "
            "--config or --max-frames with it"
        )
    if workers > 1 and (rerun is not None or resume is not None):
        raise SlamError(
            "--workers tracks frames in other processes: no --rerun recording with it (record "
            "the finished run with `slam view RUN_DIR`); --resume continues a parallel run "
            "with its own workers, give no --workers with it"
        )
    if ray is not None and workers < 2:
        raise SlamError("--ray runs chunks of a parallel run: give --workers N (N >= 2) with it")
    if rerun is not None:
        from slam.tools.viewer import check_recording_path

        check_recording_path(rerun)
    if sequence is None and resume is None:
        sequence = _generate_demo(quiet)
    bar = _RunProgress(quiet, parallel=workers > 1 or _chunked_run(resume))
    try:
        if resume is not None:
            result, run_dir = resume_run(
                resume,
                progress=bar.on_frame,
                checkpoint_every=checkpoint_every,
                rerun=rerun,
            )
        else:
            result, run_dir = run_sequence(
                sequence,
                out,
                config_path=config,
                max_frames=max_frames,
                progress=bar.on_frame,
                checkpoint_every=checkpoint_every,
                overwrite=overwrite,
                rerun=rerun,
                workers=workers,
                ray_address=ray,
            )
    finally:
        bar.stop()
    if quiet:
        return
    files = ", ".join(sorted(p.name for p in run_dir.iterdir() if p.is_file()))
    console.print(f"[green]wrote[/] {escape(f'{run_dir}: {files}')}")
    if rerun is not None:
        console.print(f"[green]wrote[/] {escape(f'{rerun} (open it with `rerun {rerun}`)')}")
    typer.echo(summary_line(result.metrics))


@command(short_help="Write (and --open) the rerun 3D recording of a finished run.")
def view(
    run_dir: Annotated[Path, typer.Argument(help="Run folder written by `slam run`.")],
    out: Annotated[
        Optional[Path],
        typer.Option("--out", "-o", help=f"Recording file to write [RUN_DIR/{RECORDING_FILE}]."),
    ] = None,
    open_viewer: Annotated[
        bool, typer.Option("--open", help="Start the rerun viewer on it (needs a display).")
    ] = False,
    image_scale: Annotated[
        int,
        typer.Option(
            "--image-scale",
            min=0,
            help="Log colour and depth at 1/N resolution (0: no images; they are read again "
            "from the run's sequence folder).",
        ),
    ] = 4,
    verbose: Verbose = 0,
) -> None:
    """Write the rerun 3D recording of a finished run (as `slam run --rerun` makes it while
    running): camera, images, tracking state, trajectory, keyframes, loops, mesh."""
    from slam.tools.viewer import open_in_viewer, record_run_folder

    _setup_logging(verbose)
    path = record_run_folder(run_dir, out, image_scale=image_scale)
    typer.echo(f"wrote {path}")
    if open_viewer:
        open_in_viewer(path)
    else:
        typer.echo(f"open it with: rerun {path}")


@command(short_help="Render a synthetic RGB-D sequence with exact ground truth.")
def synth(
    out: Annotated[Path, typer.Argument(help="Folder to write the TUM-layout sequence into.")],
    frames: Annotated[int, typer.Option("--frames", help="Number of frames.")] = 300,
    loop: Annotated[
        bool, typer.Option("--loop/--no-loop", help="Closed loop that revisits its start.")
    ] = True,
    seed: Annotated[int, typer.Option("--seed", help="Random seed (scene and noise).")] = 0,
    alias: Annotated[
        bool, typer.Option("--alias", help="Repeat one textured structure in two places.")
    ] = False,
    noise: Annotated[
        bool, typer.Option("--noise/--no-noise", help="Kinect-like depth noise.")
    ] = True,
    drift_bias: Annotated[
        float,
        typer.Option(
            "--drift-bias",
            help="Radial depth distortion (e.g. 0.006) that makes odometry drift, for loop "
            "closure experiments.",
        ),
    ] = 0.0,
) -> None:
    """Render a synthetic RGB-D sequence with exact ground truth (TUM layout + calibration.yaml)."""
    from slam.synthetic import SynthConfig, generate_sequence

    _setup_logging()
    cfg = SynthConfig(
        frames=frames, loop=loop, seed=seed, alias=alias, noise=noise, drift_bias=drift_bias
    )
    with _progress() as bar:
        task = bar.add_task("rendering", total=frames)
        path = generate_sequence(
            out, cfg, progress=lambda done, total: bar.update(task, completed=done)
        )
    typer.echo(f"wrote {frames} frames to {path}")


@command("eval", short_help="ATE, RPE and drift of a run folder or of a trajectory file.")
def eval_cmd(
    gt: Annotated[
        Path,
        typer.Argument(
            help=f"A run folder (evaluates its {TRAJECTORY_FILE} and {ODOMETRY_FILE} against the "
            "sequence's ground truth), or a ground-truth trajectory file (TUM format)."
        ),
    ],
    est: Annotated[
        Optional[Path],
        typer.Argument(help="Estimated trajectory (TUM format) when GT is a file."),
    ] = None,
    plot: Annotated[
        Optional[Path], typer.Option("--plot", help="Write a top-view plot to this PNG.")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    t_max_diff: TMaxDiff = 0.01,
    correct_scale: CorrectScale = False,
    rpe_delta: Annotated[
        Optional[list[str]],
        typer.Option(
            "--rpe-delta",
            help="RPE pair spacing, repeatable: '1f' (frames), '1s' (seconds), '0.5m' "
            "(metres travelled). Default: 1f, 1s, 1m.",
        ),
    ] = None,
    drift_align: Annotated[
        Optional[str],
        typer.Option(
            "--drift-align",
            help="Alignment for drift: 'origin' (first poses made equal: all accumulated "
            "error shows) or se3/sim3/scale/none. Default: the ATE alignment.",
        ),
    ] = None,
    gt_file: Annotated[
        Optional[Path],
        typer.Option("--gt", help="Ground-truth file for a run folder (default: from its config)."),
    ] = None,
) -> None:
    """ATE, RPE and drift (as evo_ape / evo_rpe -a) of a trajectory or of a whole run folder.

    `slam eval RUN_DIR` evaluates the final trajectory and the odometry of a run, so the effect of
    loop closure is one command; `slam eval GT EST` evaluates any TUM-format trajectory.
    """
    from slam.tools import eval as slam_eval
    from slam.trajectory import read_tum

    _setup_logging()
    deltas = rpe_delta or ["1f", "1s", "1m"]
    if gt.is_dir():
        if est is not None:
            raise SlamError(
                f"{gt} is a run folder: give it alone (`slam eval RUN_DIR`), or give two "
                f"trajectory files (`slam eval GT EST`)"
            )
        _eval_run_folder(gt, gt_file, plot, as_json, t_max_diff, correct_scale, deltas, drift_align)
        return
    if est is None:
        raise SlamError(
            f"{gt} is not a folder: give a run folder (`slam eval RUN_DIR`) or a ground-truth "
            f"and an estimated trajectory file (`slam eval GT EST`)"
        )
    gt_traj, est_traj = read_tum(gt), read_tum(est)
    res = slam_eval.evaluate_full(
        gt_traj,
        est_traj,
        max_diff=t_max_diff,
        correct_scale=correct_scale,
        rpe_deltas=deltas,
        drift_alignment=drift_align,
    )
    if plot is not None:
        from slam.tools.plots import plot_trajectories

        aligned = slam_eval.align_trajectory(gt_traj, est_traj, correct_scale, t_max_diff)
        plot_trajectories(plot, gt_traj, {est.stem: aligned}, title=str(est))
    if as_json:
        typer.echo(json.dumps(res.as_dict()))
        return
    echo_result(res)


def _eval_run_folder(
    run_dir: Path,
    gt_file: Optional[Path],
    plot: Optional[Path],
    as_json: bool,
    t_max_diff: float,
    correct_scale: bool,
    deltas: list[str],
    drift_align: Optional[str],
) -> None:
    """`slam eval RUN_DIR`: final and odometry side by side (and their top-view plot)."""
    from slam.run_folder import RunFolder
    from slam.tools import eval as slam_eval

    run = RunFolder(run_dir)
    ev = slam_eval.evaluate_run(run, gt_file, t_max_diff, correct_scale, deltas, drift_align)
    if plot is not None:
        from slam.tools.plots import plot_trajectories

        ref, _ = slam_eval.load_run_ground_truth(run, gt_file)
        trajs = {}
        odo = run.odometry() if not ev.odometry_identical else None
        if ev.odometry is not None and odo is not None:
            trajs["odometry"] = slam_eval.align_trajectory(ref, odo, correct_scale, t_max_diff)
        trajs["final"] = slam_eval.align_trajectory(
            ref, run.trajectory(), correct_scale, t_max_diff
        )
        plot_trajectories(plot, ref, trajs, title=str(run_dir))
    if as_json:
        typer.echo(json.dumps(ev.as_dict()))
    else:
        echo_run(ev)


@command("report", short_help=f"Write a run's {REPORT_FILE} with plots: top view, error, timing.")
def report_cmd(
    run_dir: Annotated[Path, typer.Argument(help="Run folder written by `slam run`.")],
    out: Annotated[
        Optional[Path],
        typer.Option(
            "--out", "-o", help=f"Folder for {REPORT_FILE} and the PNGs (default: RUN_DIR)."
        ),
    ] = None,
    gt_file: Annotated[
        Optional[Path],
        typer.Option("--gt", help="Ground-truth file (default: from the run's config)."),
    ] = None,
    t_max_diff: TMaxDiff = 0.01,
    correct_scale: CorrectScale = False,
) -> None:
    """Write RUN_DIR/report.md with plots: top view with loop edges, error over time, timing."""
    from slam.tools.report import write_report

    _setup_logging()
    rep = write_report(run_dir, out, gt_file, t_max_diff, correct_scale)
    typer.echo(f"wrote {rep.markdown}")
    for p in rep.plots:
        typer.echo(f"wrote {p}")
    if rep.evaluation is None:
        typer.echo(f"no ground truth: {rep.ground_truth_error}")


@command("bench", short_help="Run a suite of sequences x configurations; write one table.")
def bench_cmd(
    suite: Annotated[Path, typer.Argument(help="Suite YAML: sequences x configs.")],
    out: Annotated[
        Optional[Path],
        typer.Option(
            "--out", "-o", help="Folder for the tables and run folders [runs/bench/SUITE_NAME]."
        ),
    ] = None,
    jobs: Annotated[int, typer.Option("--jobs", "-j", help="Runs at a time (local).")] = 1,
    ray: Annotated[
        Optional[str],
        typer.Option(
            "--ray",
            help="Run as Ray tasks: a cluster address, 'auto' (the running cluster) or "
            "'local' (start a local instance with --jobs CPUs). Needs `pip install ray`.",
        ),
    ] = None,
    verbose: Verbose = 0,
) -> None:
    """Run every sequence x configuration of SUITE; write one table (bench.md/.csv/.json).

    Each run is a separate process (or Ray task) writing OUT/runs/<sequence>__<config>/; a failed
    run is a row with its error and the suite goes on. Exit code 1 when any run failed.
    """
    from slam.tools.bench import format_markdown, load_suite, run_suite

    _setup_logging(verbose)
    s = load_suite(suite)
    out_dir = out if out is not None else Path("runs") / "bench" / s.name

    def progress(row: dict, done: int, total: int) -> None:
        failed = f"[red]failed[/] {escape(str(row['error']))}"
        state = "[green]ok[/]" if row["status"] == "ok" else failed
        ate = row.get("ate_rmse_m")
        ate_txt = f" ATE {ate:.4f} m" if isinstance(ate, float) else ""
        what = escape(f"[{done}/{total}] {row['sequence']} / {row['config']}: ")
        console.print(f"{what}{state}{ate_txt}")

    res = run_suite(s, out_dir, jobs=jobs, ray_address=ray, progress=progress)
    typer.echo(format_markdown(res.rows))
    for path in res.tables.values():
        typer.echo(f"wrote {path}")
    if res.failed:
        raise typer.Exit(code=1)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
