"""Elastic correction of all frames from corrected keyframes."""

import numpy as np

from slam.backend.finalise import elastic_correction
from slam.geometry import exp_se3, inv_T, make_T


def test_keyframes_land_on_their_corrected_poses_and_frames_bend_smoothly():
    n = 50
    odo = np.stack([make_T(np.eye(3), [0.02 * k, 0.0, 0.0]) for k in range(n)])
    kf_rows = [0, 10, 20, 30, 40]
    kf_odo = [odo[r] for r in kf_rows]
    # a correction that grows along the path (as after closing a loop)
    kf_new = [
        exp_se3(np.array([0, 0, 0.01 * i, 0, 0.005 * i, 0])) @ T for i, T in enumerate(kf_odo)
    ]
    out = elastic_correction(odo, kf_rows, kf_odo, kf_new)
    for r, T in zip(kf_rows, kf_new):
        np.testing.assert_allclose(out[r], T, atol=1e-12)
    # relative motion of the frames after the last keyframe is kept
    np.testing.assert_allclose(inv_T(out[40]) @ out[49], inv_T(odo[40]) @ odo[49], atol=1e-12)
    # continuity: no step between consecutive frames exceeds 3x the largest odometry step
    step = lambda P: np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)  # noqa: E731
    assert step(out).max() <= 3 * step(odo).max()
    # and the correction is spread evenly: steps inside one keyframe interval are equal
    s = step(out)[10:20]
    assert s.max() - s.min() < 1e-3


def test_no_keyframes_means_no_change():
    odo = np.stack([np.eye(4)] * 3)
    np.testing.assert_array_equal(elastic_correction(odo, [], [], []), odo)
