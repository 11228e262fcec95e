"""Frame-to-model tracking: projective point-to-plane ICP against the model ray-cast, seeded and
rescued by ORB + RANSAC against the last keyframe."""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from slam.config import TrackingConfig
from slam.data.base import Frame
from slam.frontend.features import FeatureSet, OrbExtractor, match_descriptors
from slam.frontend.icp import IcpResult, projective_icp, projective_overlap
from slam.frontend.pointcloud import downsample_depth, scale_intrinsics
from slam.frontend.ransac import RansacResult, ransac_rigid
from slam.geometry import inv_T, rotation_angle_deg, translation_norm
from slam.mapping.tsdf import TSDFVolume

log = logging.getLogger(__name__)


@dataclass
class Keyframe:
    """A keyframe: its index, pose and ORB features with 3D points (camera frame)."""

    index: int
    timestamp: float
    T_world_cam: np.ndarray
    features: FeatureSet


@dataclass
class TrackingStatus:
    """Per-frame tracking record (written to ``tracking.csv``; summarised in ``metrics.json``).

    ``path``: ``init`` (first frame), ``icp`` (ICP from the motion prediction), ``ransac+icp``
    (ICP seeded by RANSAC), ``ransac`` (RANSAC pose, ICP rejected), ``lost`` (no estimate passed
    the checks; the prediction is used and the frame is not fused).
    """

    index: int
    path: str
    ok: bool
    icp_fitness: float = 0.0
    icp_rmse_m: float = 0.0
    ransac_inliers: int = 0
    ransac_matches: int = 0
    overlap: float = 0.0
    keyframe: bool = False
    ms: float = 0.0

    def as_row(self) -> dict:
        return asdict(self)


@dataclass
class TrackerState:
    """What tracking carries from frame to frame (saved/restored for checkpoints)."""

    T_world_prev: np.ndarray | None = None
    prev_features: Keyframe | None = None  # the previous frame's features, when it computed them
    velocity: np.ndarray = field(default_factory=lambda: np.eye(4))  # T_prev_cur of last step
    keyframes: list[Keyframe] = field(default_factory=list)


