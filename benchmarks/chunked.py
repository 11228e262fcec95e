"""A parallel run (``slam run SEQ --workers N``) against the sequential run of the same
sequence: accuracy (final and odometry ATE, and for synthetic sequences the mesh's median
distance to the true surface) and wall time, in alternating fresh processes (nothing else
should run meanwhile).

    python benchmarks/chunked.py tum-fr1-xyz demo --workers 1 2 4
    python benchmarks/chunked.py tum-fr1-xyz --workers 1 2 --repeats 3 --tag speed
    python benchmarks/chunked.py tum-fr1-xyz --workers 2 --threads 2 --tag threads2
    python benchmarks/chunked.py room-1200 room-2400 --workers 1 4 --tag long   # the join's growth

``--workers 1`` is the ordinary sequential run. The wall time is the whole command's
(``python -m slam run``: start-up, tracking, join, writing the run folder). Writes
benchmarks/results/chunked-<tag>.json and prints a table.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import ROOT, machine, sequence_path, write_result

_CHILD = """
import logging, sys
from slam.api import run_sequence
logging.basicConfig(level=logging.WARNING)
seq, out, workers, threads, executor = sys.argv[1:6]
run_sequence(seq, out, workers=int(workers), worker_threads=int(threads) or None,
             executor=executor)
"""


def mesh_distance_mm(run_dir: Path, seq: Path) -> float | None:
    """Median distance (mm) of the mesh's vertices to the true surface (``scene.ply`` of a
    synthetic sequence), the mesh moved by the trajectory's SE(3) alignment to ground truth."""
    scene = seq / "scene.ply"
    if not scene.is_file() or not (run_dir / "mesh.ply").is_file():
        return None
    import numpy as np
    import open3d as o3d

    from slam.run_folder import RunFolder
    from slam.tools.eval import sequence_ground_truth
    from slam.tools.eval_metrics import align_trajectory

    est = RunFolder(run_dir).trajectory()
    gt, _ = sequence_ground_truth(seq)
    aligned = align_trajectory(gt, est)
    T = aligned.poses[0] @ np.linalg.inv(est.poses[0])
    mesh = o3d.io.read_triangle_mesh(str(run_dir / "mesh.ply")).transform(T)
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(o3d.io.read_triangle_mesh(str(scene))))
    pts = o3d.core.Tensor(np.asarray(mesh.vertices, np.float32))
    return float(np.median(rc.compute_distance(pts).numpy()) * 1e3)


def resolve(name: str) -> Path:
    """``room-N``: a synthetic room at 320x240 whose camera turns N / 300 times in N frames (the
    demo's motion per frame, revisiting every 300 frames), generated once into the cache;
    anything else as :func:`common.sequence_path`."""
    if name.startswith("room-") and name[5:].isdigit():
        from slam.synthetic import SynthConfig, generate_sequence
        from slam.synthetic.writer import is_complete

        n = int(name[5:])
        out = Path.home() / ".cache" / "rgbd-slam" / "chunked" / name
        if not is_complete(out):
            cfg = SynthConfig.half_resolution(frames=n, loop=True, seed=3, speed=n / 300)
            generate_sequence(out, cfg)
        return out
    return sequence_path(name)


def one_run(seq: Path, workers: int, threads: int, executor: str) -> dict:
    out = Path(tempfile.mkdtemp(prefix="chunked-")) / "run"
    t0 = time.perf_counter()
    subprocess.run(
        [sys.executable, "-c", _CHILD, str(seq), str(out), str(workers), str(threads), executor],
        check=True, cwd=ROOT,
    )  # fmt: skip
    wall = time.perf_counter() - t0
    m = json.loads((out / "metrics.json").read_text())
    row = {
        "workers": workers, "wall_s": round(wall, 2), "seconds": m["seconds"],
        "ate_rmse_m": m.get("ate_rmse_m"), "ate_rmse_odometry_m": m.get("ate_rmse_odometry_m"),
        "loops_accepted": m["loops_accepted"], "keyframes": m["keyframes"],
        "peak_rss_mb": m["peak_rss_mb"],
        "map_segments": len(m["map_segments"]), "mesh_median_mm": mesh_distance_mm(out, seq),
    }  # fmt: skip
    if (out / "chunks.json").is_file():
        c = json.loads((out / "chunks.json").read_text())
        row["chunk_seconds"] = c["seconds"]
        row["worker_seconds"] = [x["worker"]["seconds"] for x in c["chunks"]]
        row["joins"] = [
            {k: j[k] for k in ("how", "overlap_fit", "verification")} for j in c["joins"]
        ]
    shutil.rmtree(out.parent, ignore_errors=True)
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "sequences", nargs="+", help="demo, demo-drift, or folders under ../shared/datasets"
    )
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument(
        "--threads", type=int, default=0, help="kernel threads per worker (0: cores / workers)"
    )
    p.add_argument("--executor", default="auto", choices=["auto", "ray", "processes"])
    p.add_argument("--tag", default="accuracy")
    a = p.parse_args()
    rows = []
    for name in a.sequences:
        seq = resolve(name)
        for r in range(a.repeats):
            for w in a.workers:
                row = {"sequence": name, "repeat": r, **one_run(seq, w, a.threads, a.executor)}
                print(json.dumps(row), flush=True)
                rows.append(row)
    summary = {}
    for name in a.sequences:
        base = [x["wall_s"] for x in rows if x["sequence"] == name and x["workers"] == 1]
        for w in a.workers:
            mine = [x for x in rows if x["sequence"] == name and x["workers"] == w]
            s = {
                "wall_s_median": statistics.median(x["wall_s"] for x in mine),
                "ate_rmse_m": [x["ate_rmse_m"] for x in mine],
                "mesh_median_mm": [x["mesh_median_mm"] for x in mine],
            }
            if base and w != 1:  # ratios of alternating pairs (repeat r of each arm)
                s["wall_ratio_median"] = statistics.median(
                    x["wall_s"] / b for x, b in zip(mine, base)
                )
            summary[f"{name} x{w}"] = s
            print(f"{name:16s} workers {w}: {json.dumps(s)}")
    out = write_result(f"chunked-{a.tag}", {
        "command": " ".join(["python", "benchmarks/chunked.py", *sys.argv[1:]]),
        "machine": machine(), "runs": rows, "summary": summary,
    })  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
