import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slam.camera import backproject, project, scale_intrinsics
from slam.frontend.pointcloud import (
    bilateral_depth,
    depth_pyramid,
    downsample_depth,
    geometry_rows,
)
from tests.frontend.reference import normal_map

K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


@settings(max_examples=100, deadline=None)
@given(st.floats(0.3, 8.0), st.integers(0, 639), st.integers(0, 479))
def test_backproject_then_project_returns_the_pixel(z, u, v):
    depth = np.zeros((480, 640), np.float32)
    depth[v, u] = z
    vert = backproject(depth, K)
    p = vert[v, u][None].astype(float)
    np.testing.assert_allclose(project(p, K)[0], [u, v], atol=1e-3)
    assert abs(vert[v, u, 2] - np.float32(z)) < 1e-6


def _normals(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) normals of a depth image, as the tracker computes them
    (:func:`geometry_rows`)."""
    return geometry_rows(depth, K)[:, 4:7].reshape(*depth.shape, 3)


def test_normals_of_a_tilted_plane():
    # plane z = 2 + 0.5 x  -> normal ~ (0.5, 0, -1) normalised, facing the camera
    u, v = np.meshgrid(np.arange(640), np.arange(480))
    xn = (u - K[0, 2]) / K[0, 0]
    z = 2.0 / (1 - 0.5 * xn)
    n = _normals(z.astype(np.float32), K)
    expected = np.array([0.5, 0.0, -1.0]) / np.linalg.norm([0.5, 0.0, -1.0])
    inner = n[5:-5, 5:-5].reshape(-1, 3)
    assert np.abs(inner - expected).max() < 1e-3


def test_normals_zero_at_holes_and_edges():
    depth = np.full((48, 64), 2.0, np.float32)
    depth[10, 10] = 0.0
    depth[:, 40:] = 3.0  # a 1 m step
    n = _normals(depth, K)
    for v, u in [(10, 10), (9, 10), (11, 10), (10, 9), (10, 11)]:  # the hole and its 4-neighbours
        assert np.all(n[v, u] == 0)
    assert np.all(n[5:-5, 39:41] == 0)
    assert np.all(np.linalg.norm(n[20, 15:35], axis=-1) > 0.99)


def test_normals_of_a_far_floor_at_a_coarse_level_survive_with_the_focal_length():
    # a floor 1.5 m below the camera, seen up to 5 m away at 1/8 resolution (80 x 60): its
    # depth steps up to 45 cm from pixel to pixel, past the fixed 5 cm jump, but it is a
    # surface at < 75 deg incidence; a real 1 m step at 2 m is still an edge
    Kc = scale_intrinsics(K, 8)
    u, v = np.meshgrid(np.arange(80), np.arange(60))
    yn = (v - Kc[1, 2]) / Kc[1, 1]
    z = np.where(yn > 1.5 / 5.0, 1.5 / np.maximum(yn, 1e-6), 0.0).astype(np.float32)
    floor = z > 0
    vert = backproject(z, Kc)
    fixed = normal_map(vert)
    scaled = _normals(z, Kc)
    inner = floor[1:-1, 1:-1] & floor[2:, 1:-1] & floor[:-2, 1:-1]
    assert np.count_nonzero(np.linalg.norm(fixed[1:-1, 1:-1][inner], axis=-1)) < 0.6 * inner.sum()
    ok = np.linalg.norm(scaled[1:-1, 1:-1][inner], axis=-1) > 0.99
    assert ok.mean() > 0.95
    up = scaled[1:-1, 1:-1][inner][ok]
    assert np.abs(up[:, 1]).min() > 0.99  # the floor's normal is the camera's y axis
    step = np.full((60, 80), 2.0, np.float32)
    step[:, 40:] = 3.0
    assert np.all(_normals(step, Kc)[5:-5, 39:41] == 0)


def test_downsample_ignores_holes():
    d = np.array([[1.0, 0.0], [1.02, 0.0]], np.float32)
    assert abs(downsample_depth(d)[0, 0] - 1.01) < 1e-6
    d = np.array(
        [[1.0, 2.0], [1.0, 2.0]], np.float32
    )  # across a depth edge: the far side is ignored
    assert downsample_depth(d)[0, 0] == 1.0
    d = np.array([[0.0, 2.0], [2.0, 2.0]], np.float32)
    assert downsample_depth(d)[0, 0] == 0.0  # top-left invalid -> invalid
    d = np.array([[np.nan, 2.0], [2.0, np.nan]], np.float32)
    assert downsample_depth(d)[0, 0] == 0.0  # a non-finite top-left too


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 40), st.integers(1, 40), st.integers(0, 2**32 - 1), st.floats(0.0, 0.9))
def test_downsample_is_the_mean_of_each_blocks_close_valid_values(h, w, seed, holes):
    # per block: the valid values within 3 cm of the top-left one, averaged; a top-left hole
    # stays a hole (odd last rows and columns are dropped)
    rng = np.random.default_rng(seed)
    d = rng.uniform(0.5, 0.56, (h, w)).astype(np.float32)
    d[rng.random((h, w)) < holes] = 0.0
    out = downsample_depth(d)
    assert out.shape == (h // 2, w // 2) and out.dtype == np.float32
    for i in range(h // 2):
        for j in range(w // 2):
            block = d[2 * i : 2 * i + 2, 2 * j : 2 * j + 2].ravel()
            ref = block[0]
            use = block[(block > 0) & (np.abs(block - ref) < np.float32(0.03))]
            expected = use.mean(dtype=np.float64) if ref > 0 else 0.0
            assert abs(out[i, j] - expected) < 1e-6


def test_pyramid_and_scaled_intrinsics_agree():
    depth = np.full((480, 640), 2.5, np.float32)
    pyr = depth_pyramid(depth, 3)
    assert [p.shape for p in pyr] == [(480, 640), (240, 320), (120, 160)]
    K2 = scale_intrinsics(K, 2)
    # the centre of a 2x2 block projects to the same ray at both levels
    ray_full = (np.array([1.5, 1.5]) - K[:2, 2]) / K[0, 0]
    np.testing.assert_allclose(ray_full, (np.array([0.5, 0.5]) - K2[:2, 2]) / K2[0, 0], atol=1e-9)


def test_bilateral_smooths_noise_keeps_edges_and_holes():
    rng = np.random.default_rng(0)
    depth = np.full((60, 80), 1.0, np.float32)
    depth[:, 40:] = 2.0  # a 1 m step
    noisy = depth + rng.normal(0, 0.003, depth.shape).astype(np.float32)
    noisy[20:25, 10:15] = 0.0  # a hole
    out = bilateral_depth(noisy, 0.03, 2.0)
    assert np.all(out[20:25, 10:15] == 0.0)  # holes stay holes
    valid = noisy > 0
    inner = valid.copy()
    inner[:, 35:45] = False  # away from the step
    err_in = np.abs(noisy - depth)[inner].std()
    err_out = np.abs(out - depth)[inner].std()
    assert err_out < 0.5 * err_in
    # no bleeding across the step, and no pull towards 0 next to the hole
    assert np.abs(out[:, 39] - 1.0).max() < 0.02 and np.abs(out[:, 40] - 2.0).max() < 0.02
    assert np.abs(out[19, 10:15] - 1.0).max() < 0.02
