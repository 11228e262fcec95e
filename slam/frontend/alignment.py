"""One frame's tracking attempt and the ICP steps it is made of.

:class:`Attempt` carries what the stages of :meth:`slam.frontend.tracker.Tracker.track` hand on
to each other (the prediction, the model-ICP starts tried, the best estimate, the status
record); :func:`align_from` and :func:`align_to_model` are the two ICP steps every guess goes
through: frame-to-frame ICP against the previous frame, then frame-to-model ICP against the
model's ray-cast.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np

from slam.config import TrackingConfig
from slam.frontend.frame import PreparedFrame, depth_noise
from slam.frontend.icp import IcpResult, projective_agreement
from slam.frontend.keyframe_ransac import FeatureEvidence, KeyframeRansac
from slam.frontend.model import TrackingModel
from slam.frontend.photometric import colour_pose, mean_warped_intensity, photometric_costs
from slam.frontend.ransac import RansacResult
from slam.frontend.rgbd_image import RgbdImage, grey
from slam.geometry import inv_T, rotation_angle_deg, translation_norm
from slam.keyframe import FeatureSet, Keyframe
from slam.records import TrackingStatus

log = logging.getLogger(__name__)

#: An estimate: ``T_world_cam``, its frame-to-model ICP and its verified overlap with the model.
Estimate = tuple[np.ndarray, IcpResult, float]


@dataclass
class Attempt:
    """One frame's way through the stages of tracking: the prediction, what the stages found
    so far and the frame's status record. Stages read and update it instead of sharing
    closures, so each stage can be run (and tested) on its own.

    ``prev_depth``: the previous frame's ICP pyramid (or depth), None when there is no previous
    frame to align to (after a loss); ``prev_frame``: the previous frame itself (for its grey pyramids)."""

    frame: PreparedFrame
    status: TrackingStatus
    T_world_prev: np.ndarray  # the previous frame's pose, where the motion starts
    velocity: np.ndarray  # predicted T_prev_cur (constant velocity over the interval)
    large: bool  # the predicted motion is large, or the frame follows a gap
    verify: bool  # the frame follows a gap: its pose needs ORB support
    dt_ratio: float = 1.0  # the frame's interval over the usual one
    # the first step since tracking (re)started: its motion is unknown (RANSAC seeds it, but
    # that alone is no reason for a keyframe)
    first_step: bool = False
    dt_s: float = 1.0 / 30.0  # seconds since the previous frame (a 30 Hz sensor's when unknown)
    prev_depth: np.ndarray | list[np.ndarray] | None = None
    prev_frame: PreparedFrame | None = None  # the previous frame (its colour, on demand)
    # the images (depth + grey pyramids) and poses whose colour model alignments warp into the
    # model's view and average (the last keyframes': tracking.colour.photometric_reference); empty:
    # the model's own colour
    references: list[tuple[RgbdImage, np.ndarray]] = field(default_factory=list)
    feats: FeatureSet | None = None  # the frame's ORB features, once a stage used them
    ransac: RansacResult | None = None  # the seed's / rescue's RANSAC with the most inliers
    tried: list[np.ndarray] = field(default_factory=list)  # model-ICP starts (T_world_cam)
    T_world_cam: np.ndarray | None = None  # the best estimate so far ...
    icp: IcpResult | None = None  # ... its frame-to-model ICP
    overlap: float = 0.0  # ... and its verified overlap with the model ray-cast
    ok: bool = False  # the best estimate passes the checks
    # colour joins depth in every alignment of this attempt (weight of the photometric term;
    # 0: depth alone)
    photometric: float = 0.0
    # ICP iterations per level of this attempt's alignments (None: tracking.icp.iterations; a
    # large or unknown motion: tracking.icp.large_motion_iterations)
    iterations: list[int] | None = None
    # the last frame-to-frame estimate of T_prev_cur by depth alone that was accepted
    f2f: np.ndarray | None = None
    # a photometric alignment can reach the frame's pose (no fast motion, no gap before it)
    colour_reach: bool = True
    # the frame's ORB matches against the tracker's candidates, made once (Attempt.evidence)
    matched: FeatureEvidence | None = None
    # the weight down to which the model renders surfaces for this attempt's alignments
    # (None: the model's own threshold; Tracker.track's min_weight)
    min_weight: float | None = None
    # the departure of the estimate kept from the prediction as an acceleration (m/s^2;
    # Tracker.check_motion), None when there was no prediction to depart from
    acceleration: float | None = None

    def keep(self, T_world_cam: np.ndarray, icp: IcpResult, overlap: float) -> None:
        self.T_world_cam, self.icp, self.overlap = T_world_cam, icp, overlap

    def passes(self, cfg: TrackingConfig) -> bool:
        """The estimate overlaps the model and ICP found enough correspondences."""
        assert self.icp is not None
        return self.overlap >= cfg.icp.min_overlap and self.icp.fitness >= cfg.icp.min_fitness

    def features(self) -> FeatureSet | None:
        """The frame's features, from now on used by this attempt (None without colour)."""
        if self.feats is None:
            self.feats = self.frame.features
        return self.feats

    def ransac_guess(
        self, matcher: KeyframeRansac, candidates: list[Keyframe]
    ) -> np.ndarray | None:
        """``T_world_cur`` by RANSAC against the candidates (the previous frame, else the most
        recent keyframes, newest first); records the best RANSAC here and in the status."""
        feats = self.features()
        if feats is None:
            return None
        g, best, n_matches = matcher.seed(feats, candidates)
        if best is not None:
            self.ransac = best
            self.status.ransac_inliers = best.n_inliers
            self.status.ransac_matches = n_matches
        return g

    def hypothesis_features(self) -> FeatureSet | None:
        """The features the alternative guesses are weighed with: the attempt's, else the
        frame's (extracted now if need be, not kept for the attempt; None without colour)."""
        if self.feats is None and self.frame.has_color:
            return self.frame.features
        return self.feats

    def evidence(self, matcher: KeyframeRansac, candidates: list[Keyframe]) -> FeatureEvidence:
        """The frame's ORB matches against the candidates (of :meth:`hypothesis_features`),
        made on first use and kept for the attempt: several poses are weighed by them."""
        if self.matched is None:
            self.matched = matcher.evidence(self.hypothesis_features(), candidates)
        return self.matched

    def hypotheses(
        self,
        matcher: KeyframeRansac,
        candidates: list[Keyframe],
        evidence: FeatureEvidence | None = None,
    ) -> list[tuple[str, np.ndarray]]:
        """Alternative guesses of ``T_prev_cur`` (with the path each reports): no motion,
        constant velocity, and the RANSAC pose with the most inliers against the candidates
        (the previous frame and the recent keyframes). Features extracted here are not kept
        for the attempt (so whether the frame leaves its features for the next one depends
        only on the seed, the verification and the keyframe decision). ``evidence``: the
        features' matches against the candidates, when already made."""
        out = [("icp", np.eye(4)), ("icp", self.velocity)]
        feats = self.hypothesis_features()
        if feats is not None and len(feats) > 0:
            g = matcher.best_motion(feats, candidates, self.T_world_prev, evidence)
            if g is not None:
                out.append(("ransac+icp", g))
        return out


