"""The colour stages' helpers: the recording's usual departure and the points colour scores on
the way from depth's step to the prediction (the stages themselves are tested through the
tracker, in test_tracker.py)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slam.config import MotionConfig, TrackingConfig
from slam.frontend import colour_stages
from slam.frontend.colour_stages import PROBES, usual_departure
from slam.geometry import exp_se3, inv_T, log_se3


def test_the_usual_departure_is_the_median_acceleration_over_the_interval():
    cfg = TrackingConfig(
        motion=MotionConfig(unusual_departure_factor=3.0, unusual_departure_window=30)
    )
    recent = [0.2] * 5 + [0.5] * 6  # median 0.5 m/s^2
    assert np.isclose(usual_departure(cfg, recent, 0.1), 3.0 * 0.5 * 0.01)
    # before a third of the window is known, or with the check off: no bound
    assert usual_departure(cfg, recent[:9], 0.1) == float("inf")
    off = TrackingConfig(motion=MotionConfig(unusual_departure_factor=0.0))
    assert usual_departure(off, recent, 0.1) == float("inf")


class _Att:
    def __init__(self, T_world_prev, T_world_cam, velocity):
        self.T_world_prev, self.T_world_cam, self.velocity = T_world_prev, T_world_cam, velocity


twists = st.lists(st.floats(-0.3, 0.3), min_size=6, max_size=6).map(np.array)


@settings(max_examples=30, deadline=None)
@given(twists, twists, twists)
def test_the_probes_run_from_depths_step_to_the_prediction(prev, step, velocity):
    T_world_prev = exp_se3(prev)
    depth_step, T_prev_pred = exp_se3(step), exp_se3(velocity)
    att = _Att(T_world_prev, T_world_prev @ depth_step, T_prev_pred)
    probes = colour_stages._towards_prediction(att)
    assert len(probes) == PROBES
    np.testing.assert_allclose(probes[0], depth_step, atol=1e-9)
    np.testing.assert_allclose(probes[-1], T_prev_pred, atol=1e-7)
    # evenly spaced along the geodesic: equal twists between neighbours
    gaps = [log_se3(inv_T(a) @ b) for a, b in zip(probes, probes[1:])]
    for g in gaps[1:]:
        np.testing.assert_allclose(g, gaps[0], atol=1e-7)
