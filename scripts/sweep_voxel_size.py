"""ATE versus TSDF voxel size: an example evaluation script built on the ``slam`` API.

    python scripts/sweep_voxel_size.py                         # small synthetic sequence, ~20 s
    python scripts/sweep_voxel_size.py --voxel 0.005 0.01 0.015 0.02 --frames 100
    python scripts/sweep_voxel_size.py --sequence ../shared/datasets/7scenes-300 \\
        --frames 300 --csv sweep.csv --plot sweep.png

Without ``--sequence`` it renders a synthetic loop sequence with exact ground truth (320x240,
``--frames`` frames) into a temporary folder. Every voxel size is one in-process run
(``slam.run``) with only ``mapping.voxel_size_m`` changed; the trajectory is evaluated with
``slam.tools.eval.evaluate_full`` (ATE SE(3)-aligned as ``evo_ape -a``, RPE over 1 frame, drift).
Prints a Markdown table; ``--csv`` and ``--plot`` also save it. For many sequences and settings
at once, in parallel or on a Ray cluster, use ``slam bench`` instead.
"""

from __future__ import annotations

import argparse
import csv
import logging
import sys
import tempfile
from pathlib import Path

import slam
from slam.synthetic import SynthConfig, generate_sequence
from slam.tools import eval as slam_eval
from slam.tools.plots import save_figure


def synthetic_sequence(folder: Path, frames: int) -> Path:
    """A small synthetic loop: the first ``frames`` frames of a 300-frame path at 320x240."""
    cfg = SynthConfig.half_resolution(frames=300, render_frames=frames, seed=0)
    return generate_sequence(folder / "synthetic", cfg)


def sweep(sequence: Path, voxels: list[float], frames: int | None) -> list[dict]:
    seq = slam.open_sequence(sequence)
    gt = seq.ground_truth
    if gt is None:
        raise slam.SlamError(f"{sequence}: no ground truth, nothing to evaluate against")
    rows = []
    for v in voxels:
        cfg = slam.config_from_dict(
            {
                "dataset": {"max_frames": frames},
                "mapping": {"voxel_size_m": v},
                "output": {"save_mesh": False},
            }
        )
        result = slam.run(seq, cfg)
        ev = slam_eval.evaluate_full(gt, result.trajectory)
        rows.append(
            {
                "voxel_size_m": v,
                "frames": result.metrics["frames"],
                "ate_rmse_m": ev.ate.rmse,
                "ate_max_m": ev.ate.max,
                "rpe_trans_rmse_m": ev.rpe[0].trans.rmse if ev.rpe[0].trans else None,
                "drift_percent": ev.drift.percent,
                "fps": result.metrics["fps"],
                "tracking_failures": result.metrics["tracking_failures"],
            }
        )
    return rows


def markdown(rows: list[dict]) -> str:
    head = "| voxel [m] | frames | ATE rmse [m] | ATE max [m] | RPE [m] | drift [%] | fps | lost |"
    lines = [head, "|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(
            f"| {r['voxel_size_m']:.3f} | {r['frames']} | {r['ate_rmse_m']:.4f} | "
            f"{r['ate_max_m']:.4f} | {r['rpe_trans_rmse_m']:.4f} | {r['drift_percent']:.2f} | "
            f"{r['fps']:.1f} | {r['tracking_failures']} |"
        )
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    x = [r["voxel_size_m"] * 100 for r in rows]
    ax.plot(x, [r["ate_rmse_m"] * 100 for r in rows], "o-", label="ATE rmse")
    ax.plot(x, [r["ate_max_m"] * 100 for r in rows], "s--", label="ATE max")
    ax.set_xlabel("TSDF voxel size [cm]")
    ax.set_ylabel("absolute trajectory error [cm]")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sequence", type=Path, help="sequence folder (default: synthetic)")
    ap.add_argument("--frames", type=int, default=20, help="frames to process (default 20)")
    ap.add_argument(
        "--voxel", type=float, nargs="+", default=[0.01, 0.015, 0.02], help="voxel sizes [m]"
    )
    ap.add_argument("--csv", type=Path, help="also write the table as CSV")
    ap.add_argument("--plot", type=Path, help="also plot ATE vs voxel size to this PNG")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        with tempfile.TemporaryDirectory() as tmp:
            seq = args.sequence or synthetic_sequence(Path(tmp), args.frames)
            rows = sweep(seq, args.voxel, args.frames)
    except slam.SlamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(markdown(rows))
    if args.csv:
        with args.csv.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    if args.plot:
        plot(rows, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
