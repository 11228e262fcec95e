"""The ``slam`` command line: a thin layer over the library."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.logging import RichHandler
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from slam.errors import SlamError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Offline RGB-D SLAM: KinectFusion tracking, TSDF mapping, trajectory evaluation.",
)
console = Console(stderr=True)


def _setup_logging(verbose: bool) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(message)s",
        handlers=[RichHandler(console=console, show_path=False, show_time=False)],
        force=True,
    )


def _fail(exc: Exception) -> None:
    console.print(f"[bold red]error:[/] {exc}")
    raise typer.Exit(code=2)


@app.command()
def run(
    sequence: Annotated[
        Optional[Path],
        typer.Argument(help="Sequence folder (TUM RGB-D or 7-Scenes). Omit for the built-in demo."),
    ] = None,
    out: Annotated[Path, typer.Option("--out", "-o", help="Run folder for the results.")] = Path(
        "runs/latest"
    ),
    config: Annotated[
        Optional[Path], typer.Option("--config", "-c", help="YAML file overriding defaults.")
    ] = None,
    max_frames: Annotated[
        Optional[int], typer.Option("--max-frames", help="Process at most N frames.")
    ] = None,
    verbose: Annotated[bool, typer.Option("--verbose", "-v")] = False,
) -> None:
    """Track a sequence, fuse a TSDF map and write trajectory, mesh and metrics to the run folder."""
    from slam.api import run_sequence

    _setup_logging(verbose)
    try:
        with Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[fps]:>5.1f} fps"),
            TextColumn("{task.fields[state]}"),
            TimeElapsedColumn(),
            console=console,
            transient=False,
        ) as progress:
            task = progress.add_task("tracking", total=None, fps=0.0, state="")
            import time

            t0: list[float] = []  # set at the first frame, after any demo generation

            def on_frame(done: int, total: int, status) -> None:
                if not t0:
                    t0.append(time.perf_counter())
                fps = (done - 1) / max(time.perf_counter() - t0[0], 1e-9)
                state = "" if status is None else f"{status.path} overlap {status.overlap:.2f}"
                progress.update(task, completed=done, total=total, fps=fps, state=state)

            result, run_dir = run_sequence(
                sequence, out, config_path=config, max_frames=max_frames, progress=on_frame
            )
    except SlamError as exc:
        _fail(exc)
        return
    m = result.metrics
    console.print(
        f"[green]wrote[/] {run_dir}: trajectory.txt, odometry.txt, mesh.ply, metrics.json"
    )
    line = f"{m['frames']} frames, {m['fps']:.1f} fps, {m['tracking_failures']} tracking failures"
    if "ate_rmse_m" in m:
        line += f", ATE RMSE {m['ate_rmse_m']:.4f} m"
    typer.echo(line)


@app.command()
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
) -> None:
    """Render a synthetic RGB-D sequence with exact ground truth (TUM layout + calibration.yaml)."""
    from slam.data.synthetic import SynthConfig, generate_sequence

    _setup_logging(False)
    try:
        path = generate_sequence(
            out, SynthConfig(frames=frames, loop=loop, seed=seed, alias=alias, noise=noise)
        )
    except SlamError as exc:
        _fail(exc)
        return
    typer.echo(f"wrote {frames} frames to {path}")


@app.command("eval")
def eval_cmd(
    gt: Annotated[Path, typer.Argument(help="Ground-truth trajectory (TUM format).")],
    est: Annotated[Path, typer.Argument(help="Estimated trajectory (TUM format).")],
    plot: Annotated[
        Optional[Path], typer.Option("--plot", help="Write a top-view plot to this PNG.")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    t_max_diff: Annotated[
        float, typer.Option("--t-max-diff", help="Max timestamp difference to associate (s).")
    ] = 0.01,
    correct_scale: Annotated[
        bool, typer.Option("--correct-scale", help="Sim(3) alignment instead of SE(3).")
    ] = False,
) -> None:
    """ATE (SE(3)-aligned, as evo_ape -a) and RPE (1-frame pairs) of EST against GT."""
    from slam import eval as slam_eval
    from slam.trajectory import read_tum

    _setup_logging(False)
    try:
        gt_traj, est_traj = read_tum(gt), read_tum(est)
        res = slam_eval.evaluate(
            gt_traj, est_traj, max_diff=t_max_diff, correct_scale=correct_scale
        )
        if plot is not None:
            aligned = slam_eval.align_trajectory(gt_traj, est_traj, correct_scale, t_max_diff)
            slam_eval.plot_trajectories(plot, gt_traj, {est.stem: aligned}, title=str(est))
    except SlamError as exc:
        _fail(exc)
        return
    if as_json:
        typer.echo(json.dumps(res))
        return
    typer.echo(f"matched poses      {res['matched_poses']}")
    typer.echo(f"ATE RMSE           {res['ate_rmse_m']:.6f} m")
    typer.echo(f"ATE mean / max     {res['ate_mean_m']:.6f} / {res['ate_max_m']:.6f} m")
    typer.echo(f"RPE trans RMSE     {res['rpe_trans_rmse_m']:.6f} m")
    typer.echo(f"RPE rot RMSE       {res['rpe_rot_rmse_deg']:.6f} deg")
    typer.echo(f"drift              {res['drift_percent']:.3f} % of {res['path_length_m']:.2f} m")


def main() -> None:
    app()


if __name__ == "__main__":
    main()
