"""The tracking state machine: a lost frame is relocalised, else tracked against every surface
the model has seen."""

from __future__ import annotations

import numpy as np
import pytest

from slam.config import MappingConfig
from slam.frontend.tracker import Tracker
from slam.geometry import inv_T, translation_norm
from slam.loops.recovery import LossRecovery
from slam.mapping.submaps import SubmapMap
from tests.frontend.test_tracker import World
from tests.tracking_configs import tracking_config


class NoKeyframe:
    """A relocaliser that finds no keyframe."""

    def relocalise(self, *args, **kw):
        return None


@pytest.fixture(scope="module")
def world() -> World:
    return World()


def _recovery(world: World, **cfg) -> LossRecovery:
    """Tracking at frame 11 against a model that renders only surfaces every one of its 11
    frames fused (a fast pan's newest surfaces are left out so): frame 12 overlaps it 0.56."""
    model = SubmapMap(MappingConfig(raycast_weight_threshold=11.0), has_color=True)
    for i in range(11):
        f = world.frame(i)
        model.integrate(f.depth_m, f.color, f.K, world.poses[i])
    tracking = tracking_config(min_overlap=0.7, **cfg)
    tracker = Tracker(tracking)
    tracker.reset(world.frame(11), world.poses[11])
    tracker.state.recent_overlaps = [0.9]
    return LossRecovery(tracking, tracker, model, NoKeyframe(), 0.01, segment=0, run=0)


def test_a_frame_no_keyframe_relocalises_is_tracked_against_every_surface_seen(world):
    recovery = _recovery(world)
    out = recovery.track(recovery.tracker.prepare(world.frame(12)), 1.0, False)
    assert out.T_world_cam is not None and not recovery.lost
    assert translation_norm(inv_T(world.poses[12]) @ out.T_world_cam) < 0.002
    assert "every surface" in out.status.reason
    assert recovery.relocalisations == [{"frame": 12, "method": "model", "min_weight": 1.0}]


def test_off_the_frame_stays_lost(world):
    recovery = _recovery(world, rescue_min_weight=0.0)
    out = recovery.track(recovery.tracker.prepare(world.frame(12)), 1.0, False)
    assert out.T_world_cam is None and recovery.lost and not recovery.relocalisations
    assert np.isfinite(out.status.overlap) and out.status.overlap < 0.6
