"""The stages of tracking where colour checks or refines what depth estimated
(:meth:`slam.frontend.tracker.Tracker.track`'s stage 4, after the alternatives):

- :func:`check_motion`: a step that breaks the motion pattern is aligned again with colour
  joining depth;
- :func:`colour_first_step`: the first step since tracking (re)started, aligned again once the
  step says where the colour cameras were.

Each takes the tracking config, the tracker's state and the frame's :class:`Attempt`, and
updates the attempt; the tracker calls them as its named stages.
"""

from __future__ import annotations

import logging

import numpy as np

from slam.config import TrackingConfig
from slam.frontend.alignment import Attempt, align_from, colour_prefers, joint_weight
from slam.frontend.model import TrackingModel
from slam.frontend.motion import colour_motion
from slam.frontend.tracker_state import TrackerState
from slam.geometry import exp_se3, inv_T, log_se3, translation_norm

__all__ = ["check_motion", "colour_first_step", "usual_departure"]

log = logging.getLogger(__name__)

#: points colour is scored at on the way from depth's step to the prediction (both ends included)
PROBES = 5


def check_motion(
    cfg: TrackingConfig, state: TrackerState, att: Attempt, model: TrackingModel
) -> None:
    """Stage 4b: a step that breaks the motion pattern is not accepted on depth alone (depth
    slides where its geometry is blind: a wall filling the view, a corridor, a far hall).
    It breaks it when it departs from the constant-velocity prediction by more than a
    hand-held camera can accelerate over the interval (``max_acceleration_m_s2 * dt^2``), or
    by more than ``unusual_departure_factor`` times this recording's usual departure
    (:func:`usual_departure`). Such a step is aligned again, frame to frame and then to the
    model, with colour joining depth (where colour is registered), from the prediction, and
    that estimate is kept when it passes the checks. A step that is only unusual is first
    scored by the images on the way to the prediction (:func:`_towards_prediction`, a few
    milliseconds where aligning again costs a hundred): it stands where depth's end is the
    cheapest, and colour's estimate is kept only when it departs less than depth's. Every
    frame's departure, of the estimate kept, joins the pattern (:attr:`Attempt.acceleration`),
    a frame aligned with colour already (its depth blind) too, unchecked."""
    if not (att.ok and cfg.colour.motion_check_photometric_weight > 0):
        return
    if not state.velocity_known:  # no motion pattern to break yet
        return
    assert att.T_world_cam is not None
    predicted = att.T_world_prev @ att.velocity
    departure = translation_norm(inv_T(predicted) @ att.T_world_cam)
    att.acceleration = departure / att.dt_s**2
    if att.photometric != 0:  # aligned with colour already (depth was blind): kept as it is
        return
    bound = cfg.motion.max_acceleration_m_s2 * att.dt_s**2
    what = _breaks_pattern(cfg, state, att, departure, bound)
    if what is None:
        return
    att.status.motion_check = "acceleration" if departure > bound else "unusual"
    if att.frame.photometric_image(len(cfg.icp.iterations)) is None:
        _warn_unconfirmed(att, what, bound, "there is no registered colour to check it")
        return
    # a step only unusual for this recording: kept on depth where the images agree with it
    # better than with any point on the way to the prediction
    unusual_only = departure <= bound
    if unusual_only and colour_prefers(cfg, att, _towards_prediction(att)) == 0:
        return
    _align_with_colour(cfg, att, model, (predicted, departure, bound), what, unusual_only)


def _breaks_pattern(
    cfg: TrackingConfig, state: TrackerState, att: Attempt, departure: float, bound: float
) -> str | None:
    """How the step breaks the motion pattern, in words for the log; None when it does not."""
    cm = 100 * departure
    if departure > bound:
        return f"its step departs {cm:.1f} cm from the constant-velocity prediction"
    usual = usual_departure(cfg, state.recent_accelerations, att.dt_s)
    if departure > usual:
        times = departure / usual * cfg.motion.unusual_departure_factor
        return (
            f"its step departs {cm:.1f} cm from the constant-velocity prediction, "
            f"{times:.1f} times the recent frames' median"
        )
    return None


