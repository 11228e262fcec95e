"""Frame-to-model tracking: projective point-to-plane ICP against the model ray-cast, seeded and
rescued by ORB + RANSAC against the last keyframes.

:meth:`Tracker.track` runs a frame through named stages, each a method with its own test:

1. :meth:`~Tracker.predict`: constant-velocity motion over the frame's interval; large motion
   (or a gap) means the prediction alone is not trusted; where the frame's depth is blind in
   one direction (its ``constraint_ratio``: a wall filling the view, a corridor) colour joins
   depth in every alignment of the frame;
2. :meth:`~Tracker.seed`: under large motion, a RANSAC pose against the previous frame or a
   recent keyframe replaces the prediction;
3. :meth:`~Tracker.align`: frame-to-frame ICP from the guess, then frame-to-model ICP against
   the ray-cast (a large model correction of a measured guess is distrusted); when the checks
   fail, RANSAC rescues;
4. :meth:`~Tracker.alternatives`: under large motion or failure, other guesses (no motion,
   constant velocity, the best RANSAC pose); the best overlap wins;
   :meth:`~Tracker.check_motion`: an estimate that departs from the prediction by more than a
   hand-held camera can accelerate is aligned again with colour joining depth (also one
   departing several times more than this recording's recent frames did,
   ``tracking.motion.unusual_departure_factor``, kept only where colour returns it towards the
   prediction); depth slides along a wall filling the view, texture does not;
   :meth:`~Tracker.colour_first_step`: the
   first step, aligned with colour taken off the depth's instant, again once the step gives
   where the colour cameras were;
5. :meth:`~Tracker.verify`: the checks; after a gap, or with an overlap far below the recent
   frames', the pose must be supported by ORB matches;
6. :meth:`~Tracker.commit`: the pose becomes the previous frame of the next one, and maybe a
   keyframe.

The frame's derived inputs come from one :class:`~slam.frontend.frame.PreparedFrame`; what a
stage leaves for the next is on a per-frame :class:`Attempt`.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Protocol

import numpy as np

from slam.config import TrackingConfig
from slam.data.base import Frame
from slam.errors import ConfigError, TrackingError
from slam.frontend import colour_stages
from slam.frontend.alignment import Attempt, align_from, align_to_model
from slam.frontend.features import OrbExtractor
from slam.frontend.frame import PreparedFrame, icp_depth_range
from slam.frontend.keyframe_ransac import KeyframeRansac
from slam.frontend.model import TrackingModel
from slam.frontend.motion import MAX_EXTRAPOLATION, colour_motion, scale_motion
from slam.frontend.tracker_state import TrackerState
from slam.geometry import (
    inv_T,
    orthonormalize,
    rotation_angle_deg,
    translation_norm,
)
from slam.keyframe import FeatureSet, Keyframe
from slam.records import TrackingStatus

__all__ = ["Attempt", "PreparedFrame", "Tracker", "TrackerState", "icp_depth_range"]

log = logging.getLogger(__name__)


class Evidence(Protocol):
    """The registration a relocalised frame was found by (a loop verification's outcome)."""

    overlap: float
    icp_fitness: float
    inliers: int


class Tracker:
    """Estimates ``T_world_cam`` of each new frame against the TSDF model. ``has_color``: frames
    carry colour (ORB features); ``color_registered``: colour is pixel-aligned with depth (the
    photometric term needs it)."""

    def __init__(
        self, cfg: TrackingConfig, has_color: bool = True, color_registered: bool = True
    ) -> None:
        if cfg.downsample not in (1, 2, 4):
            raise ConfigError(f"tracking.downsample must be 1, 2 or 4, got {cfg.downsample}")
        self.cfg = cfg
        self.has_color = has_color
        self.color_registered = has_color and color_registered
        self.orb = OrbExtractor(cfg.ransac.n_features, cfg.depth_min_m, cfg.depth_max_m)
        self.state = TrackerState()
        self._rng = np.random.default_rng(cfg.ransac.seed)
        self.ransac = KeyframeRansac(cfg.ransac, self._rng)

    @property
    def last_keyframe(self) -> Keyframe | None:
        return self.state.keyframes[-1] if self.state.keyframes else None

    @property
    def initialised(self) -> bool:
        """True once a frame has set the pose (and until the tracker is lost)."""
        return self.state.T_world_prev is not None

    def prepare(self, frame: Frame | PreparedFrame) -> PreparedFrame:
        """The frame's tracking inputs, derived once (a prepared frame is returned as it is).
        Pass the result to :meth:`track`, :meth:`reset` and relocalisation (``view()``)."""
        if isinstance(frame, PreparedFrame):
            return frame
        orb = self.orb if self.has_color else None
        return PreparedFrame.build(frame, self.cfg, orb, colour_registered=self.color_registered)

    def reset(
        self,
        prepared: PreparedFrame | Frame,
        T_world_cam: np.ndarray,
        path: str = "init",
        segment: int = 0,
        evidence: Evidence | None = None,
    ) -> TrackingStatus:
        """(Re)start tracking at a frame with a known pose: the first frame of a map segment
        (``init``) or a relocalised frame (``reloc``, with the registration that found it as
        ``evidence``). The frame becomes a keyframe; motion prediction starts from rest."""
        t0 = time.perf_counter()
        p = self.prepare(prepared)
        st = self.state
        T = orthonormalize(np.asarray(T_world_cam, float))
        status = TrackingStatus(p.index, path, True, p.timestamp, segment=segment)
        if evidence is not None:
            status.overlap = round(evidence.overlap, 4)
            status.icp_fitness = evidence.icp_fitness
            status.ransac_inliers = evidence.inliers
        p.T_depth_colour = None  # the motion is unknown: the colour is taken as seen from T
        feats = p.features
        st.restart(p, T, feats)
        self._add_keyframe(p, T, feats, segment)
        status.keyframe = True
        status.ms = (time.perf_counter() - t0) * 1e3 + (p.prep_ms if p is prepared else 0.0)
        return status

    def lost_status(
        self, frame: PreparedFrame | Frame, reason: str, gap: bool = False, segment: int = 0
    ) -> TrackingStatus:
        """The record of a frame lost without tracking (e.g. no usable depth, or no keyframe
        relocalises it); ``segment``: the map segment tracking was in."""
        f = frame.frame if isinstance(frame, PreparedFrame) else frame
        return TrackingStatus(
            f.index, "lost", False, f.timestamp, reason=reason, gap=gap, segment=segment
        )

    def mark_lost(self) -> None:
        """Forget the previous frame (the next one cannot be aligned to it); the last pose and
        velocity stay, to extrapolate from when tracking is tried again."""
        self.state.forget_previous()

    def track(
        self,
        prepared: PreparedFrame | Frame,
        model: TrackingModel,
        verify: bool = False,
        dt_ratio: float = 1.0,
        segment: int = 0,
        min_weight: float | None = None,
    ) -> tuple[np.ndarray | None, TrackingStatus]:
        """Pose of the frame (None when lost); the caller fuses it into ``model`` when
        ``status.ok``. ``dt_ratio``: this frame's interval over the usual one (the
        constant-velocity prediction is scaled by it). ``verify``: the frame follows a gap,
        so the prediction is not trusted: RANSAC and the alternative guesses are always tried,
        and the pose is accepted only when ORB matches support it (or, without features, when
        the depth overlaps the model well). ``min_weight``: the model renders surfaces down
        to this fused weight for every alignment of the frame (None: its own threshold; a
        lost frame is tried against every surface seen once, see
        :class:`slam.loops.recovery.LossRecovery`). Call :meth:`reset` for the first frame."""
        if not self.initialised:
            raise TrackingError(
                "Tracker.track called before Tracker.reset: there is no pose to start from; "
                "call reset(frame, T_world_cam) with the first frame (or a relocalised one)"
            )
        p = self.prepare(prepared)
        t0 = time.perf_counter()
        att = self.predict(p, verify, dt_ratio, segment)
        att.min_weight = min_weight
        self.align(att, model, *self.seed(att))
        self.alternatives(att, model)
        self.check_motion(att, model)
        self.colour_first_step(att, model)
        self.verify(att)
        T = self.commit(att)
        att.status.ms = (time.perf_counter() - t0) * 1e3 + p.prep_ms
        return T, att.status

    # --- the stages of track()
    def predict(
        self, p: PreparedFrame, verify: bool = False, dt_ratio: float = 1.0, segment: int = 0
    ) -> Attempt:
        """Stage 1: the constant-velocity motion ``T_prev_cur`` over this frame's interval
        (``dt_ratio`` usual intervals, at most :data:`MAX_EXTRAPOLATION`), and whether it is
        large (or the frame follows a gap, or is the first since tracking started: its motion
        is unknown): then the prediction alone is not trusted, and every ICP of the frame runs
        ``large_motion_iterations`` (a far start needs more Gauss-Newton steps). A frame
        whose depth is blind in one direction (``constraint_ratio`` above
        ``degenerate_ratio``), or weak in it (above ``photometric_ratio``) while the predicted
        motion is not fast and no gap precedes it, is aligned with colour joining depth (where
        colour is registered)."""
        cfg, st = self.cfg, self.state
        assert st.T_world_prev is not None, "predict needs a previous pose (call reset)"
        velocity = scale_motion(st.velocity, float(np.clip(dt_ratio, 0.0, MAX_EXTRAPOLATION)))
        first_step = not st.velocity_known
        fast = (
            translation_norm(velocity) > cfg.motion.large_motion_translation_m
            or rotation_angle_deg(velocity) > cfg.motion.large_motion_rotation_deg
        )
        large = verify or first_step or fast
        status = TrackingStatus(p.index, "icp", False, p.timestamp, gap=verify)
        status.segment = segment
        prev: np.ndarray | list[np.ndarray] | None = None  # what frame-to-frame ICP aligns to
        if st.prev_depth is not None:
            prev = st.prev_pyramid if st.prev_pyramid is not None else st.prev_depth
        att = Attempt(p, status, st.T_world_prev, velocity, large, verify, dt_ratio, first_step)
        if large:  # a far start: more Gauss-Newton steps to converge
            att.iterations = cfg.icp.large_motion_iterations
        att.prev_depth, att.prev_frame = prev, st.prev_frame
        att.references = list(st.references)
        status.constraint_ratio = round(p.constraint_ratio, 2)
        # depth is blind along one direction, or weak along it while the motion is small
        # enough for the photometric term (not a fast, RANSAC-seeded step: on frames 0.66 s
        # apart colour joining weak depth made the cabinet 0.02 -> 0.11 m): colour joins
        # depth in every alignment. The first step's motion is unknown, not fast: its RANSAC
        # seed puts colour within reach (depth alone slid 36 mm on the first step of a hall)
        att.colour_reach = not (verify or fast)
        weak = p.constraint_ratio > cfg.colour.photometric_ratio and att.colour_reach
        blind = p.constraint_ratio > cfg.colour.degenerate_ratio or weak
        if blind and p.photometric_image(len(cfg.icp.iterations)) is not None:
            att.photometric = cfg.colour.motion_check_photometric_weight
            status.photometric = att.photometric > 0
        if st.t_prev is not None and p.timestamp > st.t_prev:
            att.dt_s = p.timestamp - st.t_prev
        # where the colour camera was when it took its image (Frame.color_dt_s), predicted
        p.T_depth_colour = None
        if not first_step:
            p.T_depth_colour = colour_motion(velocity, att.dt_s, p.frame.color_dt_s)
        return att

    def seed(self, att: Attempt) -> tuple[np.ndarray, bool]:
        """Stage 2: the guess of ``T_prev_cur`` ICP starts from, and whether it was measured
        (trusted) rather than predicted: under large motion a RANSAC pose against the previous
        frame or a recent keyframe, else (or when RANSAC fails) the prediction."""
        if att.large and att.frame.has_color:
            g = att.ransac_guess(self.ransac, self._candidates())
            if g is not None:
                att.status.path = "ransac+icp"
                return inv_T(att.T_world_prev) @ g, True
        return att.velocity, False

    def align(
        self, att: Attempt, model: TrackingModel, T_prev_cur: np.ndarray, trusted: bool
    ) -> None:
        """Stage 3: frame-to-frame then frame-to-model ICP from the seed; when the estimate
        fails the checks and RANSAC was not tried yet, frame-to-model ICP from a RANSAC pose
        (kept when it overlaps the model better)."""
        cfg = self.cfg
        # a RANSAC seed (the only trusted one here) is weighed against the frame's matches
        evidence = att.evidence(self.ransac, self._candidates()) if trusted else None
        first = align_from(cfg, att, model, T_prev_cur, trusted, evidence)
        assert first is not None  # nothing was tried before
        att.keep(*first)
        att.ok = att.passes(cfg)
        if not att.ok and att.frame.has_color and att.ransac is None:
            g = att.ransac_guess(self.ransac, self._candidates())
            if g is not None:
                att.tried.append(g)
                T2, icp2, score2 = align_to_model(cfg, att, model, g)
                if score2 > att.overlap:
                    att.keep(T2, icp2, score2)
                    att.status.path = "ransac+icp"
                att.ok = att.passes(cfg)

    def alternatives(self, att: Attempt, model: TrackingModel) -> None:
        """Stage 4: under large motion or failure (unless the estimate already overlaps the
        model well), ICP from other guesses of ``T_prev_cur`` (:meth:`Attempt.hypotheses`);
        the best overlap with enough ICP correspondences wins, unless the frame's ORB matches
        contradict it: a guess that explains fewer than half the matches the estimate so far
        explains is not kept. (Overlap with the model favours a pose that lags behind a fast
        pan, whose view stays on what is mapped: on a textured wall panned at 120 deg/s a
        hypothesis slid 18 cm along it overlapped 0.76 against the true pose's 0.68.)"""
        cfg = self.cfg
        if not (
            cfg.motion.hypotheses
            and (att.large or not att.ok)
            and att.overlap < cfg.motion.hypothesis_overlap
        ):
            return
        candidates = self._candidates()
        evidence = att.evidence(self.ransac, candidates)
        assert att.T_world_cam is not None
        support = evidence.support(att.T_world_cam)
        for name, guess in att.hypotheses(self.ransac, candidates, evidence):
            ransac = evidence if name == "ransac+icp" else None  # a guess the features made
            estimate = align_from(cfg, att, model, guess, True, ransac)
            if estimate is None:
                continue
            T2, icp2, score2 = estimate
            if score2 > att.overlap and icp2.fitness >= cfg.icp.min_fitness:
                support2 = evidence.support(T2)
                if 2 * support2 < support:  # the features contradict it
                    log.debug(
                        "frame %d: a hypothesis overlapping the model %.2f (estimate: %.2f) is "
                        "not kept: %d ORB matches agree with it, %d with the estimate",
                        att.frame.index, score2, att.overlap, support2, support,
                    )  # fmt: skip
                    continue
                att.keep(T2, icp2, score2)
                att.status.path = name
                support = support2
        att.ok = att.passes(cfg)

    def check_motion(self, att: Attempt, model: TrackingModel) -> None:
        """Stage 4b: :func:`slam.frontend.colour_stages.check_motion` (a step that breaks the
        motion pattern is aligned again with colour joining depth)."""
        colour_stages.check_motion(self.cfg, self.state, att, model)

    def colour_first_step(self, att: Attempt, model: TrackingModel) -> None:
        """Stage 4c: :func:`slam.frontend.colour_stages.colour_first_step` (the first step,
        aligned again once it says where the colour cameras were)."""
        colour_stages.colour_first_step(self.cfg, self.state, att, model)

    def verify(self, att: Attempt) -> None:
        """Stage 5: record the estimate's checks in the status. A passing estimate after a gap,
        or with an overlap far below the recent frames' (a jump the prediction did not see,
        e.g. the camera put down and picked up elsewhere), must also be supported by ORB
        matches, or overlap the model as well as the frames before the gap did."""
        cfg, status = self.cfg, att.status
        assert att.icp is not None and att.T_world_cam is not None
        score = att.overlap
        status.icp_fitness = float(att.icp.fitness)
        status.icp_rmse_m = float(att.icp.inlier_rmse)
        status.overlap = round(score, 4)
        if not att.ok:
            status.reason = (
                f"overlap {score:.2f} (min {cfg.icp.min_overlap}), ICP fitness {att.icp.fitness:.2f} "
                f"(min {cfg.icp.min_fitness}), RANSAC inliers {status.ransac_inliers}"
            )
            return
        recent = self.state.recent_overlaps[-10:]
        usual = float(np.median(recent)) if len(recent) >= 3 else 0.0
        suspect = score < cfg.recovery.suspect_overlap_ratio * usual
        if not (att.verify or suspect):
            return
        support = self.ransac.support(att.features(), att.T_world_cam, self._candidates())
        # depth alone verifies a pose that overlaps the model as well as the frames before
        # the gap did (textureless scenes have no ORB evidence to offer)
        as_before = not suspect and score >= cfg.recovery.verify_overlap_ratio * usual > 0
        if (
            support < cfg.recovery.verify_min_matches
            and score < cfg.motion.hypothesis_overlap
            and not as_before
        ):
            att.ok = False
            status.reason = _unverified_reason(cfg, att.verify, support, score, usual)

    def commit(self, att: Attempt) -> np.ndarray | None:
        """Stage 6: a verified pose (orthonormalised) becomes the previous frame of the next
        one (pose, velocity per usual interval, depth, features, overlap) and a keyframe when
        far enough from the last one, found by RANSAC under a large motion, or after a gap. (The
        first step's RANSAC seed says the motion was unknown, not large: a keyframe there would
        shift every later keyframe, which moved 7-Scenes' odometry 0.0376 -> 0.0395 m.) A lost
        frame: the previous frame is forgotten (:meth:`mark_lost`); returns None."""
        cfg, st, p, status = self.cfg, self.state, att.frame, att.status
        status.ok = att.ok
        if not att.ok:
            status.path = "lost"
            log.info("frame %d: tracking lost: %s", p.index, status.reason)
            self.mark_lost()
            return None
        assert att.T_world_cam is not None
        T = orthonormalize(att.T_world_cam)
        dt = float(np.clip(att.dt_ratio, 0.2, 5.0))
        step = inv_T(att.T_world_prev) @ T
        velocity = scale_motion(step, 1.0 / dt)
        # the colour camera's pose, from the motion measured (the next frame and the keyframe
        # references see this frame's colour, the keyframes its features, from there)
        p.T_depth_colour = colour_motion(step, att.dt_s, p.frame.color_dt_s)
        if att.feats is not None:
            att.feats = p.features
        st.advance(p, T, velocity, att.overlap, att.feats)
        if att.acceleration is not None:
            st.record_departure(att.acceleration, cfg.motion.unusual_departure_window)
        kf = self.last_keyframe
        if kf is not None:
            rel = inv_T(kf.T_world_cam) @ T
            if (
                translation_norm(rel) > cfg.keyframe_translation_m
                or rotation_angle_deg(rel) > cfg.keyframe_rotation_deg
                or (status.path.startswith("ransac") and not att.first_step)
                or att.verify
            ):
                self._add_keyframe(p, T, att.features(), status.segment)
                status.keyframe = True
        return T

    # --- helpers
    def _add_keyframe(
        self, p: PreparedFrame, T: np.ndarray, feats: FeatureSet | None, segment: int
    ) -> None:
        """The frame becomes the next keyframe and, with registered colour, the newest of the
        references whose images the joint alignment against the model warps into the model's
        view and averages."""
        st = self.state
        st.add_keyframe(p, T, feats, segment)
        image = None  # without registered colour: the model's own colour
        if self.cfg.colour.photometric_reference == "keyframe":
            image = p.photometric_image(len(self.cfg.icp.iterations))
        if image is None:
            st.references = []
        else:  # the pose its colour was seen from
            T_colour = T.copy() if p.T_depth_colour is None else T @ p.T_depth_colour
            st.references = (st.references + [(image, T_colour)])[
                -self.cfg.colour.photometric_keyframes :
            ]

    def _candidates(self) -> list[Keyframe]:
        return self.state.ransac_candidates(self.cfg.recovery.relocalisation_keyframes)

    # --- checkpoints
    def state_dict(self) -> dict[str, Any]:
        """The tracker's checkpoint state as plain data and numpy arrays: pose, velocity,
        previous depth and features, recent overlaps, keyframes by id (the caller saves the
        keyframes themselves once, ``Keyframe.to_state``) and the RANSAC generator's state."""
        return {**self.state.to_dict(), "rng": self._rng.bit_generator.state}

    def load_state_dict(self, state: dict[str, Any], keyframes_by_id: dict[int, Keyframe]) -> None:
        """Continue from :meth:`state_dict` (``keyframes_by_id``: the checkpoint's keyframes,
        ``Keyframe.from_state``): the next ``track`` gives what it would have given."""
        self.state = TrackerState.from_dict(state, keyframes_by_id, len(self.cfg.icp.iterations))
        self._rng.bit_generator.state = state["rng"]


def _unverified_reason(
    cfg: TrackingConfig, gap: bool, support: int, overlap: float, usual: float
) -> str:
    why = (
        "after a gap"
        if gap
        else f"(overlap below {cfg.recovery.suspect_overlap_ratio} of the recent frames' {usual:.2f})"
    )
    return (
        f"unverified {why}: {support} ORB matches agree with the pose "
        f"(min {cfg.recovery.verify_min_matches}) and overlap {overlap:.2f} < "
        f"{cfg.motion.hypothesis_overlap} and < {cfg.recovery.verify_overlap_ratio} x the "
        f"recent frames' {usual:.2f}"
    )
