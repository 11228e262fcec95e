import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slam.frontend.ransac import kabsch, kabsch_batch, ransac_rigid, umeyama
from slam.geometry import exp_se3, inv_T, rotation_angle_deg, translation_norm

twist = st.tuples(*[st.floats(-2.0, 2.0)] * 3, *[st.floats(-2.0, 2.0)] * 3).map(np.array)


@settings(max_examples=100, deadline=None)
@given(twist, st.integers(0, 10_000))
def test_kabsch_recovers_random_rigid_motion(xi, seed):
    rng = np.random.default_rng(seed)
    T = exp_se3(xi)
    src = rng.uniform(-1, 1, (20, 3))
    dst = src @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(kabsch(src, dst), T, atol=1e-8)


@settings(max_examples=50, deadline=None)
@given(st.lists(twist, min_size=1, max_size=4), st.integers(0, 10_000))
def test_kabsch_batch_solves_each_item_on_its_weighted_pairs(xis, seed):
    """Each item of a batch is its own weighted problem: pairs of weight 0 (here wrong ones)
    do not count, and the batch agrees with the single solve."""
    rng = np.random.default_rng(seed)
    Ts = np.array([exp_se3(xi) for xi in xis])
    src = rng.uniform(-1, 1, (len(xis), 12, 3))
    dst = np.einsum("bij,bnj->bni", Ts[:, :3, :3], src) + Ts[:, None, :3, 3]
    weights = rng.uniform(0.5, 2.0, (len(xis), 12))
    weights[:, :3] = 0.0
    dst[:, :3] += rng.uniform(-1, 1, (len(xis), 3, 3))  # wrong, and weightless
    got = kabsch_batch(src, dst, weights)
    np.testing.assert_allclose(got, Ts, atol=1e-8)
    np.testing.assert_allclose(got[0], kabsch(src[0], dst[0], weights[0]), atol=1e-12)


@settings(max_examples=50, deadline=None)
@given(twist, st.floats(0.2, 5.0))
def test_umeyama_recovers_similarity(xi, scale):
    rng = np.random.default_rng(1)
    T = exp_se3(xi)
    src = rng.uniform(-1, 1, (30, 3))
    dst = scale * src @ T[:3, :3].T + T[:3, 3]
    T_est, s_est = umeyama(src, dst)
    assert abs(s_est - scale) < 1e-8
    np.testing.assert_allclose(T_est[:3, :3], T[:3, :3], atol=1e-8)


def test_ransac_with_half_outliers():
    rng = np.random.default_rng(7)
    T = exp_se3(np.array([0.2, -0.3, 0.5, 0.4, -0.2, 0.3]))
    src = rng.uniform([-2, -1.5, 0.5], [2, 1.5, 4.0], (200, 3))
    dst = src @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.003, (200, 3))
    outliers = rng.permutation(200)[:100]  # 50% wrong matches
    dst[outliers] = rng.uniform([-2, -1.5, 0.5], [2, 1.5, 4.0], (100, 3))
    res = ransac_rigid(src, dst, iterations=500, threshold=0.02, min_inliers=20, rng=rng)
    assert res.success
    err = inv_T(T) @ res.T
    assert translation_norm(err) < 0.003
    assert rotation_angle_deg(err) < 0.2
    true_inliers = np.ones(200, bool)
    true_inliers[outliers] = False
    assert (res.inliers == true_inliers).mean() > 0.97


def test_ransac_fails_cleanly_on_pure_noise():
    rng = np.random.default_rng(3)
    src = rng.uniform(-1, 1, (60, 3))
    dst = rng.uniform(-1, 1, (60, 3))
    res = ransac_rigid(src, dst, iterations=300, threshold=0.01, min_inliers=15, rng=rng)
    assert not res.success


def test_ransac_too_few_points():
    res = ransac_rigid(np.zeros((2, 3)), np.zeros((2, 3)))
    assert not res.success and res.n_inliers == 0
