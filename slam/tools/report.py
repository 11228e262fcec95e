"""Run reports: ``report.md`` plus PNG plots that explain a run folder without a notebook.

:func:`write_report` reads the files ``slam run`` writes (``trajectory.txt``, ``odometry.txt``,
``metrics.json``, ``tracking.csv``, ``config.yaml`` and, with loop closure, ``loops.json``) and
writes, next to them or into ``out_dir``:

* ``report_topview.png``: ground truth, odometry and final trajectory (each SE(3)-aligned to the
  ground truth as ATE aligns it) in the plane in which the ground truth extends most (its axes
  labelled; a coordinate plane such as x-y when it is close to one), with the accepted
  loop-closure edges drawn thin and light
* ``report_error.png``: translation error of odometry and final trajectory over time, with the
  times of accepted loop closures marked
* ``report_timing.png``: total time per pipeline stage and tracking time of every frame
* ``report.md``: the numbers (ATE, RPE, drift for both trajectories, loops, tracking, timing)
  and the plots

Every input but ``trajectory.txt`` is optional: without ground truth the trajectory plot shows the
trajectories in the SLAM world frame and there is no error plot; without ``loops.json`` no loop
edges are drawn. Plots use matplotlib's Agg backend (no display needed).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from slam.errors import RunFolderError, SlamError
from slam.run_folder import (
    ERROR_PNG,
    LOOPS_FILE,
    METRICS_FILE,
    ODOMETRY_FILE,
    REPORT_FILE,
    TIMING_PNG,
    TOPVIEW_PNG,
    TRAJECTORY_FILE,
    RunFolder,
)
from slam.run_folder.reader import same_trajectory
from slam.run_folder.tracking_csv import columns
from slam.tools import eval as slam_eval
from slam.tools.plots import (
    PlotPlane,
    plot_error,
    plot_timing,
    plot_trajectories,
    trajectory_plane,
)
from slam.tools.report_md import (
    accuracy_md,
    fmt_value,
    loops_md,
    rejection_reasons,
    stage_totals,
    timing_md,
    tracking_md,
    wall_seconds,
)
from slam.trajectory import Trajectory, atomic_write_text

logger = logging.getLogger(__name__)

__all__ = [
    "ERROR_PNG",
    "REPORT_MD",
    "TIMING_PNG",
    "TOPVIEW_PNG",
    "Report",
    "RunContents",
    "load_run_folder",
    "loop_edges",
    "rejection_reasons",
    "write_report",
]

#: ``report.md`` (the name is :data:`slam.run_folder.REPORT_FILE`).
REPORT_MD = REPORT_FILE


@dataclass
class RunContents:
    """The files of a run folder a report draws on, read with :class:`RunFolder`. Optional
    files are ``None`` / empty when absent; ``tracking`` is ``tracking.csv`` as columns
    (:func:`slam.run_folder.tracking_csv.columns`), ``loops`` the ``loops.json`` candidates."""

    path: Path
    trajectory: Trajectory
    odometry: Trajectory | None
    metrics: dict[str, Any] = field(default_factory=dict)
    tracking: dict[str, np.ndarray] | None = None
    loops: list[dict[str, Any]] | None = None

    @property
    def odometry_identical(self) -> bool:
        return self.odometry is None or same_trajectory(self.odometry, self.trajectory)

    @property
    def accepted_loops(self) -> list[dict[str, Any]]:
        return [c for c in self.loops or [] if c.get("accepted")]


@dataclass
class Report:
    """What :func:`write_report` wrote. ``evaluation`` is ``None`` without ground truth, and
    ``ground_truth_error`` then says why."""

    markdown: Path
    plots: list[Path]
    evaluation: slam_eval.RunEvaluation | None
    ground_truth_error: str | None = None


def load_run_folder(run_dir: str | Path | RunFolder) -> RunContents:
    """Read what a report needs of a complete run folder. Only ``trajectory.txt`` is required;
    raises :class:`SlamError` naming the file when it is missing or a present file is
    malformed."""
    run = run_dir if isinstance(run_dir, RunFolder) else RunFolder(run_dir)
    run.require_complete()
    contents = RunContents(run.path, run.trajectory(), run.odometry(), run.metrics())
    statuses = run.tracking()
    contents.tracking = None if statuses is None else columns(statuses)
    contents.loops = run.loops()
    return contents


def _index_at(stamps: np.ndarray, t: float, tol: float) -> int | None:
    i = int(np.argmin(np.abs(stamps - t)))
    return i if abs(stamps[i] - t) <= tol else None


def loop_edges(
    traj: Trajectory, loops: list[dict[str, Any]], tol: float = 0.01
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Positions ``(query, match)`` in ``traj`` of each loop candidate, found by timestamp
    (nearest pose within ``tol`` s; candidates without a matching pose are skipped)."""
    if len(traj) == 0:
        return []
    edges = []
    for c in loops:
        try:
            tq, tm = float(c["query_timestamp"]), float(c["match_timestamp"])
        except (KeyError, TypeError, ValueError):
            logger.debug("loop candidate without timestamps skipped: %s", c)
            continue
        iq, im = _index_at(traj.timestamps, tq, tol), _index_at(traj.timestamps, tm, tol)
        if iq is None or im is None:
            logger.debug("loop candidate at t=%.3f/%.3f not in the trajectory", tq, tm)
            continue
        edges.append((traj.positions[iq].copy(), traj.positions[im].copy()))
    return edges


