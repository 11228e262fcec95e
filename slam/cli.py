"""The ``slam`` command line: a thin layer over the library. This module holds ``slam run``,
``view`` and ``synth``; :mod:`slam.cli_eval` holds ``eval``, ``report`` and ``bench``;
:mod:`slam.cli_app` the app, the error boundary, the console and the progress bars."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.markup import escape
from rich.progress import TextColumn

from slam import cli_app
from slam.cli_app import Quiet, Verbose, app, command, progress_bar, setup_logging
from slam.data.layouts import formats_text
from slam.errors import SlamError
from slam.run_folder import CHECKPOINT_DIR, CHUNKS_FILE, RECORDING_FILE

__all__ = ["app", "main"]


def _generate_demo(quiet: bool) -> Path:
    """The built-in demo sequence, generated (once) as its own step with its own progress bar."""
    from slam.demo import builtin_path, demo_sequence_path, is_generated

    if is_generated() or quiet:
        return demo_sequence_path()
    cli_app.console.print(
        f"first run: generating the synthetic demo sequence into {escape(str(builtin_path()))} "
        "(once, about a minute)"
    )
    with progress_bar() as bar:
        task = bar.add_task("generating", total=None)
        return demo_sequence_path(
            progress=lambda done, total: bar.update(task, completed=done, total=total)
        )


def _prepare_kernels(quiet: bool) -> None:
    """The tracker's compiled kernels: on a machine that has not compiled them yet, compiled as
    their own step before the run (once, a few seconds; numba caches them), with a line saying
    so."""
    from slam import kernels

    if kernels.cached() or quiet:
        return
    cli_app.console.print(
        "first run on this machine: compiling the tracker's kernels (once, a few seconds)"
    )
    with cli_app.console.status("compiling"):
        kernels.prepare()


class _RunProgress:
    """The progress of `slam run`: on a terminal a bar that appears at the first frame (not
    while the sequence is checked) and shows fps and the tracking state; to a pipe or a file a
    plain line every ``PLAIN_EVERY_S`` seconds and one when the frames are done; nothing with
    --quiet."""

    PLAIN_EVERY_S = 5.0

    def __init__(self, quiet: bool, parallel: bool = False) -> None:
        self.quiet = quiet
        self.parallel = parallel  # frames stepped by worker processes: no status of their own
        self.plain = not cli_app.console.is_terminal
        self.bar = progress_bar(
            TextColumn("{task.fields[fps]:>5.1f} fps"), TextColumn("{task.fields[state]}")
        )
        self.task = self.bar.add_task("tracking", total=None, fps=0.0, state="")
        self.t0: float | None = None  # set at the first frame
        self.first = 0
        self.last_line = 0.0  # when the last plain line was written

    def on_frame(self, done: int, total: int, status) -> None:
        if self.quiet:
            return
        now = time.perf_counter()
        if self.t0 is None:
            if not self.plain:
                self.bar.start()
            self.t0 = self.last_line = now
            self.first = done
        fps = (done - self.first) / max(now - self.t0, 1e-9)
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
        if self.plain and (done == total or now - self.last_line >= self.PLAIN_EVERY_S):
            self.last_line = now
            line = f"tracking {done}/{total} frames, {fps:.1f} fps, {now - self.t0:.0f} s"
            if done == total:
                line += f"; {state}"
            print(line, file=sys.stderr, flush=True)

    def stop(self) -> None:
        if self.t0 is not None and not self.plain:  # started at the first frame
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
    first_frame: Annotated[
        Optional[int],
        typer.Option("--first-frame", min=0, help="Start at frame N of the sequence (0-based)."),
    ] = None,
    map_dir: Annotated[
        Optional[Path],
        typer.Option(
            "--map",
            help="Localise the sequence in the map of this finished run folder (its map/) "
            "instead of mapping it: poses in the map's world frame, nothing fused; frames the "
            "map does not explain get no pose. The map is only read.",
        ),
    ] = None,
    extend: Annotated[
        bool,
        typer.Option(
            "--extend",
            help="With --map: map the sequence and join it to that map (loops between the old "
            "and new keyframes, one pose graph, one re-fused surface); OUT gets the merged mesh "
            "and map, the old folder is left as it was.",
        ),
    ] = False,
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

    setup_logging(verbose, quiet)
    _check_run_options(sequence, config, max_frames, resume, workers, rerun, ray)
    if resume is not None and (map_dir is not None or first_frame is not None):
        raise SlamError(
            "--resume continues a run as it was started: leave out --map and --first-frame"
        )
    if sequence is None and resume is None:
        sequence = _generate_demo(quiet)
    _prepare_kernels(quiet)
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
                map_dir=map_dir,
                first_frame=first_frame,
                extend=extend,
            )
    finally:
        bar.stop()
    if quiet:
        return
    files = ", ".join(sorted(p.name for p in run_dir.iterdir() if p.is_file()))
    cli_app.console.print(f"[green]wrote[/] {escape(f'{run_dir}: {files}')}")
    if rerun is not None:
        cli_app.console.print(
            f"[green]wrote[/] {escape(f'{rerun} (open it with `rerun {rerun}`)')}"
        )
    typer.echo(summary_line(result.metrics))
    if result.metrics.get("calibration_source"):
        typer.echo(f"calibration: {result.metrics['calibration_source']}")


def _check_run_options(
    sequence: Path | None,
    config: Path | None,
    max_frames: int | None,
    resume: Path | None,
    workers: int,
    rerun: Path | None,
    ray: str | None,
) -> None:
    """Options of `slam run` that do not go together, refused before anything runs."""
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

    setup_logging(verbose)
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
    scene: Annotated[
        str,
        typer.Option(
            "--scene",
            help="Scene kind: room (the furnished room of the demo), or a kind that stresses "
            "tracking: wall (a textured wall filling the view), corridor, hall (walls 4-8 m "
            "away), desk (objects 0.5-1 m away).",
        ),
    ] = "room",
    speed: Annotated[
        float,
        typer.Option("--speed", help="Multiplies every rate of the camera path (2: fast pans)."),
    ] = 1.0,
    loop: Annotated[
        bool,
        typer.Option(
            "--loop/--no-loop", help="Closed loop that revisits its start (the room only)."
        ),
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
    color_offset_ms: Annotated[
        float,
        typer.Option(
            "--color-offset-ms",
            help="Colour not synchronised with depth: a colour camera at its own rate, its images "
            "drifting from this many ms after their depth images to as many before (TUM "
            "fr1/fr2's Kinect: up to 17), as rgb.txt says.",
        ),
    ] = 0.0,
    handheld: Annotated[
        str,
        typer.Option(
            "--handheld",
            help="Add a recorded hand's motion to the camera path (TUM motion capture: "
            "fr1_360, fr1_desk2, fr1_plant, fr1_room, fr1_teddy).",
        ),
    ] = "",
    kinect: Annotated[
        bool,
        typer.Option(
            "--kinect",
            help="Take the images as a hand-held Kinect v1 does: rolling-shutter, motion-blurred "
            "colour under auto exposure; depth with projector shadows, ragged edges and "
            "correlated noise.",
        ),
    ] = False,
) -> None:
    """Render a synthetic RGB-D sequence with exact ground truth (TUM layout + calibration.yaml)."""
    from slam.synthetic import SynthConfig, generate_sequence

    setup_logging()
    cfg = SynthConfig(
        frames=frames,
        scene=scene,
        speed=speed,
        loop=loop,
        seed=seed,
        alias=alias,
        noise=noise,
        drift_bias=drift_bias,
        color_offset_ms=color_offset_ms,
        handheld=handheld,
        kinect=kinect,
    )
    with progress_bar() as bar:
        task = bar.add_task("rendering", total=frames)
        path = generate_sequence(
            out, cfg, progress=lambda done, total: bar.update(task, completed=done)
        )
    typer.echo(f"wrote {frames} frames to {path}")


# the evaluation commands register on the same app, after these (the order `slam --help` lists)
from slam import cli_eval  # noqa: E402, F401


def main() -> None:
    app()


if __name__ == "__main__":
    main()
