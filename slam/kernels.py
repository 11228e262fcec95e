"""The compiled kernels of the per-frame path, made ready before a run's first frame.

numba compiles a kernel on its first call and caches the machine code on disk (next to its
module, or in the user's cache folder when the package folder is read-only), so the first run on
a machine spends a few seconds compiling and every later one loads the cache in a fraction of a
second. :func:`prepare` makes that happen before the frame loop, by running each kernel once on
a tiny input of the types the tracker passes, so no frame of a run pays for it (before, the
first frame colour joined depth did: a pause in the middle of the run).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["cached", "prepare"]


def _dispatchers() -> list:
    from slam.frontend import depth_kernels, joint_kernels

    return [
        joint_kernels.geometric_rows,
        joint_kernels.photometric_rows,
        joint_kernels.weighted_system,
        joint_kernels.warp_accumulate,
        depth_kernels.agreement,
        depth_kernels.downsample,
        depth_kernels.geometry,
        depth_kernels.information,
    ]


def cached() -> bool:
    """Whether every kernel has machine code in numba's cache (False when unsure)."""
    try:
        return all(Path(d._cache._cache_file._index_path).exists() for d in _dispatchers())
    except AttributeError:  # another numba's internals: say it may compile
        return False


def prepare() -> float:
    """Compile (once per machine) or load every kernel of the per-frame path; the seconds it
    took."""
    t0 = time.perf_counter()
    _joint_align_once()
    _depth_kernels_once()
    seconds = time.perf_counter() - t0
    log.debug("compiled kernels ready in %.1f s", seconds)
    return seconds


def _joint_align_once() -> None:
    from slam.frontend.photometric import joint_align, mean_warped_intensity
    from slam.frontend.rgbd_image import RgbdImage

    h, w = 24, 32
    K = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    v, u = np.mgrid[0:h, 0:w]
    depth = (1.0 + 0.01 * u).astype(np.float32)
    grey = (0.5 + 0.4 * np.sin(u / 2.0) * np.cos(v / 3.0)).astype(np.float32)
    image = RgbdImage(depth, grey, K, 2)
    joint_align(image, RgbdImage(depth, grey, K, 2), np.eye(4), [1, 1], photometric_weight=1.0)
    mean_warped_intensity(depth, K, np.eye(4), [(image, np.eye(4))], 0.05)


def _depth_kernels_once() -> None:
    from slam.camera import DepthNoise
    from slam.frontend.icp import projective_agreement
    from slam.frontend.pointcloud import depth_pyramid
    from slam.frontend.weighted_icp import depth_constraint

    K = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    depth = np.full((24, 32), 1.5, np.float32)
    projective_agreement(depth, depth, K, np.eye(4), noise=DepthNoise())
    depth_pyramid(depth, 2)
    depth_constraint(depth, K, 4.0, DepthNoise())
