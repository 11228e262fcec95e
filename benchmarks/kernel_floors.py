"""What the three heavy kernels cost alone, per resolution and thread count (issue 17's floors).

    python benchmarks/kernel_floors.py                   # tum-fr1-xyz, downsample 1/2/4, 1/2 threads
    python benchmarks/kernel_floors.py demo --reps 30

For each thread count (a fresh process each, ``open3d.utility.set_max_threads`` and
``cv2.setNumThreads`` set before any work) and tracking resolution (``tracking.downsample``),
a TSDF volume is fused from the sequence's first frames (default config, poses from the
sequence's ground truth: only to build a realistic model, nothing is evaluated) and then, at a
later frame, each kernel is called ``--reps`` times as the pipeline calls it:

- ``integrate``: one frame fused at full resolution (as ``Slam.step`` does), frustum blocks
  included;
- ``ray_cast``: the model rendered at tracking resolution from the frame's pose, frustum blocks
  from its tracking depth included (as frame-to-model tracking does);
- ``odometry``: one coarse-to-fine point-to-plane ICP of the frame's tracking depth to that
  rendering (``PreparedFrame.icp_to``);
- ``prepare``: the frame's tracking inputs (downsampling, bilateral filter, pyramid).

Writes medians (ms) to ``benchmarks/results/kernel-floors-<sequence>.json``. Time nothing else
while it runs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from common import ROOT, machine, sequence_path, write_result

sys.path.insert(0, str(ROOT))

FUSED_FRAMES = 30  # frames fused into the volume before timing
TIMED_FRAME = 40  # the frame whose kernels are timed


def _median_ms(fn, reps: int) -> float:
    import numpy as np

    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return round(float(np.median(times)), 2)


def child(sequence: str, threads: int, reps: int) -> dict:
    """One thread count, every resolution (this process only)."""
    import cv2
    import open3d as o3d

    o3d.utility.set_max_threads(threads)
    cv2.setNumThreads(threads)
    import numpy as np

    import slam
    from slam.config import config_from_dict
    from slam.frontend.frame import PreparedFrame
    from slam.mapping.tsdf import TSDFVolume

    seq = slam.open_sequence(sequence_path(sequence))
    gt = seq.ground_truth
    assert gt is not None, f"{sequence} has no ground truth to place its frames with"
    by_time = dict(zip(np.round(gt.timestamps, 6), gt.poses, strict=True))
    frames = [seq[i] for i in range(TIMED_FRAME + 1)]
    out = {}
    for downsample in (1, 2, 4):
        cfg = config_from_dict({"tracking": {"downsample": downsample}})
        vol = TSDFVolume(cfg.mapping, has_color=True)
        poses = [by_time.get(round(f.timestamp, 6)) for f in frames]
        for f, T in zip(frames[:FUSED_FRAMES], poses[:FUSED_FRAMES], strict=True):
            if T is not None:
                vol.integrate(f.depth_m, f.color, f.K, T)
        f, T = frames[TIMED_FRAME], poses[TIMED_FRAME]
        p = PreparedFrame.build(f, cfg.tracking, None)
        w, h = p.size

        def render(p=p, T=T, w=w, h=h, vol=vol):
            return vol.raycast(p.K_track, w, h, T, False, False, frustum_depth_m=p.depth_m)

        target = render().depth_m
        row = {
            "size": f"{w}x{h}",
            "prepare": _median_ms(
                lambda f=f, cfg=cfg: PreparedFrame.build(f, cfg.tracking, None), reps
            ),
            "ray_cast": _median_ms(render, reps),
            "odometry": _median_ms(
                lambda p=p, t=target, c=cfg: p.icp_to(t, np.eye(4), c.tracking), reps
            ),
            "integrate": _median_ms(
                lambda f=f, T=T, vol=vol: vol.integrate(f.depth_m, f.color, f.K, T), reps
            ),
            "blocks": vol.n_blocks,
        }
        out[str(downsample)] = row
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", nargs="?", default="tum-fr1-xyz")
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--child", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.sequence, args.child, args.reps)))
        return
    rows = {}
    for threads in (1, 2):
        cmd = [sys.executable, __file__, args.sequence, "--reps", str(args.reps),
               "--child", str(threads)]  # fmt: skip
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        res = subprocess.run(cmd, capture_output=True, text=True, check=True, env=env)
        rows[str(threads)] = json.loads(res.stdout.strip().splitlines()[-1])
    out = {"sequence": args.sequence, "reps": args.reps, "floors_ms": rows, "machine": machine()}
    path = write_result(f"kernel-floors-{Path(args.sequence).name}", out)
    print(f"wrote {path}")
    for threads, by_res in rows.items():
        for ds, r in by_res.items():
            print(f"threads {threads} downsample {ds}: {r}")


if __name__ == "__main__":
    main()
