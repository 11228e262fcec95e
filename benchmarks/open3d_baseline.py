"""Open3D's own dense RGB-D SLAM (``open3d.t.pipelines.slam.Model``: frame-to-model tracking,
TSDF voxel block grid, no loop closure) on one sequence, for comparison. Writes JSON.

    python benchmarks/open3d_baseline.py 7scenes-300 [--voxel 0.01]

Follows Open3D's example ``t_reconstruction_system/dense_slam.py`` (depth_max 3.0,
depth_diff 0.07, truncation 8 voxels), with voxel size 1 cm. Frames are read with this project's
loaders; ATE with ``slam.tools.eval`` (equal to evo_ape -a).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import open3d.core as o3c
from common import machine, peak_rss_mb, sequence_path, write_result

import slam
from slam.tools import eval as slam_eval


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequence")
    parser.add_argument("--voxel", type=float, default=0.01)
    parser.add_argument("--max-frames", type=int, default=None)
    args = parser.parse_args()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    seq = slam.open_sequence(sequence_path(args.sequence))
    n = len(seq) if args.max_frames is None else min(len(seq), args.max_frames)
    device = o3c.Device("CPU:0")
    depth_scale, depth_max, depth_diff, trunc = seq.calibration.depth_scale, 3.0, 0.07, 8.0
    K = o3c.Tensor(seq.calibration.K, o3c.float64)
    T = o3c.Tensor(np.eye(4))
    model = o3d.t.pipelines.slam.Model(args.voxel, 16, 50000, T, device)
    first = seq[0]
    h, w = first.depth_m.shape
    input_frame = o3d.t.pipelines.slam.Frame(h, w, K, device)
    raycast_frame = o3d.t.pipelines.slam.Frame(h, w, K, device)
    poses, stamps, failures = [], [], 0
    t0 = time.perf_counter()
    for i in range(n):
        frame = seq[i]
        depth_u16 = np.round(frame.depth_m * depth_scale).astype(np.uint16)
        color = frame.color if frame.color is not None else np.zeros((h, w, 3), np.uint8)
        input_frame.set_data_from_image("depth", o3d.t.geometry.Image(o3c.Tensor(depth_u16)))
        input_frame.set_data_from_image("color", o3d.t.geometry.Image(o3c.Tensor(color)))
        if i > 0:
            try:
                result = model.track_frame_to_model(
                    input_frame, raycast_frame, depth_scale, depth_max, depth_diff
                )
                T = T @ result.transformation
            except RuntimeError:
                failures += 1
        poses.append(T.cpu().numpy().copy())
        stamps.append(frame.timestamp)
        model.update_frame_pose(i, T)
        model.integrate(input_frame, depth_scale, depth_max, trunc)
        model.synthesize_model_frame(raycast_frame, depth_scale, 0.1, depth_max, trunc, False)
    seconds = time.perf_counter() - t0
    traj = slam.Trajectory(np.array(stamps), np.stack(poses))
    ate = slam_eval.ate(seq.ground_truth, traj).rmse if seq.ground_truth is not None else None
    data = {
        "system": "Open3D dense SLAM (t.pipelines.slam.Model)",
        "sequence": args.sequence,
        "frames": n,
        "voxel_size_m": args.voxel,
        "ate_rmse_m": ate,
        "fps": round(n / seconds, 3),
        "tracking_failures": failures,
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "open3d": o3d.__version__,
        "machine": machine(),
    }
    out = write_result(f"open3d-{Path(args.sequence).name}", data)
    print(f"{out}: ATE {ate:.4f} m, {data['fps']:.2f} fps, peak {data['peak_rss_mb']:.0f} MB")


if __name__ == "__main__":
    main()
