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
   hand-held camera can accelerate is aligned again with colour joining depth (opt-in,
   ``tracking.unusual_departure_factor``: also one departing several times more than this
   recording's recent frames did, kept only where colour returns it towards the
   prediction; ``tracking.depth_disagreement_check``: one whose frame-to-frame and model
   ICP end far apart); depth slides along a wall filling the view, texture does not;
   :meth:`~Tracker.colour_first_step`: the
   first step, aligned with colour taken off the depth's instant, again once the step gives
   where the colour cameras were; :meth:`~Tracker.colour_step` (opt-in,
   ``tracking.colour_step_weight``): the estimate refined against the previous frame's
   colour, depth's estimate a prior, at the weight colour has earned on the recording;
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
from slam.frontend.alignment import Attempt, align_from, align_to_model, joint_weight
from slam.frontend.colour_step import StepSettings, step_with_colour
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
        self.photometric = has_color and color_registered and cfg.photometric_weight > 0
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
        return PreparedFrame.build(
            frame, self.cfg, orb, self.photometric, colour_registered=self.color_registered
        )

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
        self.colour_step(att)
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
            translation_norm(velocity) > cfg.large_motion_translation_m
            or rotation_angle_deg(velocity) > cfg.large_motion_rotation_deg
        )
        large = verify or first_step or fast
        status = TrackingStatus(p.index, "icp", False, p.timestamp, gap=verify)
        status.segment = segment
        prev: np.ndarray | list[np.ndarray] | None = None  # what frame-to-frame ICP aligns to
        if st.prev_depth is not None:
            prev = st.prev_pyramid if st.prev_pyramid is not None else st.prev_depth
        att = Attempt(p, status, st.T_world_prev, velocity, large, verify, dt_ratio, first_step)
        if large:  # a far start: more Gauss-Newton steps to converge
            att.iterations = cfg.large_motion_iterations
        att.prev_depth, att.prev_frame = prev, st.prev_frame
        att.references = list(st.references)
        status.constraint_ratio = round(p.constraint_ratio, 2)
        # depth is blind along one direction, or weak along it while the motion is small
        # enough for the photometric term (not a fast, RANSAC-seeded step: on frames 0.66 s
        # apart colour joining weak depth made the cabinet 0.02 -> 0.11 m): colour joins
        # depth in every alignment. The first step's motion is unknown, not fast: its RANSAC
        # seed puts colour within reach (depth alone slid 36 mm on the first step of a hall)
        att.colour_reach = not (verify or fast)
        weak = p.constraint_ratio > cfg.photometric_ratio and att.colour_reach
        blind = p.constraint_ratio > cfg.degenerate_ratio or weak
        if blind and p.photometric_image(len(cfg.iterations)) is not None:
            att.photometric = cfg.motion_check_photometric_weight
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
            cfg.hypotheses and (att.large or not att.ok) and att.overlap < cfg.hypothesis_overlap
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
            if score2 > att.overlap and icp2.fitness >= cfg.min_fitness:
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
        """Stage 4b: a step that breaks the motion pattern, or that depth's two estimates
        disagree on, is not accepted on depth alone. The bound is what a hand-held camera can
        accelerate over the interval (``max_acceleration_m_s2 * dt^2``). When the estimate
        departs from the constant-velocity prediction by more, or (opt-in,
        ``tracking.depth_disagreement_check``) frame-to-frame ICP and the model ICP that
        started from it end further apart (one of them slid), depth may be
        sliding where its geometry is blind (a wall filling the view, a corridor, a far hall):
        the frame is aligned again, frame to frame and then to the model, with colour joining
        depth (where colour is registered), from the prediction, and that estimate is kept when
        it passes the checks. (Aligning to the model alone, or keeping the colour estimate only
        where it disagrees with depth by more than the bound, let slides through on the fast
        wall and corridor rows of the scene matrix; the disagreement of depth's two estimates
        catches slides the prediction does not: a wall whose frame-to-frame ICP slid 25 mm
        and the model ICP took back to 7 mm, within the bound of the prediction. See
        docs/benchmarks.md, session 32.) Opt-in: a departure below the bound but more than
        ``tracking.unusual_departure_factor`` times this recording's usual one (the median
        acceleration of the last ``unusual_departure_window`` estimates kept) breaks the
        recording's own motion pattern: colour's estimate is kept there only when it departs
        less than depth's (a smooth pan's slides stand out against its pattern; a hand-held
        Kinect's colour moved such steps away). Every checked frame's departure, of the
        estimate kept, joins the pattern (:attr:`Attempt.acceleration`)."""
        cfg = self.cfg
        if not (att.ok and cfg.motion_check_photometric_weight > 0 and att.photometric == 0):
            return
        if not self.state.velocity_known:  # no motion pattern to break yet
            return
        assert att.T_world_cam is not None
        predicted = att.T_world_prev @ att.velocity
        bound = cfg.max_acceleration_m_s2 * att.dt_s**2
        departure = translation_norm(inv_T(predicted) @ att.T_world_cam)
        att.acceleration = departure / att.dt_s**2
        disagreement = att.depth_disagreement() if cfg.depth_disagreement_check else 0.0
        usual = self._usual_departure(att.dt_s)
        if max(departure, disagreement) <= bound and departure <= usual:
            return
        if departure > bound:
            what = (
                f"its step departs {100 * departure:.1f} cm from the constant-velocity prediction"
            )
        elif departure > usual:
            what = (
                f"its step departs {100 * departure:.1f} cm from the constant-velocity "
                f"prediction, {departure / usual * cfg.unusual_departure_factor:.1f} times "
                "the recent frames' median"
            )
        else:
            what = f"depth's two estimates of it are {100 * disagreement:.1f} cm apart"
        if att.frame.photometric_image(len(cfg.iterations)) is None:
            _warn_unconfirmed(att, what, bound, "there is no registered colour to check it")
            return
        att.photometric = cfg.motion_check_photometric_weight
        att.tried = []
        estimate = align_from(cfg, att, model, att.velocity, False)
        assert estimate is not None  # nothing was tried since the list was emptied
        T2, icp2, score2 = estimate
        # a step only unusual for this recording is kept on depth unless colour's estimate
        # returns towards the motion pattern (colour on a real Kinect moved such steps away)
        unusual_only = max(departure, disagreement) <= bound
        colour_departure = translation_norm(inv_T(predicted) @ T2)
        if unusual_only and colour_departure >= departure:
            att.photometric = 0.0
            return
        if score2 >= cfg.min_overlap and icp2.fitness >= cfg.min_fitness:
            att.keep(T2, icp2, score2)
            att.status.photometric = True
            # the motion pattern is the estimates kept (a slide colour undid is not part of it)
            att.acceleration = colour_departure / att.dt_s**2
        else:
            _warn_unconfirmed(att, what, bound, "aligning with colour failed the checks")
        att.ok = att.passes(cfg)

    def colour_first_step(self, att: Attempt, model: TrackingModel) -> None:
        """Stage 4c: the first step since tracking (re)started, with colour taken off the
        depth's instant (``Frame.color_dt_s``). No motion was known, so the restart frame's
        colour was taken as seen from its depth camera (and this frame's too). Now the step
        is estimated, the restart frame's colour camera follows from it (constant velocity
        over the step): its keyframe's features and colour reference move there. A step
        aligned with colour is aligned again from the estimate, both colour cameras placed,
        and kept when it passes the checks. (Colour 15 ms off the depth on a wall panned at
        90 deg/s moved the first step 32 mm, 10 mm now; RANSAC against the restart keyframe's
        raw features disagreed with depth, and a fast hall lost four frames: see
        docs/benchmarks.md, session 20. A second and third pass move the step less each
        time: the colour images of one step may be a few milliseconds apart.)"""
        p, prev = att.frame, att.prev_frame
        if not (att.first_step and att.ok and prev is not None):
            return
        if p.frame.color_dt_s == 0.0 and prev.frame.color_dt_s == 0.0:
            return
        assert att.T_world_cam is not None
        step = inv_T(att.T_world_prev) @ att.T_world_cam
        prev.T_depth_colour = colour_motion(step, att.dt_s, prev.frame.color_dt_s)
        if prev.T_depth_colour is not None:
            kf = self.last_keyframe  # the restart keyframe, as its depth camera saw it
            if kf is not None and kf.index == prev.index and prev.features is not None:
                kf.features = prev.features
            image = prev.photometric_image(len(self.cfg.iterations))
            T_colour = att.T_world_prev @ prev.T_depth_colour
            att.references = [(im, T_colour if im is image else T) for im, T in att.references]
            self.state.references = list(att.references)
        if not joint_weight(self.cfg, att):
            return
        p.T_depth_colour = colour_motion(step, att.dt_s, p.frame.color_dt_s)
        att.tried = []
        estimate = align_from(self.cfg, att, model, step, True)
        assert estimate is not None  # nothing was tried since the list was emptied
        if estimate[2] >= self.cfg.min_overlap and estimate[1].fitness >= self.cfg.min_fitness:
            att.keep(*estimate)

    def colour_step(self, att: Attempt) -> None:
        """Stage 4d (``tracking.colour_step_weight`` > 0, where colour is registered): the
        estimate refined against the previous frame's image, depth's estimate as a prior with
        its information (:func:`slam.frontend.colour_step.colour_refine`), at the weight colour
        has earned on this recording (:class:`~slam.frontend.colour_step.ColourAgreement`:
        colour's disagreement with depth where depth is surest, over depth's own). The colour
        cameras are where :meth:`predict` or, on the first step, :meth:`colour_first_step`
        placed them. Not under a large motion (a fast step, a gap: the photometric term's basin
        is a few pixels; on the cabinet, frames 0.66 s apart, its worst step went 29 -> 41 mm).
        The first step's motion is unknown, not large: its RANSAC seed puts colour in reach."""
        cfg, st, prev = self.cfg, self.state, att.prev_frame
        att.T_world_depth = att.T_world_cam
        if not (cfg.colour_step_weight > 0 and att.ok and prev is not None):
            return
        if att.large and not att.first_step:  # fast, or after a gap: beyond colour's basin
            return
        levels = len(cfg.iterations)
        source, target = att.frame.photometric_image(levels), prev.photometric_image(levels)
        if source is None or target is None:
            return
        assert att.T_world_cam is not None
        depth_step = None  # this frame's depth estimate relative to the previous frame's
        if st.T_world_prev_depth is not None:
            depth_step = inv_T(st.T_world_prev_depth) @ att.T_world_cam
        T_prev_cur = inv_T(att.T_world_prev) @ att.T_world_cam
        settings = StepSettings(
            cfg.max_correspondence_m, cfg.huber_delta_m,
            cfg.colour_step_textured, cfg.colour_step_geometry_stride,
        )  # fmt: skip
        refined = step_with_colour(
            source, target, T_prev_cur, st.colour_agreement,
            (depth_step, att.f2f), cfg.colour_step_weight, cfg.colour_step_iterations,
            settings, (att.frame.T_depth_colour, prev.T_depth_colour),
        )  # fmt: skip
        if refined is not T_prev_cur:
            att.T_world_cam = att.T_world_prev @ refined

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
                f"overlap {score:.2f} (min {cfg.min_overlap}), ICP fitness {att.icp.fitness:.2f} "
                f"(min {cfg.min_fitness}), RANSAC inliers {status.ransac_inliers}"
            )
            return
        recent = self.state.recent_overlaps[-10:]
        usual = float(np.median(recent)) if len(recent) >= 3 else 0.0
        suspect = score < cfg.suspect_overlap_ratio * usual
        if not (att.verify or suspect):
            return
        support = self.ransac.support(att.features(), att.T_world_cam, self._candidates())
        # depth alone verifies a pose that overlaps the model as well as the frames before
        # the gap did (textureless scenes have no ORB evidence to offer)
        as_before = not suspect and score >= cfg.verify_overlap_ratio * usual > 0
        if support < cfg.verify_min_matches and score < cfg.hypothesis_overlap and not as_before:
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
        moved = att.T_world_depth is not None and att.T_world_depth is not att.T_world_cam
        st.advance(p, T, velocity, att.overlap, att.feats, att.T_world_depth if moved else None)
        if att.acceleration is not None:
            st.record_departure(att.acceleration, cfg.unusual_departure_window)
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
        if self.cfg.photometric_reference == "keyframe":
            image = p.photometric_image(len(self.cfg.iterations))
        if image is None:
            st.references = []
        else:  # the pose its colour was seen from
            T_colour = T.copy() if p.T_depth_colour is None else T @ p.T_depth_colour
            st.references = (st.references + [(image, T_colour)])[-self.cfg.photometric_keyframes :]

    def _usual_departure(self, dt_s: float) -> float:
        """The departure from the prediction (m) over ``dt_s`` above which a step breaks this
        recording's own motion pattern: ``tracking.unusual_departure_factor`` times the
        median acceleration of the recent estimates' departures (infinite when off, or before
        a third of the window has been seen since tracking (re)started)."""
        cfg, recent = self.cfg, self.state.recent_accelerations
        if cfg.unusual_departure_factor <= 0 or 3 * len(recent) < cfg.unusual_departure_window:
            return float("inf")
        return cfg.unusual_departure_factor * float(np.median(recent)) * dt_s**2

    def _candidates(self) -> list[Keyframe]:
        return self.state.ransac_candidates(self.cfg.relocalisation_keyframes)

    # --- checkpoints
    def state_dict(self) -> dict[str, Any]:
        """The tracker's checkpoint state as plain data and numpy arrays: pose, velocity,
        previous depth and features, recent overlaps, keyframes by id (the caller saves the
        keyframes themselves once, ``Keyframe.to_state``) and the RANSAC generator's state."""
        return {**self.state.to_dict(), "rng": self._rng.bit_generator.state}

    def load_state_dict(self, state: dict[str, Any], keyframes_by_id: dict[int, Keyframe]) -> None:
        """Continue from :meth:`state_dict` (``keyframes_by_id``: the checkpoint's keyframes,
        ``Keyframe.from_state``): the next ``track`` gives what it would have given."""
        self.state = TrackerState.from_dict(state, keyframes_by_id, len(self.cfg.iterations))
        self._rng.bit_generator.state = state["rng"]


def _warn_unconfirmed(att: Attempt, what: str, bound_m: float, why: str) -> None:
    log.warning(
        "frame %d: %s (a hand-held camera: at most %.1f cm in %.3f s) and %s: kept on depth "
        "alone (ICP fitness %.2f)",
        att.frame.index, what, 100 * bound_m, att.dt_s, why,
        att.icp.fitness if att.icp is not None else 0.0,
    )  # fmt: skip


def _unverified_reason(
    cfg: TrackingConfig, gap: bool, support: int, overlap: float, usual: float
) -> str:
    why = (
        "after a gap"
        if gap
        else f"(overlap below {cfg.suspect_overlap_ratio} of the recent frames' {usual:.2f})"
    )
    return (
        f"unverified {why}: {support} ORB matches agree with the pose "
        f"(min {cfg.verify_min_matches}) and overlap {overlap:.2f} < "
        f"{cfg.hypothesis_overlap} and < {cfg.verify_overlap_ratio} x the "
        f"recent frames' {usual:.2f}"
    )
