"""The tracker: its helpers, each stage of ``Tracker.track`` on a small synthetic scene with exact
depth (pose errors against ground truth), the prepared frame, and checkpoints."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from slam.config import ColourConfig, MappingConfig, MotionConfig, TrackingConfig
from slam.data.base import Frame
from slam.errors import TrackingError
from slam.frontend import colour_stages
from slam.frontend import frame as frame_module
from slam.frontend.alignment import Attempt, align_from, align_to_model
from slam.frontend.features import OrbExtractor
from slam.frontend.frame import PreparedFrame
from slam.frontend.icp import IcpResult
from slam.frontend.motion import scale_motion
from slam.frontend.tracker import Tracker, icp_depth_range
from slam.frontend.tracker_state import TrackerState
from slam.geometry import exp_se3, inv_T, rotation_angle_deg, translation_norm
from slam.keyframe import Keyframe
from slam.mapping.submaps import SubmapMap
from slam.synthetic import SynthConfig, build_scene, make_trajectory, render_frame
from tests.tracking_configs import tracking_config

# ------------------------------------------------------------------------------------------------
# helpers


def _depth(near_fraction: float, near_m: float = 1.5, far_m: float = 3.5) -> np.ndarray:
    d = np.full((60, 80), far_m, np.float32)
    d.flat[: int(near_fraction * d.size)] = near_m
    d[-5:] = 0.0  # holes (here in the far part) do not count
    return d


def test_near_range_when_it_holds_enough_of_the_frame():
    assert icp_depth_range(_depth(0.8), 4.0, 2.5, 0.3) == 2.5
    assert icp_depth_range(_depth(0.3), 4.0, 2.5, 0.3) == 2.5


def test_full_range_for_a_far_scene():
    assert icp_depth_range(_depth(0.2), 4.0, 2.5, 0.3) == 4.0
    assert icp_depth_range(np.zeros((60, 80), np.float32), 4.0, 2.5, 0.3) == 4.0


def test_near_range_beyond_the_full_one_is_the_full_one():
    assert icp_depth_range(_depth(0.8), 2.0, 2.5, 0.3) == 2.0


# ------------------------------------------------------------------------------------------------
# a 320x240 synthetic loop with exact depth (1.8 cm and 1.6 deg between frames), a model fused
# from its first frames at the true poses


class World:
    def __init__(self) -> None:
        self.cfg = SynthConfig.half_resolution(frames=300, loop=True, seed=1, noise=False)
        self.scene = build_scene(self.cfg)
        self.poses = make_trajectory(self.cfg).poses
        self.K = self.cfg.calibration().K
        self._frames: dict[int, Frame] = {}

    def frame(self, i: int) -> Frame:
        if i not in self._frames:
            color, depth = render_frame(self.scene, self.poses[i], self.cfg)
            self._frames[i] = Frame(i, i / 30.0, color, depth, self.K)
        return self._frames[i]

    def model(self, frames: range) -> SubmapMap:
        m = SubmapMap(MappingConfig(), has_color=True)
        for i in frames:
            f = self.frame(i)
            m.integrate(f.depth_m, f.color, f.K, self.poses[i])
        return m


@pytest.fixture(scope="module")
def world() -> World:
    return World()


@pytest.fixture(scope="module")
def model(world) -> SubmapMap:
    """The model of frames 0-10 (the tracker only ray-casts it: tests share it)."""
    return world.model(range(0, 11))


def _errors(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(translation m, rotation deg) between two poses."""
    d = inv_T(T_true) @ T
    return translation_norm(d), rotation_angle_deg(d)


def _tracker_at(world: World, i: int, **cfg) -> Tracker:
    """A tracker reset at frame ``i``'s true pose, as if it had tracked a step there at rest
    (so the motion is known: no motion)."""
    tracker = Tracker(tracking_config(**cfg))
    tracker.reset(world.frame(i), world.poses[i])
    tracker.state.recent_overlaps = [0.9]
    return tracker


def test_the_first_frame_after_a_reset_does_not_trust_the_prediction(world, model):
    # the motion is unknown, not zero (a sequence may start mid-pan): RANSAC seeds it, and no
    # motion pattern can be broken yet
    tracker = Tracker(TrackingConfig())
    tracker.reset(world.frame(9), world.poses[9])
    assert not tracker.state.velocity_known
    att = tracker.predict(tracker.prepare(world.frame(10)))
    assert att.large and not att.verify
    tracker.align(att, model, *tracker.seed(att))
    tracker.check_motion(att, model)
    assert att.ok and not att.status.photometric
    assert att.first_step and att.status.path == "ransac+icp"
    n_keyframes = len(tracker.state.keyframes)
    tracker.commit(att)
    assert tracker.state.velocity_known
    # a small first step seeded by RANSAC makes no keyframe: RANSAC was used because the
    # motion was unknown, not because it was large
    assert len(tracker.state.keyframes) == n_keyframes and not att.status.keyframe
    assert not tracker.predict(tracker.prepare(world.frame(11))).large


def _motion(t_m: float, r_deg: float) -> np.ndarray:
    """A motion of ``t_m`` along x and ``r_deg`` about y."""
    T = exp_se3(np.array([0.0, np.radians(r_deg), 0.0, 0.0, 0.0, 0.0]))
    T[0, 3] = t_m
    return T


# ------------------------------------------------------------------------------------------------
# the stages


