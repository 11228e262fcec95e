"""Projective point-to-plane ICP, coarse to fine (Open3D tensor odometry kernels do the per-pixel
work: projective association, point-to-plane residuals with a Huber loss, 6x6 normal equations)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import open3d.core as o3c

from slam.camera import DepthNoise, scale_intrinsics
from slam.frontend.pointcloud import depth_pyramid

_odom = o3d.t.pipelines.odometry
log = logging.getLogger(__name__)


@dataclass
class IcpResult:
    """``T_target_source`` maps source-camera points into the target camera frame."""

    T_target_source: np.ndarray
    # fraction of the source pixels in range (valid, nearer than the ICP depth range) with a
    # valid correspondence (finest level)
    fitness: float
    inlier_rmse: float  # point-to-plane RMSE of the correspondences, metres


Depth = np.ndarray | list[np.ndarray]  # a depth image, or its pyramid (finest first)


def projective_icp(
    source_depth_m: Depth,
    target_depth_m: Depth,
    K: np.ndarray,
    init_T_target_source: np.ndarray,
    iterations: list[int],
    depth_max_m: float = 4.0,
    max_correspondence_m: float = 0.07,
    huber_delta_m: float = 0.05,
    coarse_factor: float = 1.0,
) -> IcpResult:
    """Align a source depth image to a target depth image (e.g. the model ray-cast).

    ``iterations`` lists iterations per pyramid level, coarse to fine (its length is the number
    of levels). Target normals come from the target depth's vertex map. With ``coarse_factor``
    > 1 the correspondence distance and Huber delta grow by that factor per level above the
    finest, so coarse levels can pull in larger motions. Either depth may be given as its
    :func:`depth_pyramid` (at least ``len(iterations)`` levels), so a caller aligning one image
    several times builds it once.
    """
    levels = len(iterations)
    if coarse_factor != 1.0 and levels > 1:
        return _coarse_to_fine(
            source_depth_m, target_depth_m, K, init_T_target_source, iterations, depth_max_m,
            max_correspondence_m, huber_delta_m, coarse_factor,
        )  # fmt: skip
    return _open3d_icp(
        source_depth_m, target_depth_m, K, init_T_target_source, iterations, depth_max_m,
        max_correspondence_m, huber_delta_m,
    )  # fmt: skip


def _coarse_to_fine(
    source_depth_m: Depth,
    target_depth_m: Depth,
    K: np.ndarray,
    init_T_target_source: np.ndarray,
    iterations: list[int],
    depth_max_m: float,
    max_correspondence_m: float,
    huber_delta_m: float,
    coarse_factor: float,
) -> IcpResult:
    """Open3D's kernel one level at a time, coarse to fine, the correspondence distance and
    Huber delta ``coarse_factor`` times larger per level above the finest."""
    levels = len(iterations)
    src_pyr = _pyramid(source_depth_m, levels)
    tgt_pyr = _pyramid(target_depth_m, levels)
    T = np.asarray(init_T_target_source, float)
    for level in reversed(range(levels)):
        scale = coarse_factor**level
        res = _open3d_icp(
            src_pyr[level],
            tgt_pyr[level],
            scale_intrinsics(K, 2**level),
            T,
            [iterations[levels - 1 - level]],
            depth_max_m,
            max_correspondence_m * scale,
            huber_delta_m * scale,
        )
        if res.fitness == 0.0:
            return IcpResult(np.asarray(init_T_target_source, float).copy(), 0.0, np.inf)
        T = res.T_target_source
    return res


def _open3d_icp(
    source_depth_m: Depth,
    target_depth_m: Depth,
    K: np.ndarray,
    init_T_target_source: np.ndarray,
    iterations: list[int],
    depth_max_m: float,
    max_correspondence_m: float,
    huber_delta_m: float,
) -> IcpResult:
    """Open3D's multi-scale point-to-plane kernel, one correspondence distance on every level
    (pyramids given: their finest level; Open3D builds its own)."""
    source_depth_m = source_depth_m[0] if isinstance(source_depth_m, list) else source_depth_m
    target_depth_m = target_depth_m[0] if isinstance(target_depth_m, list) else target_depth_m
    src_d = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(source_depth_m, np.float32)))
    tgt_d = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(target_depth_m, np.float32)))
    source = o3d.t.geometry.RGBDImage(src_d, src_d)
    target = o3d.t.geometry.RGBDImage(tgt_d, tgt_d)
    # Open3D takes the criteria coarsest level first, like ``iterations`` (checked by timing)
    criteria = [_odom.OdometryConvergenceCriteria(int(n)) for n in iterations]
    try:
        result = _odom.rgbd_odometry_multi_scale(
            source,
            target,
            o3c.Tensor(np.ascontiguousarray(K, np.float64)),
            o3c.Tensor(np.ascontiguousarray(init_T_target_source, np.float64)),
            1.0,
            depth_max_m,
            criteria,
            _odom.Method.PointToPlane,
            _odom.OdometryLossParams(max_correspondence_m, huber_delta_m, 0.1),
        )
    except RuntimeError as exc:  # Open3D raises on a singular 6x6 system (too few correspondences)
        log.debug("ICP failed: %s", exc)
        return IcpResult(np.asarray(init_T_target_source, float).copy(), 0.0, float("inf"))
    # Open3D's fitness is a fraction of all pixels; ours, of the source pixels ICP could use
    # (valid and within depth_max_m): a far scene keeps most of its pixels beyond the range
    usable = np.count_nonzero((source_depth_m > 0) & (source_depth_m < depth_max_m))
    fitness = min(1.0, result.fitness * source_depth_m.size / usable) if usable else 0.0
    return IcpResult(result.transformation.numpy().astype(float), fitness, result.inlier_rmse)


def _pyramid(depth: Depth, levels: int) -> list[np.ndarray]:
    if isinstance(depth, list):
        if len(depth) < levels:
            raise ValueError(f"a depth pyramid of {len(depth)} levels; ICP needs {levels}")
        return depth
    return depth_pyramid(depth, levels)


def projective_overlap(
    source_depth_m: np.ndarray,
    target_depth_m: np.ndarray,
    K: np.ndarray,
    T_target_source: np.ndarray,
    threshold_m: float = 0.03,
    step: int = 2,
    noise: DepthNoise | None = None,
    noise_sigmas: float = 3.0,
    source_max_m: float = float("inf"),
) -> float:
    """Fraction of valid source pixels that land, after ``T_target_source``, within
    ``threshold_m`` (along the ray) of the target depth at their projected pixel; with a
    ``noise`` model the gate of a pixel widens to ``noise_sigmas`` of its depth noise where
    that is larger (far depth: a Kinect's sigma is 2 cm at 3.5 m, 6 cm at 6 m). Source pixels
    deeper than ``source_max_m`` are not counted (a model fused up to that depth cannot hold
    them: in a hall most of the view is beyond it).

    An alignment score independent of the optimiser; used to verify and rank ICP results.
    Every ``step``-th pixel in each direction is tested (the score is a fraction).
    """
    return projective_agreement(
        source_depth_m, target_depth_m, K, T_target_source, threshold_m, step, noise,
        noise_sigmas, source_max_m, residuals=False,
    )[0]  # fmt: skip


#: Agreeing pixels the residual RMSE of :func:`projective_agreement` is measured on (at most).
RMSE_SAMPLES = 2048


def projective_agreement(
    source_depth_m: np.ndarray,
    target_depth_m: np.ndarray,
    K: np.ndarray,
    T_target_source: np.ndarray,
    threshold_m: float = 0.03,
    step: int = 2,
    noise: DepthNoise | None = None,
    noise_sigmas: float = 3.0,
    source_max_m: float = float("inf"),
    residuals: bool = True,
) -> tuple[float, float]:
    """:func:`projective_overlap` and the point-to-plane RMSE (metres) of the agreeing pixels
    against the target surface (its normal from the target depth's neighbours at the pixel;
    pixels without a normal are left out); the RMSE is NaN when none agrees (or not
    ``residuals``)."""
    sub = source_depth_m[::step, ::step]
    v, u = np.nonzero((sub > 0) & (sub <= source_max_m))
    v, u = v * step, u * step
    if len(u) == 0:
        return 0.0, float("nan")
    z = source_depth_m[v, u].astype(np.float64)
    pts = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=-1)
    p = pts @ T_target_source[:3, :3].T + T_target_source[:3, 3]
    front = p[:, 2] > 1e-6
    p = p[front]
    ut = np.round(K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]).astype(np.int64)
    vt = np.round(K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]).astype(np.int64)
    h, w = target_depth_m.shape
    inside = (ut >= 0) & (ut < w) & (vt >= 0) & (vt < h)
    zt = np.zeros(len(p))
    zt[inside] = target_depth_m[vt[inside], ut[inside]]
    gate = threshold_m
    if noise is not None:
        gate = np.maximum(threshold_m, noise_sigmas * noise.sigma(p[:, 2]))
    good = (zt > 0) & (np.abs(zt - p[:, 2]) < gate)
    fraction = float(good.sum()) / len(u)
    if not residuals or not good.any():
        return fraction, float("nan")
    idx = np.flatnonzero(good)
    if len(idx) > RMSE_SAMPLES:  # an RMSE needs a sample, not every pixel (~8x cheaper)
        idx = idx[:: len(idx) // RMSE_SAMPLES]
    r = _point_to_plane(target_depth_m, K, p[idx], ut[idx], vt[idx])
    return fraction, float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")


def _point_to_plane(
    depth: np.ndarray, K: np.ndarray, p: np.ndarray, u: np.ndarray, v: np.ndarray
) -> np.ndarray:
    """Distances of points ``p`` (target camera frame) to the target surface's tangent plane
    at pixels (u, v), the normal from central differences of the target's vertices there."""
    h, w = depth.shape
    ok = (u > 0) & (u < w - 1) & (v > 0) & (v < h - 1)
    p, u, v = p[ok], u[ok], v[ok]

    def vertex(uu: np.ndarray, vv: np.ndarray) -> np.ndarray:
        zz = depth[vv, uu].astype(np.float64)
        return np.stack([(uu - K[0, 2]) * zz / K[0, 0], (vv - K[1, 2]) * zz / K[1, 1], zz], -1)

    right, left, down, up = vertex(u + 1, v), vertex(u - 1, v), vertex(u, v + 1), vertex(u, v - 1)
    n = np.cross(right - left, down - up)
    norm = np.linalg.norm(n, axis=1)
    known = (
        (norm > 1e-12) & (right[:, 2] > 0) & (left[:, 2] > 0) & (down[:, 2] > 0) & (up[:, 2] > 0)
    )
    q = vertex(u[known], v[known])
    return np.einsum("ij,ij->i", p[known] - q, n[known] / norm[known, None])
