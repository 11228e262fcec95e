"""How a TSDF surface's rendered depth depends on how it lies in the voxel grid.

    python benchmarks/grid_bias.py            # writes benchmarks/results/grid-bias.json

A box room (4 x 3 x 2.5 m) is rendered exactly from 12 views, fused into a TSDFVolume (default
mapping config) with the whole scene turned by a rotation R relative to the grid, then
ray-cast from 4 of the views; the mean rendered-minus-true depth is the bias. R = identity
(walls along the grid's axes) and 5 random turns. A bias that changes with R is what two
submaps with differently turned grids disagree by (docs/benchmarks.md, issue 20 third part).
"""

from __future__ import annotations

import sys

import numpy as np
import open3d as o3d
from common import ROOT, machine, write_result

sys.path.insert(0, str(ROOT))

from slam.config import MappingConfig  # noqa: E402
from slam.geometry import exp_se3  # noqa: E402
from slam.mapping.tsdf import TSDFVolume  # noqa: E402

K = np.array([[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1]])
W, H = 320, 240


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world pose at ``eye`` looking at ``target`` (y down, z forward)."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(np.array([0.0, 0.0, 1.0]), z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T


def render_depth(scene: o3d.t.geometry.RaycastingScene, T_world_cam: np.ndarray) -> np.ndarray:
    """Exact z-depth (0: no surface): rays whose camera-frame direction has z = 1."""
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1)
    d_world = d_cam @ T_world_cam[:3, :3].T
    origins = np.broadcast_to(T_world_cam[:3, 3], d_world.shape)
    rays = np.concatenate([origins, d_world], -1).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return np.where(np.isfinite(t), t, 0.0).astype(np.float32)


def main() -> None:
    box = o3d.geometry.TriangleMesh.create_box(4, 3, 2.5).translate([-2, -1.5, -1.25])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(box))
    poses = [
        look_at(
            np.array([0.3 * np.cos(a), 0.2 * np.sin(a), 0.1]),
            np.array([2 * np.cos(a + 1), 1.5 * np.sin(a + 1), 0.0]),
        )
        for a in np.linspace(0, 1.0, 12)
    ]
    depths = [render_depth(scene, T) for T in poses]
    rng = np.random.default_rng(0)
    rows = []
    for trial in range(6):
        R = np.eye(4) if trial == 0 else exp_se3(np.r_[0, 0, 0, rng.normal(size=3) * 0.6])
        vol = TSDFVolume(MappingConfig(), has_color=False)
        for T, d in zip(poses, depths):
            vol.integrate(d, None, K, R @ T)  # the grid turned by R against the scene
        bias = []
        for T, d in list(zip(poses, depths))[1::3]:  # views 1, 4, 7, 10
            r = vol.render(K, W, H, R @ T, with_normals=False)  # all blocks
            ok = (d > 0) & (r.depth_m > 0)
            bias.append(float(np.mean(r.depth_m[ok] - d[ok])))
        rows.append({"turn": trial, "mean_depth_error_mm": [round(b * 1e3, 3) for b in bias]})
        print(f"turn {trial}: mean rendered - true depth (mm) {np.round(np.array(bias) * 1e3, 2)}")
    out = write_result("grid-bias", {"rows": rows, "machine": machine()})
    print(f"written: {out}")


if __name__ == "__main__":
    main()
