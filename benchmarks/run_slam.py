"""Benchmark this project's pipeline on one sequence (default config) and write JSON.

    python benchmarks/run_slam.py demo
    python benchmarks/run_slam.py 7scenes-300

Writes benchmarks/results/slam-<sequence>.json with ATE, fps and peak memory. Run one sequence
per process so the peak memory belongs to that sequence.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from common import machine, peak_rss_mb, sequence_path, write_result

import slam


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "sequence", help="demo, demo-drift, a folder name under ../shared/datasets, or a path"
    )
    parser.add_argument("--config", default=None, help="YAML config overrides")
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--out", default=None, help="also save the run folder here")
    parser.add_argument("--tag", default="", help="suffix of the result name (config variants)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    path = sequence_path(args.sequence)
    cfg = slam.load_config(args.config)
    cfg.dataset.max_frames = args.max_frames
    cfg.dataset.path = str(path)
    seq = slam.open_sequence(path, cfg.dataset.layout, cfg.dataset.calibration)
    result = slam.run(seq, cfg)
    if args.out:
        slam.save_run(result, args.out)
    m = result.metrics
    data = {
        "system": "rgbd-slam (this project)",
        "sequence": args.sequence,
        "frames": m["frames"],
        "ate_rmse_m": m.get("ate_rmse_m"),
        "ate_rmse_odometry_m": m.get("ate_rmse_odometry_m"),
        "ate_rmse_pose_graph_m": m.get("ate_rmse_pose_graph_m"),
        "ba": m.get("ba"),
        "rpe_trans_rmse_m": m.get("rpe_trans_rmse_m"),
        "fps": m["fps"],
        "fps_tracking_fusion": m["fps_tracking_fusion"],
        "seconds": m["seconds"],
        "loops_accepted": m["loops_accepted"],
        "loops_rejected": m["loops_rejected"],
        "keyframes": m["keyframes"],
        "submaps": m["submaps"],
        "stage_ms_per_frame": m["stage_ms_per_frame"],
        "stage_ms_total": m["stage_ms_total"],
        "tracking_failures": m["tracking_failures"],
        "tracking_paths": m["tracking_paths"],
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "machine": machine(),
    }
    out = write_result(f"slam-{Path(args.sequence).name}{args.tag}", data)
    print(
        f"{out}: ATE {data['ate_rmse_m']:.4f} m (odometry {data['ate_rmse_odometry_m']:.4f} m), "
        f"{data['loops_accepted']} loops, {data['seconds']:.1f} s, {data['fps']:.2f} fps, "
        f"{data['tracking_failures']} failures, peak {data['peak_rss_mb']:.0f} MB"
    )


if __name__ == "__main__":
    main()