def joint_weight(cfg: TrackingConfig, att: Attempt) -> float | None:
    """The photometric weight of this attempt's alignments, None for depth alone (or when the
    frame has no registered colour)."""
    weight = att.photometric
    if weight <= 0 or att.frame.photometric_image(len(cfg.icp.iterations)) is None:
        return None
    return weight


def colour_prefers(cfg: TrackingConfig, att: Attempt, steps: list[np.ndarray]) -> int | None:
    """Which of the competing ``steps`` (``T_prev_cur``) the frame's and the previous frame's
    images agree with best (:func:`~slam.frontend.photometric.photometric_costs` on pyramid
    level 1, every pixel with depth, each colour camera where it was at its image's instant):
    the index of the cheapest; None without registered colour on both frames, or when the
    images do not overlap. A comparison of hypotheses: a few milliseconds, where aligning
    with colour costs a hundred."""
    prev = att.prev_frame
    levels = len(cfg.icp.iterations)
    image = att.frame.photometric_image(levels)
    prev_image = None if prev is None else prev.photometric_image(levels)
    if prev is None or image is None or prev_image is None:
        return None
    level = min(1, levels - 1)
    poses = [(T, colour_pose(T, att.frame.T_depth_colour, prev.T_depth_colour)) for T in steps]
    costs = photometric_costs(
        image.source(level), prev_image.target(level, geometry=False), prev_image.K[level],
        poses, cfg.icp.max_correspondence_m * cfg.icp.coarse_correspondence_factor**level,
    )  # fmt: skip
    if not np.isfinite(min(costs)):
        return None
    return int(np.argmin(costs))


