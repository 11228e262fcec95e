"""Compare two (or more) run folders side by side: an example built on ``slam.tools.eval``.

    python scripts/compare_runs.py runs/baseline runs/loopclosure
    python scripts/compare_runs.py runs/a runs/b --labels before after --plot compare.png --json

For each run folder it evaluates ``trajectory.txt`` (final) and ``odometry.txt`` against the
sequence's ground truth, found from the run's ``config.yaml`` exactly as ``slam eval RUN_DIR``
does (``--gt FILE`` overrides), and prints one Markdown table: ATE, RPE over 1 frame and over
1 s, drift, loops accepted, fps and peak memory (from ``metrics.json``), plus the change of each
run relative to the first. ``--plot`` overlays the final trajectories (each SE(3)-aligned to the
ground truth) in a top view; ``--json`` prints the numbers as one JSON object instead.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from slam.errors import SlamError
from slam.run_folder import RunFolder
from slam.tools import eval as slam_eval
from slam.tools.plots import plot_trajectories


def _rmse(rpe: slam_eval.RPEResult) -> float | None:
    return None if rpe.trans is None else rpe.trans.rmse


def summarize(run_dir: Path, gt_file: Path | None) -> dict:
    ev = slam_eval.evaluate_run(run_dir, gt_file, rpe_deltas=["1f", "1s"])
    try:
        metrics = RunFolder(run_dir).metrics()
    except SlamError:
        metrics = {}
    odo = ev.odometry or ev.final
    return {
        "run": str(run_dir),
        "ate_rmse_m": ev.final.ate.rmse,
        "ate_rmse_odometry_m": odo.ate.rmse,
        "rpe_1f_trans_rmse_m": _rmse(ev.final.rpe[0]),
        "rpe_1s_trans_rmse_m": _rmse(ev.final.rpe[1]),
        "drift_percent": ev.final.drift.percent,
        "drift_odometry_percent": odo.drift.percent,
        "matched_poses": ev.final.matched_poses,
        "loops_accepted": metrics.get("loops_accepted"),
        "fps": metrics.get("fps"),
        "peak_rss_mb": metrics.get("peak_rss_mb"),
        "ground_truth": ev.ground_truth,
    }


ROWS = [
    ("ATE rmse final [m]", "ate_rmse_m", ".4f"),
    ("ATE rmse odometry [m]", "ate_rmse_odometry_m", ".4f"),
    ("RPE 1 frame [m]", "rpe_1f_trans_rmse_m", ".4f"),
    ("RPE 1 s [m]", "rpe_1s_trans_rmse_m", ".4f"),
    ("drift final [%]", "drift_percent", ".2f"),
    ("drift odometry [%]", "drift_odometry_percent", ".2f"),
    ("matched poses", "matched_poses", "d"),
    ("loops accepted", "loops_accepted", "d"),
    ("fps", "fps", ".1f"),
    ("peak memory [MB]", "peak_rss_mb", ".0f"),
]


def _cell(v, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def markdown(labels: list[str], runs: list[dict]) -> str:
    cols = list(labels)
    for lab in labels[1:]:
        cols.append(f"{lab} - {labels[0]}")
    lines = ["| | " + " | ".join(cols) + " |", "|---|" + "---:|" * len(cols)]
    for name, key, fmt in ROWS:
        vals = [r.get(key) for r in runs]
        cells = [_cell(v, fmt) for v in vals]
        for v in vals[1:]:
            ok = isinstance(v, (int, float)) and isinstance(vals[0], (int, float))
            cells.append(_cell(v - vals[0], "+" + fmt) if ok else "-")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("runs", type=Path, nargs="+", help="run folders (first = reference)")
    ap.add_argument("--labels", nargs="+", help="column labels (default: folder names)")
    ap.add_argument("--gt", type=Path, help="ground-truth file (default: from each run)")
    ap.add_argument("--plot", type=Path, help="top view of the final trajectories to this PNG")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    labels = args.labels or [p.name for p in args.runs]
    if len(labels) != len(args.runs):
        print(f"error: {len(args.runs)} runs but {len(labels)} labels", file=sys.stderr)
        return 2
    try:
        runs = [summarize(p, args.gt) for p in args.runs]
        if args.plot:
            gt, _ = slam_eval.load_run_ground_truth(args.runs[0], args.gt)
            trajs = {
                lab: slam_eval.align_trajectory(gt, RunFolder(p).trajectory())
                for lab, p in zip(labels, args.runs)
            }
            plot_trajectories(args.plot, gt, trajs, title="final trajectories")
    except SlamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(dict(zip(labels, runs))))
    else:
        print(markdown(labels, runs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
