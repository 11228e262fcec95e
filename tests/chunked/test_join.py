"""Chaining chunks through their overlap, and the joined system against a sequential run."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slam.chunked.join import fit_overlap
from slam.geometry import exp_se3, inv_T, rotation_angle_deg, translation_norm


def _random_T(rng, t_scale=1.0, r_scale=1.0):
    return exp_se3(np.concatenate([rng.normal(0, r_scale, 3), rng.normal(0, t_scale, 3)]))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(3, 40))
def test_overlap_fit_recovers_the_frames_relation_despite_a_few_wrong_pairs(seed, n):
    rng = np.random.default_rng(seed)
    T_prev_cur = _random_T(rng)
    # an overlap's frames: within about 0.3 m of each other (30 frames of a hand-held camera)
    Q = [_random_T(rng, 0.3) for _ in range(n)]
    # the earlier chunk's poses of the same frames: exact up to tracking noise (0.5 mm and
    # 0.03 deg a component: a pair is then at most ~2 mm off, the fit's bound below is 3 mm)
    P = [T_prev_cur @ q @ _random_T(rng, 5e-4, np.radians(0.03)) for q in Q]
    bad = rng.choice(n, size=(n - 1) // 4, replace=False)  # a quarter of the pairs slid far
    for k in bad:
        P[k] = P[k] @ _random_T(rng, 0.2, 0.2)
    fit = fit_overlap(P, Q)
    err = inv_T(T_prev_cur) @ fit.T_prev_cur
    assert translation_norm(err) < 3e-3 and rotation_angle_deg(err) < 0.15
    assert fit.pairs == n and fit.median_mm < 5.0 and fit.max_mm >= fit.median_mm


def test_overlap_fit_of_exact_pairs_is_exact():
    rng = np.random.default_rng(3)
    T = _random_T(rng)
    Q = [_random_T(rng) for _ in range(5)]
    fit = fit_overlap([T @ q for q in Q], Q)
    np.testing.assert_allclose(fit.T_prev_cur, T, atol=1e-9)
    assert fit.max_mm < 1e-6
