"""How far a run's mesh lies from the true surface, on synthetic sequences (their scene.ply).

    python benchmarks/mesh_accuracy.py demo room-hh-s0 wall-x2-s0 --tag new
    python benchmarks/mesh_accuracy.py demo --tree /path/to/old/checkout --tag old

One fresh ``slam run`` process per sequence (default config; ``--tree``: import ``slam`` from
another source tree), then the distance of every mesh vertex to ``scene.ply``, the mesh moved
by the trajectory's SE(3) alignment to the ground truth: median and 90th percentile (mm),
with the run's final ATE. A sequence name is ``demo``, a folder, or a row of the scene
matrix's cache (``room-hh-s0`` for ``~/.cache/rgbd-slam/matrix/room-hh-s0-240-v2``). Writes
benchmarks/results/mesh-accuracy-<tag>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from common import ROOT, machine, sequence_path, write_result

sys.path.insert(0, str(ROOT))

MATRIX_CACHE = Path.home() / ".cache" / "rgbd-slam" / "matrix"


def resolve(name: str) -> Path:
    """A matrix row's cached folder (``room-hh-s0`` -> ``room-hh-s0-240-v2``), else
    :func:`common.sequence_path`."""
    rows = sorted(MATRIX_CACHE.glob(f"{name}-240-v*")) if MATRIX_CACHE.is_dir() else []
    return rows[-1] if rows else sequence_path(name)


def mesh_distances_mm(run_dir: Path, seq: Path) -> np.ndarray:
    """Every mesh vertex's distance (mm) to the true surface, the mesh aligned as the
    trajectory is."""
    import open3d as o3d

    from slam.run_folder import RunFolder
    from slam.tools.eval import sequence_ground_truth
    from slam.tools.eval_metrics import align_trajectory

    est = RunFolder(run_dir).trajectory()
    gt, _ = sequence_ground_truth(seq)
    T = align_trajectory(gt, est).poses[0] @ np.linalg.inv(est.poses[0])
    mesh = o3d.io.read_triangle_mesh(str(run_dir / "mesh.ply")).transform(T)
    scene = o3d.t.geometry.RaycastingScene()
    truth = o3d.io.read_triangle_mesh(str(seq / "scene.ply"))
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(truth))
    pts = o3d.core.Tensor(np.asarray(mesh.vertices, np.float32))
    return scene.compute_distance(pts).numpy() * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequences", nargs="+")
    ap.add_argument("--tree", default=str(ROOT), help="the source tree to run")
    ap.add_argument("--tag", default="", help="the result's name")
    args = ap.parse_args()
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.sequences:
            seq = resolve(name)
            run = Path(tmp) / name
            env = dict(os.environ, PYTHONPATH=args.tree)
            cmd = [sys.executable, "-m", "slam", "run", str(seq), "--out", str(run), "-q"]
            subprocess.run(cmd, check=True, env=env, cwd=args.tree)
            d = mesh_distances_mm(run, seq)
            m = json.loads((run / "metrics.json").read_text())
            rows[name] = {
                "median_mm": round(float(np.median(d)), 3),
                "p90_mm": round(float(np.percentile(d, 90)), 3),
                "ate_rmse_m": m.get("ate_rmse_m"),
                "submaps": m.get("submaps"),
            }
            print(name, rows[name], flush=True)
    out = write_result(
        f"mesh-accuracy-{args.tag}", {"tree": args.tree, "rows": rows, "machine": machine()}
    )
    print(out)


if __name__ == "__main__":
    main()