def _align_with_colour(
    cfg: TrackingConfig,
    att: Attempt,
    model: TrackingModel,
    prediction: tuple[np.ndarray, float, float],
    what: str,
    unusual_only: bool,
) -> None:
    """:func:`check_motion`'s second alignment, with colour, from the prediction
    (``prediction``: the predicted pose, depth's departure from it and the bound)."""
    predicted, departure, bound = prediction
    att.photometric = cfg.colour.motion_check_photometric_weight
    att.tried = []
    estimate = align_from(cfg, att, model, att.velocity, False)
    assert estimate is not None  # nothing was tried since the list was emptied
    T2, icp2, score2 = estimate
    colour_departure = translation_norm(inv_T(predicted) @ T2)
    if unusual_only and colour_departure >= departure:
        att.photometric = 0.0
        return
    if score2 >= cfg.icp.min_overlap and icp2.fitness >= cfg.icp.min_fitness:
        att.keep(T2, icp2, score2)
        att.status.photometric = True
        # the motion pattern is the estimates kept (a slide colour undid is not part of it)
        att.acceleration = colour_departure / att.dt_s**2
    else:
        _warn_unconfirmed(att, what, bound, "aligning with colour failed the checks")
    att.ok = att.passes(cfg)


def _towards_prediction(att: Attempt) -> list[np.ndarray]:
    """The steps (``T_prev_cur``) from depth's estimate to the prediction, at
    :data:`PROBES` evenly spaced points of the way (geodesically), depth's first: where colour
    is cheapest along them says whether it agrees with depth's step. (Both ends can be wrong:
    a desk whose prediction was 5 mm off and whose depth slid 4 mm scored depth's end better
    than the prediction's, and a point between them better still.)"""
    assert att.T_world_cam is not None
    depth_step = inv_T(att.T_world_prev) @ att.T_world_cam
    way = log_se3(inv_T(depth_step) @ att.velocity)
    return [depth_step @ exp_se3(f * way) for f in np.linspace(0.0, 1.0, PROBES)]


def colour_first_step(
    cfg: TrackingConfig, state: TrackerState, att: Attempt, model: TrackingModel
) -> None:
    """Stage 4c: the first step since tracking (re)started, with colour taken off the
    depth's instant (``Frame.color_dt_s``). No motion was known, so the restart frame's
    colour was taken as seen from its depth camera (and this frame's too). Now the step
    is estimated, the restart frame's colour camera follows from it (constant velocity
    over the step): its keyframe's features and colour reference move there. A step
    aligned with colour is aligned again from the estimate, both colour cameras placed,
    and kept when it passes the checks. (Colour 15 ms off the depth on a wall panned at
    90 deg/s moved the first step 32 mm, 10 mm now; RANSAC against the restart keyframe's
    raw features disagreed with depth, and a fast hall lost four frames: see
    docs/archive/journal.md. A second and third pass move the step less each
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
        kf = (
            state.keyframes[-1] if state.keyframes else None
        )  # the restart keyframe, as its depth camera saw it
        if kf is not None and kf.index == prev.index and prev.features is not None:
            kf.features = prev.features
        image = prev.photometric_image(len(cfg.icp.iterations))
        T_colour = att.T_world_prev @ prev.T_depth_colour
        att.references = [(im, T_colour if im is image else T) for im, T in att.references]
        state.references = list(att.references)
    if not joint_weight(cfg, att):
        return
    p.T_depth_colour = colour_motion(step, att.dt_s, p.frame.color_dt_s)
    att.tried = []
    estimate = align_from(cfg, att, model, step, True)
    assert estimate is not None  # nothing was tried since the list was emptied
    if estimate[2] >= cfg.icp.min_overlap and estimate[1].fitness >= cfg.icp.min_fitness:
        att.keep(*estimate)


def usual_departure(cfg: TrackingConfig, recent: list[float], dt_s: float) -> float:
    """The departure from the prediction (m) over ``dt_s`` above which a step breaks this
    recording's own motion pattern: ``tracking.motion.unusual_departure_factor`` times the
    median acceleration of the recent estimates' departures (``recent``, m/s^2) (infinite when off, or before
    a third of the window has been seen since tracking (re)started)."""
    if (
        cfg.motion.unusual_departure_factor <= 0
        or 3 * len(recent) < cfg.motion.unusual_departure_window
    ):
        return float("inf")
    return cfg.motion.unusual_departure_factor * float(np.median(recent)) * dt_s**2


def _warn_unconfirmed(att: Attempt, what: str, bound_m: float, why: str) -> None:
    log.warning(
        "frame %d: %s (a hand-held camera: at most %.1f cm in %.3f s) and %s: kept on depth "
        "alone (ICP fitness %.2f)",
        att.frame.index, what, 100 * bound_m, att.dt_s, why,
        att.icp.fitness if att.icp is not None else 0.0,
    )  # fmt: skip
