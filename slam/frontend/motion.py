"""The camera's motion between frames: the constant-velocity model tracking predicts with, and
where a moving camera's colour camera was when colour and depth were taken at different
instants (TUM's freiburg1/2 Kinect pairs images up to 17 ms apart)."""

from __future__ import annotations

import numpy as np

from slam.geometry import exp_se3, log_se3

#: The constant-velocity prediction extrapolates over at most this many usual frame intervals.
MAX_EXTRAPOLATION = 30.0


def scale_motion(T: np.ndarray, factor: float) -> np.ndarray:
    """The motion ``T`` continued for ``factor`` times as long (constant twist):
    ``exp(factor * log(T))``. Used to predict across a longer (or shorter) frame interval."""
    if abs(factor - 1.0) < 1e-6:
        return T
    return exp_se3(factor * log_se3(T))


def colour_motion(velocity: np.ndarray, dt_s: float, color_dt_s: float) -> np.ndarray | None:
    """``T_depth_colour``: where the colour camera was, in the depth camera's frame, when it
    took its image ``color_dt_s`` seconds after the depth image, for a camera moving by
    ``velocity`` (``T_prev_cur``) in ``dt_s`` seconds at a constant twist. None when the two
    were taken at the same instant (or the motion is unknown: ``dt_s`` <= 0)."""
    if color_dt_s == 0.0 or dt_s <= 0.0:
        return None
    return scale_motion(velocity, color_dt_s / dt_s)
