"""How close the fused surface is to the truth, with and without noise-weighted fusion.

    python benchmarks/fusion_weighting.py [--frames 40] [--stride 3] [--kinds corridor,room]

For each synthetic scene kind (Kinect-like depth noise and quantisation), frames 0, stride, ...
are fused at their true poses into a fresh TSDF volume (default mapping config, 640x480), once
with each observation counted as 1 (the default) and once weighted by its depth's noise
(``mapping.fusion_noise_weighting``). The volume is then ray-cast at 320x240 from the true pose
of the next frame, with the ordinary and the refined ray-cast (``mapping.raycast_refine``), and
compared with that frame's exact depth: median and p90 of the absolute error (mm) over pixels
with both. The fused surface's error, not tracking: every pose is exact.
Writes ``benchmarks/results/fusion-weighting-<frames>.json``.
"""

from __future__ import annotations

import argparse

import numpy as np
from common import machine, write_result

from slam.config import MappingConfig
from slam.mapping.tsdf import TSDFVolume
from slam.synthetic import SynthConfig, build_scene, make_trajectory, render_frame

KINDS = ("desk", "room", "wall", "corridor", "hall")


def error_mm(render: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    ok = (render > 0) & (truth > 0)
    e = np.abs(render[ok] - truth[ok]) * 1e3
    return round(float(np.median(e)), 2), round(float(np.percentile(e, 90)), 2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40, help="fuse frames 0 .. frames-1")
    ap.add_argument("--stride", type=int, default=3)
    ap.add_argument("--kinds", default=",".join(KINDS))
    args = ap.parse_args()
    rows = []
    for kind in args.kinds.split(","):
        cfg = SynthConfig(frames=240, scene=kind, seed=0, loop=kind == "room")
        exact_cfg = SynthConfig.half_resolution(
            frames=240, scene=kind, seed=0, loop=kind == "room", noise=False
        )
        scene, traj = build_scene(cfg), make_trajectory(cfg)
        K = cfg.calibration().K
        rng = np.random.default_rng(0)
        poses = [traj.poses[i] for i in range(0, args.frames, args.stride)]
        frames = [render_frame(scene, T, cfg, rng) for T in poses]
        T_view = traj.poses[args.frames]
        _, truth = render_frame(scene, T_view, exact_cfg)
        K_half = exact_cfg.calibration().K
        row: dict = {"kind": kind, "fused_frames": len(frames)}
        for weighted in (False, True):
            for refine in (False, True):
                vol = TSDFVolume(
                    MappingConfig(fusion_noise_weighting=weighted, raycast_refine=refine)
                )
                for (color, depth), T in zip(frames, poses):
                    vol.integrate(depth, color, K, T)
                r = vol.raycast(K_half, 320, 240, T_view, False, False)
                key = ("weighted" if weighted else "counted") + ("_refined" if refine else "")
                row[key] = error_mm(r.depth_m, truth)
        rows.append(row)
        print(row, flush=True)
    out = write_result(f"fusion-weighting-{args.frames}", {"machine": machine(), "args": vars(args), "rows": rows})
    print(out)


if __name__ == "__main__":
    main()
