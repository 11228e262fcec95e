"""Vertices and normals of depth images, depth pyramids and the bilateral filter (a pyramid level
and a depth image's vertex + normal rows in one compiled pass each,
:mod:`slam.frontend.depth_kernels`)."""

from __future__ import annotations

import cv2
import numpy as np

from slam.frontend.depth_kernels import downsample, geometry

#: A surface seen at up to this incidence angle is a surface, not a depth discontinuity.
MAX_INCIDENCE_DEG = 75.0
#: ... and a depth step up to this (metres) between neighbours, at any angle.
MAX_DEPTH_JUMP_M = 0.05


def geometry_rows(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H * W, 8) float32 rows of a depth image: vertex (:func:`slam.frontend.weighted_icp.
    vertex_map`), 0, normal, 1 where the normal is known else 0: one row of 32 bytes a pixel,
    one compiled pass (:func:`slam.frontend.depth_kernels.geometry`).

    The normal is from central differences of the vertices over one pixel each side, oriented
    towards the camera; zero where a neighbour has no depth or lies across a depth
    discontinuity: a step over :data:`MAX_DEPTH_JUMP_M`, or over what a surface at
    :data:`MAX_INCIDENCE_DEG` produces across one pixel (``z tan(75 deg) / f``: at coarse
    pyramid levels and far away, e.g. a floor 3.5 m ahead at 1/8 resolution, the fixed step
    alone removes every normal)."""
    h, w = depth_m.shape
    xs = ((np.arange(w) - K[0, 2]) / K[0, 0]).astype(np.float32)
    ys = ((np.arange(h) - K[1, 2]) / K[1, 1]).astype(np.float32)
    jump = np.float32(2 * MAX_DEPTH_JUMP_M)
    slope = np.float32(2 * np.tan(np.radians(MAX_INCIDENCE_DEG)) / float(K[0, 0]))
    return geometry(np.ascontiguousarray(depth_m, np.float32), xs, ys, jump, slope)


def downsample_depth(depth_m: np.ndarray, max_diff_m: float = 0.03) -> np.ndarray:
    """Half-resolution depth: mean of each 2x2 block's valid values close to its top-left value.

    Invalid (0) pixels never contribute, so holes do not pull depth towards the camera. One
    compiled pass (:func:`slam.frontend.depth_kernels.downsample`)."""
    return downsample(np.ascontiguousarray(depth_m, np.float32), np.float32(max_diff_m))


def depth_pyramid(depth_m: np.ndarray, levels: int = 3) -> list[np.ndarray]:
    """Depth pyramid, finest first: level i has 1/2^i resolution."""
    pyr = [depth_m.astype(np.float32)]
    for _ in range(levels - 1):
        pyr.append(downsample_depth(pyr[-1]))
    return pyr


def resize_color(color: np.ndarray, factor: int) -> np.ndarray:
    """Colour image downsampled by an integer factor (area interpolation)."""
    if factor == 1:
        return color
    h, w = color.shape[:2]
    return cv2.resize(color, (w // factor, h // factor), interpolation=cv2.INTER_AREA)


def bilateral_depth(depth_m: np.ndarray, sigma_m: float, sigma_px: float) -> np.ndarray:
    """Edge-preserving smoothing of a depth image (KinectFusion's bilateral filter): holes (0)
    stay holes, and since the range kernel weighs a 0 neighbour of a valid pixel by
    ``exp(-z^2 / 2 sigma^2)`` ~ 0, holes do not pull valid depth towards the camera."""
    d = depth_m.astype(np.float32)
    radius = int(np.ceil(1.5 * sigma_px))
    out = cv2.bilateralFilter(d, 2 * radius + 1, float(sigma_m), float(sigma_px))
    out[d <= 0] = 0.0
    return out
