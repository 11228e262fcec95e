"""Frame-to-model tracking: projective point-to-plane ICP against the model ray-cast, seeded and
rescued by ORB + RANSAC against the last keyframe."""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from slam.config import TrackingConfig
from slam.data.base import Frame
from slam.errors import ConfigError
from slam.frontend.features import FeatureSet, OrbExtractor, match_descriptors
from slam.frontend.icp import IcpResult, projective_icp, projective_overlap
from slam.frontend.photometric import RgbdImage, grey, joint_align
from slam.frontend.pointcloud import (
    bilateral_depth,
    depth_pyramid,
    downsample_depth,
    scale_intrinsics,
)
from slam.frontend.ransac import RansacResult, ransac_rigid
from slam.geometry import inv_T, orthonormalize, rotation_angle_deg, translation_norm
from slam.mapping.tsdf import TSDFVolume

log = logging.getLogger(__name__)


@dataclass
class Keyframe:
    """A keyframe: frame index, odometry pose and ORB features with 3D points (camera frame);
    keyframes also keep their depth at tracking resolution (with its intrinsics ``K``) for
    loop verification, and ``id``, their number in the run (0, 1, ...)."""

    index: int
    timestamp: float
    T_world_cam: np.ndarray
    features: FeatureSet
    depth_m: np.ndarray | None = None
    K: np.ndarray | None = None
    id: int = -1


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
    f2f_fitness: float = 0.0
    model_rejected: bool = False
    keyframe: bool = False
    ms: float = 0.0

    def as_row(self) -> dict:
        return asdict(self)


@dataclass
class TrackerState:
    """What tracking carries from frame to frame (saved/restored for checkpoints)."""

    T_world_prev: np.ndarray | None = None
    prev_features: Keyframe | None = None  # the previous frame's features, when it computed them
    prev_depth: np.ndarray | None = None  # the previous frame's depth at tracking resolution
    prev_pyramid: list[np.ndarray] | None = None  # ... and its ICP pyramid (not saved)
    prev_rgbd: RgbdImage | None = None  # ... and its joint-alignment pyramids (not saved)
    velocity: np.ndarray = field(default_factory=lambda: np.eye(4))  # T_prev_cur of last step
    keyframes: list[Keyframe] = field(default_factory=list)


