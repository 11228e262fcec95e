"""Keeping Open3D's ray-caster from dropping blocks out of its range map.

``VoxelBlockGrid.ray_cast`` first bounds every ray by a coarse range map: each block given is
projected into a down-sampled image and its bounding rectangle, cut into 16x16 "fragments", is
written into a buffer that the grid keeps between calls. The buffer is sized on the first call by
a guess (about 400 fragments for a 320x240 image at 1 cm voxels) and grows only *after* a call
overflowed it; in the overflowing call the blocks past the end (whichever threads came last:
not reproducible) are left out of the range map, and the rays behind them see no surface or a
farther one. Measured on a loaded submap: the first ray-cast needed 1951 fragments with 400
allocated, and the rendered depth differed from the next call's at 56,751 pixels; a call that
needs exactly the buffer's size drops one block too. Every fresh volume's first ray-cast and
every view seeing more blocks than any before were affected, and two runs of the same input
could differ by millimetres.

The fix: bound the fragments a call needs (:func:`fragments_bound`; the tests check it against a
numpy copy of Open3D's exact count) and, when they might not fit, first grow the buffer with a
cheap call that needs more: duplicates of one block, one fragment each, on a 32x32 image.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import open3d.core as o3c

FRAGMENT_PX = 16  # Open3D's fragment side, in range-map pixels
# the priming call's image side: with range-map factor 2, a 16x16 range map, so every block in
# front gives one fragment (and Open3D's first-call guess of the buffer is not empty)
_PRIME_SIZE = 32


def fragments_bound(
    block_keys: np.ndarray,
    K: np.ndarray,
    T_cam_world: np.ndarray,
    width: int,
    height: int,
    down: int,
    block_size_m: float,
) -> int:
    """An upper bound of the fragments ``VoxelBlockGrid.ray_cast`` writes for these blocks
    (``(N, 3)`` keys; each block's corners in front of the camera give a rectangle in the
    range map, clamped to it and cut into 16x16 fragments), from each block's centre alone
    (30x cheaper than projecting the corners: it runs before every ray-cast). A block lies in a sphere of radius r (half its
    diagonal) around its centre at depth z; where z > r, its image spans at most
    ``f * 2r (1 + |x/z|) / (z - r)`` pixels along u (likewise v), plus 2 for the rounding of
    its corners; otherwise, or beyond the image, the whole range map."""
    keys = np.asarray(block_keys, np.float64).reshape(-1, 3)
    if keys.shape[0] == 0:
        return 0
    r = 0.5 * np.sqrt(3.0) * block_size_m
    c = (keys + 0.5) * block_size_m @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    z = c[:, 2]
    w_down, h_down = width // down, height // down
    full_u, full_v = -(-w_down // FRAGMENT_PX), -(-h_down // FRAGMENT_PX)
    near = z <= r
    z_off = np.where(near, 1.0, z - r)
    z_c = np.where(near, 1.0, z)
    span_u = K[0, 0] / down * 2 * r * (1 + np.abs(c[:, 0]) / z_c) / z_off + 3
    span_v = K[1, 1] / down * 2 * r * (1 + np.abs(c[:, 1]) / z_c) / z_off + 3
    n_u = np.where(near, full_u, np.minimum(np.ceil(span_u / FRAGMENT_PX), full_u))
    n_v = np.where(near, full_v, np.minimum(np.ceil(span_v / FRAGMENT_PX), full_v))
    return int(np.sum(n_u * n_v))


def priming_view(n_fragments: int) -> tuple[np.ndarray, np.ndarray, int, int, int]:
    """A ray-cast that needs exactly ``n_fragments`` fragments and costs little: (block keys,
    ``K``, width, height, range-map factor) from an identity pose. One block in front of the
    camera, repeated; in the 16x16 range map of a 32x32 image it spans one fragment."""
    s = _PRIME_SIZE
    keys = np.tile(np.array([[0, 0, 1]], np.int32), (n_fragments, 1))
    K = np.array([[s / 2, 0, s / 2], [0, s / 2, s / 2], [0, 0, 1]], np.float64)
    return keys, K, s, s, 2


class RangeMapBuffer:
    """What is known of one grid's fragment buffer: at least ``capacity`` fragments (0 before
    the first priming call: Open3D's own first guess is not relied on)."""

    def __init__(self) -> None:
        self.capacity = 0

    def ensure(self, vbg: o3d.t.geometry.VoxelBlockGrid, needed: int) -> None:
        """Make the buffer hold more than ``needed`` fragments (a call needing as many as it
        holds still drops a block). Grows to twice the need, so priming stays rare."""
        if needed < self.capacity:
            return
        target = 2 * needed + 64
        keys, K, w, h, down = priming_view(target)
        vbg.ray_cast(
            o3c.Tensor(keys), o3c.Tensor(K), o3c.Tensor(np.eye(4)), w, h, ["depth"],
            1.0, 1e-3, 1e3, 1.0, 1.0, down,
        )  # fmt: skip
        self.capacity = target
