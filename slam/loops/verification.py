"""Geometric verification of a revisit candidate between two keyframes.

ORB matches lifted to 3D, the tracking frontend's RANSAC (minimal 3-point Kabsch sets), then
projective point-to-plane ICP between the two keyframes' depth images from the RANSAC pose.
Where colour is registered to depth (a feature's 3D point is where the feature is), the two
must agree: ICP's pose has to keep most of RANSAC's inliers within a few times their own
scatter. Depth alone slides along a wall filling both views, or settles on a wrong fit between
views from opposite sides of an object; the features then say it slid.
A candidate is accepted only when every check passes; the outcome says which one failed.
Reused by relocalisation (same checks, a keyframe against the current frame).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
import open3d.core as o3c

from slam.config import LoopConfig
from slam.frontend.features import match_descriptors
from slam.frontend.icp import projective_icp, projective_overlap
from slam.frontend.ransac import ransac_rigid
from slam.geometry import inv_T, rotation_angle_deg, transform_points, translation_norm
from slam.keyframe import Keyframe, KeyframeView
from slam.records import LoopRecord

log = logging.getLogger(__name__)

ICP_ITERATIONS = [8, 6, 4]  # coarse ... fine; keyframes are farther apart than frames


@dataclass
class Verification:
    """Outcome of verifying ``query`` against ``candidate``. ``T_candidate_query`` maps query
    camera points into the candidate camera; ``information`` (6x6, rotation first) is the
    per-correspondence J^T J of the final alignment, expressed for the right-perturbation of
    ``T_candidate_query`` (GTSAM's ``BetweenFactor`` convention)."""

    accepted: bool
    reason: str
    matches: int = 0
    inliers: int = 0
    inlier_ratio: float = 0.0
    icp_fitness: float = 0.0
    overlap: float = 0.0
    T_candidate_query: np.ndarray = field(default_factory=lambda: np.eye(4))
    information: np.ndarray = field(default_factory=lambda: np.eye(6))

    def record(self, query: Keyframe, match: Keyframe, score: float) -> LoopRecord:
        """This outcome as the loop record of ``query`` against ``match`` (retrieval score
        ``score``)."""
        return LoopRecord(
            query.id,
            match.id,
            query.index,
            match.index,
            query.timestamp,
            match.timestamp,
            score,
            self.accepted,
            self.reason,
            self.matches,
            self.inliers,
            self.inlier_ratio,
            self.icp_fitness,
            self.overlap,
            self.T_candidate_query.copy(),
        )


def adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of an SE(3) transform for twists ordered (rotation, translation)."""
    R, t = T[:3, :3], T[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = tx @ R
    return A


def registration_information(
    source_depth_m: np.ndarray,
    target_depth_m: np.ndarray,
    K: np.ndarray,
    T_target_source: np.ndarray,
    threshold_m: float = 0.03,
    depth_max_m: float = 4.0,
) -> tuple[np.ndarray, int]:
    """Per-correspondence information of a depth-image alignment: Open3D's J^T J of the
    point-to-point residuals (rotation first, perturbation on the left in the target frame),
    divided by the number of correspondences and moved to the right-perturbation of
    ``T_target_source``; callers scale it by 1/sigma^2. Returns (info, n). Point-to-point:
    its translation block is the identity, so it says every translation is measured even
    where the overlap is one plane (a wall, a desk top) along which ICP can slide; only the
    rotation block has the overlap's shape. A point-to-plane information was measured on the
    scene matrix (docs/archive/journal.md) and is not used yet."""
    info = o3d.t.pipelines.odometry.compute_odometry_information_matrix(
        o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(source_depth_m, np.float32))),
        o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(target_depth_m, np.float32))),
        o3c.Tensor(np.ascontiguousarray(K, np.float64)),
        o3c.Tensor(np.ascontiguousarray(T_target_source, np.float64)),
        float(threshold_m),
        1.0,
        float(depth_max_m),
    ).numpy()
    n = int(round(info[3, 3]))  # translation block of point-to-point J^T J is n * I
    if n < 10:
        return np.eye(6) * 1e-6, n
    A = adjoint(T_target_source)
    return A.T @ (info / n) @ A, n


def feature_agreement(
    src_pts: np.ndarray, dst_pts: np.ndarray, T_dst_src: np.ndarray, threshold_m: float
) -> float:
    """Fraction of 3D feature pairs (rows of ``src_pts`` / ``dst_pts``, camera frames) that
    ``T_dst_src`` brings within ``threshold_m`` of each other: how many of RANSAC's inliers
    an alignment found by another sensor (ICP on depth) keeps. 0 for no pairs."""
    if len(src_pts) == 0:
        return 0.0
    d = transform_points(T_dst_src, src_pts) - dst_pts
    return float(np.mean(np.linalg.norm(d, axis=1) < threshold_m))


class LoopVerifier:
    """Accepts or rejects revisit candidates (RANSAC on ORB, then ICP on depth).
    ``features_on_depth``: the features' 3D points are read from depth registered to the colour
    they were detected in, so ICP's pose must agree with them (not so where colour and depth
    are separate cameras: 7-Scenes)."""

    def __init__(
        self,
        cfg: LoopConfig,
        depth_max_m: float = 4.0,
        seed: int = 0,
        features_on_depth: bool = True,
    ) -> None:
        self.cfg = cfg
        self.depth_max_m = depth_max_m
        self.features_on_depth = features_on_depth
        self._rng = np.random.default_rng(seed)

    def state_dict(self) -> dict:
        """RANSAC's random state (checkpoints)."""
        return {"rng": self._rng.bit_generator.state}

    def load_state_dict(self, state: dict) -> None:
        self._rng.bit_generator.state = state["rng"]

    def verify(self, query: KeyframeView, candidate: KeyframeView) -> Verification:
        cfg = self.cfg
        m = match_descriptors(query.features.descriptors, candidate.features.descriptors, cfg.ratio)
        if len(m) < cfg.min_inliers:
            return Verification(False, f"{len(m)} descriptor matches < {cfg.min_inliers}", len(m))
        rs = ransac_rigid(
            query.features.points_cam[m[:, 0]],
            candidate.features.points_cam[m[:, 1]],
            cfg.ransac_iterations,
            cfg.ransac_threshold_m,
            cfg.min_inliers,
            rng=self._rng,
        )
        ratio = rs.n_inliers / len(m)
        out = Verification(False, "", len(m), rs.n_inliers, ratio)
        if not rs.success or rs.n_inliers < cfg.min_inliers:
            out.reason = f"{rs.n_inliers} RANSAC inliers < {cfg.min_inliers}"
            return out
        if ratio < cfg.min_inlier_ratio:
            out.reason = f"RANSAC inlier ratio {ratio:.2f} < {cfg.min_inlier_ratio}"
            return out
        icp = projective_icp(
            query.depth_m,
            candidate.depth_m,
            query.K,
            rs.T,
            ICP_ITERATIONS,
            self.depth_max_m,
            max_correspondence_m=cfg.icp_max_correspondence_m,
            huber_delta_m=cfg.icp_huber_delta_m,
        )
        T = icp.T_target_source
        out.icp_fitness = float(icp.fitness)
        out.T_candidate_query = T
        step = inv_T(rs.T) @ T
        if (
            translation_norm(step) > cfg.max_icp_correction_m
            or rotation_angle_deg(step) > cfg.max_icp_correction_deg
        ):
            out.reason = (
                f"ICP moved the RANSAC pose by {translation_norm(step):.3f} m / "
                f"{rotation_angle_deg(step):.1f} deg (max {cfg.max_icp_correction_m} m / "
                f"{cfg.max_icp_correction_deg} deg)"
            )
            return out
        if self.features_on_depth:
            gate = cfg.feature_agreement_scatter * rs.inlier_rmse
            kept = feature_agreement(
                query.features.points_cam[m[rs.inliers, 0]],
                candidate.features.points_cam[m[rs.inliers, 1]],
                T,
                gate,
            )
            if kept < cfg.min_feature_agreement:
                out.reason = (
                    f"ICP's pose keeps {kept:.2f} of the RANSAC inliers within {gate * 1e3:.1f} "
                    f"mm ({cfg.feature_agreement_scatter} x their RMS residual; min "
                    f"{cfg.min_feature_agreement}): depth and features disagree"
                )
                return out
        if icp.fitness < cfg.min_icp_fitness:
            out.reason = f"ICP fitness {icp.fitness:.2f} < {cfg.min_icp_fitness}"
            return out
        out.overlap = projective_overlap(
            query.depth_m, candidate.depth_m, query.K, T, cfg.overlap_threshold_m
        )
        if out.overlap < cfg.min_overlap:
            out.reason = f"overlap {out.overlap:.2f} < {cfg.min_overlap}"
            return out
        out.information, _ = registration_information(
            query.depth_m, candidate.depth_m, query.K, T, cfg.overlap_threshold_m, self.depth_max_m
        )
        out.accepted = True
        out.reason = "accepted"
        return out