def test_predict_scales_the_velocity_by_the_interval_and_flags_large_motion(world):
    tracker = _tracker_at(world, 5)
    tracker.state.velocity = _motion(0.02, 1.0)
    p = tracker.prepare(world.frame(6))
    att = tracker.predict(p, dt_ratio=2.0, segment=3)
    # the same twist for twice as long: twice the angle, a little more than twice the distance
    np.testing.assert_allclose(att.velocity, scale_motion(_motion(0.02, 1.0), 2.0), atol=1e-15)
    assert rotation_angle_deg(att.velocity) == pytest.approx(2.0, abs=1e-9)
    assert translation_norm(att.velocity) == pytest.approx(0.04, abs=1e-5)
    assert not att.large and not att.verify
    assert att.status.path == "icp" and att.status.segment == 3 and not att.status.gap
    np.testing.assert_array_equal(att.T_world_prev, tracker.state.T_world_prev)
    # after reset the previous frame's pyramid is not built: frame-to-frame ICP gets the depth
    assert att.prev_depth is tracker.state.prev_depth
    tracker.state.velocity = _motion(0.02, 0.0)
    # 2.9 intervals: 5.8 cm, not above large_motion_translation_m (6 cm); 4 intervals: 8 cm
    assert not tracker.predict(p, dt_ratio=2.9).large
    assert tracker.predict(p, dt_ratio=4.0).large
    # at most MAX_EXTRAPOLATION (30) intervals
    far = tracker.predict(p, dt_ratio=100.0).velocity
    assert translation_norm(far) == pytest.approx(0.6, abs=1e-9)
    # after a gap the prediction is never trusted
    gap = tracker.predict(p, verify=True)
    assert gap.large and gap.verify and gap.status.gap


def test_a_large_or_unknown_motion_gets_the_large_motion_iterations(world, model, monkeypatch):
    tracker = _tracker_at(world, 5, large_motion_iterations=[9, 7, 5])
    tracker.state.velocity = _motion(0.02, 1.0)
    p = tracker.prepare(world.frame(6))
    assert tracker.predict(p).iterations is None  # tracking.icp.iterations
    gap = tracker.predict(p, verify=True)
    assert gap.large and gap.iterations == [9, 7, 5]
    # every ICP of the attempt (frame to frame, frame to model) runs on that budget
    seen = []
    real = frame_module.projective_icp

    def spy(*args, **kw):
        seen.append(list(args[4]))
        return real(*args, **kw)

    monkeypatch.setattr(frame_module, "projective_icp", spy)
    align_from(tracker.cfg, gap, model, inv_T(world.poses[5]) @ world.poses[6], True)
    assert seen == [[9, 7, 5], [9, 7, 5]]


def test_seed_is_a_ransac_pose_under_large_motion_and_the_prediction_otherwise(world):
    tracker = _tracker_at(world, 0)
    p = tracker.prepare(world.frame(5))  # 8.6 cm and 8.1 deg from frame 0
    rng_before = tracker.state_dict()["rng"]
    guess, trusted = tracker.seed(tracker.predict(p))  # at rest: small motion, no RANSAC
    np.testing.assert_array_equal(guess, np.eye(4))
    assert not trusted
    assert tracker.state_dict()["rng"] == rng_before  # RANSAC drew nothing

    att = tracker.predict(p, verify=True)
    guess, trusted = tracker.seed(att)
    assert trusted and att.status.path == "ransac+icp"
    assert att.status.ransac_inliers >= tracker.cfg.ransac.min_inliers
    assert att.status.ransac_matches >= att.status.ransac_inliers
    assert att.ransac is not None and att.ransac.success and att.feats is p.features
    dt, dr = _errors(att.T_world_prev @ guess, world.poses[5])
    assert dt < 0.02 and dr < 1.0


def test_align_refines_the_guess_against_the_model(world, model):
    tracker = _tracker_at(world, 8)
    att = tracker.predict(tracker.prepare(world.frame(10)))  # 2.8 cm and 3.3 deg away
    tracker.align(att, model, *tracker.seed(att))
    assert att.ok and att.status.path == "icp" and len(att.tried) == 1
    assert att.status.f2f_fitness > 0.85 and att.overlap > 0.6
    dt, dr = _errors(att.T_world_cam, world.poses[10])
    assert dt < 0.003 and dr < 0.2


def test_align_distrusts_a_large_model_correction_of_a_measured_guess(world, model):
    # no frame-to-frame ICP: the model ICP alone corrects a guess 2 cm off the true pose
    tracker = _tracker_at(world, 9, frame_to_frame=False, max_model_correction_m=0.01)
    p = tracker.prepare(world.frame(9))
    off = _motion(0.02, 0.0)
    for trusted in (False, True):
        att = tracker.predict(p)
        tracker.align(att, model, off, trusted)
        dt, _ = _errors(att.T_world_cam, world.poses[9])
        if trusted:  # a measured guess keeps its pose: the 2 cm correction is distrusted
            assert att.status.model_rejected and dt == pytest.approx(0.02, abs=1e-6)
        else:
            assert not att.status.model_rejected and dt < 0.003


def test_a_start_already_tried_is_skipped(world, model):
    tracker = _tracker_at(world, 9, frame_to_frame=False)
    att = tracker.predict(tracker.prepare(world.frame(9)))
    assert align_from(tracker.cfg, att, model, np.eye(4), False) is not None
    # within same_start_translation_m (5 mm) and same_start_rotation_deg (0.3 deg)
    assert align_from(tracker.cfg, att, model, _motion(0.004, 0.2), False) is None
    assert align_from(tracker.cfg, att, model, _motion(0.006, 0.0), False) is not None
    assert len(att.tried) == 2
    tracker.cfg.icp.same_start_translation_m = 0.01
    assert align_from(tracker.cfg, att, model, _motion(0.008, 0.0), False) is None


