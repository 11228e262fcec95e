"""The pinhole camera: intrinsics ``K`` (3x3, pixel-centre convention), projection of camera-frame
points to pixels, back-projection of depth to points, and intrinsics of a resized image. Shared
by tracking, mapping, loop verification and bundle adjustment."""

from __future__ import annotations

import numpy as np


def backproject(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Vertex map HxWx3 in the camera frame: ``v = depth * K^-1 [u, v, 1]``; zero where no depth."""
    h, w = depth_m.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = (np.arange(w, dtype=np.float32) - cx) / fx
    v = (np.arange(h, dtype=np.float32) - cy) / fy
    z = depth_m.astype(np.float32)
    return np.stack([z * u[None, :], z * v[:, None], z], axis=-1)


def project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) of camera-frame points (N, 3) with z > 0."""
    z = points[:, 2]
    return np.stack(
        [K[0, 0] * points[:, 0] / z + K[0, 2], K[1, 1] * points[:, 1] / z + K[1, 2]], axis=-1
    )


def scale_intrinsics(K: np.ndarray, factor: float) -> np.ndarray:
    """Intrinsics of an image resized by 1/factor (pixel-centre convention)."""
    if factor == 1:
        return K.copy()
    Ks = K.astype(float).copy()
    Ks[0, 0] /= factor
    Ks[1, 1] /= factor
    Ks[0, 2] = (K[0, 2] + 0.5) / factor - 0.5
    Ks[1, 2] = (K[1, 2] + 0.5) / factor - 0.5
    return Ks