# ----------------------------------------------------------------------------------------------
# the report


def _ground_truth(
    run: RunContents,
    gt_path: str | Path | None,
    max_diff: float,
    correct_scale: bool,
    rpe_deltas: tuple,
) -> tuple[Trajectory | None, slam_eval.RunEvaluation | None, str | None]:
    """(ground truth, evaluation, why there is no evaluation); an explicit ``gt_path`` must
    work. Ground truth that is found but cannot evaluate the run (a run of one frame) is still
    drawn."""
    gt = None
    try:
        gt, _ = slam_eval.load_run_ground_truth(run.path, gt_path)
        ev = slam_eval.evaluate_run(
            run.path, gt_path, max_diff, correct_scale, rpe_deltas=rpe_deltas
        )
    except SlamError as exc:
        if gt_path is not None:
            raise
        logger.warning("report without accuracy: %s", exc)
        return gt, None, str(exc)
    return gt, ev, None


def _plots(
    run: RunContents,
    out: Path,
    title: str,
    gt: Trajectory | None,
    max_diff: float,
    correct_scale: bool,
) -> tuple[list[Path], PlotPlane, Path | None]:
    """The trajectory plot (in the plane of largest extent), the error over time (with ground
    truth) and the timing plot: (plots written, the trajectory plot's plane, the timing plot)."""
    plots: list[Path] = []
    show_odo = run.odometry is not None and not run.odometry_identical
    trajs: dict[str, Trajectory] = {}
    if gt is not None:
        final = slam_eval.align_trajectory(gt, run.trajectory, correct_scale, max_diff)
        if run.odometry is not None and show_odo:
            trajs["odometry (aligned)"] = slam_eval.align_trajectory(
                gt, run.odometry, correct_scale, max_diff
            )
        trajs["final (aligned)"] = final
    else:
        final = run.trajectory
        if run.odometry is not None and show_odo:
            trajs["odometry"] = run.odometry
        trajs["final"] = final
    edges = loop_edges(final, run.accepted_loops, tol=max(max_diff, 1e-3))
    top = out / TOPVIEW_PNG
    # the plane `slam eval RUN_DIR --plot` draws the run in too (trajectory_plane)
    plane = trajectory_plane(gt, trajs, max_diff)
    plot_trajectories(
        top,
        gt,
        trajs,
        title=f"{title}: {plane.name}" + ("" if gt is not None else " (not aligned)"),
        loop_edges=edges,
        loop_label="accepted loop",
        tol=max_diff,
    )
    plots.append(top)
    if gt is not None:
        curves = {}
        if run.odometry is not None and show_odo:
            curves["odometry"] = slam_eval.ape_per_pose(
                gt, run.odometry, True, correct_scale, max_diff
            )
        curves["final"] = slam_eval.ape_per_pose(gt, run.trajectory, True, correct_scale, max_diff)
        loop_times = [
            float(c["query_timestamp"]) for c in run.accepted_loops if "query_timestamp" in c
        ]
        plots.append(
            plot_error(
                out / ERROR_PNG,
                curves,
                float(run.trajectory.timestamps[0]),
                loop_times,
                f"{title}: translation error over time",
            )
        )
    m = run.metrics
    timing = plot_timing(
        out / TIMING_PNG, stage_totals(m), wall_seconds(m), run.tracking, f"{title}: timing"
    )
    if timing is not None:
        plots.append(timing)
    return plots, plane, timing


