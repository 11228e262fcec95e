"""Bundle adjustment: time and memory over 50/100/200 keyframes (synthetic and real), and whether
a global BA from the pose-graph solution improves the keyframes (and, by elastic correction,
every frame) against ground truth.

    python benchmarks/ba_scaling.py                       # everything (real runs are cached)
    python benchmarks/ba_scaling.py --skip-real --skip-accuracy
    python benchmarks/ba_scaling.py --skip-synthetic --skip-real --accuracy demo-drift

Real keyframes come from a run of ``slam.Slam`` over the sequence (default config, or keyframes
every 3 cm for the 200-keyframe scaling case), cached in ``<slam cache>/ba-bench/``. Tracks are
built offline from the run's final pose-graph poses in keyframe order, then merged across the
run's accepted loops (in a run they are built as keyframes arrive, from the poses of the time).
Each timing runs in a fresh process so its peak memory is its own. Writes
benchmarks/results/ba-scaling.json.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import multiprocessing as mp
import pickle
import resource
import time
from pathlib import Path
from typing import Any

import numpy as np
from common import machine, sequence_path, write_result

log = logging.getLogger("ba_scaling")

#: keyframes every 3 cm / 4 deg: tum-fr1-xyz then has over 200 keyframes
DENSE = {"tracking": {"keyframe_translation_m": 0.03, "keyframe_rotation_deg": 4.0}}


def _cache_dir() -> Path:
    from slam.demo import cache_dir

    d = cache_dir() / "ba-bench"
    d.mkdir(parents=True, exist_ok=True)
    return d


def collect(name: str, overrides: dict | None = None) -> Path:
    """Run slam.Slam over a sequence; pickle its keyframes, pose graph, loops, frame rows and
    ground truth (cached by sequence and config overrides). Returns the pickle's path."""
    import slam
    from slam.config import config_from_dict

    overrides = overrides or {}
    key = hashlib.sha1(json.dumps(overrides, sort_keys=True).encode()).hexdigest()[:8]
    out = _cache_dir() / f"{name}-{key}.pkl"
    if out.is_file():
        return out
    seq = slam.open_sequence(sequence_path(name))
    cfg = config_from_dict({"output": {"save_mesh": False}, **overrides})
    cfg.ba.enabled = False  # the pose-graph-only run BA starts from
    system = slam.Slam(cfg, has_color=seq.has_color)
    t0 = time.perf_counter()
    for i in range(len(seq)):
        system.step(seq[i])
    log.info("%s: %d frames in %.0f s", name, len(seq), time.perf_counter() - t0)
    gt = seq.ground_truth
    data = {
        "name": name,
        "overrides": overrides,
        "color_registered": getattr(seq, "color_registered", True),
        "keyframes": system.tracker.state.keyframes,
        "nodes": {k: v.copy() for k, v in system.closer.graph.nodes.items()},
        "edges": system.closer.graph.edges,
        "records": system.closer.records,
        "gt": None if gt is None else (gt.timestamps, gt.poses),
        "downsample": cfg.tracking.downsample,
        "loop_kernel_width": cfg.backend.loop_kernel_width,
        "rows": dict(system.rows.__dict__),
        "kf_rows": list(system.kf_rows),
    }
    with open(out, "wb") as f:
        pickle.dump(data, f)
    return out


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2**20


def build_adjuster(data: dict, n_keyframes: int | None = None):
    """A BundleAdjuster with the run's tracks (first ``n_keyframes`` keyframes), merged across
    the run's accepted loops among them; returns (adjuster, ms per keyframe for tracks)."""
    from slam.backend.adjuster import BundleAdjuster
    from slam.config import BAConfig

    kfs = data["keyframes"][:n_keyframes]
    ids = {kf.id for kf in kfs}
    ba = BundleAdjuster(
        BAConfig(),
        data["downsample"],
        color_registered=data.get("color_registered", True),
        loop_kernel_width=data["loop_kernel_width"],
    )
    nodes = data["nodes"]
    t0 = time.perf_counter()
    for kf in kfs:
        ba.add_keyframe(kf, nodes)
    for r in data["records"]:
        if r["accepted"] and r["query_kf"] in ids and r["match_kf"] in ids:
            ba.merge_loop(r["query_kf"], r["match_kf"], np.array(r["T_match_query"]), nodes)
    return ba, (time.perf_counter() - t0) * 1e3 / max(len(kfs), 1)


def _time_real(path: str, n: int) -> dict[str, Any]:
    with open(path, "rb") as f:
        data = pickle.load(f)
    ba, tracks_ms = build_adjuster(data, n)
    ids = set(ba.landmarks.keyframes)
    poses = {k: T for k, T in data["nodes"].items() if k in ids}
    edges = [e for e in data["edges"] if e.i in ids and e.j in ids]
    rss0 = _rss_mb()
    t0, c0 = time.perf_counter(), time.process_time()
    res = ba.optimise(poses, edges)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {
        "keyframes": len(ids),
        "tracks_ms_per_keyframe": round(tracks_ms, 2),
        "seconds": round(wall, 3),
        "cpu_seconds": round(cpu, 3),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "rss_before_mb": round(rss0, 1),
        **{k: v for k, v in res.summary().items() if k != "ms"},
    }


