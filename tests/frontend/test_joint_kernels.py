"""The compiled passes of the joint alignment against the same arithmetic in numpy."""

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slam.frontend.joint_kernels import geometric_rows, photometric_rows, weighted_system
from slam.frontend.photometric import _sample
from slam.frontend.rgbd_image import RgbdImage, grey
from slam.geometry import exp_se3
from tests.frontend.test_photometric import wall_views


def _rows(Q: np.ndarray, g: np.ndarray) -> np.ndarray:
    return np.concatenate([np.cross(Q, g), g], axis=1)


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 500))
def test_weighted_system_is_the_huber_weighted_normal_equations(seed, n):
    rng = np.random.default_rng(seed)
    J = rng.normal(size=(n + 5, 6)).astype(np.float32)
    r = rng.normal(0.0, 0.02, n + 5).astype(np.float32)
    offset, scale, delta, weight = 0.003, 0.015, 0.02, 0.7
    H, b = weighted_system(J, r, n, offset, scale, delta, weight)  # the first n rows only
    res = (r[:n] - np.float32(offset)).astype(np.float64)
    w = np.where(np.abs(res) <= delta, 1.0, delta / np.abs(res)) * weight / scale**2
    J64 = J[:n].astype(np.float64)
    np.testing.assert_allclose(H, (J64 * w[:, None]).T @ J64, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(b, (J64 * w[:, None]).T @ res, rtol=1e-9, atol=1e-6)
    assert np.array_equal(H, H.T)


def _views():
    motion = exp_se3(np.array([0.01, -0.02, 0.005, 0.03, -0.01, 0.02]))
    K, source, target = wall_views(motion)
    return K, source.source(0), target.target(0)


def test_geometric_rows_are_the_projective_point_to_plane_correspondences():
    """Every source point moved by T, rounded to the pixel it falls in, associated where the
    target has depth; rows and residuals where the target's normal is known and the
    point-to-plane residual is below the gate; visible where the depths agree within it."""
    K, src, tgt = _views()
    T = exp_se3(np.array([0.002, 0.001, -0.003, 0.01, 0.004, -0.006]))
    R, t = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)
    intrinsics = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float32)
    n, gate = len(src.points), np.float32(0.05)
    J, r, z = np.empty((n, 6), np.float32), np.empty(n, np.float32), np.empty(n, np.float32)
    visible = np.empty(n, np.int64)
    n_assoc, n_geo, n_vis = geometric_rows(
        src.points, R, t, intrinsics, tgt.depth, tgt.geometry, tgt.shape, gate,
        J, r, z, visible,
    )  # fmt: skip
    # the same in numpy
    Q = src.points @ R.T + t
    u = np.rint(intrinsics[0] * Q[:, 0] / Q[:, 2] + intrinsics[2]).astype(int)
    v = np.rint(intrinsics[1] * Q[:, 1] / Q[:, 2] + intrinsics[3]).astype(int)
    h, w = tgt.shape
    idx = np.flatnonzero((Q[:, 2] > 1e-3) & (u >= 0) & (u < w) & (v >= 0) & (v < h))
    pix = v[idx] * w + u[idx]
    assoc = tgt.depth[pix] > 0
    idx, pix = idx[assoc], pix[assoc]
    g = tgt.geometry[pix]
    res = np.einsum("ij,ij->i", Q[idx] - g[:, :3], g[:, 4:7])
    geo = (np.abs(res) < gate) & (g[:, 7] > 0)
    assert n_assoc == len(idx) and n_geo == np.count_nonzero(geo) > 0.5 * n
    np.testing.assert_allclose(r[:n_geo], res[geo], atol=1e-6)
    np.testing.assert_allclose(z[:n_geo], Q[idx[geo], 2], rtol=1e-6)
    np.testing.assert_allclose(J[:n_geo], _rows(Q[idx[geo]], g[geo, 4:7]), atol=1e-5)
    seen = idx[np.abs(tgt.depth[pix] - Q[idx, 2]) < gate]
    assert np.array_equal(visible[:n_vis], seen)


