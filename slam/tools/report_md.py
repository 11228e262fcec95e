"""The sections of ``report.md`` (:func:`slam.tools.report.write_report`): accuracy, loop
closure, tracking and timing, as Markdown lines, from a run's contents."""

from __future__ import annotations

import numbers
import re
from typing import TYPE_CHECKING, Any

import numpy as np

from slam.run_folder import LOOPS_FILE, METRICS_FILE, TRACKING_FILE

if TYPE_CHECKING:
    from slam.tools.eval import DriftResult, RunEvaluation
    from slam.tools.report import RunContents

__all__ = [
    "accuracy_md",
    "fmt_value",
    "loops_md",
    "rejection_reasons",
    "stage_totals",
    "timing_md",
    "tracking_md",
    "wall_seconds",
]

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


# ----------------------------------------------------------------------------------------------
# timing


def stage_totals(metrics: dict[str, Any]) -> list[tuple[str, float]]:
    totals = metrics.get("stage_ms_total")
    if not isinstance(totals, dict):
        return []
    out = [(k, float(v)) for k, v in totals.items() if isinstance(v, (int, float))]
    order = {k: i for i, k in enumerate(_STAGE_ORDER)}
    return sorted(out, key=lambda kv: order.get(kv[0], len(order)))


# ----------------------------------------------------------------------------------------------
# markdown


def fmt_value(v: Any, fmt: str) -> str:
    """``v`` formatted, "n/a" when missing, not finite, or not a number (a damaged file)."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        return "n/a"
    if isinstance(v, float) and not np.isfinite(v):
        return "n/a"
    return format(v, fmt)


def accuracy_md(ev: RunEvaluation, origin_drift: dict[str, DriftResult]) -> list[str]:
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
        out.append(f"| {name} | " + " | ".join(fmt_value(get(r), fmt) for r in res) + " |")

    row("matched poses", lambda r: r.matched_poses, "d")
    for k in ("rmse", "mean", "median", "std", "min", "max"):
        row(f"ATE {k} [m]", lambda r, k=k: getattr(r.ate, k), ".4f")
    notes: list[str] = []
    evaluated = [r for r in res if r is not None]
    for i, rp in enumerate(fin.rpe):
        why: dict[str, list[str]] = {}  # reason -> the columns it applies to
        for c, r in zip(cols, evaluated):
            reason = r.rpe[i].left_out
            if reason:
                why.setdefault(reason, []).append(c)
        for reason, where in why.items():
            who = "" if same else f" ({', '.join(where)})"
            notes.append(f"- RPE {rp.label}{who} is left out: {reason}")
        if all(r.rpe[i].left_out for r in evaluated):
            pairs = " / ".join(str(r.rpe[i].pairs) for r in evaluated)
            out.append(
                f"| RPE {rp.label} ({pairs} pose pairs, see below) | "
                + " | ".join("n/a" for _ in res)
                + " |"
            )
            continue
        row(f"RPE {rp.label} pose pairs", lambda r, i=i: r.rpe[i].pairs, "d")
        for k in ("rmse", "mean", "max"):
            row(
                f"RPE {rp.label} translation {k} [m]",
                lambda r, i=i, k=k: None if r.rpe[i].left_out else getattr(r.rpe[i].trans, k),
                ".4f",
            )
        row(
            f"RPE {rp.label} rotation rmse [deg]",
            lambda r, i=i: None if r.rpe[i].left_out else r.rpe[i].rot.rmse,
            ".3f",
        )
    row("drift (final position error / path length) [%]", lambda r: r.drift.percent, ".3f")
    row("final position error [m]", lambda r: r.drift.final_error_m, ".4f")
    if all(d is not None for d in origin):
        out.append(
            "| drift from the start (first poses aligned) [%] | "
            + " | ".join(fmt_value(d.percent, ".3f") for d in origin if d is not None)
            + " |"
        )
        out.append(
            "| final position error, first poses aligned [m] | "
            + " | ".join(fmt_value(d.final_error_m, ".4f") for d in origin if d is not None)
            + " |"
        )
    row("ground-truth path length [m]", lambda r: r.drift.path_length_m, ".2f")
    if notes:
        out += [""] + notes
    return out


def loops_md(run: RunContents) -> list[str]:
    m = run.metrics
    if run.loops is None:
        if "loops_accepted" in m:
            return [
                f"{m.get('loops_accepted')} loop closures accepted, {m.get('loops_rejected', 'n/a')} "
                f"rejected (no `{LOOPS_FILE}` with the details).",
            ]
        return [f"No loop closure in this run (no `{LOOPS_FILE}`)."]
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
                f"| {c.get('query_frame', '?')} | {c.get('match_frame', '?')} | {fmt_value(dt, '.1f')} "
                f"| {fmt_value(c.get('score'), '.3f')} | {c.get('inliers', 'n/a')} "
                f"| {fmt_value(c.get('inlier_ratio'), '.2f')} | {fmt_value(c.get('icp_fitness'), '.2f')} |"
            )
        if len(acc) > len(shown):
            out.append(f"\n({len(acc) - len(shown)} more accepted loops in `{LOOPS_FILE}`.)")
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


def tracking_md(run: RunContents) -> list[str]:
    m = run.metrics
    out = []
    if m:
        paths = m.get("tracking_paths") or {}
        path_txt = ", ".join(f"{k}: {v}" for k, v in paths.items()) if paths else "n/a"
        out += [
            f"- tracking failures: {m.get('tracking_failures', 'n/a')}; paths: {path_txt}",
            f"- keyframes: {m.get('keyframes', 'n/a')}; mean ICP fitness: "
            f"{fmt_value(m.get('icp_fitness_mean'), '.3f')}",
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
    return out or [f"No run statistics or {TRACKING_FILE} in the run folder."]


def wall_seconds(metrics: dict[str, Any]) -> float:
    """The run's wall time (``seconds``), else the sum of the stage totals (s)."""
    s = metrics.get("seconds")
    if isinstance(s, (int, float)) and s > 0:
        return float(s)
    return sum(v for _, v in stage_totals(metrics)) / 1e3


def timing_md(run: RunContents) -> list[str]:
    stages = stage_totals(run.metrics)
    if not stages:
        return []
    frames = run.metrics.get("frames") or len(run.trajectory)
    wall = wall_seconds(run.metrics)
    out = [
        f"Stage totals from `{METRICS_FILE}` (`stage_ms_total`); some stages may contain others "
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