class Tracker:
    """Estimates ``T_world_cam`` of each new frame against the TSDF model."""

    def __init__(self, cfg: TrackingConfig, use_color: bool = True) -> None:
        self.cfg = cfg
        self.use_color = use_color
        self.orb = OrbExtractor(cfg.ransac.n_features, cfg.depth_min_m, cfg.depth_max_m)
        self.state = TrackerState()
        self._rng = np.random.default_rng(cfg.ransac.seed)

    @property
    def last_keyframe(self) -> Keyframe | None:
        return self.state.keyframes[-1] if self.state.keyframes else None

    def _features(self, frame: Frame) -> FeatureSet | None:
        if not self.use_color or frame.color is None:
            return None
        return self.orb.extract(frame.color, frame.depth_m, frame.K)

    def ransac_to_keyframe(self, feats: FeatureSet, kf: Keyframe) -> tuple[RansacResult, int]:
        """RANSAC pose of the current camera in the keyframe's frame (``T_kf_cur``)."""
        r = self.cfg.ransac
        matches = match_descriptors(feats.descriptors, kf.features.descriptors, r.ratio)
        if len(matches) < r.min_inliers:
            return RansacResult(np.eye(4), np.zeros(len(matches), bool), 0, np.inf, False), len(
                matches
            )
        res = ransac_rigid(
            feats.points_cam[matches[:, 0]],
            kf.features.points_cam[matches[:, 1]],
            r.iterations,
            r.inlier_threshold_m,
            r.min_inliers,
            rng=self._rng,
        )
        return res, len(matches)

    def track(self, frame: Frame, model: TSDFVolume) -> tuple[np.ndarray, TrackingStatus]:
        """Pose of ``frame``; the caller fuses it into ``model`` when ``status.ok``."""
        t0 = time.perf_counter()
        cfg = self.cfg
        st = self.state
        if st.T_world_prev is None:
            T = np.eye(4)
            status = TrackingStatus(frame.index, "init", True)
            feats = self._features(frame)
            self._add_keyframe(frame, T, feats, status)
            st.T_world_prev = T
            status.ms = (time.perf_counter() - t0) * 1e3
            return T, status

        T_prev = st.T_world_prev
        factor = cfg.downsample
        K_track = scale_intrinsics(frame.K, factor)
        depth = frame.depth_m
        for _ in range(int(np.log2(factor))):
            depth = downsample_depth(depth)
        h, w = depth.shape

        velocity = st.velocity
        large = (
            translation_norm(velocity) > cfg.large_motion_translation_m
            or rotation_angle_deg(velocity) > cfg.large_motion_rotation_deg
        )
        feats: FeatureSet | None = None
        ransac: RansacResult | None = None
        status = TrackingStatus(frame.index, "icp", False)

        def run_icp(T_world_guess: np.ndarray) -> tuple[np.ndarray, IcpResult, float]:
            """ICP of the frame against the model ray-cast at the guessed pose; returns the
            refined pose, the ICP result and the verified overlap score."""
            render = model.raycast(K_track, w, h, T_world_guess, False, False, frustum_depth_m=depth)
            icp = projective_icp(
                depth,
                render.depth_m,
                K_track,
                np.eye(4),
                cfg.iterations,
                cfg.depth_max_m,
                cfg.max_correspondence_m,
                cfg.huber_delta_m,
            )
            score = 0.0
            if translation_norm(icp.T_target_source) <= cfg.max_step_translation_m:
                score = projective_overlap(
                    depth, render.depth_m, K_track, icp.T_target_source, cfg.inlier_threshold_m
                )
            return T_world_guess @ icp.T_target_source, icp, score

        def ransac_guess() -> np.ndarray | None:
            nonlocal feats, ransac
            kf = st.prev_features or self.last_keyframe
            if feats is None:
                feats = self._features(frame)
            if feats is None or kf is None:
                return None
            ransac, n_matches = self.ransac_to_keyframe(feats, kf)
            status.ransac_inliers = ransac.n_inliers
            status.ransac_matches = n_matches
            if not ransac.success:
                return None
            return kf.T_world_cam @ ransac.T  # T_world_cur

        # hypotheses, tried in order until one passes the check: constant velocity (or RANSAC
        # first when the predicted motion is large), RANSAC, no motion; the best score wins.
        color_ok = self.use_color and frame.color is not None
        guesses: list[tuple[str, np.ndarray | None]] = [("icp", T_prev @ velocity)]
        if large and color_ok:
            guesses.insert(0, ("ransac+icp", None))
        elif color_ok:
            guesses.append(("ransac+icp", None))
        if large:
            guesses.append(("icp", T_prev))
        best: tuple[float, str, np.ndarray, IcpResult] | None = None
        tried_ransac = False
        for name, guess in guesses:
            if guess is None:
                if tried_ransac:
                    continue
                tried_ransac = True
                guess = ransac_guess()
                if guess is None:
                    continue
            T_cand, icp, score = run_icp(guess)
            if best is None or score > best[0]:
                best = (score, name, T_cand, icp)
            if score >= cfg.min_overlap and icp.fitness >= cfg.min_fitness:
                break
        assert best is not None
        score, name, T, icp = best
        status.path = name
        status.icp_fitness = float(icp.fitness)
        status.icp_rmse_m = float(icp.inlier_rmse)
        status.overlap = round(score, 4)
        ok = score >= cfg.min_overlap and icp.fitness >= cfg.min_fitness
        if not ok and ransac is not None and ransac.success:
            kf = st.prev_features or self.last_keyframe
            T = kf.T_world_cam @ ransac.T if kf is not None else T
            status.path = "ransac"
            ok = True
        elif not ok:
            T = T_prev @ velocity
            status.path = "lost"
            log.warning(
                "frame %d: tracking lost (best overlap %.2f, ICP fitness %.2f, RANSAC inliers "
                "%d); using the constant-velocity prediction",
                frame.index,
                score,
                icp.fitness,
                status.ransac_inliers,
            )
        status.ok = ok
        st.velocity = inv_T(T_prev) @ T if ok else np.eye(4)
        st.T_world_prev = T
        st.prev_features = (
            Keyframe(frame.index, frame.timestamp, T.copy(), feats)
            if ok and feats is not None and len(feats) > 0
            else None
        )

        kf = self.last_keyframe
        if ok and kf is not None:
            rel = inv_T(kf.T_world_cam) @ T
            if (
                translation_norm(rel) > cfg.keyframe_translation_m
                or rotation_angle_deg(rel) > cfg.keyframe_rotation_deg
                or status.path.startswith("ransac")
            ):
                if feats is None:
                    feats = self._features(frame)
                self._add_keyframe(frame, T, feats, status)
        status.ms = (time.perf_counter() - t0) * 1e3
        return T, status

    def _add_keyframe(
        self, frame: Frame, T: np.ndarray, feats: FeatureSet | None, status: TrackingStatus
    ) -> None:
        self.state.keyframes.append(
            Keyframe(frame.index, frame.timestamp, T.copy(), feats or FeatureSet.empty())
        )
        status.keyframe = True
