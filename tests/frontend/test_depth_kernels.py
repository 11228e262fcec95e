"""The compiled overlap score (:func:`slam.frontend.icp.projective_agreement`) against the same
arithmetic in numpy."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slam.camera import DepthNoise
from slam.frontend.icp import RMSE_SAMPLES, projective_agreement
from slam.geometry import exp_se3


def _reference(source, target, K, T, threshold, step, noise, sigmas, source_max):
    """The numpy the kernel replaced: (fraction, rmse)."""
    sub = source[::step, ::step]
    v, u = np.nonzero((sub > 0) & (sub <= source_max))
    v, u = v * step, u * step
    if len(u) == 0:
        return 0.0, float("nan")
    z = source[v, u].astype(np.float64)
    pts = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=-1)
    p = pts @ T[:3, :3].T + T[:3, 3]
    p = p[p[:, 2] > 1e-6]
    ut = np.round(K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]).astype(np.int64)
    vt = np.round(K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]).astype(np.int64)
    h, w = target.shape
    inside = (ut >= 0) & (ut < w) & (vt >= 0) & (vt < h)
    zt = np.zeros(len(p))
    zt[inside] = target[vt[inside], ut[inside]]
    gate = threshold if noise is None else np.maximum(threshold, sigmas * noise.sigma(p[:, 2]))
    good = (zt > 0) & (np.abs(zt - p[:, 2]) < gate)
    fraction = float(good.sum()) / len(u)
    idx = np.flatnonzero(good)
    if len(idx) == 0:
        return fraction, float("nan")
    if len(idx) > RMSE_SAMPLES:
        idx = idx[:: len(idx) // RMSE_SAMPLES]
    p, u, v = p[idx], ut[idx], vt[idx]
    ok = (u > 0) & (u < w - 1) & (v > 0) & (v < h - 1)
    p, u, v = p[ok], u[ok], v[ok]

    def vertex(uu, vv):
        zz = target[vv, uu].astype(np.float64)
        return np.stack([(uu - K[0, 2]) * zz / K[0, 0], (vv - K[1, 2]) * zz / K[1, 1], zz], -1)

    right, left, down, up = vertex(u + 1, v), vertex(u - 1, v), vertex(u, v + 1), vertex(u, v - 1)
    n = np.cross(right - left, down - up)
    norm = np.linalg.norm(n, axis=1)
    known = (norm > 1e-12) & (right[:, 2] > 0) & (left[:, 2] > 0) & (down[:, 2] > 0)
    known &= up[:, 2] > 0
    r = np.einsum("ij,ij->i", p[known] - vertex(u[known], v[known]), n[known] / norm[known, None])
    return fraction, float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")


def _scene(seed: int, h: int = 60, w: int = 80):
    """A smooth surface with holes and a far part, and a second view of it (noisy)."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:h, 0:w]
    depth = (1.2 + 0.4 * np.sin(u / 7.0) + 0.3 * np.cos(v / 5.0)).astype(np.float32)
    depth[rng.random((h, w)) < 0.1] = 0.0
    depth[:, -10:] += 4.0
    other = (depth + rng.normal(0.0, 0.004, (h, w)) * (depth > 0)).astype(np.float32)
    return depth, other


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1, 2, 3]), st.booleans(), st.booleans())
def test_agreement_is_the_numpy_it_replaced(seed, step, with_noise, near_only):
    rng = np.random.default_rng(seed)
    source, target = _scene(seed)
    K = np.array([[70.0, 0.0, 39.5], [0.0, 70.0, 29.5], [0.0, 0.0, 1.0]])
    T = exp_se3(np.r_[rng.normal(0.0, 0.02, 3), rng.normal(0.0, 0.03, 3)])
    noise = DepthNoise() if with_noise else None
    source_max = 3.0 if near_only else float("inf")
    fraction, rmse = projective_agreement(
        source, target, K, T, 0.01, step, noise, 3.0, source_max_m=source_max
    )
    ref_fraction, ref_rmse = _reference(source, target, K, T, 0.01, step, noise, 3.0, source_max)
    assert fraction == ref_fraction
    if np.isnan(ref_rmse):
        assert np.isnan(rmse)
    else:
        assert abs(rmse - ref_rmse) <= 1e-9 * max(ref_rmse, 1e-6)  # float64 rounding


