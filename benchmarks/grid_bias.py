"""How a TSDF surface's rendered depth depends on how it lies in the voxel grid.

    python benchmarks/grid_bias.py            # writes benchmarks/results/grid-bias.json

A box room (4 x 3 x 2.5 m) is rendered exactly from 12 views, fused into a TSDFVolume (default
mapping config) with the whole scene turned by a rotation R relative to the grid, then
ray-cast from 4 of the views; the mean rendered-minus-true depth is the bias. R = identity
(walls along the grid's axes) and 5 random turns. A bias that changes with R is what two
submaps with differently turned grids disagree by (docs/archive/journal.md, issue 20 third part).
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
from tests.conftest import look_at, render_depth  # noqa: E402  (the tests' exact renderer)

K = np.array([[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1]])
W, H = 320, 240


def main() -> None:
    box = o3d.geometry.TriangleMesh.create_box(4, 3, 2.5).translate([-2, -1.5, -1.25])
    poses = [
        look_at(
            np.array([0.3 * np.cos(a), 0.2 * np.sin(a), 0.1]),
            np.array([2 * np.cos(a + 1), 1.5 * np.sin(a + 1), 0.0]),
        )
        for a in np.linspace(0, 1.0, 12)
    ]
    depths = [render_depth(box, K, W, H, T) for T in poses]
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
