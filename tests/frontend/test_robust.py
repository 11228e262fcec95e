import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from slam.frontend.photometric import _BLOCK_ROWS, _tall_times
from slam.frontend.robust import MAD, median, robust_scale


@settings(max_examples=200, deadline=None)
@given(
    arrays(
        st.sampled_from([np.float32, np.float64]),
        st.integers(1, 300),
        elements=st.floats(-1e3, 1e3, width=32),
    )
)
def test_median_is_numpys(a):
    assert median(a) == float(np.median(a))


def test_robust_scale_of_normal_residuals_is_their_sigma():
    r = np.random.default_rng(0).normal(0.0, 0.01, 100_000)
    assert robust_scale(r, 1e-6) == np.float64(MAD * median(np.abs(r)))
    assert abs(robust_scale(r, 1e-6) - 0.01) < 2e-4
    assert robust_scale(r, 1.0) == 1.0
    assert robust_scale(np.zeros(0), 0.5) == 0.5


def test_block_by_block_products_are_the_whole_products():
    """Point transforms are multiplied block by block (one BLAS thread): the same values as
    the whole product, to float32 rounding."""
    rng = np.random.default_rng(1)
    n = 3 * _BLOCK_ROWS + 17
    J = rng.normal(size=(n, 6)).astype(np.float32)
    M = rng.normal(size=(6, 3)).astype(np.float32)
    np.testing.assert_array_equal(_tall_times(J, M), np.concatenate(
        [J[s : s + _BLOCK_ROWS] @ M for s in range(0, n, _BLOCK_ROWS)]
    ))  # fmt: skip
    np.testing.assert_allclose(_tall_times(J, M), J @ M, rtol=1e-5, atol=1e-5)
