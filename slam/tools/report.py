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

import csv
import json
import logging
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from slam.errors import SlamError
from slam.tools import eval as slam_eval
from slam.tools.plots import plot_error, plot_timing
from slam.trajectory import Trajectory, atomic_write_text, read_tum

logger = logging.getLogger(__name__)

__all__ = [
    "Report",
    "RunFolder",
    "load_run_folder",
    "loop_edges",
    "rejection_reasons",
    "write_report",
]

TOPVIEW_PNG = "report_topview.png"
ERROR_PNG = "report_error.png"
TIMING_PNG = "report_timing.png"
REPORT_MD = "report.md"

#: Stage names of ``metrics.json`` ``stage_ms_total`` in pipeline order (others follow).
_STAGE_ORDER = (
    "load",
    "tracking",
    "integration",
    "loop",
    "loop_detection",
    "optimisation",
    "graph",
    "reintegration",
    "meshing",
)


@dataclass
class RunFolder:
    """The files of a run folder, parsed. Optional files are ``None`` / empty when absent."""

    path: Path
    trajectory: Trajectory
    odometry: Trajectory | None
    metrics: dict[str, Any] = field(default_factory=dict)
    tracking: dict[str, np.ndarray] | None = None  # tracking.csv columns
    loops: list[dict[str, Any]] | None = None  # loops.json "candidates"

    @property
    def odometry_identical(self) -> bool:
        o, t = self.odometry, self.trajectory
        return o is None or (
            len(o) == len(t)
            and np.array_equal(o.timestamps, t.timestamps)
            and np.array_equal(o.poses, t.poses)
        )

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


# ----------------------------------------------------------------------------------------------
# reading


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except OSError as exc:
        raise SlamError(f"{path}: cannot read: {exc}") from exc
    except ValueError as exc:
        raise SlamError(
            f"{path}: not valid JSON ({exc}); was the run interrupted while writing it?"
        ) from exc


def _parse_cell(value: str) -> float:
    if value in ("True", "true"):
        return 1.0
    if value in ("False", "false"):
        return 0.0
    try:
        return float(value)
    except ValueError:
        return float("nan")


def _read_tracking_csv(path: Path) -> dict[str, np.ndarray]:
    """Numeric columns of ``tracking.csv`` (booleans as 0/1, text columns kept as strings)."""
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return {}
    cols: dict[str, np.ndarray] = {}
    for name in rows[0]:
        raw = [r.get(name) or "" for r in rows]
        values = np.array([_parse_cell(v) for v in raw])
        cols[name] = np.array(raw) if np.all(np.isnan(values)) else values
    return cols


def load_run_folder(run_dir: str | Path) -> RunFolder:
    """Read a run folder. Only ``trajectory.txt`` is required; raises :class:`SlamError` naming
    the file when it is missing or a present file is malformed."""
    path = Path(run_dir)
    run = RunFolder(path, read_tum(slam_eval.run_trajectory_path(path)), None)
    if (path / "odometry.txt").is_file():
        run.odometry = read_tum(path / "odometry.txt")
    if (path / "metrics.json").is_file():
        data = _read_json(path / "metrics.json")
        run.metrics = data if isinstance(data, dict) else {}
    if (path / "tracking.csv").is_file():
        run.tracking = _read_tracking_csv(path / "tracking.csv")
    if (path / "loops.json").is_file():
        data = _read_json(path / "loops.json")
        cands = data.get("candidates") if isinstance(data, dict) else None
        if not isinstance(cands, list):
            raise SlamError(
                f"{path / 'loops.json'}: expected an object with a 'candidates' list, "
                f"got {type(data).__name__}"
            )
        run.loops = [c for c in cands if isinstance(c, dict)]
    return run


def _during(gt: Trajectory, traj: Trajectory, tol: float) -> Trajectory:
    """The ground truth over the time the trajectory covers (a run of part of a sequence, or
    motion capture that starts before the camera, would otherwise draw what was not run)."""
    if len(traj) == 0:
        return gt
    t = gt.timestamps
    keep = (t >= traj.timestamps[0] - tol) & (t <= traj.timestamps[-1] + tol)
    return Trajectory(t[keep], gt.poses[keep]) if np.count_nonzero(keep) >= 2 else gt


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
# timing


def _stages(metrics: dict[str, Any]) -> list[tuple[str, float]]:
    totals = metrics.get("stage_ms_total")
    if not isinstance(totals, dict):
        return []
    out = [(k, float(v)) for k, v in totals.items() if isinstance(v, (int, float))]
    order = {k: i for i, k in enumerate(_STAGE_ORDER)}
    return sorted(out, key=lambda kv: order.get(kv[0], len(order)))


