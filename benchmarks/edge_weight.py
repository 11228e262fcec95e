"""How much should the pose graph's edges weigh against the landmarks in bundle adjustment?

    python benchmarks/edge_weight.py tum-fr1-xyz ~/.cache/rgbd-slam/matrix/room-x2-s0-240-v1

Each sequence is run once (default config; the final adjustment left out), then:

- **at the true poses**: the odometry and loop edges' chi^2 per degree of freedom at
  ``ba.pose_graph_weight``, and the landmark observations' (landmarks at the mean of their
  observations lifted by depth under the true poses): 1 means the noise each is given is its
  real one. Keyframes take the ground-truth pose nearest their timestamp (within 20 ms).
- **the final adjustment at fixed weights** (``--weights``) and with the weight estimated from
  its residuals in up to ``--rounds`` rounds (``ba.edge_weight_rounds``, opt-in;
  :mod:`slam.backend.variance_components`): keyframe ATE (mm, SE(3)-aligned, keyframes only)
  and the weight it settled on.

Synthetic rows: the folders ``benchmarks/matrix.py`` generates under
``~/.cache/rgbd-slam/matrix``. Writes ``results/edge-weight[-TAG].json``.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import logging

import numpy as np
from common import machine, sequence_path, write_result

import slam
from slam.backend.ba_problem import BAProblem
from slam.backend.bundle_adjustment import depth_sigmas, residuals
from slam.geometry import inv_T, log_se3


def _keyframe_truth(seq, kfs) -> dict[int, np.ndarray]:
    gt = seq.ground_truth
    out = {}
    for kf in kfs:
        j = int(np.argmin(np.abs(gt.timestamps - kf.timestamp)))
        if abs(gt.timestamps[j] - kf.timestamp) < 0.02:
            out[kf.id] = gt.poses[j]
    return out


def _aligned_rmse_mm(poses: dict[int, np.ndarray], truth: dict[int, np.ndarray]) -> float:
    """Translation RMSE after the SE(3) (Umeyama, no scale) alignment of the positions."""
    ks = [k for k in poses if k in truth]
    X = np.array([poses[k][:3, 3] for k in ks])
    Y = np.array([truth[k][:3, 3] for k in ks])
    mx, my = X.mean(0), Y.mean(0)
    U, _, Vt = np.linalg.svd((Y - my).T @ (X - mx))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    aligned = (X - mx) @ (U @ D @ Vt).T + my
    return float(np.sqrt(np.mean(np.sum((aligned - Y) ** 2, axis=1))) * 1e3)


def _edges_chi2(system, truth, weight: float) -> dict[str, float]:
    out = {}
    for kind in ("odometry", "loop"):
        c = [
            float(r @ (weight * e.information) @ r) / 6
            for e in system.closer.graph.edges
            if e.kind == kind and e.i in truth and e.j in truth
            for r in [log_se3(inv_T(e.T_i_j) @ inv_T(truth[e.i]) @ truth[e.j])]
        ]
        if c:
            out[f"{kind}_edges"] = len(c)
            out[f"{kind}_chi2_per_dof_median"] = round(float(np.median(c)), 5)
    return out


def _landmarks_chi2(system, truth, cfg) -> dict[str, float]:
    prob = BAProblem.from_landmarks(system.ba.landmarks)
    keep = np.isin(prob.kf, list(truth)) & (prob.depth > 0)
    prob = prob.subset(keep)
    K, (u, v), z = prob.K, prob.uv.T, prob.depth
    cam = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
    T = np.stack([truth[int(k)] for k in prob.kf])
    world = np.einsum("nij,nj->ni", T[:, :3, :3], cam) + T[:, :3, 3]
    count = np.bincount(prob.landmark, minlength=prob.n_landmarks)
    sums = [np.bincount(prob.landmark, world[:, k], prob.n_landmarks) for k in range(3)]
    points = np.stack(sums, axis=1) / np.maximum(count, 1)[:, None]
    seen = count[prob.landmark] >= 2
    reproj, chi2 = residuals(prob, truth, points, cfg.pixel_sigma_px, depth_sigmas(prob, cfg))
    return {
        "landmark_observations": int(seen.sum()),
        "landmark_chi2_per_dof_median": round(float(np.median(chi2[seen])) / 3, 5),
        "landmark_reprojection_px_median": round(float(np.median(reproj[seen])), 3),
    }


def study(name: str, weights: list[float], rounds: int) -> dict:
    path = sequence_path(name)
    cfg = slam.load_config(None)
    cfg.ba.at_finish = False  # the final adjustments are made here
    seq = slam.open_sequence(path, cfg.dataset.layout, cfg.dataset.calibration)
    system = slam.Slam(cfg, has_color=seq.has_color, color_registered=seq.color_registered)
    for i in range(len(seq)):
        system.step(seq[i])
    kfs = system.closer.keyframes
    truth = _keyframe_truth(seq, kfs)
    if system.graph_adjusted:  # a mid-run BA left its poses in the graph's nodes
        system.closer.graph.optimize()
    nodes = {kf.id: system.closer.graph.nodes[kf.id] for kf in kfs}
    base = system.ba.cfg
    row: dict = {
        "keyframes": len(kfs),
        "odometry_mm": round(_aligned_rmse_mm({kf.id: kf.T_world_cam for kf in kfs}, truth), 3),
        "pose_graph_mm": round(_aligned_rmse_mm(nodes, truth), 3),
        **_edges_chi2(system, truth, base.pose_graph_weight),
        **_landmarks_chi2(system, truth, system.ba.effective_config),
    }
    landmarks = system.ba.landmarks
    for label, cfg_w, n_rounds in [(f"w{w:g}", w, 0) for w in weights] + [
        ("estimated", base.pose_graph_weight, rounds)
    ]:
        system.ba.cfg = dataclasses.replace(
            base, pose_graph_weight=cfg_w, edge_weight_rounds=n_rounds
        )
        system.ba.landmarks = copy.deepcopy(landmarks)  # outliers are removed from the tracks
        res = system.ba.optimise(nodes, system.closer.graph.edges, reason="finish")
        poses = {k: res.poses.get(k, nodes[k]) for k in nodes}
        row[f"{label}_mm"] = round(_aligned_rmse_mm(poses, truth), 3)
        if n_rounds:
            row["estimated_weight"] = round(res.edge_weight, 3)
        if res.skipped:
            row[f"{label}_skipped"] = res.skipped
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequences", nargs="+", help="names (run_slam.py's) or folders")
    parser.add_argument("--weights", default="1,10,100,1000,10000")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of the estimate")
    parser.add_argument("--tag", default="")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    weights = [float(w) for w in args.weights.split(",")]
    rows = {}
    for name in args.sequences:
        rows[name.rstrip("/").split("/")[-1]] = row = study(name, weights, args.rounds)
        print(name.rstrip("/").split("/")[-1], row, flush=True)
    out = write_result(f"edge-weight{args.tag}", {"machine": machine(), "rows": rows})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