def test_alternatives_recover_from_a_wrong_prediction(world, model):
    tracker = _tracker_at(world, 9)
    tracker.state.velocity = _motion(0.25, 20.0)  # far off: the frame barely moved
    att = tracker.predict(tracker.prepare(world.frame(10)))
    assert att.large
    hypotheses = att.hypotheses(tracker.ransac, tracker._candidates())
    assert [name for name, _ in hypotheses] == ["icp", "icp", "ransac+icp"]
    dt, dr = _errors(att.T_world_prev @ hypotheses[2][1], world.poses[10])
    assert dt < 0.01 and dr < 1.0  # the RANSAC guess
    # ICP from the prediction alone (as if neither the seed nor the rescue had found a pose)
    first = align_from(tracker.cfg, att, model, att.velocity, False)
    assert first is not None
    att.keep(*first)
    att.ok = att.passes(tracker.cfg)
    assert not att.ok and _errors(att.T_world_cam, world.poses[10])[0] > 0.05
    tracker.alternatives(att, model)
    dt, dr = _errors(att.T_world_cam, world.poses[10])
    assert att.ok and dt < 0.003 and dr < 0.2
    assert len(att.tried) >= 2 and att.overlap > 0.6


def test_alternatives_do_not_keep_a_pose_the_features_contradict(world, model, monkeypatch):
    # a fast pan over a wall: a hypothesis that lags behind the motion stays on what is mapped
    # and overlaps the model better than the true pose; the frame's ORB matches tell them apart
    tracker = _tracker_at(world, 9)
    tracker.state.velocity = _motion(0.25, 20.0)  # large: the alternatives are tried
    att = tracker.predict(tracker.prepare(world.frame(10)))
    att.keep(world.poses[10], IcpResult(np.eye(4), 0.6, 0.001), 0.5)
    att.ok = True

    def hypothesis_at(offset_m):
        T = world.poses[10] @ _motion(offset_m, 0.0)
        return lambda *args, **kw: (T, IcpResult(np.eye(4), 0.9, 0.001), 0.9)

    evidence = tracker.ransac.evidence(att.frame.features, tracker._candidates())
    assert evidence.support(world.poses[10]) >= 20
    assert evidence.support(world.poses[10] @ _motion(0.15, 0.0)) == 0
    monkeypatch.setattr("slam.frontend.tracker.align_from", hypothesis_at(0.15))
    tracker.alternatives(att, model)
    assert att.overlap == 0.5 and _errors(att.T_world_cam, world.poses[10])[0] < 1e-9
    # a hypothesis the features agree with (2 mm off: within their 3 cm) wins on overlap
    monkeypatch.setattr("slam.frontend.tracker.align_from", hypothesis_at(0.002))
    tracker.alternatives(att, model)
    assert att.overlap == 0.9 and _errors(att.T_world_cam, world.poses[10])[0] > 1e-3


def test_frame_to_frame_icp_does_not_move_a_ransac_guess_the_features_contradict(
    world, model, monkeypatch
):
    # along a corridor panned fast, frame-to-frame ICP slid a RANSAC seed of 236 inliers 6 cm
    # to a pose 25 matches agree with; the model ICP's correction back was then distrusted
    tracker = _tracker_at(world, 9)
    att = tracker.predict(tracker.prepare(world.frame(10)))
    guess = inv_T(world.poses[9]) @ world.poses[10]  # what RANSAC would give
    slid = guess @ _motion(0.06, 0.0)
    f2f = IcpResult(slid, 0.9, 0.001)
    icp_to = PreparedFrame.icp_to

    def slides_on_the_previous_frame(self, target, *args, **kw):
        return f2f if target is att.prev_depth else icp_to(self, target, *args, **kw)

    monkeypatch.setattr(PreparedFrame, "icp_to", slides_on_the_previous_frame)
    evidence = att.evidence(tracker.ransac, tracker._candidates())
    assert att.evidence(tracker.ransac, tracker._candidates()) is evidence  # matched once
    assert evidence.support(world.poses[10]) >= 20
    kept, _, _ = align_from(tracker.cfg, att, model, guess, True, evidence)
    assert _errors(kept, world.poses[10])[0] < 0.003 and att.f2f is None
    # without the features, the frame-to-frame result is taken (and the model ICP's
    # correction of 6 cm distrusted)
    att.tried = []
    kept, _, _ = align_from(tracker.cfg, att, model, guess, True)
    assert _errors(kept, world.poses[10])[0] > 0.05 and att.status.model_rejected
    # a result the features agree with is taken
    f2f = IcpResult(guess @ _motion(0.002, 0.0), 0.9, 0.001)
    att.tried = []
    align_from(tracker.cfg, att, model, guess, True, evidence)
    assert att.f2f is f2f.T_target_source


def test_track_renders_the_model_down_to_min_weight(world):
    # a model that renders only surfaces every one of its 11 frames fused (as a fast pan's
    # newest surfaces are left out by the weight threshold): the frame overlaps it too little
    model = SubmapMap(MappingConfig(raycast_weight_threshold=11.0), has_color=True)
    for i in range(11):
        f = world.frame(i)
        model.integrate(f.depth_m, f.color, f.K, world.poses[i])
    tracker = _tracker_at(world, 11, min_overlap=0.7)
    T, status = tracker.track(world.frame(12), model)
    assert T is None and status.overlap < 0.6
    # against every surface seen once (as a lost frame is tried when no keyframe relocalises
    # it: after a gap, ORB matches verify the pose)
    tracker = _tracker_at(world, 11, min_overlap=0.7)
    T, status = tracker.track(world.frame(12), model, verify=True, min_weight=1.0)
    assert T is not None and status.overlap > 0.85
    dt, dr = _errors(T, world.poses[12])
    assert dt < 0.002 and dr < 0.1