def _accuracy_section(
    run: RunContents,
    gt: Trajectory | None,
    ev: slam_eval.RunEvaluation | None,
    max_diff: float,
    correct_scale: bool,
) -> list[str]:
    if ev is None and gt is not None:
        return [
            "The ground truth cannot evaluate this run (see above), so no accuracy numbers. "
            "The trajectory plot is in the SLAM world frame (first camera)."
        ]
    if ev is None or gt is None:
        return [
            "No ground truth, so no accuracy numbers; give one with `slam report RUN_DIR --gt "
            "FILE`. The trajectory plot is in the SLAM world frame (first camera)."
        ]
    align = {"se3": "SE(3)", "sim3": "Sim(3)"}.get(ev.final.alignment, ev.final.alignment)
    lines = [
        f"Each trajectory is associated with the ground truth by timestamp (within "
        f"{max_diff:g} s) and aligned to it by its own {align} Umeyama fit over all "
        f"associated positions, as `evo_ape tum GT EST -a{'s' if correct_scale else ''}` "
        f"does; ATE and RPE are evo's numbers (RPE over consecutive pose pairs, their number "
        f"given; a delta with fewer than {slam_eval.MIN_RPE_PAIRS} pairs is left out, with the "
        f"reason, as too few to be an average). Drift is "
        f"the distance between the last aligned position and the ground truth, in % of the "
        f'ground-truth path length; "drift from the start" instead aligns only the first '
        f"poses (evo's `--align_origin`), so all error accumulated since the start shows.",
        "",
    ]
    if ev.odometry is not None and ev.odometry_identical:
        lines += [
            f"`{ODOMETRY_FILE}` equals `{TRAJECTORY_FILE}`: no pose was corrected, one column.",
            "",
        ]
    origin = {"final": slam_eval.drift(gt, run.trajectory, "origin", max_diff)}
    if run.odometry is not None and not run.odometry_identical:
        origin["odometry"] = slam_eval.drift(gt, run.odometry, "origin", max_diff)
    return lines + accuracy_md(ev, origin)


def _markdown(
    run: RunContents,
    title: str,
    gt: Trajectory | None,
    ev: slam_eval.RunEvaluation | None,
    gt_error: str | None,
    plane: PlotPlane,
    timing: Path | None,
    max_diff: float,
    correct_scale: bool,
) -> str:
    m = run.metrics
    frames = m.get("frames", len(run.trajectory))
    lines = [f"# Run report: {title}", ""]
    lines.append(f"- run folder: `{run.path}`")
    if m.get("sequence"):
        lines.append(f"- sequence: `{m['sequence']}`")
    lines.append(
        f"- frames: {frames}; time {fmt_value(m.get('seconds'), '.1f')} s; "
        f"{fmt_value(m.get('fps'), '.1f')} fps; "
        f"peak memory {fmt_value(m.get('peak_rss_mb'), '.0f')} MB"
    )
    if ev is not None:
        lines.append(f"- ground truth: `{ev.ground_truth}`")
    elif gt is not None:
        lines.append(f"- ground truth: found, but no evaluation ({gt_error})")
    else:
        lines.append(f"- ground truth: none ({gt_error})")
    lines += ["", "## Accuracy", ""]
    lines += _accuracy_section(run, gt, ev, max_diff, correct_scale)
    lines += [
        "",
        f"Trajectories in the {plane.name} of the "
        + ("ground truth" if ev is not None else "SLAM world frame")
        + f" (horizontal: {plane.u_label}, vertical: {plane.v_label}; the plane in which "
        "the trajectory extends most), with the accepted loop edges in red.",
        "",
        f"![trajectories]({TOPVIEW_PNG})",
        "",
    ]
    if gt is not None:
        lines += [f"![translation error over time]({ERROR_PNG})", ""]
    lines += ["## Loop closure", ""] + loops_md(run) + [""]
    lines += ["## Tracking", ""] + tracking_md(run) + [""]
    timing_lines = timing_md(run)
    if timing_lines or timing is not None:
        lines += ["## Timing", ""] + timing_lines + [""]
        if timing is not None:
            lines += [f"![timing]({TIMING_PNG})", ""]
    return "\n".join(lines).rstrip() + "\n"


def write_report(
    run_dir: str | Path,
    out_dir: str | Path | None = None,
    gt_path: str | Path | None = None,
    max_diff: float = 0.01,
    correct_scale: bool = False,
    rpe_deltas: tuple = ("1f", "1s", "1m"),
) -> Report:
    """Write ``report.md`` and the PNG plots of a run folder into ``out_dir`` (default: the run
    folder). Ground truth as :func:`slam.tools.eval.load_run_ground_truth` finds it (``gt_path`` wins);
    a run without ground truth gets a report without the accuracy section and error plot."""
    run = load_run_folder(run_dir)
    out = Path(out_dir) if out_dir is not None else run.path
    out.mkdir(parents=True, exist_ok=True)
    title = run.path.resolve().name
    gt, ev, gt_error = _ground_truth(run, gt_path, max_diff, correct_scale, rpe_deltas)
    try:
        aligned_to = gt if ev is not None else None  # too few poses: drawn as estimated
        plots, plane, timing = _plots(run, out, title, aligned_to, max_diff, correct_scale)
        text = _markdown(run, title, gt, ev, gt_error, plane, timing, max_diff, correct_scale)
    except (TypeError, ValueError, KeyError, AttributeError) as exc:  # edited or damaged files
        raise RunFolderError(
            f"{run.path}: {METRICS_FILE} or {LOOPS_FILE} holds a value of the wrong kind "
            f"({type(exc).__name__}: {exc}); was it edited? Run the sequence again for a "
            "report"
        ) from None
    md = out / REPORT_FILE
    atomic_write_text(md, text)
    logger.info("wrote %s and %d plots", md, len(plots))
    return Report(md, plots, ev, gt_error)
