"""Does colour agree with depth where depth is sure? Consecutive frames aligned from their true
step by depth alone and by colour leading, and how far apart the two land along the directions
the frame's depth constrains well.

    python benchmarks/colour_agreement.py                         # real rows, x2 kinds, -c15 rows
    python benchmarks/colour_agreement.py --only tum-fr1-xyz,room-x2-s0 --o3d-hybrid
    python benchmarks/colour_agreement.py --sequences demo,demo-drift --only none

Each frame ``i`` (every ``--every``) is aligned to frame ``i - 1`` from the ground-truth step
with the default config's alignments: ``PreparedFrame.icp_to`` (depth alone, Open3D's ICP) and
``PreparedFrame.joint_to`` at photometric weight 10 (colour leads; both colour cameras placed
along the true step, as ``colour_depth_pairs.py`` places them). Their difference, a twist with
rotations counted as the motion they give at the scene's median depth, is split along the
eigen-directions of frame ``i``'s own point-to-plane information
(``weighted_icp.depth_information``, the matrix behind the constraint ratio):

- ``strong``: the directions constrained within ``--strong`` times the best one (standard
  deviations). There depth is sure of itself, and a colour estimate that lands far away is
  biased against the geometry: colour that will hurt wherever it joins depth.
- ``weak``: the rest, where depth may slide and colour is meant to hold.

Both alignments' translation errors against the ground truth are reported too (they include the
ground truth's own error). ``--o3d-hybrid`` adds Open3D's hybrid RGB-D odometry
(``t.pipelines.odometry``, photometric + point-to-plane in C++, the same iterations) as a third
alignment, with the milliseconds each alignment takes (meaningful only with nothing else
running). Writes ``results/colour-agreement[-TAG].json`` and prints a table.
"""

from __future__ import annotations

import argparse
import logging
import time

import cv2
import numpy as np
import open3d as o3d
from colour_depth_pairs import _align, registered_sequence
from common import machine, sequence_path, write_result
from matrix import KINDS, UNSYNCED, Row, real_rows, synthetic_rows

from slam.camera import scale_intrinsics
from slam.frontend.frame import depth_noise
from slam.frontend.weighted_icp import depth_information, metric_eigen
from slam.geometry import inv_T, log_se3, translation_norm

WEIGHT = 10.0
ALIGNMENTS = ("depth", "colour")


def _o3d_rgbd(p) -> o3d.t.geometry.RGBDImage:
    """A prepared frame as Open3D's RGB-D image at tracking resolution (colour in [0, 1])."""
    d = np.ascontiguousarray(p.depth_m, np.float32)
    c = cv2.resize(p.frame.color, d.shape[::-1], interpolation=cv2.INTER_AREA)
    c = np.ascontiguousarray(c, np.float32) / 255.0
    return o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(c), o3d.t.geometry.Image(d[..., None]))


def _o3d_hybrid(pa, pb, T_init: np.ndarray, cfg) -> np.ndarray:
    """``T_a_b`` by Open3D's hybrid odometry, with tracking's iterations per level."""
    od = o3d.t.pipelines.odometry
    criteria = [od.OdometryConvergenceCriteria(n) for n in cfg.tracking.iterations]
    result = od.rgbd_odometry_multi_scale(
        _o3d_rgbd(pb), _o3d_rgbd(pa), o3d.core.Tensor(pb.K_track.astype(np.float64)),
        o3d.core.Tensor(T_init), 1.0, float(cfg.tracking.depth_max_m), criteria,
        od.Method.Hybrid,
    )  # fmt: skip
    return result.transformation.numpy()


def _split(difference: np.ndarray, p, cfg, strong_ratio: float) -> tuple[float, float] | None:
    """``difference`` (a 4x4 motion) along frame ``p``'s strong and weak depth directions, mm
    (rotations as motion at the median depth); None when its depth has no information."""
    level = min(1, len(p.pyramid) - 1)  # where tracking measures its constraint ratio
    K = scale_intrinsics(p.K_track, 2**level)
    info = depth_information(p.pyramid[level], K, p.icp_depth_max_m, depth_noise(cfg.tracking))
    if info is None:
        return None
    s, vals, vecs = metric_eigen(*info)
    along = vecs.T @ (log_se3(difference) / s)
    std_ratio = np.sqrt(vals[-1] / np.maximum(vals, 1e-30))
    strong = std_ratio < strong_ratio
    return float(np.linalg.norm(along[strong])) * 1e3, float(np.linalg.norm(along[~strong])) * 1e3