def test_a_step_that_breaks_the_motion_pattern_is_aligned_again_with_colour(world, model, caplog):
    tracker = _tracker_at(world, 9)
    p = tracker.prepare(world.frame(10))
    att = tracker.predict(p)  # at rest: the prediction is no motion
    assert att.dt_s == pytest.approx(1.0 / 30.0)  # from the frames' timestamps
    # an estimate 2 cm off the prediction, more than 10 m/s^2 allow in 1/30 s (1.1 cm): as if
    # depth had slid; the check aligns again with colour from the prediction
    slid = world.poses[9] @ _motion(0.02, 0.0)
    att.keep(slid, IcpResult(np.eye(4), 0.9, 0.001), 0.9)
    att.ok = True
    tracker.check_motion(att, model)
    assert att.status.photometric and att.ok and att.photometric > 0
    assert att.status.motion_check == "acceleration"  # recorded in tracking.csv
    dt, dr = _errors(att.T_world_cam, world.poses[10])
    assert dt < 0.003 and dr < 0.2
    # within the bound (a slower camera, or a longer interval), depth alone stands
    calm = tracker.predict(p)
    calm.dt_s = 0.1  # 10 m/s^2 * 0.01 s^2 = 10 cm
    calm.keep(slid, IcpResult(np.eye(4), 0.9, 0.001), 0.9)
    calm.ok = True
    tracker.check_motion(calm, model)
    assert not calm.status.photometric and calm.T_world_cam is slid
    assert calm.status.motion_check == ""
    # without registered colour there is nothing to check with
    blind = Tracker(TrackingConfig(), has_color=True, color_registered=False)
    blind.reset(world.frame(9), world.poses[9])
    blind.state.recent_overlaps = [0.9]
    att = blind.predict(blind.prepare(world.frame(10)))
    att.keep(slid, IcpResult(np.eye(4), 0.9, 0.001), 0.9)
    att.ok = True
    with caplog.at_level(logging.WARNING, logger="slam.frontend.tracker"):
        blind.check_motion(att, model)
    assert not att.status.photometric and att.T_world_cam is slid
    assert "frame 10: its step departs 2.0 cm from the constant-velocity prediction" in caplog.text
    assert "there is no registered colour to check it" in caplog.text


def _checked(tracker: Tracker, p: PreparedFrame, model, T_world_cam: np.ndarray) -> Attempt:
    """The frame's attempt with ``T_world_cam`` as depth's passing estimate, through
    ``check_motion``."""
    att = tracker.predict(p)
    att.keep(T_world_cam, IcpResult(np.eye(4), 0.9, 0.001), 0.9)
    att.ok = True
    tracker.check_motion(att, model)
    return att


def test_a_step_unusual_for_the_recording_is_checked_with_colour(world, model):
    # the recording's camera has accelerated 0.5 m/s^2 (median of its recent departures):
    # 3x that over 1/30 s is 1.7 mm, far below what a hand-held camera can (1.1 cm)
    tracker = _tracker_at(world, 9, unusual_departure_factor=3.0)
    tracker.state.velocity = inv_T(world.poses[9]) @ world.poses[10]  # the true step
    tracker.state.recent_accelerations = [0.5] * 30
    p = tracker.prepare(world.frame(10))

    def attempt(T_world_cam: np.ndarray) -> Attempt:
        return _checked(tracker, p, model, T_world_cam)

    # depth slid 5 mm: unusual here, within the bound: colour returns it to the prediction
    slid = world.poses[10] @ _motion(0.005, 0.0)
    att = attempt(slid)
    assert att.status.photometric and att.ok and att.status.motion_check == "unusual"
    dt, dr = _errors(att.T_world_cam, world.poses[10])
    assert dt < 0.002 and dr < 0.2
    # the motion pattern goes on from the estimate kept, not the slide colour undid
    assert att.acceleration == pytest.approx(dt * 30**2, rel=1e-6)
    # colour's estimate departs further than depth's: depth's step stands
    tracker.state.velocity = inv_T(world.poses[9]) @ world.poses[10] @ _motion(0.006, 0.0)
    near = world.poses[10] @ _motion(0.002, 0.0)
    att = attempt(near)
    assert not att.status.photometric and att.photometric == 0 and att.T_world_cam is near
    tracker.state.velocity = inv_T(world.poses[9]) @ world.poses[10]
    # a frame aligned with colour already (depth was blind) is kept as it is, and its departure
    # joins the pattern too: a far hall tracked with colour for 40 frames had no pattern, and
    # its first depth-only frames slid 12 mm unchecked
    att = tracker.predict(p)
    att.keep(slid, IcpResult(np.eye(4), 0.9, 0.001), 0.9)
    att.ok, att.photometric = True, 1.0
    tracker.check_motion(att, model)
    assert att.T_world_cam is slid and not att.status.photometric
    assert att.acceleration == pytest.approx(0.005 * 30**2, rel=1e-6)
    # before a third of the window is known, or off, depth alone stands
    tracker.state.recent_accelerations = [0.5] * 9
    assert attempt(slid).T_world_cam is slid
    tracker.cfg = TrackingConfig(motion=MotionConfig(unusual_departure_factor=0.0))  # off
    tracker.state.recent_accelerations = [0.5] * 30
    assert attempt(slid).T_world_cam is slid
    # commit records the departure of the estimate kept, the last window of them
    att = attempt(slid)
    assert att.acceleration == pytest.approx(0.005 * 30**2, rel=1e-6)
    tracker.cfg = TrackingConfig(
        motion=MotionConfig(unusual_departure_factor=3.0, unusual_departure_window=30)
    )
    tracker.commit(att)  # (recorded whether or not the check is on)
    assert tracker.state.recent_accelerations == [0.5] * 29 + [att.acceleration]


