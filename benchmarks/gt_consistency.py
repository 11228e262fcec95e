"""How well a sequence's ground truth agrees with its own depth images, independently of the
SLAM pipeline: for frame pairs ``gap`` frames apart, ICP between the two raw depth images
(projective point-to-plane, started *from the ground-truth relative pose*) gives the relative
pose the depth data support; compare it with the ground truth's.

    python benchmarks/gt_consistency.py demo
    python benchmarks/gt_consistency.py 7scenes-300

With exact ground truth (the synthetic demo) the two agree to a fraction of a millimetre; a
translation ratio away from 1 with rotations in agreement means the ground truth's scale
differs from the depth's, and a large disagreement means ground-truth noise. A time offset
between ground truth and frames would show as a smaller disagreement at a shifted pairing.
Writes benchmarks/results/gt-consistency-<sequence>.json.
"""

from __future__ import annotations

import argparse

import numpy as np
from common import machine, sequence_path, write_result

import slam
from slam.frontend.icp import projective_icp, projective_overlap
from slam.geometry import inv_T, rotation_angle_deg


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequence", help="demo, or a folder name under ../shared/datasets")
    parser.add_argument("--gap", type=int, default=10, help="frames between the two of a pair")
    parser.add_argument("--step", type=int, default=5, help="frames between pairs")
    args = parser.parse_args()
    seq = slam.open_sequence(sequence_path(args.sequence))
    gt = seq.ground_truth
    if gt is None:
        raise SystemExit(f"{args.sequence}: no ground truth")
    poses = gt.poses  # associated to the frames, one per frame
    rows = []
    for i in range(0, len(seq) - args.gap, args.step):
        a, b = seq[i], seq[i + args.gap]
        T_gt = inv_T(poses[i]) @ poses[i + args.gap]
        r = projective_icp(b.depth_m, a.depth_m, a.K, T_gt, [20, 20, 20], 4.0, 0.05, 0.03, 2.0)
        if r.fitness < 0.5:
            continue
        T_icp = r.T_target_source
        d = inv_T(T_gt) @ T_icp
        rows.append(
            {
                "frame": i,
                "t_gt_m": float(np.linalg.norm(T_gt[:3, 3])),
                "t_icp_m": float(np.linalg.norm(T_icp[:3, 3])),
                "rot_gt_deg": rotation_angle_deg(T_gt),
                "rot_icp_deg": rotation_angle_deg(T_icp),
                "disagreement_m": float(np.linalg.norm(d[:3, 3])),
                "disagreement_deg": rotation_angle_deg(d),
                "overlap_1cm_gt": projective_overlap(b.depth_m, a.depth_m, a.K, T_gt, 0.01),
                "overlap_1cm_icp": projective_overlap(b.depth_m, a.depth_m, a.K, T_icp, 0.01),
                "T_icp": T_icp.tolist(),
            }
        )
    moving = [r for r in rows if r["t_gt_m"] > 0.03]
    turning = [r for r in rows if r["rot_gt_deg"] > 2.0]
    # time offset: the same ICP poses against ground truth pairs shifted by k frames
    offsets = {}
    for k in range(-3, 4):
        dk = []
        for r in rows:
            j = r["frame"] + k
            if 0 <= j and j + args.gap < len(poses):
                T_gt_k = inv_T(poses[j]) @ poses[j + args.gap]
                dk.append(np.linalg.norm(np.asarray(r["T_icp"])[:3, 3] - T_gt_k[:3, 3]))
        offsets[str(k)] = float(np.median(dk))
    summary = {
        "pairs": len(rows),
        "translation_ratio_median": float(np.median([r["t_icp_m"] / r["t_gt_m"] for r in moving]))
        if moving
        else None,
        "rotation_ratio_median": float(
            np.median([r["rot_icp_deg"] / r["rot_gt_deg"] for r in turning])
        )
        if turning
        else None,
        "disagreement_m_median": float(np.median([r["disagreement_m"] for r in rows])),
        "disagreement_deg_median": float(np.median([r["disagreement_deg"] for r in rows])),
        "overlap_1cm_gt_median": float(np.median([r["overlap_1cm_gt"] for r in rows])),
        "overlap_1cm_icp_median": float(np.median([r["overlap_1cm_icp"] for r in rows])),
        "icp_better_fraction": float(
            np.mean([r["overlap_1cm_icp"] > r["overlap_1cm_gt"] for r in rows])
        ),
        "disagreement_m_median_by_time_offset": offsets,
    }
    for r in rows:
        del r["T_icp"]
    data = {
        "sequence": args.sequence,
        "gap": args.gap,
        "step": args.step,
        **summary,
        "rows": rows,
        "machine": machine(),
    }
    out = write_result(f"gt-consistency-{args.sequence}", data)
    print(f"{out}: " + ", ".join(f"{k} {v}" for k, v in summary.items() if not isinstance(v, dict)))


if __name__ == "__main__":
    main()