class Tracker:
    """Estimates ``T_world_cam`` of each new frame against the TSDF model."""

    def __init__(
        self, cfg: TrackingConfig, use_color: bool = True, color_registered: bool = True
    ) -> None:
        if cfg.downsample not in (1, 2, 4):
            raise ConfigError(f"tracking.downsample must be 1, 2 or 4, got {cfg.downsample}")
        self.cfg = cfg
        self.use_color = use_color
        # the photometric term needs colour pixel-aligned with depth
        self.photometric = use_color and color_registered and cfg.photometric_weight > 0
        self.orb = OrbExtractor(cfg.ransac.n_features, cfg.depth_min_m, cfg.depth_max_m)
        self.state = TrackerState()
        self._rng = np.random.default_rng(cfg.ransac.seed)

    @property
    def last_keyframe(self) -> Keyframe | None:
        return self.state.keyframes[-1] if self.state.keyframes else None

    def _tracking_depth(self, depth_m: np.ndarray) -> np.ndarray:
        """Depth at tracking resolution (1/downsample, by depth-aware 2x2 averaging), then
        bilateral-filtered (at that resolution: ~4x cheaper than at full resolution)."""
        cfg = self.cfg
        for _ in range(int(np.log2(cfg.downsample))):
            depth_m = downsample_depth(depth_m)
        if cfg.bilateral_sigma_m > 0:
            sigma_px = cfg.bilateral_sigma_px / cfg.downsample
            depth_m = bilateral_depth(depth_m, cfg.bilateral_sigma_m, sigma_px)
        return depth_m

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
            st.prev_depth = self._tracking_depth(frame.depth_m)
            self._add_keyframe(frame, T, feats, status, st.prev_depth)
            st.T_world_prev = T
            status.ms = (time.perf_counter() - t0) * 1e3
            return T, status

        T_prev = st.T_world_prev
        factor = cfg.downsample
        K_track = scale_intrinsics(frame.K, factor)
        depth = self._tracking_depth(frame.depth_m)
        h, w = depth.shape

        velocity = st.velocity
        large = (
            translation_norm(velocity) > cfg.large_motion_translation_m
            or rotation_angle_deg(velocity) > cfg.large_motion_rotation_deg
        )
        feats: FeatureSet | None = None
        ransac: RansacResult | None = None
        status = TrackingStatus(frame.index, "icp", False)

        levels = len(cfg.iterations)
        depth_pyr = depth_pyramid(depth, levels)  # built once: every ICP of this frame uses it
        rgbd: RgbdImage | None = None  # the frame for joint photometric + geometric alignment
        if self.photometric and frame.color is not None:
            rgbd = RgbdImage(depth_pyr, grey(frame.color, factor), K_track, levels)

        def joint_against(target: RgbdImage, init: np.ndarray) -> IcpResult:
            assert rgbd is not None
            return joint_align(
                rgbd,
                target,
                init,
                cfg.iterations,
                cfg.max_correspondence_m,
                cfg.huber_delta_m,
                cfg.coarse_correspondence_factor,
                cfg.photometric_weight,
            )

        def icp_against(target_depth: np.ndarray | list[np.ndarray], init: np.ndarray) -> IcpResult:
            return projective_icp(
                depth_pyr,
                target_depth,
                K_track,
                init,
                cfg.iterations,
                cfg.depth_max_m,
                cfg.max_correspondence_m,
                cfg.huber_delta_m,
                cfg.coarse_correspondence_factor,
            )

        def run_icp(
            T_world_guess: np.ndarray, trusted: bool = True
        ) -> tuple[np.ndarray, IcpResult, float]:
            """Frame-to-model ICP: align the frame to the model ray-cast at the guessed pose.
            Returns the refined pose, the ICP result and the verified overlap score; a
            correction larger than ``max_model_correction`` falls back to a ``trusted`` guess
            (one measured by frame-to-frame ICP or RANSAC, not merely predicted)."""
            render = model.raycast(
                K_track, w, h, T_world_guess, False, rgbd is not None, frustum_depth_m=depth
            )
            if rgbd is not None and render.color is not None:
                target = RgbdImage(render.depth_m, grey(render.color), K_track, levels)
                icp = joint_against(target, np.eye(4))
            else:
                icp = icp_against(render.depth_m, np.eye(4))
            step = icp.T_target_source
            if trusted and (
                translation_norm(step) > cfg.max_model_correction_m
                or rotation_angle_deg(step) > cfg.max_model_correction_deg
            ):
                step = np.eye(4)  # distrust a large jump of the model ICP; keep the guess
                status.model_rejected = True
            score = projective_overlap(depth, render.depth_m, K_track, step, cfg.inlier_threshold_m)
            return T_world_guess @ step, icp, score

        def ransac_guess() -> np.ndarray | None:
            """RANSAC against the previous frame, else the most recent keyframes (newest first)."""
            nonlocal feats, ransac
            if feats is None:
                feats = self._features(frame)
            if feats is None:
                return None
            for kf in self._ransac_candidates():
                res, n_matches = self.ransac_to_keyframe(feats, kf)
                if ransac is None or res.n_inliers > ransac.n_inliers:
                    ransac = res
                    status.ransac_inliers = res.n_inliers
                    status.ransac_matches = n_matches
                if res.success:
                    return kf.T_world_cam @ res.T  # T_world_cur
            return None

        tried: list[np.ndarray] = []  # model-ICP starting poses of this frame

        def attempt(
            T_prev_cur: np.ndarray, trusted: bool
        ) -> tuple[np.ndarray, IcpResult, float] | None:
            """Frame-to-frame ICP from a guess of ``T_prev_cur`` (when enabled), then
            frame-to-model ICP; None when frame-to-frame ICP lands where an earlier attempt
            of this frame started its model ICP (the same result again, at the cost of a
            ray-cast)."""
            if cfg.frame_to_frame and st.prev_depth is not None:
                prev = st.prev_pyramid if st.prev_pyramid is not None else st.prev_depth
                if rgbd is not None and cfg.photometric_frame_to_frame and st.prev_rgbd is not None:
                    f2f = joint_against(st.prev_rgbd, T_prev_cur)
                else:
                    f2f = icp_against(prev, T_prev_cur)
                status.f2f_fitness = round(float(f2f.fitness), 4)
                if f2f.fitness >= cfg.min_fitness and (
                    translation_norm(inv_T(T_prev_cur) @ f2f.T_target_source)
                    <= cfg.max_step_translation_m
                ):
                    T_prev_cur = f2f.T_target_source
                    trusted = True
            T_world_guess = T_prev @ T_prev_cur
            for T_done in tried:
                d = inv_T(T_done) @ T_world_guess
                if translation_norm(d) < 0.005 and rotation_angle_deg(d) < 0.3:
                    return None
            tried.append(T_world_guess)
            return run_icp(T_world_guess, trusted)

        # 1. the guess: RANSAC when the predicted motion is large, then frame-to-frame ICP
        #    against the previous frame from that guess (or from constant velocity)
        color_ok = self.use_color and frame.color is not None
        T_prev_cur = velocity
        trusted = False
        if large and color_ok:
            g = ransac_guess()
            if g is not None:
                T_prev_cur = inv_T(T_prev) @ g
                status.path = "ransac+icp"
                trusted = True
        # 2. frame-to-model ICP from the guess; RANSAC rescue when the check fails
        first = attempt(T_prev_cur, trusted)
        assert first is not None  # nothing was tried before
        T, icp, score = first
        ok = score >= cfg.min_overlap and icp.fitness >= cfg.min_fitness
        if not ok and color_ok and ransac is None:
            g = ransac_guess()
            if g is not None:
                tried.append(g)
                T2, icp2, score2 = run_icp(g)
                if score2 > score:
                    T, icp, score = T2, icp2, score2
                    status.path = "ransac+icp"
                ok = score >= cfg.min_overlap and icp.fitness >= cfg.min_fitness
        # 3. under large motion or failure, try other initial guesses; keep the best overlap
        if cfg.hypotheses and (large or not ok) and score < cfg.hypothesis_overlap:
            for name, guess in self._hypotheses(frame, feats, T_prev, velocity):
                tried_guess = attempt(guess, True)
                if tried_guess is None:
                    continue
                T2, icp2, score2 = tried_guess
                if score2 > score and icp2.fitness >= cfg.min_fitness:
                    T, icp, score = T2, icp2, score2
                    status.path = name
            ok = score >= cfg.min_overlap and icp.fitness >= cfg.min_fitness
        status.icp_fitness = float(icp.fitness)
        status.icp_rmse_m = float(icp.inlier_rmse)
        status.overlap = round(score, 4)
        if not ok:
            T = T_prev @ velocity
            status.path = "lost"
            log.warning(
                "frame %d: tracking lost (overlap %.2f, ICP fitness %.2f, RANSAC inliers %d); "
                "using the constant-velocity prediction",
                frame.index,
                score,
                icp.fitness,
                status.ransac_inliers,
            )
        T = orthonormalize(T)
        status.ok = ok
        st.velocity = inv_T(T_prev) @ T if ok else np.eye(4)
        st.T_world_prev = T
        st.prev_depth = depth if ok else None
        st.prev_pyramid = depth_pyr if ok else None
        st.prev_rgbd = rgbd if ok else None
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
                self._add_keyframe(frame, T, feats, status, depth)
        status.ms = (time.perf_counter() - t0) * 1e3
        return T, status

    def _ransac_candidates(self) -> list[Keyframe]:
        """What RANSAC tries against: the previous frame, then the recent keyframes (newest
        first)."""
        st = self.state
        return ([st.prev_features] if st.prev_features else []) + list(
            reversed(st.keyframes[-self.cfg.relocalisation_keyframes :])
        )

    def _hypotheses(
        self, frame: Frame, feats: FeatureSet | None, T_prev: np.ndarray, velocity: np.ndarray
    ) -> list[tuple[str, np.ndarray]]:
        """Alternative guesses of ``T_prev_cur``: no motion, constant velocity, and the RANSAC
        pose with the most inliers against the previous frame and the recent keyframes."""
        out = [("icp", np.eye(4)), ("icp", velocity)]
        if feats is None and self.use_color and frame.color is not None:
            feats = self._features(frame)
        if feats is not None and len(feats) > 0:
            best: tuple[int, np.ndarray] | None = None
            for kf in self._ransac_candidates():
                res, _ = self.ransac_to_keyframe(feats, kf)
                if res.success and (best is None or res.n_inliers > best[0]):
                    best = (res.n_inliers, inv_T(T_prev) @ kf.T_world_cam @ res.T)
            if best is not None:
                out.append(("ransac+icp", best[1]))
        return out

    def _add_keyframe(
        self,
        frame: Frame,
        T: np.ndarray,
        feats: FeatureSet | None,
        status: TrackingStatus,
        depth: np.ndarray,
    ) -> None:
        kfs = self.state.keyframes
        kfs.append(
            Keyframe(
                frame.index,
                frame.timestamp,
                T.copy(),
                feats or FeatureSet.empty(),
                depth,
                scale_intrinsics(frame.K, self.cfg.downsample),
                len(kfs),
            )
        )
        status.keyframe = True