def test_an_unusual_step_the_images_agree_with_is_not_aligned_again(world, model, monkeypatch):
    # the images are scored on the way from depth's step to the prediction first (a few ms):
    # only where depth's end is not the cheapest is the frame aligned again (~100 ms)
    calls = []

    def counted(*args, **kwargs):
        calls.append(args)
        return align_from(*args, **kwargs)

    monkeypatch.setattr(colour_stages, "align_from", counted)
    tracker = _tracker_at(world, 9, unusual_departure_factor=3.0)
    tracker.state.recent_accelerations = [0.5] * 30
    p = tracker.prepare(world.frame(10))

    def attempt(T_world_cam: np.ndarray) -> Attempt:
        return _checked(tracker, p, model, T_world_cam)

    # the camera really accelerated: the prediction is 6 mm off the true step, depth's estimate
    # 1 mm; the images agree with depth, which stands without another alignment
    tracker.state.velocity = inv_T(world.poses[9]) @ world.poses[10] @ _motion(0.006, 0.0)
    near = world.poses[10] @ _motion(0.001, 0.0)
    att = attempt(near)
    assert att.T_world_cam is near and not att.status.photometric and calls == []
    # depth slid 5 mm from a true prediction: the images agree with the prediction's end
    tracker.state.velocity = inv_T(world.poses[9]) @ world.poses[10]
    att = attempt(world.poses[10] @ _motion(0.005, 0.0))
    assert len(calls) == 1 and att.status.photometric
    assert _errors(att.T_world_cam, world.poses[10])[0] < 0.002


def test_the_near_cut_is_dropped_where_near_depth_alone_is_blind():
    # the wall scene kind, frame 24: a textured wall ~2 m away fills most of the view, so the
    # near-fraction rule picks the 2.5 m cut; the near depth is then blind along the wall and
    # the corner beyond 2.5 m is the only hold: all depth is used
    cfg_s = SynthConfig.half_resolution(frames=240, seed=0, noise=False, scene="wall")
    T = make_trajectory(cfg_s).poses[24]
    color, depth = render_frame(build_scene(cfg_s), T, cfg_s)
    cfg = TrackingConfig()
    p = frame_module.PreparedFrame.build(
        Frame(24, 0.8, color, depth, cfg_s.calibration().K), cfg, None
    )
    rule = icp_depth_range(
        p.depth_m, cfg.depth_max_m, cfg.icp.icp_depth_max_m, cfg.icp.icp_near_fraction
    )
    assert rule == cfg.icp.icp_depth_max_m
    near_only = frame_module.depth_constraint(
        p.pyramid[1], frame_module.scale_intrinsics(p.K_track, 2), rule, frame_module.DepthNoise()
    )
    assert near_only.ratio > cfg.colour.degenerate_ratio
    assert p.icp_depth_max_m == cfg.depth_max_m
    assert p.constraint_ratio < cfg.colour.degenerate_ratio


def test_a_frame_whose_depth_is_blind_is_aligned_with_colour(world, model):
    tracker = _tracker_at(world, 9)
    p = tracker.prepare(world.frame(10))
    cfg = tracker.cfg
    assert p.constraint_ratio < cfg.colour.photometric_ratio  # the room constrains every motion
    # ... so the depth range is the usual one
    assert p.icp_depth_max_m == icp_depth_range(
        p.depth_m, cfg.depth_max_m, cfg.icp.icp_depth_max_m, cfg.icp.icp_near_fraction
    )
    att = tracker.predict(p)
    assert att.photometric == 0 and not att.status.photometric
    assert att.status.constraint_ratio == round(p.constraint_ratio, 2)
    p.constraint_ratio = 100.0  # as if a wall filled the view
    att = tracker.predict(p)
    assert att.photometric > 0 and att.status.photometric
    # weak, not blind: depth keeps its near cut, yet colour joins it, unless the motion is
    # large (after a gap, or RANSAC-seeded: beyond the photometric term's basin)
    p.constraint_ratio = 0.5 * (cfg.colour.photometric_ratio + cfg.colour.degenerate_ratio)
    assert tracker.predict(p).status.photometric
    assert not tracker.predict(p, verify=True).status.photometric
    state = tracker.state
    velocity, overlaps = state.velocity, state.recent_overlaps
    state.velocity = _motion(0.2, 0.0)  # a fast predicted step
    assert tracker.predict(p).large and not tracker.predict(p).status.photometric
    # the first step after a reset: its motion is unknown (large: RANSAC seeds it), not fast
    state.velocity, state.recent_overlaps = np.eye(4), []
    first = tracker.predict(p)
    assert first.first_step and first.large and first.status.photometric
    state.velocity, state.recent_overlaps = velocity, overlaps
    p.constraint_ratio = 100.0
    tracker.align(att, model, *tracker.seed(att))
    dt, dr = _errors(att.T_world_cam, world.poses[10])
    assert att.ok and dt < 0.003 and dr < 0.2


def test_verify_needs_orb_support_after_a_gap(world, model):
    tracker = _tracker_at(world, 9)
    p = tracker.prepare(world.frame(10))
    # a good pose after a gap: ORB matches agree with it
    att = tracker.predict(p, verify=True)
    tracker.align(att, model, *tracker.seed(att))
    att.overlap = 0.5  # below hypothesis_overlap: depth alone does not verify it
    tracker.verify(att)
    assert att.ok and att.status.reason == ""
    assert tracker.ransac.support(att.feats, att.T_world_cam, tracker._candidates()) > 50
    # a pose 20 cm off: no match agrees
    att.T_world_cam = att.T_world_cam @ _motion(0.2, 0.0)
    assert tracker.ransac.support(att.feats, att.T_world_cam, tracker._candidates()) < 8
    tracker.verify(att)
    assert not att.ok and att.status.reason.startswith("unverified after a gap: ")
    assert att.status.overlap == 0.5 and att.status.icp_fitness > 0.7