def align_to_model(
    cfg: TrackingConfig,
    att: Attempt,
    model: TrackingModel,
    T_world_guess: np.ndarray,
    trusted: bool = True,
) -> Estimate:
    """Frame-to-model ICP: align the frame to the model ray-cast at the guessed pose. Returns
    the refined pose, the ICP result and the verified overlap. A correction larger than
    ``max_model_correction`` of a ``trusted`` guess (one measured by frame-to-frame ICP or
    RANSAC, not merely predicted) is distrusted: the guess is kept."""
    p = att.frame
    w, h = p.size
    joint = joint_weight(cfg, att)
    refs = att.references if joint is not None else []
    render = model.raycast(
        p.K_track, w, h, T_world_guess, False, joint is not None and not refs,
        frustum_depth_m=p.depth_m, min_weight=att.min_weight,
    )  # fmt: skip
    if refs:
        # the references' real images seen from the guess, through the model's depth: a
        # TSDF's own colour is smeared along the rays it was fused from (unseen pixels: NaN)
        grey_ref = mean_warped_intensity(
            render.depth_m, p.K_track, T_world_guess, refs, cfg.icp.max_correspondence_m
        )
        target = RgbdImage(render.depth_m, grey_ref, p.K_track, len(cfg.icp.iterations))
        icp = p.joint_to(target, np.eye(4), cfg, joint, iterations=att.iterations)
    elif joint is not None and render.color is not None:
        target = RgbdImage(render.depth_m, grey(render.color), p.K_track, len(cfg.icp.iterations))
        icp = p.joint_to(target, np.eye(4), cfg, joint, iterations=att.iterations)
    else:
        icp = p.icp_to(render.depth_m, np.eye(4), cfg, att.iterations)
    step = icp.T_target_source
    if trusted and (
        translation_norm(step) > cfg.icp.max_model_correction_m
        or rotation_angle_deg(step) > cfg.icp.max_model_correction_deg
    ):
        step = np.eye(4)
        att.status.model_rejected = True
    score, rmse = projective_agreement(
        p.depth_m, render.depth_m, p.K_track, step, cfg.icp.inlier_threshold_m,
        noise=depth_noise(cfg), source_max_m=model.depth_max_m,
    )  # fmt: skip
    # the ICP's residual as measured against the model, in metres (Open3D's inlier_rmse is
    # not: 1e-5 "m" on Kinect data)
    icp = dataclasses.replace(icp, inlier_rmse=rmse)
    return T_world_guess @ step, icp, score


def align_from(
    cfg: TrackingConfig,
    att: Attempt,
    model: TrackingModel,
    T_prev_cur: np.ndarray,
    trusted: bool,
    evidence: FeatureEvidence | None = None,
) -> Estimate | None:
    """Frame-to-frame ICP against the previous frame from a guess of ``T_prev_cur`` (when
    enabled; its result is kept when it fits and does not jump), then frame-to-model ICP.
    None when the model ICP would start where this frame already started one (within
    ``same_start_*``): the same result again, at the cost of a ray-cast. ``evidence``: the
    frame's ORB matches, given when the guess is a RANSAC pose: a frame-to-frame result that
    explains fewer than half the matches the guess explains is not kept (along a corridor
    panned fast, ICP slid a RANSAC seed of 236 inliers 6 cm to a pose 25 matches agree with)."""
    p = att.frame
    if cfg.frame_to_frame and att.prev_depth is not None:
        joint = joint_weight(cfg, att) if att.photometric > 0 else None
        prev = None  # the previous frame's grey pyramids, built only when colour joins depth
        if joint is not None and att.prev_frame is not None:
            prev = att.prev_frame.photometric_image(len(cfg.icp.iterations))
        if joint is not None and prev is not None:
            assert att.prev_frame is not None
            f2f = p.joint_to(
                prev, T_prev_cur, cfg, joint, att.prev_frame.T_depth_colour, att.iterations
            )
        else:
            f2f = p.icp_to(att.prev_depth, T_prev_cur, cfg, att.iterations)
        att.status.f2f_fitness = round(float(f2f.fitness), 4)
        if (
            f2f.fitness >= cfg.icp.min_fitness
            and translation_norm(inv_T(T_prev_cur) @ f2f.T_target_source)
            <= cfg.icp.max_step_translation_m
            and not _contradicted(att, evidence, T_prev_cur, f2f.T_target_source)
        ):
            T_prev_cur = f2f.T_target_source
            if joint is None or prev is None:  # depth alone: what depth says of the step
                att.f2f = T_prev_cur
            trusted = True
    T_world_guess = att.T_world_prev @ T_prev_cur
    for T_done in att.tried:
        d = inv_T(T_done) @ T_world_guess
        if (
            translation_norm(d) < cfg.icp.same_start_translation_m
            and rotation_angle_deg(d) < cfg.icp.same_start_rotation_deg
        ):
            return None
    att.tried.append(T_world_guess)
    return align_to_model(cfg, att, model, T_world_guess, trusted)


def _contradicted(
    att: Attempt, evidence: FeatureEvidence | None, T_prev_guess: np.ndarray, T_prev_icp: np.ndarray
) -> bool:
    """The frame's ORB matches contradict an ICP result that moved a guess: it explains fewer
    than half the matches the guess explains (False without ``evidence``)."""
    if evidence is None:
        return False
    guess = evidence.support(att.T_world_prev @ T_prev_guess)
    icp = evidence.support(att.T_world_prev @ T_prev_icp)
    if 2 * icp >= guess:
        return False
    log.debug(
        "frame %d: frame-to-frame ICP moved the RANSAC guess to a pose %d ORB matches agree "
        "with (the guess: %d); the guess is kept", att.frame.index, icp, guess,
    )  # fmt: skip
    return True
