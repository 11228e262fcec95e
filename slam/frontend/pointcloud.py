"""Back-projection of depth images to vertex and normal maps, and depth pyramids (vectorised)."""

from __future__ import annotations

import cv2
import numpy as np


def normal_map(vertex: np.ndarray, max_depth_jump_m: float = 0.05) -> np.ndarray:
    """Normals from central differences of the vertex map, oriented towards the camera.

    Zero where a neighbour has no depth or lies across a depth discontinuity.
    """
    z = vertex[..., 2]
    dx = np.zeros_like(vertex)
    dy = np.zeros_like(vertex)
    dx[:, 1:-1] = vertex[:, 2:] - vertex[:, :-2]
    dy[1:-1, :] = vertex[2:, :] - vertex[:-2, :]
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    valid = (z > 0) & (norm[..., 0] > 1e-12)
    valid[:, 1:-1] &= (z[:, 2:] > 0) & (z[:, :-2] > 0)
    valid[1:-1, :] &= (z[2:, :] > 0) & (z[:-2, :] > 0)
    valid[:, 1:-1] &= np.abs(dx[:, 1:-1, 2]) < 2 * max_depth_jump_m
    valid[1:-1, :] &= np.abs(dy[1:-1, :, 2]) < 2 * max_depth_jump_m
    valid[[0, -1], :] = False
    valid[:, [0, -1]] = False
    n = np.where(valid[..., None], n / np.maximum(norm, 1e-12), 0.0)
    # orient towards the camera (the viewing ray is +vertex)
    flip = np.einsum("hwc,hwc->hw", n, vertex) > 0
    n[flip] *= -1
    return n.astype(np.float32)


def downsample_depth(depth_m: np.ndarray, max_diff_m: float = 0.03) -> np.ndarray:
    """Half-resolution depth: mean of each 2x2 block's valid values close to its top-left value.

    Invalid (0) pixels never contribute, so holes do not pull depth towards the camera.
    """
    h, w = depth_m.shape
    d = depth_m[: h - h % 2, : w - w % 2].astype(np.float32)
    blocks = np.stack([d[0::2, 0::2], d[0::2, 1::2], d[1::2, 0::2], d[1::2, 1::2]])
    ref = blocks[0]
    use = (blocks > 0) & (np.abs(blocks - ref) < max_diff_m)
    count = use.sum(axis=0)
    total = np.where(use, blocks, 0.0).sum(axis=0)
    out = np.where((ref > 0) & (count > 0), total / np.maximum(count, 1), 0.0)
    return out.astype(np.float32)


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