def _time_synthetic(n: int) -> dict[str, Any]:
    from slam.backend.bundle_adjustment import bundle_adjust
    from slam.config import BAConfig
    from slam.synthetic.ba_problem import make_problem, pose_errors

    # keyframes 3.6 deg apart on the circle (200: two laps, the second revisiting the first),
    # 300 observations each, 5% outliers, poses perturbed by 3 cm / 2 deg
    s = make_problem(
        n_keyframes=n,
        n_points=100 * n,
        laps=n / 100,
        max_observations=300,
        depth_sigma=0.003,
        outlier_fraction=0.05,
        seed=0,
    )
    cfg = BAConfig(pose_graph_weight=0.0, depth_sigma_m=0.003)
    rss0 = _rss_mb()
    t0, c0 = time.perf_counter(), time.process_time()
    res = bundle_adjust(s.problem, s.poses_init, cfg)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    trans, rot = pose_errors(res.poses, s.poses_true)
    return {
        "keyframes": n,
        "seconds": round(wall, 3),
        "cpu_seconds": round(cpu, 3),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "rss_before_mb": round(rss0, 1),
        "pose_error_max_mm": round(1e3 * float(trans.max()), 3),
        "pose_error_max_deg": round(float(rot.max()), 4),
        **{k: v for k, v in res.summary().items() if k != "ms"},
    }


def _in_child(fn, *args) -> dict[str, Any]:
    with mp.get_context("spawn").Pool(1) as pool:
        return pool.apply(fn, args)


def accuracy(name: str) -> dict[str, Any]:
    """Global BA from the pose-graph keyframes of a default run: keyframe ATE and the ATE of
    every frame after elastic correction (as the run's final trajectory is made), pose graph
    alone vs BA."""
    from slam.backend.finalise import elastic_correction
    from slam.tools import eval as slam_eval
    from slam.trajectory import Trajectory

    with open(collect(name), "rb") as f:
        data = pickle.load(f)
    kfs = data["keyframes"]
    ba, tracks_ms = build_adjuster(data)
    t0 = time.perf_counter()
    res = ba.optimise(data["nodes"], data["edges"])
    ms = (time.perf_counter() - t0) * 1e3
    out: dict[str, Any] = {
        "keyframes": len(kfs),
        "loops_accepted": sum(r["accepted"] for r in data["records"]),
        "tracks": ba.landmarks.stats(),
        "tracks_ms_per_keyframe": round(tracks_ms, 2),
        "ba": {**res.summary(), "ms": round(ms, 1)},
    }
    if data["gt"] is None or res.skipped:
        return out
    gt = Trajectory(*data["gt"])
    stamps = np.array([kf.timestamp for kf in kfs])

    def ate(traj: Trajectory) -> float:
        return round(float(slam_eval.ate(gt, traj, max_diff=0.02).rmse), 5)

    odo = [kf.T_world_cam for kf in kfs]
    pg = [data["nodes"][kf.id] for kf in kfs]
    adj = [res.poses[kf.id] for kf in kfs]
    rows = data["rows"]
    odo_all = np.stack(rows["pose"])
    frames = np.array(rows["timestamp"])

    def frames_ate(corrected: list[np.ndarray]) -> float:
        poses = elastic_correction(odo_all, data["kf_rows"], odo, corrected, np.array(rows["run"]))
        return ate(Trajectory(frames, poses))

    out["keyframe_ate_m"] = {
        "odometry": ate(Trajectory(stamps, np.stack(odo))),
        "pose_graph": ate(Trajectory(stamps, np.stack(pg))),
        "ba": ate(Trajectory(stamps, np.stack(adj))),
    }
    out["frame_ate_m"] = {
        "odometry": ate(Trajectory(frames, odo_all)),
        "pose_graph": frames_ate(pg),
        "ba": frames_ate(adj),
    }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[50, 100, 200])
    parser.add_argument("--real", default="tum-fr1-xyz", help="sequence for the real scaling")
    parser.add_argument(
        "--accuracy",
        nargs="*",
        default=["tum-fr1-xyz", "7scenes-300", "demo", "demo-drift", "tum-fr3-cabinet-kf58"],
    )
    parser.add_argument("--skip-synthetic", action="store_true")
    parser.add_argument("--skip-real", action="store_true")
    parser.add_argument("--skip-accuracy", action="store_true")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    logging.getLogger("slam").setLevel(logging.WARNING)
    result: dict[str, Any] = {"machine": machine()}
    if not args.skip_synthetic:
        result["synthetic"] = [_in_child(_time_synthetic, n) for n in args.sizes]
        for r in result["synthetic"]:
            log.info("synthetic %s", r)
    if not args.skip_real:
        path = collect(args.real, DENSE)
        with open(path, "rb") as f:
            n_kf = len(pickle.load(f)["keyframes"])
        sizes = [n for n in args.sizes if n <= n_kf]
        result["real"] = {
            "sequence": args.real,
            "config": DENSE,
            "keyframes_available": n_kf,
            "runs": [_in_child(_time_real, str(path), n) for n in sizes],
        }
        for r in result["real"]["runs"]:
            log.info("real %s", r)
    if not args.skip_accuracy:
        result["accuracy"] = {name: accuracy(name) for name in args.accuracy}
        for name, r in result["accuracy"].items():
            log.info("accuracy %s: %s", name, r)
    out = write_result("ba-scaling", result)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