# ----------------------------------------------------------------------------------------------
# markdown


def _f(v: Any, fmt: str) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "n/a"
    return format(v, fmt)


def _accuracy_md(
    ev: slam_eval.RunEvaluation, origin_drift: dict[str, slam_eval.DriftResult]
) -> list[str]:
    fin, odo = ev.final, ev.odometry
    same = odo is None or ev.odometry_identical
    cols = ["final"] if same else ["final", "odometry"]
    res = [fin] if same else [fin, odo]
    origin = [origin_drift.get(c) for c in cols]
    out = [
        "| metric | " + " | ".join(cols) + " |",
        "|---|" + "---:|" * len(cols),
    ]

    def row(name: str, get, fmt: str) -> None:
        out.append(f"| {name} | " + " | ".join(_f(get(r), fmt) for r in res) + " |")

    row("matched poses", lambda r: r.matched_poses, "d")
    for k in ("rmse", "mean", "median", "std", "min", "max"):
        row(f"ATE {k} [m]", lambda r, k=k: getattr(r.ate, k), ".4f")
    for i, rp in enumerate(fin.rpe):
        if rp.trans is None:
            out.append(f"| RPE {rp.label} | " + " | ".join("n/a" for _ in res) + " |")
            continue
        for k in ("rmse", "mean", "max"):
            row(
                f"RPE {rp.label} translation {k} [m]",
                lambda r, i=i, k=k: None if r.rpe[i].trans is None else getattr(r.rpe[i].trans, k),
                ".4f",
            )
        row(
            f"RPE {rp.label} rotation rmse [deg]",
            lambda r, i=i: None if r.rpe[i].rot is None else r.rpe[i].rot.rmse,
            ".3f",
        )
    row("drift (final position error / path length) [%]", lambda r: r.drift.percent, ".3f")
    row("final position error [m]", lambda r: r.drift.final_error_m, ".4f")
    if all(d is not None for d in origin):
        out.append(
            "| drift from the start (first poses aligned) [%] | "
            + " | ".join(_f(d.percent, ".3f") for d in origin if d is not None)
            + " |"
        )
        out.append(
            "| final position error, first poses aligned [m] | "
            + " | ".join(_f(d.final_error_m, ".4f") for d in origin if d is not None)
            + " |"
        )
    row("ground-truth path length [m]", lambda r: r.drift.path_length_m, ".2f")
    return out


def _loops_md(run: RunFolder) -> list[str]:
    m = run.metrics
    if run.loops is None:
        if "loops_accepted" in m:
            return [
                f"{m.get('loops_accepted')} loop closures accepted, {m.get('loops_rejected', 'n/a')} "
                "rejected (no `loops.json` with the details).",
            ]
        return ["No loop closure in this run (no `loops.json`)."]
    acc = run.accepted_loops
    rejected = [c for c in run.loops if not c.get("accepted")]
    out = [
        f"{len(run.loops)} loop candidates verified: **{len(acc)} accepted**, "
        f"{len(rejected)} rejected. Accepted loops are the red edges in the trajectory plot "
        "(between the two camera positions of the final trajectory).",
        "",
    ]
    if rejected:
        out += ["| rejection reason | count | values |", "|---|---:|---|"]
        out += [f"| {r} | {n} | {v} |" for r, n, v in rejection_reasons(rejected)]
        out.append("")
    if acc:
        out += [
            "| query frame | match frame | time apart [s] | score | inliers | inlier ratio "
            "| ICP fitness |",
            "|---:|---:|---:|---:|---:|---:|---:|",
        ]
        shown = acc[:25]
        for c in shown:
            dt = None
            if "query_timestamp" in c and "match_timestamp" in c:
                dt = float(c["query_timestamp"]) - float(c["match_timestamp"])
            out.append(
                f"| {c.get('query_frame', '?')} | {c.get('match_frame', '?')} | {_f(dt, '.1f')} "
                f"| {_f(c.get('score'), '.3f')} | {c.get('inliers', 'n/a')} "
                f"| {_f(c.get('inlier_ratio'), '.2f')} | {_f(c.get('icp_fitness'), '.2f')} |"
            )
        if len(acc) > len(shown):
            out.append(f"\n({len(acc) - len(shown)} more accepted loops in `loops.json`.)")
    return out


_NUMBER = re.compile(r"-?\d+(?:\.\d+)?")


