"""ORB evidence for tracking: RANSAC poses of a frame against recent keyframes, and how many
matches agree with a pose found otherwise.

Tracking uses features in three ways: to seed ICP when the predicted motion is large, to offer
an alternative guess when ICP fails, and to verify a pose after a gap. All three match the
frame's features against the same candidates (the previous frame, then the recent keyframes,
newest first) and draw from one random generator, in a fixed order, so a run is repeatable.
"""

from __future__ import annotations

import numpy as np

from slam.config import RansacConfig
from slam.frontend.features import match_descriptors
from slam.frontend.ransac import RansacResult, ransac_rigid
from slam.geometry import inv_T, transform_points
from slam.keyframe import FeatureSet, Keyframe


class KeyframeRansac:
    """RANSAC and feature support against keyframes. ``rng``: the generator RANSAC draws
    from (shared with the owner, which saves and restores its state)."""

    def __init__(self, cfg: RansacConfig, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.rng = rng

    def to_keyframe(
        self, feats: FeatureSet, kf: Keyframe, matches: np.ndarray | None = None
    ) -> tuple[RansacResult, int]:
        """RANSAC pose of the current camera in the keyframe's frame (``T_kf_cur``) and the
        number of descriptor matches it started from (``matches``, when already made). Too
        few matches: a failed result, and no random draw."""
        r = self.cfg
        if matches is None:
            matches = match_descriptors(feats.descriptors, kf.features.descriptors, r.ratio)
        if len(matches) < r.min_inliers:
            failed = RansacResult(np.eye(4), np.zeros(len(matches), bool), 0, np.inf, False)
            return failed, len(matches)
        res = ransac_rigid(
            feats.points_cam[matches[:, 0]],
            kf.features.points_cam[matches[:, 1]],
            r.iterations,
            r.inlier_threshold_m,
            r.min_inliers,
            rng=self.rng,
        )
        return res, len(matches)

    def seed(
        self, feats: FeatureSet, candidates: list[Keyframe]
    ) -> tuple[np.ndarray | None, RansacResult | None, int]:
        """A starting pose: RANSAC against the candidates in order, stopping at the first
        success. Returns its ``T_world_cur`` (None when none succeeds), the result with the
        most inliers (the first of equals; None without candidates) and its match count (what
        the frame's status reports)."""
        best: RansacResult | None = None
        n_best = 0
        for kf in candidates:
            res, n_matches = self.to_keyframe(feats, kf)
            if best is None or res.n_inliers > best.n_inliers:
                best, n_best = res, n_matches
            if res.success:
                return kf.T_world_cam @ res.T, best, n_best
        return None, best, n_best

    def best_motion(
        self,
        feats: FeatureSet,
        candidates: list[Keyframe],
        T_world_prev: np.ndarray,
        evidence: FeatureEvidence | None = None,
    ) -> np.ndarray | None:
        """``T_prev_cur`` (motion from the previous pose ``T_world_prev``) of the successful
        RANSAC with the most inliers over all candidates, None when none succeeds. Every
        candidate is tried, unlike a seed, which stops at the first success. ``evidence``:
        the same features' matches against the same candidates, when already made."""
        best: tuple[int, np.ndarray] | None = None
        for i, kf in enumerate(candidates):
            res, _ = self.to_keyframe(feats, kf, None if evidence is None else evidence.matches[i])
            if res.success and (best is None or res.n_inliers > best[0]):
                best = (res.n_inliers, inv_T(T_world_prev) @ kf.T_world_cam @ res.T)
        return None if best is None else best[1]

    def support(
        self, feats: FeatureSet | None, T_world_cam: np.ndarray, candidates: list[Keyframe]
    ) -> int:
        """How many ORB matches between the frame and a candidate agree with the pose (3D
        points within the RANSAC threshold): independent evidence for a pose found by ICP.
        The best over the candidates; no random draw."""
        return self.evidence(feats, candidates).support(T_world_cam)

    def evidence(self, feats: FeatureSet | None, candidates: list[Keyframe]) -> FeatureEvidence:
        """The frame's matches against the candidates, made once, to weigh several poses."""
        return FeatureEvidence(self.cfg, feats, candidates)


class FeatureEvidence:
    """A frame's ORB matches against candidate keyframes (their 3D points in each camera),
    matched once: :meth:`support` counts the matches a pose explains."""

    def __init__(
        self, cfg: RansacConfig, feats: FeatureSet | None, candidates: list[Keyframe]
    ) -> None:
        self.threshold_m = cfg.inlier_threshold_m
        #: the matches (frame index, keyframe index) against each candidate, in order
        self.matches: list[np.ndarray] = []
        # (T_world_kf, the frame's matched points, the keyframe's), per candidate with enough
        self.pairs: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        if feats is None or len(feats) == 0:
            return
        for kf in candidates:
            m = match_descriptors(feats.descriptors, kf.features.descriptors, cfg.ratio)
            self.matches.append(m)
            if len(m) >= cfg.min_inliers:
                self.pairs.append(
                    (kf.T_world_cam, feats.points_cam[m[:, 0]], kf.features.points_cam[m[:, 1]])
                )

    def support(self, T_world_cam: np.ndarray) -> int:
        """How many matches agree with the pose (3D points within the RANSAC threshold), the
        best over the candidates."""
        best = 0
        for T_world_kf, cur, ref in self.pairs:
            d = transform_points(inv_T(T_world_kf) @ T_world_cam, cur) - ref
            best = max(best, int(np.count_nonzero(np.linalg.norm(d, axis=1) < self.threshold_m)))
        return best