def test_verify_checks_an_overlap_far_below_the_recent_frames(world, model):
    tracker = _tracker_at(world, 9)
    att = tracker.predict(tracker.prepare(world.frame(10)))
    tracker.align(att, model, *tracker.seed(att))
    att.T_world_cam = att.T_world_cam @ _motion(0.2, 0.0)
    att.overlap = 0.4
    tracker.state.recent_overlaps = [0.9] * 5  # 0.4 < suspect_overlap_ratio (0.6) x 0.9
    tracker.verify(att)
    assert not att.ok and "overlap below 0.6 of the recent frames' 0.90" in att.status.reason
    # not suspect (0.6 >= 0.54) and not after a gap: no verification
    att.ok, att.overlap, att.status.reason = True, 0.6, ""
    tracker.verify(att)
    assert att.ok
    # failing estimates report why
    att.ok = False
    tracker.verify(att)
    assert att.status.reason.startswith("overlap 0.60 (min 0.3), ICP fitness")


def test_commit_updates_the_state_and_decides_keyframes(world, model):
    tracker = _tracker_at(world, 9)
    st = tracker.state
    T_prev = st.T_world_prev
    p = tracker.prepare(world.frame(10))
    att = tracker.predict(p, dt_ratio=2.0)
    tracker.align(att, model, *tracker.seed(att))
    tracker.verify(att)
    T = tracker.commit(att)
    assert T is not None and att.status.ok and not att.status.keyframe
    np.testing.assert_allclose(T, att.T_world_cam, atol=1e-9)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert st.T_world_prev is T and st.prev_depth is p.depth_m and st.prev_pyramid is p.pyramid
    assert st.recent_overlaps == [0.9, float(att.overlap)]
    assert st.prev_features is None  # this frame never needed its features
    # velocity per usual interval: half of the motion over two intervals
    np.testing.assert_allclose(st.velocity, scale_motion(inv_T(T_prev) @ T, 0.5), atol=1e-15)
    assert len(st.keyframes) == 1  # 2.8 cm from the keyframe: none

    # 15 cm (> keyframe_translation_m) from the keyframe: a new one
    att = tracker.predict(tracker.prepare(world.frame(10)))
    att.T_world_cam, att.overlap, att.ok = world.poses[9] @ _motion(0.16, 0.0), 0.9, True
    assert tracker.commit(att) is not None and att.status.keyframe
    kf = st.keyframes[-1]
    assert kf.id == 1 and kf.index == 10 and len(kf.features) > 100
    np.testing.assert_allclose(kf.K, p.K_track)

    # a lost frame: the previous frame is forgotten, the pose and velocity stay
    T_last, v_last = st.T_world_prev, st.velocity
    att = tracker.predict(tracker.prepare(world.frame(10)))
    att.ok = False
    att.status.reason = "test"
    assert tracker.commit(att) is None
    assert att.status.path == "lost" and not att.status.ok
    assert st.prev_depth is None and st.prev_features is None
    assert st.T_world_prev is T_last and st.velocity is v_last


# ------------------------------------------------------------------------------------------------
# the whole of track(), the prepared frame, the API


def test_track_follows_the_true_trajectory(world, model):
    tracker = _tracker_at(world, 4)
    for i in range(5, 11):
        T, status = tracker.track(tracker.prepare(world.frame(i)), model)
        assert T is not None and status.ok and status.path == "icp"
        dt, dr = _errors(T, world.poses[i])
        assert dt < 0.003 and dr < 0.2
    # a plain frame is prepared by track itself
    T2, _ = _tracker_at(world, 9).track(world.frame(10), model)
    dt, dr = _errors(T2, world.poses[10])
    assert dt < 0.003 and dr < 0.2


def test_track_before_reset_says_what_to_do(world, model):
    with pytest.raises(TrackingError, match="call reset"):
        Tracker(TrackingConfig()).track(world.frame(0), model)


def test_model_alignment_warps_the_last_keyframes_colour(world, model):
    """Against the model, colour comes from the last keyframe's image warped into the model's
    view (a TSDF's own colour is smeared along the rays it was fused from). Frames 11-14
    aligned from their true poses with colour: the keyframe's colour lands 0.3-0.8 mm away,
    the model's own 1.0-1.5 mm (measured)."""
    errors = {}
    for reference in ("keyframe", "model"):
        tracker = _tracker_at(world, 10, photometric_reference=reference)
        assert len(tracker.state.references) == (reference == "keyframe")
        if reference == "keyframe":  # the keyframe the tracker was reset at
            np.testing.assert_allclose(tracker.state.references[0][1], world.poses[10])
        errs = []
        for k in (11, 12, 14):
            att = tracker.predict(tracker.prepare(world.frame(k)))
            att.photometric = 1.0
            T, _, overlap = align_to_model(tracker.cfg, att, model, world.poses[k], False)
            assert overlap > 0.7
            errs.append(_errors(T, world.poses[k])[0])
        errors[reference] = errs
    assert max(errors["keyframe"]) < 1e-3, errors
    assert np.mean(errors["keyframe"]) < 0.7 * np.mean(errors["model"]), errors


def test_the_colour_references_are_the_last_keyframes_of_the_segment(world, model):
    """tracking.colour.photometric_keyframes of the newest keyframes' images are kept, oldest first;
    a restart (a new segment, or a relocalised frame) starts them again. A checkpoint written
    before photometric_keyframes existed (one "reference") still loads."""
    tracker = _tracker_at(world, 0, photometric_reference="keyframe", photometric_keyframes=2)
    for i in (3, 6, 9):
        tracker._add_keyframe(tracker.prepare(world.frame(i)), world.poses[i], None, 0)

    def poses(references):  # which frames' poses the references have
        return [int(np.argmin(np.abs(world.poses - T).sum((1, 2)))) for _, T in references]

    assert poses(tracker.state.references) == [6, 9]
    att = tracker.predict(tracker.prepare(world.frame(10)))
    assert poses(att.references) == [6, 9]
    state = tracker.state_dict()
    old = {**state, "reference": state["references"][-1]}
    del old["references"]
    keyframes = {kf.id: kf for kf in tracker.state.keyframes}
    loaded = TrackerState.from_dict(old, keyframes, 3)
    assert poses(loaded.references) == [9]
    tracker.reset(world.frame(150), world.poses[150], "reloc")
    assert poses(tracker.state.references) == [150]


