"""Projective point-to-plane ICP, coarse to fine (Open3D tensor odometry kernels do the per-pixel
work: projective association, point-to-plane residuals with a Huber loss, 6x6 normal equations),
and the overlap score alignments are verified by (compiled, :mod:`slam.frontend.depth_kernels`).

What Open3D's kernel computes (read in its source and reproduced to float rounding on rpy
frames; the study branch ``kernel-icp-study``): target normals from its vertex map after a 5x5
bilateral filter; the Hessian ``sum J J^T`` is not weighted by the loss, and the gradient takes
Huber's influence as ``delta * Sign(r)`` with ``Sign`` of an integer, so a residual between
``huber_delta_m`` and a metre adds to H and nothing to b: past the delta, Open3D's "Huber" is a
cut of the gradient, not a down-weighting."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import open3d.core as o3c

from slam.camera import DepthNoise, scale_intrinsics
from slam.frontend.depth_kernels import agreement
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
    pixels without a normal are left out; at most about :data:`RMSE_SAMPLES` of them, evenly
    spaced: an RMSE needs a sample, not every pixel); the RMSE is NaN when none agrees (or not
    ``residuals``). One compiled pass (:func:`slam.frontend.depth_kernels.agreement`)."""
    noise_model = (0.0, 0.0, 0.0, -1.0)  # no noise model: the fixed threshold alone
    if noise is not None:
        noise_model = (noise.sigma0_m, noise.quadratic, noise.z0_m, noise_sigmas)
    fraction, rmse = agreement(
        np.ascontiguousarray(source_depth_m, np.float32),
        np.ascontiguousarray(target_depth_m, np.float32),
        np.ascontiguousarray(K, np.float64), np.ascontiguousarray(T_target_source, np.float64),
        float(threshold_m), int(step), np.array(noise_model), float(source_max_m),
        bool(residuals), RMSE_SAMPLES,
    )  # fmt: skip
    return float(fraction), float(rmse)
