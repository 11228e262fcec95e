"""Tracker helpers: the depth range ICP uses."""

from __future__ import annotations

import numpy as np

from slam.frontend.tracker import icp_depth_range


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
