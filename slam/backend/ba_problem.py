"""What bundle adjustment works on and gives back: the observations of landmarks by keyframes
(:class:`BAProblem`, built from the landmark tracks) and the outcome (:class:`BAResult`). The
solver is :func:`slam.backend.bundle_adjustment.bundle_adjust`."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from slam.backend.landmarks import LandmarkMap
from slam.errors import SlamError
from slam.keyframe import SCALE_FACTOR  # noqa: F401  (named in the docstrings)


class BundleAdjustmentError(SlamError):
    """The bundle adjustment problem is malformed (e.g. an observation names an unknown pose)."""


@dataclass
class BAProblem:
    """Observations for bundle adjustment: observation m is keyframe ``kf[m]`` seeing landmark
    ``landmark[m]`` (0 .. L-1; ``landmark_ids`` names them in the landmark map) at pixel
    ``uv[m]`` with measured depth ``depth[m]`` (<= 0: no depth, pixel only); ``feature[m]`` is
    the keypoint's row in the keyframe's features; ``level[m]`` its ORB pyramid level (its pixel
    noise is ``pixel_sigma_px * SCALE_FACTOR**level``, as in ORB-SLAM; None: all 0). ``K``:
    intrinsics of the pixels."""

    K: np.ndarray
    kf: np.ndarray
    feature: np.ndarray
    landmark: np.ndarray
    landmark_ids: np.ndarray
    uv: np.ndarray
    depth: np.ndarray
    level: np.ndarray | None = None
    depth_slope: np.ndarray | None = None  # m per pixel around each keypoint (None: flat)

    def __len__(self) -> int:
        return len(self.kf)

    @property
    def n_landmarks(self) -> int:
        return len(self.landmark_ids)

    @classmethod
    def from_landmarks(
        cls, landmarks: LandmarkMap, kf_ids: Iterable[int] | None = None, min_observations: int = 2
    ) -> BAProblem:
        """The observations of ``landmarks`` among ``kf_ids`` (default all keyframes) of
        landmarks seen at least ``min_observations`` times there."""
        kf, feat, lm = landmarks.observations(kf_ids, min_observations)
        ids, compact = np.unique(lm, return_inverse=True)
        uv = np.zeros((len(kf), 2))
        depth = np.zeros(len(kf))
        level = np.zeros(len(kf), np.int64)
        slope = np.zeros(len(kf))
        K = np.eye(3)
        for k in np.unique(kf):
            key = kf == k
            keyframe = landmarks.keyframes[int(k)]
            f = keyframe.features
            uv[key] = f.pixels[feat[key]]
            depth[key] = f.points_cam[feat[key], 2]
            level[key] = f.levels()[feat[key]]
            if keyframe.depth_m is not None:
                slope[key] = depth_slope_at(keyframe.depth_m, landmarks.downsample, uv[key])
        if len(kf):
            K = landmarks.K(landmarks.keyframes[int(kf[0])])
        return cls(K, kf, feat, compact.astype(np.int64), ids, uv, depth, level, slope)

    def pixel_scale(self) -> np.ndarray:
        """Per observation: its pixel noise in units of ``pixel_sigma_px`` (1 at level 0)."""
        if self.level is None:
            return np.ones(len(self))
        return SCALE_FACTOR ** self.level.astype(float)

    def cap_tracks(self, max_observations: int) -> BAProblem:
        """The problem with each landmark seen by at most ``max_observations`` keyframes,
        evenly spaced along its track (first and last kept). A landmark seen from 150
        keyframes (a desk filmed for a minute) ties all of them together: the reduced camera
        system turns dense, and time and memory grow with the square of the track length,
        for little information the spaced observations do not already carry (tum-fr1-xyz,
        223 keyframes, cap 20: 2.3 s / 0.48 GB instead of 5.7 s / 0.93 GB, ATE 12.1 mm instead
        of 12.6 mm)."""
        if max_observations <= 0 or len(self) == 0:
            return self
        order = np.lexsort((self.kf, self.landmark))
        lm_sorted = self.landmark[order]
        counts = np.bincount(self.landmark, minlength=self.n_landmarks)
        n = counts[lm_sorted]
        if n.max() <= max_observations:
            return self
        rank = np.arange(len(order)) - np.searchsorted(lm_sorted, lm_sorted)
        # ranks round(j * (n - 1) / (max - 1)), j = 0 .. max - 1
        step = (n - 1) / max(max_observations - 1, 1)
        j = np.round(rank / step)
        keep_sorted = (n <= max_observations) | (np.abs(j * step - rank) < 0.5)
        keep = np.zeros(len(self), bool)
        keep[order[keep_sorted]] = True
        return self.subset(keep)

    def subset(self, keep: np.ndarray, min_observations: int = 2) -> BAProblem:
        """The problem with only the observations ``keep`` (mask) of landmarks that keep at
        least ``min_observations`` of them; landmarks re-indexed."""
        counts = np.bincount(self.landmark[keep], minlength=self.n_landmarks)
        keep = keep & (counts[self.landmark] >= min_observations)
        ids, compact = np.unique(self.landmark[keep], return_inverse=True)
        return BAProblem(
            self.K,
            self.kf[keep],
            self.feature[keep],
            compact.astype(np.int64),
            self.landmark_ids[ids],
            self.uv[keep],
            self.depth[keep],
            None if self.level is None else self.level[keep],
            None if self.depth_slope is None else self.depth_slope[keep],
        )


def depth_slope_at(depth_m: np.ndarray, downsample: int, uv: np.ndarray) -> np.ndarray:
    """How fast depth changes around full-resolution pixels ``uv`` (N, 2), in metres per
    full-resolution pixel, from a keyframe's tracking depth (1/``downsample`` resolution): the
    range of the 3x3 neighbourhood over its width. A missing neighbour (a hole: usually the
    shadow beside a depth edge) makes the range the pixel's whole depth."""
    d = np.ascontiguousarray(depth_m, np.float32)
    kernel = np.ones((3, 3), np.uint8)
    spread = cv2.dilate(d, kernel) - cv2.erode(d, kernel)
    h, w = d.shape
    col = np.clip(np.round(uv[:, 0] / downsample).astype(int), 0, w - 1)
    row = np.clip(np.round(uv[:, 1] / downsample).astype(int), 0, h - 1)
    return spread[row, col].astype(float) / (2.0 * downsample)


