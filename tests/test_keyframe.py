import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slam.geometry import exp_se3, inv_T
from slam.keyframe import FeatureSet

K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


def _features(rng: np.random.Generator, n: int = 50) -> FeatureSet:
    z = rng.uniform(0.5, 4.0, n)
    px = rng.uniform([0, 0], [640, 480], (n, 2))
    pts = np.stack([(px[:, 0] - K[0, 2]) * z / K[0, 0], (px[:, 1] - K[1, 2]) * z / K[1, 1], z], 1)
    px_detected = px + rng.normal(0, 0.3, (n, 2))  # ORB's sub-pixel corner, depth at its pixel
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    return FeatureSet(px_detected, desc, pts, rng.integers(0, 8, n))


small_motion = st.lists(st.floats(-0.02, 0.02), min_size=6, max_size=6).map(np.array)


@settings(max_examples=50, deadline=None)
@given(small_motion, st.integers(0, 2**31))
def test_features_seen_from_another_camera(xi, seed):
    """``in_camera``: points moved into the other camera, pixels shifted as their projections
    (the detected sub-pixel offset kept), descriptors and levels unchanged; moving back
    restores them."""
    f = _features(np.random.default_rng(seed))
    T = exp_se3(xi)
    g = f.in_camera(T, K)
    np.testing.assert_allclose(g.points_cam, f.points_cam @ T[:3, :3].T + T[:3, 3], atol=1e-12)
    projected = g.points_cam[:, :2] / g.points_cam[:, 2:] * 525.0 + [319.5, 239.5]
    np.testing.assert_allclose(
        g.pixels - projected,
        f.pixels - f.points_cam[:, :2] / f.points_cam[:, 2:] * 525.0 - [319.5, 239.5],
        atol=1e-9,
    )
    assert g.descriptors is f.descriptors and g.octave is f.octave
    back = g.in_camera(inv_T(T), K)
    np.testing.assert_allclose(back.points_cam, f.points_cam, atol=1e-9)
    np.testing.assert_allclose(back.pixels, f.pixels, atol=1e-6)
    empty = FeatureSet.empty()
    assert empty.in_camera(T, K) is empty
