"""Is the model's pull on a frame the same from one view to the next? (issue 20, session 38)

    python benchmarks/first_view_pull.py

A TSDF renders its first view a little off the depth it came from (the ray-caster's voxel
pattern), and ICP follows that along the directions the view constrains weakly:
``self_render_bias.py`` measures it (13.6 mm on a noisy desk at 1 cm voxels). The next frames
take that pull as motion: the desks' worst step is their first. Try: fuse the first view
again at the pose its own pull puts it the other way, so that the model renders it where it
was seen, and ask whether the next view (frame 1, from its true pose) is then pulled less.

For each scene kind (Kinect-like noise, 1 cm voxels): frame 0 fused at its true pose, its
pull (projective point-to-plane ICP of its depth against the rendering, from the identity);
frame 0 fused again alone at ``T0 @ inv(pull)`` and its pull measured again; frame 1's pull
against each model, from frame 1's true pose. Writes ``benchmarks/results/first-view-pull.json``.
"""

from __future__ import annotations

import numpy as np
from common import machine, write_result
from self_render_bias import icp_pull

from slam.config import MappingConfig
from slam.geometry import inv_T
from slam.mapping.tsdf import TSDFVolume
from slam.synthetic import SynthConfig, build_scene, make_trajectory, render_frame


def pull(volume: TSDFVolume, depth_m: np.ndarray, K: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Where the rendering from ``T`` puts the view, ``T_cam_render``."""
    h, w = depth_m.shape
    render = volume.raycast(K, w, h, T, False, False, frustum_depth_m=depth_m)
    return icp_pull(depth_m, render.depth_m, K)


def fused(depth_m: np.ndarray, color: np.ndarray, K: np.ndarray, T: np.ndarray) -> TSDFVolume:
    volume = TSDFVolume(MappingConfig())
    volume.integrate(depth_m, color, K, T)
    return volume


def mm(T: np.ndarray) -> float:
    return round(float(np.linalg.norm(T[:3, 3])) * 1e3, 2)


def main() -> None:
    rows = []
    for kind in ("desk", "room", "wall", "corridor", "hall"):
        cfg = SynthConfig(frames=240, scene=kind, seed=0, loop=kind == "room", noise=True)
        scene, traj = build_scene(cfg), make_trajectory(cfg)
        K = cfg.calibration().K
        rng = np.random.default_rng(0)
        (c0, d0), (_, d1) = (render_frame(scene, traj.poses[i], cfg, rng) for i in range(2))
        T0, T1 = traj.poses[0], traj.poses[1]
        plain = fused(d0, c0, K, T0)
        pull0 = pull(plain, d0, K, T0)
        removed = fused(d0, c0, K, T0 @ inv_T(pull0))
        row = {
            "kind": kind,
            "frame0_pull_mm": mm(pull0),
            "frame0_pull_after_removal_mm": mm(pull(removed, d0, K, T0)),
            "frame1_pull_mm": mm(pull(plain, d1, K, T1)),
            "frame1_pull_after_removal_mm": mm(pull(removed, d1, K, T1)),
        }
        rows.append(row)
        print(
            f"{kind:8s} frame 0 pulled {row['frame0_pull_mm']:6.1f} mm, "
            f"{row['frame0_pull_after_removal_mm']:6.1f} after removal; frame 1 "
            f"{row['frame1_pull_mm']:6.1f} mm, {row['frame1_pull_after_removal_mm']:6.1f}"
        )
    print(write_result("first-view-pull", {"machine": machine(), "rows": rows}))


if __name__ == "__main__":
    main()