def test_colour_taken_off_the_depths_instant_is_seen_from_where_the_camera_was(world, model):
    """A frame whose colour was taken ``color_dt_s`` after its depth: predict places its
    colour camera along the predicted motion, commit along the motion measured; a keyframe's
    colour reference is posed there, and its features are moved into the depth camera; a
    restart knows no motion (the colour at the pose)."""
    tracker = _tracker_at(world, 9, photometric_reference="keyframe")
    tracker.state.velocity = inv_T(world.poses[9]) @ world.poses[10]
    p = tracker.prepare(dataclasses.replace(world.frame(10), color_dt_s=0.01))
    att = tracker.predict(p)
    assert p.T_depth_colour is not None
    np.testing.assert_allclose(p.T_depth_colour, scale_motion(att.velocity, 0.3), atol=1e-12)
    tracker.align(att, model, *tracker.seed(att))
    tracker.verify(att)
    att.T_world_cam = world.poses[9] @ _motion(0.16, 0.0)  # far enough for a keyframe
    T = tracker.commit(att)
    assert T is not None and att.status.keyframe
    step = inv_T(world.poses[9]) @ T
    np.testing.assert_allclose(p.T_depth_colour, scale_motion(step, 0.3), atol=1e-9)
    np.testing.assert_allclose(tracker.state.references[-1][1], T @ p.T_depth_colour, atol=1e-12)
    # its ORB features (found on the colour image) as the depth camera saw them
    kf = tracker.state.keyframes[-1]
    seen = p._features.in_camera(p.T_depth_colour, p.frame.K)
    assert p.features is kf.features
    # lifted again by the depth where the depth camera sees them
    np.testing.assert_allclose(kf.features.pixels, seen.pixels, atol=1e-9)
    u, v = np.round(seen.pixels).astype(int).T
    h, w = p.frame.depth_m.shape
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    z = np.zeros(len(u))
    z[inside] = p.frame.depth_m[v[inside], u[inside]]
    has = z > 0.2
    assert has.mean() > 0.8
    np.testing.assert_allclose(kf.features.points_cam[has, 2], z[has], atol=1e-6)
    np.testing.assert_allclose(kf.features.points_cam[~has], seen.points_cam[~has], atol=1e-12)
    # synchronised colour: no colour pose; a reset: the motion is unknown
    q = tracker.prepare(world.frame(11))
    tracker.predict(q)
    assert q.T_depth_colour is None
    tracker.reset(p, world.poses[10])
    assert p.T_depth_colour is None
    np.testing.assert_allclose(tracker.state.references[-1][1], world.poses[10], atol=1e-12)


def test_the_first_step_with_colour_off_the_depths_instant_is_aligned_again(world, model):
    """The first step after a restart knows no motion, so neither its colour camera's pose nor
    the restart frame's; once the step is estimated both follow from it, the references see
    the restart frame's colour from there, and the frame is aligned again (in the same place
    here: the frames' colour was in fact taken with their depth)."""
    tracker = Tracker(TrackingConfig())
    tracker.reset(dataclasses.replace(world.frame(9), color_dt_s=-0.01), world.poses[9])
    p = tracker.prepare(dataclasses.replace(world.frame(10), color_dt_s=0.012))
    att = tracker.predict(p)
    assert att.first_step and p.T_depth_colour is None
    att.photometric = 1.0  # colour joins depth on this frame (as where depth is weak)
    tracker.align(att, model, *tracker.seed(att))
    tracker.check_motion(att, model)
    before = att.T_world_cam
    tracker.colour_first_step(att, model)
    step = inv_T(world.poses[9]) @ before
    np.testing.assert_allclose(p.T_depth_colour, scale_motion(step, 0.36), atol=1e-9)
    prev = att.prev_frame
    np.testing.assert_allclose(prev.T_depth_colour, scale_motion(step, -0.3), atol=1e-9)
    ((_, T_ref),) = tracker.state.references
    np.testing.assert_allclose(T_ref, world.poses[9] @ prev.T_depth_colour, atol=1e-9)
    assert tracker.state.keyframes[-1].features is prev.features  # moved and lifted again
    assert att.ok and att.T_world_cam is not before
    assert _errors(att.T_world_cam, world.poses[10])[0] < 0.002
    # synchronised colour: nothing to do
    tracker.reset(world.frame(9), world.poses[9])
    att = tracker.predict(tracker.prepare(world.frame(10)))
    tracker.align(att, model, *tracker.seed(att))
    before = att.T_world_cam
    tracker.colour_first_step(att, model)
    assert att.T_world_cam is before


def test_lost_status_and_colourless_frames(world):
    tracker = Tracker(TrackingConfig(), has_color=False)
    status = tracker.lost_status(world.frame(3), "no usable depth", gap=True)
    assert (status.index, status.path, status.ok, status.gap) == (3, "lost", False, True)
    assert status.reason == "no usable depth" and status.timestamp == pytest.approx(0.1)
    p = tracker.prepare(world.frame(3))
    assert tracker.lost_status(p, "x").index == 3
    assert p.features is None and len(p.view().features) == 0
    assert p.depth_m.shape == (120, 160) and p.K_track[0, 0] == pytest.approx(world.K[0, 0] / 2)
    assert tracker.prepare(p) is p


