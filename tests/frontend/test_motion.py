import numpy as np

from slam.frontend.motion import colour_motion, scale_motion
from slam.geometry import exp_se3, inv_T


def test_a_motion_continued_keeps_its_twist():
    """``scale_motion``: twice as long is the motion twice; a factor of 1 is the motion itself;
    -1 is its inverse."""
    step = exp_se3(np.array([0.02, 0.01, -0.03, 0.01, -0.02, 0.004]))
    np.testing.assert_allclose(scale_motion(step, 2.0), step @ step, atol=1e-12)
    assert scale_motion(step, 1.0) is step
    np.testing.assert_allclose(scale_motion(step, -1.0), inv_T(step), atol=1e-12)


def test_the_colour_cameras_pose_follows_the_motion():
    """``colour_motion``: half an interval after the depth, half the interval's motion; before
    it, the motion reversed; at the same instant, or with the interval unknown, none."""
    step = exp_se3(np.array([0.01, -0.02, 0.03, 0.02, 0.01, -0.005]))
    half = colour_motion(step, 1 / 30, 1 / 60)
    assert np.allclose(half @ half, step, atol=1e-12)
    before = colour_motion(step, 1 / 30, -1 / 30)
    assert np.allclose(before, inv_T(step), atol=1e-12)
    assert colour_motion(step, 1 / 30, 0.0) is None
    assert colour_motion(step, 0.0, 0.01) is None
