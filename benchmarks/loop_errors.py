"""How wrong each loop candidate's poses are: RANSAC on ORB against ICP on depth, per candidate.

    python benchmarks/loop_errors.py tum-fr1-xyz
    python benchmarks/loop_errors.py ~/.cache/rgbd-slam/matrix/desk-x1-s1-240-v1 --config C.yaml

Runs the sequence (default config, or ``--config``) and records every loop verification that
got as far as ICP: the relative pose RANSAC found, the one ICP refined it to, both against the
ground truth (translation error in mm, rotation error in deg), the RANSAC inliers' RMS residual,
the fraction of them ICP's pose keeps within 3x that residual, the rotation between the two
views, and the verifier's decision. Writes ``benchmarks/results/loop-errors-<sequence>.json``
and prints one line per candidate. Ground truth is read only here, after the run.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
from common import sequence_path, write_result

import slam
from slam.geometry import inv_T, rotation_angle_deg, translation_norm
from slam.keyframe import Keyframe
from slam.loops import verification
from slam.trajectory import read_tum


def _record_verifications() -> list[dict]:
    """Wrap the verifier's RANSAC, ICP and ``verify`` so each candidate that reached ICP is
    recorded with its keyframes' timestamps."""
    rows: list[dict] = []
    current: dict = {}
    by_features: dict[int, Keyframe] = {}
    view, ransac, icp, verify = (
        Keyframe.view,
        verification.ransac_rigid,
        verification.projective_icp,
        verification.LoopVerifier.verify,
    )

    def view_of(self):
        v = view(self)
        by_features[id(v.features)] = self
        return v

    def ransac_of(src, dst, *a, **k):
        r = ransac(src, dst, *a, **k)
        current.update(ransac=r, src=src, dst=dst)
        return r

    def icp_of(*a, **k):
        r = icp(*a, **k)
        current["icp"] = r
        return r

    def verify_of(self, query, candidate):
        current.clear()
        out = verify(self, query, candidate)
        q, c = by_features.get(id(query.features)), by_features.get(id(candidate.features))
        if "icp" in current and q is not None and c is not None:
            rs = current["ransac"]
            src, dst = current["src"][rs.inliers], current["dst"][rs.inliers]
            T_icp = current["icp"].T_target_source
            rows.append(
                {
                    "query_frame": q.index,
                    "match_frame": c.index,
                    "query_t": q.timestamp,
                    "match_t": c.timestamp,
                    "T_ransac": rs.T.tolist(),
                    "T_icp": T_icp.tolist(),
                    "inliers": int(rs.n_inliers),
                    "inlier_rmse_m": float(rs.inlier_rmse),
                    "kept_3x": verification.feature_agreement(
                        src, dst, T_icp, 3.0 * rs.inlier_rmse
                    ),
                    "icp_fitness": float(current["icp"].fitness),
                    "accepted": bool(out.accepted),
                    "reason": out.reason,
                }
            )
        return out

    Keyframe.view = view_of
    verification.ransac_rigid = ransac_of
    verification.projective_icp = icp_of
    verification.LoopVerifier.verify = verify_of
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", help="demo, a folder under ../shared/datasets, or a path")
    ap.add_argument("--config", default=None, help="YAML overrides")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    path = sequence_path(args.sequence)
    rows = _record_verifications()
    cfg = slam.load_config(args.config)
    seq = slam.open_sequence(str(path), cfg.dataset.layout, cfg.dataset.calibration)
    res = slam.run(seq, cfg)
    gt = read_tum(path / "groundtruth.txt")

    def gt_pose(t: float) -> np.ndarray:
        return gt.poses[int(np.argmin(np.abs(gt.timestamps - t)))]

    for r in rows:
        T_true = inv_T(gt_pose(r["match_t"])) @ gt_pose(r["query_t"])
        for key in ("ransac", "icp"):
            err = inv_T(T_true) @ np.array(r[f"T_{key}"])
            r[f"{key}_error_mm"] = translation_norm(err) * 1e3
            r[f"{key}_error_deg"] = rotation_angle_deg(err)
        r["view_angle_deg"] = rotation_angle_deg(T_true)
        print(
            f"{r['query_frame']:5d} -> {r['match_frame']:5d} {'A' if r['accepted'] else '-'} "
            f"inliers {r['inliers']:3d} rmse {r['inlier_rmse_m'] * 1e3:4.1f} mm "
            f"kept {r['kept_3x']:.2f} view {r['view_angle_deg']:5.1f} deg | "
            f"RANSAC {r['ransac_error_mm']:6.1f} mm {r['ransac_error_deg']:4.2f} deg | "
            f"ICP {r['icp_error_mm']:6.1f} mm {r['icp_error_deg']:4.2f} deg | {r['reason'][:60]}"
        )
    m = res.metrics
    out = write_result(
        f"loop-errors-{Path(path).name}",
        {
            "sequence": str(path),
            "config": args.config,
            "ate_rmse_m": m.get("ate_rmse_m"),
            "ate_rmse_odometry_m": m.get("ate_rmse_odometry_m"),
            "loops_accepted": m.get("loops_accepted"),
            "candidates": rows,
        },
    )
    print(f"final ATE {m.get('ate_rmse_m')}, odometry {m.get('ate_rmse_odometry_m')}; {out}")


if __name__ == "__main__":
    main()