def test_photometric_rows_sample_as_remap_and_skip_unseen_pixels():
    """The residual is the target's intensity, sampled bilinearly as ``cv2.remap`` samples it,
    less the point's; the row is the image gradient through the projection; points whose
    target sample is NaN (unseen in a warped target) give no row."""
    K, src, tgt = _views()
    photo = tgt.photo.copy()
    photo[:40, :60] = np.nan  # a corner the target did not see
    T = exp_se3(np.array([0.01, -0.004, 0.002, 0.05, 0.03, -0.02]))  # some land outside
    R, t = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)
    intrinsics = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float32)
    indices = np.arange(0, len(src.points), 3)
    n = len(indices)
    J, r = np.empty((n, 6), np.float32), np.empty(n, np.float32)
    m = photometric_rows(src.points, src.intensity, indices, n, R, t, intrinsics, photo, J, r)
    Q = src.points[indices] @ R.T + t
    inv_z = 1.0 / Q[:, 2]
    x = (intrinsics[0] * Q[:, 0] * inv_z + intrinsics[2]).astype(np.float32)
    y = (intrinsics[1] * Q[:, 1] * inv_z + intrinsics[3]).astype(np.float32)
    smp = cv2.remap(photo, x[None], y[None], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]
    ok = np.isfinite(smp).all(axis=1)
    assert 0.5 * n < m == np.count_nonzero(ok) < n
    np.testing.assert_allclose(r[:m], smp[ok, 0] - src.intensity[indices[ok]], atol=1e-5)
    g = np.stack([smp[:, 1] * intrinsics[0] * inv_z, smp[:, 2] * intrinsics[1] * inv_z], 1)
    g = np.concatenate([g, -(g[:, :1] * Q[:, :1] + g[:, 1:] * Q[:, 1:2]) * inv_z[:, None]], 1)
    np.testing.assert_allclose(J[:m], _rows(Q[ok], g[ok]), rtol=1e-3, atol=1e-3)


def test_kernels_run_on_a_real_sized_view():
    """A 320 x 240 view with intensity, through every kernel: counts within the image."""
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.5, 3.0, (240, 320)).astype(np.float32)
    colour = rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)
    K = np.array([[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1]])
    view = RgbdImage(depth, grey(colour), K, 1)
    src, tgt = view.source(0), view.target(0)
    n = len(src.points)
    J, r, z = np.empty((n, 6), np.float32), np.empty(n, np.float32), np.empty(n, np.float32)
    visible = np.empty(n, np.int64)
    intrinsics = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float32)
    eye, zero = np.eye(3, dtype=np.float32), np.zeros(3, np.float32)
    counts = geometric_rows(src.points, eye, zero, intrinsics, tgt.depth, tgt.geometry,
                            tgt.shape, np.float32(0.05), J, r, z, visible)  # fmt: skip
    assert counts[0] == counts[2] == n  # every point on its own pixel, at its own depth
    m = photometric_rows(src.points, src.intensity, visible, counts[2], eye, zero, intrinsics,
                         tgt.photo, J, r)  # fmt: skip
    assert m == n and np.abs(r[:m]).max() < 1e-4  # the view against itself


def _warp_reference(V, K, T, intensity, depth, gate):
    """The numpy :func:`warp_accumulate` replaced: one view's intensities at ``V`` (NaN: unseen)."""
    Q = V @ T[:3, :3].T.astype(np.float32) + T[:3, 3].astype(np.float32)
    z = Q[:, 2]
    ok = (V[:, 2] > 0) & (z > 1e-3)
    inv_z = np.float32(1.0) / np.where(ok, z, np.float32(1.0))
    u = np.float32(K[0, 0]) * Q[:, 0] * inv_z + np.float32(K[0, 2])
    v = np.float32(K[1, 1]) * Q[:, 1] * inv_z + np.float32(K[1, 2])
    hs, ws = depth.shape
    ok &= (u >= 0) & (u <= ws - 1) & (v >= 0) & (v <= hs - 1)
    idx = np.flatnonzero(ok)
    zs = depth[np.rint(v[idx]).astype(np.int64), np.rint(u[idx]).astype(np.int64)]
    idx = idx[np.abs(zs - z[idx]) < gate]
    out = np.full(len(V), np.nan, np.float32)
    if len(idx):
        out[idx] = _sample(np.ascontiguousarray(intensity)[..., None], u[idx], v[idx])[:, 0]
    return out


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_warp_accumulate_is_the_bilinear_warp_it_replaced(seed):
    from slam.frontend.joint_kernels import warp_accumulate
    from slam.frontend.weighted_icp import vertex_map
    from tests.frontend.reference import wavy_depth

    rng = np.random.default_rng(seed)
    depth, K = wavy_depth(rng)
    h, w = depth.shape
    intensity = rng.random((h, w)).astype(np.float32)
    T = exp_se3(np.r_[rng.normal(0.0, 0.03, 3), rng.normal(0.0, 0.03, 3)])
    V = vertex_map(depth, K).reshape(-1, 3)
    total = np.zeros(len(V), np.float32)
    count = np.zeros(len(V), np.float32)
    intrinsics = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float32)
    R, t = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)
    warp_accumulate(V, intrinsics, R, t, intensity, depth, np.float32(0.05), total, count)
    ref = _warp_reference(V, K, T, intensity, depth, 0.05)
    seen = np.isfinite(ref)
    # a point on a gate's or a pixel's boundary may fall either way by float rounding
    assert np.count_nonzero(seen != (count > 0)) <= 2
    both = seen & (count > 0)
    np.testing.assert_allclose(total[both], ref[both], atol=1e-4)
