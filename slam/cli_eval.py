"""``slam eval``, ``slam report`` and ``slam bench``, and how ``slam eval`` prints its results
(plain text; ``--json`` prints the library's dicts). Registered on :data:`slam.cli_app.app`
when :mod:`slam.cli` is imported."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.markup import escape

from slam import cli_app
from slam.cli_app import CorrectScale, TMaxDiff, Verbose, command, setup_logging
from slam.errors import SlamError
from slam.run_folder import ODOMETRY_FILE, REPORT_FILE, TRAJECTORY_FILE

_STAT_KEYS = ("rmse", "mean", "median", "std", "min", "max")


def _fmt_stats(stats, unit: str, digits: int = 4) -> str:
    if stats is None:
        return "n/a"
    return (
        f"rmse {stats.rmse:.{digits}f}  mean {stats.mean:.{digits}f}  median "
        f"{stats.median:.{digits}f}  std {stats.std:.{digits}f}  min {stats.min:.{digits}f}  "
        f"max {stats.max:.{digits}f} {unit}"
    )


def echo_result(res) -> None:
    typer.echo(f"matched poses      {res.matched_poses} (alignment {res.alignment})")
    typer.echo(f"ATE                {_fmt_stats(res.ate, 'm')}")
    for r in res.rpe:
        if r.left_out:
            typer.echo(f"RPE {r.label:<14} n/a: {r.left_out}")
            continue
        typer.echo(f"RPE {r.label:<14} trans {_fmt_stats(r.trans, 'm')}  ({r.pairs} pairs)")
        typer.echo(f"{'':18} rot   {_fmt_stats(r.rot, 'deg', 3)}")
    d = res.drift
    typer.echo(
        f"drift              {d.percent:.3f} % ({d.final_error_m:.4f} m final error over "
        f"{d.path_length_m:.2f} m, {d.alignment} alignment)"
    )


def echo_run(ev) -> None:
    """Final vs odometry side by side."""
    rows: list[tuple[str, str, str]] = []

    def val(res, get, fmt):
        if res is None:
            return "-"
        v = get(res)
        return "n/a" if v is None else format(v, fmt)

    fin, odo = ev.final, ev.odometry
    rows.append(
        (
            "matched poses",
            val(fin, lambda r: r.matched_poses, "d"),
            val(odo, lambda r: r.matched_poses, "d"),
        )
    )
    for k in _STAT_KEYS:
        rows.append(
            (
                f"ATE {k} [m]",
                val(fin, lambda r, k=k: getattr(r.ate, k), ".4f"),
                val(odo, lambda r, k=k: getattr(r.ate, k), ".4f"),
            )
        )
    for i, r in enumerate(fin.rpe):

        def t(res, i=i):
            x = res.rpe[i]
            return None if x.left_out or x.trans is None else x.trans.rmse

        def rot(res, i=i):
            x = res.rpe[i]
            return None if x.left_out or x.rot is None else x.rot.rmse

        def pairs(res, i=i):
            return res.rpe[i].pairs

        rows.append((f"RPE {r.label} trans rmse [m]", val(fin, t, ".4f"), val(odo, t, ".4f")))
        rows.append((f"RPE {r.label} rot rmse [deg]", val(fin, rot, ".3f"), val(odo, rot, ".3f")))
        rows.append((f"RPE {r.label} pose pairs", val(fin, pairs, "d"), val(odo, pairs, "d")))
    rows.append(
        (
            "drift [%]",
            val(fin, lambda r: r.drift.percent, ".3f"),
            val(odo, lambda r: r.drift.percent, ".3f"),
        )
    )
    rows.append(
        (
            "final position error [m]",
            val(fin, lambda r: r.drift.final_error_m, ".4f"),
            val(odo, lambda r: r.drift.final_error_m, ".4f"),
        )
    )
    typer.echo(f"run          {ev.run_dir}")
    typer.echo(f"ground truth {ev.ground_truth}")
    if ev.localisation is not None:
        echo_localisation(ev.localisation)
    if ev.loops_accepted is not None:
        typer.echo(f"loops        {ev.loops_accepted} accepted")
    if ev.odometry is None:
        typer.echo(f"odometry     (no {ODOMETRY_FILE})")
    elif ev.odometry_identical:
        typer.echo("odometry     identical to the final trajectory (no pose corrected)")
    width = max(len(r[0]) for r in rows)
    typer.echo(f"{'':{width}}  {'final':>10}  {'odometry':>10}")
    for name, a, b in rows:
        typer.echo(f"{name:{width}}  {a:>10}  {b:>10}")
    for note in rpe_notes(ev):
        typer.echo(note)


def echo_localisation(loc: dict) -> None:
    """A localisation run's lines: its map, the frames placed in it, and the error in its
    frame (the map run's alignment to the ground truth, none of its own)."""
    n, miss = loc.get("frames_localised") or 0, loc.get("frames_not_localised") or 0
    first = loc.get("first_localised_frame")
    typer.echo(f"map          {loc.get('map')}")
    where = "" if first is None else f", the first at frame {first}"
    typer.echo(f"localised    {n} of {n + miss} frames{where}; {miss} not localised")
    if loc.get("ate_rmse_map_frame_m") is not None:
        typer.echo(
            f"map frame    ATE rmse {loc['ate_rmse_map_frame_m']:.4f} m (no alignment of its own)"
        )
    elif loc.get("map_frame_error"):
        typer.echo(f"map frame    n/a: {loc['map_frame_error']}")


def rpe_notes(ev) -> list[str]:
    """Why an RPE row of a run's evaluation is n/a (too few pose pairs, none), one line each."""
    why: dict[tuple[str, str], list[str]] = {}  # (label, reason) -> the columns
    for name, res in (("final", ev.final), ("odometry", ev.odometry)):
        if res is None or (name == "odometry" and res is ev.final):
            continue
        for r in res.rpe:
            if r.left_out:
                why.setdefault((r.label, r.left_out), []).append(name)
    return [
        f"RPE {label} n/a ({', '.join(names)}): {reason}" for (label, reason), names in why.items()
    ]


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

    setup_logging()
    deltas = rpe_delta or ["1f", "1s", "1m"]
    if gt.is_dir():
        if est is not None:
            raise SlamError(
                f"{gt} is a run folder: give it alone (`slam eval RUN_DIR`), or give two "
                f"trajectory files (`slam eval GT EST`)"
            )
        _eval_run_folder(gt, gt_file, plot, as_json, t_max_diff, correct_scale, deltas, drift_align)
        return
    if not gt.exists():
        raise SlamError(f"{gt} not found: give a run folder (`slam eval RUN_DIR`) or two "
                        "trajectory files (`slam eval GT EST`)")  # fmt: skip
    if est is None:
        raise SlamError(
            f"{gt} is not a folder: give a run folder (`slam eval RUN_DIR`) or a ground-truth "
            f"and an estimated trajectory file (`slam eval GT EST`)"
        )
    gt_traj, est_traj = read_tum(gt, skip_non_finite=True), read_tum(est)
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
        _wrote(plot)
    if as_json:
        typer.echo(json.dumps(res.as_dict()))
        return
    echo_result(res)


def _wrote(path: Path) -> None:
    """The plot's "wrote" line, on stderr (with --json stdout holds the JSON alone)."""
    cli_app.console.print(f"[green]wrote[/] {escape(str(path))}")


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
    run.require_complete()
    loc = slam_eval.localisation_summary(run)
    if loc is not None and not loc["frames_localised"]:  # nothing to evaluate: say so
        if as_json:
            typer.echo(json.dumps({"run_dir": str(run_dir), "localisation": loc}))
        else:
            typer.echo(f"run          {run_dir}")
            echo_localisation(loc)
        return
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
        _wrote(plot)
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

    setup_logging()
    rep = write_report(run_dir, out, gt_file, t_max_diff, correct_scale)
    typer.echo(f"wrote {rep.markdown}")
    for p in rep.plots:
        typer.echo(f"wrote {p}")
    if rep.evaluation is None:
        typer.echo(f"no accuracy: {rep.ground_truth_error}")


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

    setup_logging(verbose)
    s = load_suite(suite)
    out_dir = out if out is not None else Path("runs") / "bench" / s.name

    def progress(row: dict, done: int, total: int) -> None:
        failed = f"[red]failed[/] {escape(str(row['error']))}"
        state = "[green]ok[/]" if row["status"] == "ok" else failed
        ate = row.get("ate_rmse_m")
        ate_txt = f" ATE {ate:.4f} m" if isinstance(ate, float) else ""
        what = escape(f"[{done}/{total}] {row['sequence']} / {row['config']}: ")
        cli_app.console.print(f"{what}{state}{ate_txt}")

    res = run_suite(s, out_dir, jobs=jobs, ray_address=ray, progress=progress)
    typer.echo(format_markdown(res.rows))
    for path in res.tables.values():
        typer.echo(f"wrote {path}")
    if res.failed:
        raise typer.Exit(code=1)