def agreement(path, every: int, strong_ratio: float, hybrid: bool) -> dict[str, np.ndarray] | None:
    """Per frame (every ``every``-th): the constraint ratio, colour's distance from depth along
    the strong and weak directions (mm), each alignment's error (mm) against the true step and
    its time (ms). None when colour is not registered to depth."""
    opened = registered_sequence(path)
    if opened is None:
        return None
    cfg, seq, poses, tracker = opened
    levels = len(cfg.tracking.iterations)
    names = ALIGNMENTS + (("o3d_hybrid",) if hybrid else ())
    out: dict[str, list[float]] = {"ratio": [], "strong": [], "weak": []}
    out.update({f"{k}_err": [] for k in names} | {f"{k}_ms": [] for k in names})
    for i in range(max(every, 1), len(seq), every):
        stamps = [round(seq.timestamp(k), 6) for k in (i - 1, i)]
        if any(t not in poses for t in stamps):
            continue
        frames = [seq[i - 1], seq[i]]
        prepared = [tracker.prepare(f) for f in frames]
        for p in prepared:
            p.photometric_image(levels)
        step = inv_T(poses[stamps[0]]) @ poses[stamps[1]]
        found, ms = {}, {}
        for name in names:
            t0 = time.perf_counter()
            if name == "o3d_hybrid":
                found[name] = _o3d_hybrid(prepared[0], prepared[1], step, cfg)
            else:
                weight = None if name == "depth" else WEIGHT
                found[name] = _align(prepared, frames, (0, 1), step, weight, cfg, levels)
            ms[name] = (time.perf_counter() - t0) * 1e3
        split = _split(inv_T(found["depth"]) @ found["colour"], prepared[1], cfg, strong_ratio)
        if split is None:
            continue
        out["ratio"].append(prepared[1].constraint_ratio)
        out["strong"].append(split[0])
        out["weak"].append(split[1])
        for name in names:
            out[f"{name}_err"].append(translation_norm(inv_T(step) @ found[name]) * 1e3)
            out[f"{name}_ms"].append(ms[name])
    return {k: np.asarray(v) for k, v in out.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--every", type=int, default=6, help="every n-th frame")
    ap.add_argument("--frames", type=int, default=240, help="frames of each synthetic row")
    ap.add_argument("--only", default="", help="comma-separated substrings of row names")
    ap.add_argument("--sequences", default="", help="also these (demo, demo-drift, a folder)")
    ap.add_argument("--strong", type=float, default=4.0, help="strong: std within this of the best")
    ap.add_argument("--o3d-hybrid", action="store_true", help="also Open3D's hybrid odometry")
    ap.add_argument("--tag", default="", help="suffix of the result name")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    synthetic = synthetic_rows(args.frames, KINDS, (2.0,), (0,), only=args.only, unsynced=UNSYNCED)
    rows = [r for r in real_rows() + synthetic if not args.only
            or any(s in r.name for s in args.only.split(","))]  # fmt: skip
    rows += [Row(s, sequence_path(s), True) for s in args.sequences.split(",") if s]
    names = ALIGNMENTS + (("o3d_hybrid",) if args.o3d_hybrid else ())
    print("| sequence | frames | ratio | colour - depth, strong / weak (median / p90 mm) | "
          + " | ".join(f"{k}: error mm / ms" for k in names) + " |")  # fmt: skip
    print("|---|---|---|---|" + "---|" * len(names))
    out = {}
    for row in rows:
        found = agreement(row.path, args.every, args.strong, args.o3d_hybrid)
        if found is None or not len(found["ratio"]):
            continue
        summary = {
            k: {"median": round(float(np.median(v)), 3),
                "p90": round(float(np.percentile(v, 90)), 3)}
            for k, v in found.items()
        }  # fmt: skip
        out[row.name] = {"frames": len(found["ratio"]), **summary}
        cell = {k: f"{v['median']:.2f} / {v['p90']:.2f}" for k, v in summary.items()}
        times = " | ".join(f"{cell[f'{k}_err']}, {summary[f'{k}_ms']['median']:.0f}" for k in names)
        print(f"| {row.name} | {len(found['ratio'])} | {summary['ratio']['median']:.1f} "
              f"| {cell['strong']}; {cell['weak']} | {times} |", flush=True)  # fmt: skip
    settings = {"every": args.every, "strong": args.strong, "weight": WEIGHT}
    name = "colour-agreement" + (f"-{args.tag}" if args.tag else "")
    path = write_result(name, {"machine": machine(), "settings": settings, "rows": out})
    print(f"written: {path}")


if __name__ == "__main__":
    main()
