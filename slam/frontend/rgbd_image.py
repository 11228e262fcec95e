"""A view's depth and intensity prepared for the alignments of :mod:`slam.frontend.photometric`:
pyramids, back-projected source points, target levels with vertices, normals and intensity
gradients. Pixels follow the pinhole convention (pixel (u, v) is the ray ``K^-1 [u, v, 1]``;
pyramids are 2x2 box averages, see :func:`slam.camera.scale_intrinsics`)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from slam.camera import scale_intrinsics
from slam.frontend.pointcloud import depth_pyramid, geometry_rows


def grey(color: np.ndarray, factor: int = 1) -> np.ndarray:
    """Grey intensity in [0, 1] (float32) of an RGB image (uint8, or float in [0, 1]),
    downsampled by ``factor`` (a power of 2) with 2x2 box averages (pixel-centre convention)."""
    c = np.asarray(color)
    scale = 1.0 / 255.0 if c.dtype == np.uint8 else 1.0
    g = cv2.cvtColor(c.astype(np.float32), cv2.COLOR_RGB2GRAY) * np.float32(scale)
    for _ in range(int(np.log2(factor))):
        g = _half(g)
    return g


def _half(img: np.ndarray) -> np.ndarray:
    h, w = img.shape[:2]
    return cv2.resize(img, (w // 2, h // 2), interpolation=cv2.INTER_AREA)


def intensity_pyramid(intensity: np.ndarray, levels: int) -> list[np.ndarray]:
    """Finest first; level i has 1/2^i resolution (2x2 box averages)."""
    pyr = [np.asarray(intensity, np.float32)]
    for _ in range(levels - 1):
        pyr.append(_half(pyr[-1]))
    return pyr


@dataclass
class _SourceLevel:
    points: np.ndarray  # (N, 3) float32, camera frame
    intensity: np.ndarray | None  # (N,) float32


@dataclass
class _TargetLevel:
    shape: tuple[int, int]
    depth: np.ndarray  # (H * W,) float32, 0 = none
    # (H * W, 8) float32 rows: vertex, 0, normal (0 where unknown), 1 where the normal is
    # known else 0 (one row of 32 bytes: np.take gathers it ~10x faster than two rows of 12)
    geometry: np.ndarray
    photo: np.ndarray | None  # (H, W, 3) float32: intensity, d/du, d/dv

    @property
    def vertex(self) -> np.ndarray:
        """(H * W, 3) float32 (a view)."""
        return self.geometry[:, :3]

    @property
    def normal(self) -> np.ndarray:
        """(H * W, 3) float32, 0 where unknown (a view)."""
        return self.geometry[:, 4:7]

    @property
    def has_normal(self) -> np.ndarray:
        """(H * W,) bool: the normal is known."""
        return self.geometry[:, 7] > 0


def _pixels(depth: np.ndarray, K: np.ndarray, v: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(N, 3) float32 camera-frame points of the pixels (``v``, ``u``) of a depth image."""
    z = depth[v, u].astype(np.float32)
    x = ((u - K[0, 2]) / K[0, 0]).astype(np.float32) * z
    y = ((v - K[1, 2]) / K[1, 1]).astype(np.float32) * z
    return np.stack([x, y, z], axis=-1)


def _source_level(depth: np.ndarray, intensity: np.ndarray | None, K: np.ndarray, step: int):
    v, u = np.nonzero(depth[::step, ::step] > 0)
    v, u = v * step, u * step
    inten = None if intensity is None else intensity[v, u].astype(np.float32)
    return _SourceLevel(_pixels(depth, K, v, u), inten)


def _photo(intensity: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32: intensity and its central differences along u and v (0 at the
    border)."""
    i = np.asarray(intensity, np.float32)
    gx = np.zeros_like(i)
    gy = np.zeros_like(i)
    gx[:, 1:-1] = 0.5 * (i[:, 2:] - i[:, :-2])
    gy[1:-1, :] = 0.5 * (i[2:, :] - i[:-2, :])
    return np.ascontiguousarray(np.stack([i, gx, gy], axis=-1))


def _target_level(
    depth: np.ndarray, photo: np.ndarray | None, K: np.ndarray, geometry: bool = True
) -> _TargetLevel:
    """A target level (``photo``: :func:`_photo` of its intensity); without ``geometry`` its
    vertices and normals are empty (for the photometric term alone)."""
    h, w = depth.shape
    z = depth.astype(np.float32)
    if not geometry:
        return _TargetLevel((h, w), z.reshape(-1), np.zeros((0, 8), np.float32), photo)
    return _TargetLevel((h, w), z.reshape(-1), geometry_rows(z, K), photo)


class RgbdImage:
    """Depth (and intensity) pyramids of one view, prepared for :func:`joint_align` as a source
    (``as_source``) and/or a target (``as_target``). Build once per frame; levels are created
    on first use."""

    def __init__(
        self,
        depth_m: np.ndarray | list[np.ndarray],
        intensity: np.ndarray | list[np.ndarray] | None,
        K: np.ndarray,
        levels: int,
    ) -> None:
        self.depth = depth_m if isinstance(depth_m, list) else depth_pyramid(depth_m, levels)
        if intensity is None:
            self.intensity = None
        else:
            self.intensity = (
                intensity if isinstance(intensity, list) else intensity_pyramid(intensity, levels)
            )
        self.K = [scale_intrinsics(K, 2**lv) for lv in range(levels)]
        self._src: dict[tuple[int, int], _SourceLevel] = {}  # (level, step)
        self._tgt: dict[int, _TargetLevel] = {}
        self._photo_tgt: dict[int, _TargetLevel] = {}  # without vertices and normals
        self._photo: dict[int, np.ndarray] = {}

    def photo(self, level: int) -> np.ndarray | None:
        """:func:`_photo` of the intensity at ``level`` (None without intensity)."""
        if self.intensity is None:
            return None
        if level not in self._photo:
            self._photo[level] = _photo(self.intensity[level])
        return self._photo[level]

    def source(self, level: int, step: int = 1) -> _SourceLevel:
        key = (level, step)
        if key not in self._src:
            inten = None if self.intensity is None else self.intensity[level]
            self._src[key] = _source_level(self.depth[level], inten, self.K[level], step)
        return self._src[key]

    def target(self, level: int, geometry: bool = True) -> _TargetLevel:
        """The view as a target at ``level``; without ``geometry`` (for the photometric term
        alone) its vertices and normals may be left out."""
        if not geometry and level not in self._tgt:
            if level not in self._photo_tgt:
                photo = self.photo(level)
                self._photo_tgt[level] = _target_level(
                    self.depth[level], photo, self.K[level], False
                )
            return self._photo_tgt[level]
        if level not in self._tgt:
            self._tgt[level] = _target_level(self.depth[level], self.photo(level), self.K[level])
        return self._tgt[level]