def rejection_reasons(
    candidates: list[dict[str, Any]], max_values: int = 12
) -> list[tuple[str, int, str]]:
    """Rejection reasons of loop candidates grouped by their wording, most frequent first:
    ``(reason with its values, count, the differing values)``. A number every candidate of the
    group shares is shown as is (``< 25``), one that differs as its range (``6–23 RANSAC
    inliers < 25``), and the values of the first differing number are listed (sorted, at most
    ``max_values``)."""
    groups: dict[str, list[list[str]]] = {}
    for c in candidates:
        reason = str(c.get("reason", "?"))
        groups.setdefault(_NUMBER.sub("#", reason), []).append(_NUMBER.findall(reason))
    out = []
    for template, values in sorted(groups.items(), key=lambda kv: -len(kv[1])):
        parts = template.split("#")
        text, listed = parts[0], ""
        for k, part in enumerate(parts[1:]):
            col = [v[k] for v in values]
            nums = sorted(float(x) for x in col)
            if len(set(col)) == 1:
                text += col[0]
            else:
                digits = max((len(x.split(".")[1]) if "." in x else 0) for x in col)
                text += f"{nums[0]:.{digits}f}–{nums[-1]:.{digits}f}"
                if not listed:
                    shown = [f"{x:.{digits}f}" for x in nums[:max_values]]
                    more = len(nums) - len(shown)
                    listed = ", ".join(shown) + (f", ... ({more} more)" if more > 0 else "")
            text += part
        out.append((text, len(values), listed))
    return out


def _tracking_md(run: RunFolder) -> list[str]:
    m = run.metrics
    out = []
    if m:
        paths = m.get("tracking_paths") or {}
        path_txt = ", ".join(f"{k}: {v}" for k, v in paths.items()) if paths else "n/a"
        out += [
            f"- tracking failures: {m.get('tracking_failures', 'n/a')}; paths: {path_txt}",
            f"- keyframes: {m.get('keyframes', 'n/a')}; mean ICP fitness: "
            f"{_f(m.get('icp_fitness_mean'), '.3f')}",
        ]
        if m.get("frames_skipped"):
            out.append(f"- frames skipped (unreadable): {m['frames_skipped']}")
    tr = run.tracking
    if tr is not None and "ms" in tr and tr["ms"].dtype.kind == "f" and len(tr["ms"]):
        ms = tr["ms"]
        out.append(
            f"- tracking time per frame: median {np.nanmedian(ms):.1f} ms, 95th percentile "
            f"{np.nanpercentile(ms, 95):.1f} ms, max {np.nanmax(ms):.1f} ms"
        )
    return out or ["No run statistics or tracking.csv in the run folder."]


def _wall_seconds(metrics: dict[str, Any]) -> float:
    """The run's wall time (``seconds``), else the sum of the stage totals (s)."""
    s = metrics.get("seconds")
    if isinstance(s, (int, float)) and s > 0:
        return float(s)
    return sum(v for _, v in _stages(metrics)) / 1e3


def _timing_md(run: RunFolder) -> list[str]:
    stages = _stages(run.metrics)
    if not stages:
        return []
    frames = run.metrics.get("frames") or len(run.trajectory)
    wall = _wall_seconds(run.metrics)
    out = [
        "Stage totals from `metrics.json` (`stage_ms_total`); some stages may contain others "
        "(e.g. `loop` includes its detection and optimisation), so shares are of the run's "
        "wall time, not of their sum.",
        "",
        "| stage | total [s] | per frame [ms] | share of wall time |",
        "|---|---:|---:|---:|",
    ]
    for name, v in stages:
        share = 100 * v / 1e3 / wall if wall > 0 else 0.0
        out.append(f"| {name} | {v / 1e3:.2f} | {v / frames:.1f} | {share:.0f} % |")
    out.append(f"| **wall time** | {wall:.2f} | {wall * 1e3 / frames:.1f} | 100 % |")
    return out


