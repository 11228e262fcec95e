"""How far the TSDF model alone pulls ICP: a view aligned to the ray-cast of its own fusion.

    python benchmarks/self_render_bias.py

For synthetic views of the scene kinds (exact depth and Kinect-like noise), fuse one view into a
fresh TSDF volume at its true pose, ray-cast the volume from that same pose and align the view's
depth to the rendering with projective point-to-plane ICP from the identity. Every millimetre
ICP moves is the model's own bias (its voxel discretisation and interpolation, amplified along
the directions the view's geometry constrains weakly): the floor of frame-to-model tracking
right after a model is started. Also with the depth edges of both images masked (a rendering's
silhouettes are where a TSDF is least like its depth). Voxel sizes 1 cm (the default) and 5 mm.
Writes ``benchmarks/results/self-render-bias.json``.
"""

from __future__ import annotations

import cv2
import numpy as np
from common import machine, write_result

from slam.config import MappingConfig
from slam.frontend.icp import projective_icp
from slam.mapping.tsdf import TSDFVolume
from slam.synthetic import SynthConfig, build_scene, make_trajectory, render_frame


def depth_edges(depth_m: np.ndarray, jump_m: float, radius_px: int) -> np.ndarray:
    """Pixels within ``radius_px`` of a 3x3 depth range above ``jump_m`` or of a hole."""
    valid = depth_m > 0
    near = cv2.erode(np.where(valid, depth_m, 1e3).astype(np.float32), np.ones((3, 3)))
    far = cv2.dilate(np.where(valid, depth_m, 0).astype(np.float32), np.ones((3, 3)))
    edge = ((far - near) > jump_m) | ~valid
    size = 2 * radius_px + 1
    return cv2.dilate(edge.astype(np.uint8), np.ones((size, size), np.uint8)) > 0


def icp_pull(source: np.ndarray, target: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``T_target_source`` by projective point-to-plane ICP from the identity: how far the
    ``target`` rendering pulls the ``source`` depth (also used by ``first_view_pull.py``)."""
    icp = projective_icp(source, target, K, np.eye(4), [10, 10, 10], 4.0, 0.03, 0.02)
    return icp.T_target_source


def shift_mm(source: np.ndarray, target: np.ndarray, K: np.ndarray) -> list[float]:
    return [round(float(v) * 1e3, 2) for v in icp_pull(source, target, K)[:3, 3]]


def main() -> None:
    rows = []
    for kind in ("desk", "room", "wall", "corridor"):
        for noise in (False, True):
            cfg = SynthConfig(frames=240, scene=kind, seed=0, loop=kind == "room", noise=noise)
            scene, traj = build_scene(cfg), make_trajectory(cfg)
            K = cfg.calibration().K
            color, depth = render_frame(scene, traj.poses[0], cfg, np.random.default_rng(0))
            for voxel in (0.01, 0.005):
                vol = TSDFVolume(MappingConfig(voxel_size_m=voxel))
                vol.integrate(depth, color, K, traj.poses[0])
                h, w = depth.shape
                render = vol.raycast(K, w, h, traj.poses[0], False, False, frustum_depth_m=depth)
                edges = depth_edges(render.depth_m, 0.04, 2) | depth_edges(depth, 0.04, 2)
                row = {
                    "kind": kind,
                    "noise": noise,
                    "voxel_m": voxel,
                    "icp_shift_mm": shift_mm(depth, render.depth_m, K),
                    "icp_shift_edges_masked_mm": shift_mm(
                        depth, np.where(edges, 0, render.depth_m), K
                    ),
                }
                rows.append(row)
                print(
                    f"{kind:8s} {'noisy' if noise else 'exact'} voxel {voxel * 1e3:.0f} mm: "
                    f"ICP moves {np.linalg.norm(row['icp_shift_mm']):5.2f} mm "
                    f"{row['icp_shift_mm']}, edges masked "
                    f"{np.linalg.norm(row['icp_shift_edges_masked_mm']):5.2f} mm"
                )
    out = write_result("self-render-bias", {"machine": machine(), "rows": rows})
    print(out)


if __name__ == "__main__":
    main()