def test_a_lost_frame_is_filtered_and_orb_extracted_once(world, model, monkeypatch):
    tracker = _tracker_at(world, 10)
    calls = {"bilateral": 0, "orb": 0}
    bilateral, extract = frame_module.bilateral_depth, OrbExtractor.extract

    def counting_bilateral(*a, **kw):
        calls["bilateral"] += 1
        return bilateral(*a, **kw)

    def counting_extract(self, *a, **kw):
        calls["orb"] += 1
        return extract(self, *a, **kw)

    monkeypatch.setattr(frame_module, "bilateral_depth", counting_bilateral)
    monkeypatch.setattr(OrbExtractor, "extract", counting_extract)
    p = tracker.prepare(world.frame(150))  # the other side of the room: not in the model
    T, status = tracker.track(p, model, verify=True)
    assert T is None and status.path == "lost"
    view = p.view()  # relocalisation matches this against the keyframes ...
    assert view.features is p.features and view.depth_m is p.depth_m and view.K is p.K_track
    status = tracker.reset(p, world.poses[150], "reloc")  # ... and tracking restarts there
    assert status.path == "reloc" and status.keyframe
    assert tracker.state.keyframes[-1].features is p.features
    assert calls == {"bilateral": 1, "orb": 1}


def _plain(value) -> bool:
    """Plain data and numpy arrays only (what a checkpoint may hold)."""
    if isinstance(value, dict):
        return all(isinstance(k, str) and _plain(v) for k, v in value.items())
    if isinstance(value, (list, tuple)):
        return all(_plain(v) for v in value)
    return value is None or isinstance(value, (bool, int, float, str, np.ndarray, np.generic))


def test_state_dict_round_trip_gives_the_same_next_result(world, model):
    a = _tracker_at(world, 4, photometric_reference="keyframe")
    for i in range(5, 8):
        a.track(world.frame(i), model)
    a.track(world.frame(8), model, verify=True)  # leaves its features for the next frame
    state = a.state_dict()
    assert _plain(state) and state["keyframes"] == [kf.id for kf in a.state.keyframes]
    assert state["prev_features"] is not None
    keyframes = {kf.id: Keyframe.from_state(kf.to_state()) for kf in a.state.keyframes}
    b = Tracker(TrackingConfig(colour=ColourConfig(photometric_reference="keyframe")))
    b.load_state_dict(state, keyframes)
    assert b.state.keyframes == [keyframes[i] for i in state["keyframes"]]
    assert b.state.recent_accelerations == a.state.recent_accelerations
    assert len(a.state.recent_accelerations) == 4  # frames 5-8 (departures from the prediction)
    assert all(np.array_equal(x, y) for x, y in zip(b.state.prev_pyramid, a.state.prev_pyramid))
    # the colour references (the last keyframes' images) come back with every pyramid level
    assert len(a.state.references) == len(b.state.references) >= 1
    for (ra, Ta), (rb, Tb) in zip(a.state.references, b.state.references):
        assert np.array_equal(Ta, Tb)
        for x, y in zip(ra.depth + ra.intensity + ra.K, rb.depth + rb.intensity + rb.K):
            np.testing.assert_array_equal(x, y)
    # the previous frame: the next frame's joint alignment reads its grey pyramids (a resumed
    # run lost them, so its first frame could not align with colour)
    pa, pb = a.state.prev_frame, b.state.prev_frame
    assert (
        pa is not None and pb is not None and (pa.index, pa.timestamp) == (pb.index, pb.timestamp)
    )
    ia, ib = pa.photometric_image(3), pb.photometric_image(3)
    assert ia is not None and ib is not None
    for x, y in zip(ia.intensity + ia.depth + ia.K, ib.intensity + ib.depth + ib.K):
        np.testing.assert_array_equal(x, y)
    assert pb.frame.color_dt_s == pa.frame.color_dt_s
    assert (
        np.array_equal(pa.T_depth_colour, pb.T_depth_colour)
        or pa.T_depth_colour is None is pb.T_depth_colour
    )
    # after a gap: RANSAC seeds, so the generator's state matters too
    # (Open3D's kernels are not deterministic: the same tracking twice, even by one tracker,
    # may differ by a pixel's correspondence, a few 1e-5 m; a different RANSAC draw would show
    # in the inlier counts and the generator's state)
    results = [t.track(world.frame(10), model, verify=True, dt_ratio=2.0) for t in (a, b)]
    (Ta, sa), (Tb, sb) = results
    np.testing.assert_allclose(Ta, Tb, atol=2e-4)
    discrete = ("path", "ok", "keyframe", "ransac_inliers", "ransac_matches", "model_rejected")
    assert [getattr(sa, k) for k in discrete] == [getattr(sb, k) for k in discrete]
    assert sa.ransac_inliers > 0 and sa.overlap == pytest.approx(sb.overlap, abs=1e-3)
    assert a.state_dict()["rng"] == b.state_dict()["rng"]


def test_the_kernels_prepared_before_a_run_are_the_ones_alignment_calls(world, model):
    """``slam.kernels.prepare`` runs each compiled kernel on the types the tracker passes: a
    joint alignment against the model afterwards compiles nothing more (else the first colour
    frame of a run would pause for it)."""
    from slam import kernels

    kernels.prepare()
    prepared = {d.__name__: len(d.signatures) for d in kernels._dispatchers()}
    tracker = _tracker_at(world, 10, photometric_reference="keyframe")
    att = tracker.predict(tracker.prepare(world.frame(11)))
    att.photometric = 1.0
    align_to_model(tracker.cfg, att, model, world.poses[11], False)
    assert {d.__name__: len(d.signatures) for d in kernels._dispatchers()} == prepared