# ----------------------------------------------------------------------------------------------
# the report


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
    m = run.metrics

    gt: Trajectory | None = None
    ev: slam_eval.RunEvaluation | None = None
    gt_error: str | None = None
    try:
        gt, _ = slam_eval.load_run_ground_truth(run.path, gt_path)
        ev = slam_eval.evaluate_run(
            run.path, gt_path, max_diff, correct_scale, rpe_deltas=rpe_deltas
        )
    except SlamError as exc:
        if gt_path is not None:
            raise
        gt, ev, gt_error = None, None, str(exc)
        logger.warning("report without accuracy: %s", exc)

    plots: list[Path] = []
    # trajectories in the plane of largest extent (report_topview.png)
    show_odo = run.odometry is not None and not run.odometry_identical
    trajs: dict[str, Trajectory] = {}
    if gt is not None:
        final = slam_eval.align_trajectory(gt, run.trajectory, correct_scale, max_diff)
        if show_odo:
            assert run.odometry is not None
            trajs["odometry (aligned)"] = slam_eval.align_trajectory(
                gt, run.odometry, correct_scale, max_diff
            )
        trajs["final (aligned)"] = final
    else:
        final = run.trajectory
        if show_odo:
            assert run.odometry is not None
            trajs["odometry"] = run.odometry
        trajs["final"] = final
    edges = loop_edges(final, run.accepted_loops, tol=max(max_diff, 1e-3))
    top = out / TOPVIEW_PNG
    gt_run = None if gt is None else _during(gt, run.trajectory, max_diff)
    plane = slam_eval.plot_plane(
        gt_run.positions
        if gt_run is not None
        else np.concatenate([t.positions for t in trajs.values()])
    )
    slam_eval.plot_trajectories(
        top,
        gt_run,
        trajs,
        title=f"{title}: {plane.name}" + ("" if gt is not None else " (no ground truth)"),
        loop_edges=edges,
        loop_label="accepted loop",
    )
    plots.append(top)

    # error over time
    if gt is not None:
        curves = {}
        if show_odo:
            assert run.odometry is not None
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

    timing = plot_timing(
        out / TIMING_PNG, _stages(m), _wall_seconds(m), run.tracking, f"{title}: timing"
    )
    if timing is not None:
        plots.append(timing)

    # markdown
    frames = m.get("frames", len(run.trajectory))
    lines = [f"# Run report: {title}", ""]
    lines.append(f"- run folder: `{run.path}`")
    if m.get("sequence"):
        lines.append(f"- sequence: `{m['sequence']}`")
    lines.append(
        f"- frames: {frames}; time {_f(m.get('seconds'), '.1f')} s; {_f(m.get('fps'), '.1f')} fps; "
        f"peak memory {_f(m.get('peak_rss_mb'), '.0f')} MB"
    )
    if ev is not None:
        lines.append(f"- ground truth: `{ev.ground_truth}`")
    else:
        lines.append(f"- ground truth: none ({gt_error})")
    lines += ["", "## Accuracy", ""]
    if ev is not None and gt is not None:
        align = {"se3": "SE(3)", "sim3": "Sim(3)"}.get(ev.final.alignment, ev.final.alignment)
        lines += [
            f"Each trajectory is associated with the ground truth by timestamp (within "
            f"{max_diff:g} s) and aligned to it by its own {align} Umeyama fit over all "
            f"associated positions, as `evo_ape tum GT EST -a{'s' if correct_scale else ''}` "
            f"does; ATE and RPE are evo's numbers (RPE over consecutive pose pairs). Drift is "
            f"the distance between the last aligned position and the ground truth, in % of the "
            f'ground-truth path length; "drift from the start" instead aligns only the first '
            f"poses (evo's `--align_origin`), so all error accumulated since the start shows.",
            "",
        ]
        if ev.odometry is not None and ev.odometry_identical:
            lines += [
                "`odometry.txt` equals `trajectory.txt`: no pose was corrected, one column.",
                "",
            ]
        origin = {"final": slam_eval.drift(gt, run.trajectory, "origin", max_diff)}
        if run.odometry is not None and not run.odometry_identical:
            origin["odometry"] = slam_eval.drift(gt, run.odometry, "origin", max_diff)
        lines += _accuracy_md(ev, origin)
    else:
        lines.append(
            "No ground truth, so no accuracy numbers; give one with `slam report RUN_DIR --gt "
            "FILE`. The trajectory plot is in the SLAM world frame (first camera)."
        )
    lines += [
        "",
        f"Trajectories in the {plane.name} of the "
        + ("ground truth" if gt is not None else "SLAM world frame")
        + f" (horizontal: {plane.u_label}, vertical: {plane.v_label}; the plane in which "
        "the trajectory extends most), with the accepted loop edges in red.",
        "",
        f"![trajectories]({TOPVIEW_PNG})",
        "",
    ]
    if gt is not None:
        lines += [f"![translation error over time]({ERROR_PNG})", ""]
    lines += ["## Loop closure", ""] + _loops_md(run) + [""]
    lines += ["## Tracking", ""] + _tracking_md(run) + [""]
    timing_md = _timing_md(run)
    if timing_md or timing is not None:
        lines += ["## Timing", ""] + timing_md + [""]
        if timing is not None:
            lines += [f"![timing]({TIMING_PNG})", ""]
    md = out / REPORT_MD
    atomic_write_text(md, "\n".join(lines).rstrip() + "\n")
    logger.info("wrote %s and %d plots", md, len(plots))
    return Report(md, plots, ev, gt_error)