def test_agreement_of_nothing_is_zero_and_nan():
    K = np.array([[70.0, 0.0, 39.5], [0.0, 70.0, 29.5], [0.0, 0.0, 1.0]])
    empty = np.zeros((60, 80), np.float32)
    assert np.isnan(projective_agreement(empty, empty, K, np.eye(4))[1])
    assert projective_agreement(empty, empty, K, np.eye(4))[0] == 0.0
    source, _ = _scene(0)
    behind = np.diag([1.0, 1.0, -1.0, 1.0])  # every point behind the target camera
    fraction, rmse = projective_agreement(source, source, K, behind)
    assert fraction == 0.0 and np.isnan(rmse)


def _downsample_reference(depth_m, max_diff_m=0.03):
    """The numpy :func:`downsample_depth` replaced."""
    h, w = depth_m.shape
    d = np.asarray(depth_m[: h - h % 2, : w - w % 2], np.float32)
    ref = d[0::2, 0::2]
    total = ref.copy()
    count = np.ones(ref.shape, np.float32)
    for x in (d[0::2, 1::2], d[1::2, 0::2], d[1::2, 1::2]):
        use = (np.abs(x - ref) < np.float32(max_diff_m)) & (x > 0)
        np.add(total, x, out=total, where=use)
        count += use
    total /= count
    total[~(ref > 0)] = 0.0
    return total


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([(48, 64), (7, 9), (1, 1), (2, 5)]))
def test_downsample_is_the_numpy_it_replaced(seed, shape):
    from slam.frontend.pointcloud import downsample_depth

    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.5, 1.5, shape).astype(np.float32)
    depth[rng.random(shape) < 0.2] = 0.0
    depth[rng.random(shape) < 0.05] = np.nan
    depth += rng.choice([0.0, 0.02, 0.1], shape).astype(np.float32) * (depth > 0)
    assert np.array_equal(downsample_depth(depth), _downsample_reference(depth), equal_nan=True)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([(48, 64), (24, 32), (5, 7)]))
def test_geometry_rows_are_vertex_map_and_normal_map(seed, shape):
    from slam.frontend.pointcloud import geometry_rows
    from slam.frontend.weighted_icp import vertex_map
    from tests.frontend.reference import geometry_reference, normal_map, wavy_depth

    rng = np.random.default_rng(seed)
    h, w = shape
    depth, K = wavy_depth(rng, h, w)
    depth[:, w // 2 :] += np.float32(rng.choice([0.0, 0.04, 0.5]))  # a depth step, or not
    vertex = vertex_map(depth, K)
    normal = normal_map(vertex, f_px=float(K[0, 0])).reshape(-1, 3)
    ref = geometry_reference(vertex.reshape(-1, 3), normal)
    assert np.array_equal(geometry_rows(depth, K), ref)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_information_is_the_numpy_it_replaced(seed):
    from slam.frontend.weighted_icp import depth_information
    from tests.frontend.reference import wavy_depth

    depth, K = wavy_depth(np.random.default_rng(seed), far_from=41)
    noise = DepthNoise()
    H, median_z = depth_information(depth, K, 3.5, noise)
    ref_H, ref_median_z = _information_reference(depth, K, 3.5, noise)
    np.testing.assert_allclose(H, ref_H, rtol=1e-10)
    assert median_z == ref_median_z


def _information_reference(depth, K, depth_max, noise):
    """The numpy :func:`~slam.frontend.weighted_icp.depth_information` replaced."""
    from slam.frontend.weighted_icp import vertex_map
    from tests.frontend.reference import normal_map

    d = np.where((depth > 0) & (depth < depth_max), depth, np.float32(0.0))
    vertex = vertex_map(d, K)
    normal = normal_map(vertex, f_px=float(K[0, 0]))
    ok = normal[..., 2] != 0
    ok[:, 1::2] = False
    p, n = vertex[ok].astype(np.float64), normal[ok].astype(np.float64)
    J = np.concatenate([np.cross(p, n), n], axis=1)
    wt = 1.0 / noise.sigma(p[:, 2]).astype(np.float64) ** 2
    return (J * wt[:, None]).T @ J, float(np.partition(p[:, 2], len(p) // 2)[len(p) // 2])