@dataclass
class BAResult:
    """Outcome of :func:`bundle_adjust`. ``poses``: ``T_world_kf`` of every keyframe given
    (optimised, or unchanged when not in the problem; ``keyframes`` were optimised); ``points`` (L, 3): landmark positions (world) for ``landmark_ids``.
    Reprojection RMSE (pixels, over the inlier observations) at the starting and the
    optimised estimate; ``outliers``: observations removed (``outlier_kf``/``outlier_feature``
    name them). ``skipped``: why nothing was optimised (then ``poses`` is empty)."""

    poses: dict[int, np.ndarray] = field(default_factory=dict)
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    landmark_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    reprojection_rmse_px_before: float = 0.0
    reprojection_rmse_px_after: float = 0.0
    landmarks: int = 0
    observations: int = 0
    outliers: int = 0
    outlier_kf: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    outlier_feature: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    keyframes: int = 0
    iterations: int = 0
    ms: float = 0.0
    error_before: float = 0.0
    error_after: float = 0.0
    max_pose_change_m: float = 0.0
    max_pose_change_deg: float = 0.0
    # the pose graph edges' weight: the last estimate when it was estimated, else the one
    # given (0: no edges)
    edge_weight: float = 0.0
    skipped: str | None = None

    def summary(self) -> dict[str, Any]:
        """The ``metrics.json`` view (plain JSON types)."""
        out: dict[str, Any] = {
            "reprojection_rmse_px_before": round(self.reprojection_rmse_px_before, 4),
            "reprojection_rmse_px_after": round(self.reprojection_rmse_px_after, 4),
            "landmarks": self.landmarks,
            "observations": self.observations,
            "outliers": self.outliers,
            "keyframes": self.keyframes,
            "iterations": self.iterations,
            "ms": round(self.ms, 1),
            "max_pose_change_m": round(self.max_pose_change_m, 5),
            "max_pose_change_deg": round(self.max_pose_change_deg, 4),
            "edge_weight": round(self.edge_weight, 3),
        }
        if self.skipped:
            out["skipped"] = self.skipped
        return out
