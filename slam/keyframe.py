"""Keyframes and what they carry: ORB features lifted to 3D (:class:`FeatureSet`), the depth
and intrinsics loop verification needs (:class:`KeyframeView`). Records shared by tracking, the
loop closer, relocalisation and bundle adjustment: none of them owns the type."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from slam.camera import project

#: ORB's image pyramid: each level is this much smaller than the one below (OpenCV's default)
SCALE_FACTOR = 1.2


@dataclass
class FeatureSet:
    """ORB keypoints with valid depth: pixels (N, 2), descriptors (N, 32) uint8, 3D points (N, 3)
    in the camera frame (metres), and the pyramid level each was found at (N,), None if
    unknown (taken as 0). A keypoint of level l is located to within ~``SCALE_FACTOR**l``
    pixels (measured on synthetic corners: std 1.0, 1.3, 1.5, ... 3.9 px at levels 0-7)."""

    pixels: np.ndarray
    descriptors: np.ndarray
    points_cam: np.ndarray
    octave: np.ndarray | None = None

    def levels(self) -> np.ndarray:
        """Pyramid level of each keypoint (0 when not recorded)."""
        if self.octave is None:
            return np.zeros(len(self.pixels), np.int64)
        return np.asarray(self.octave, np.int64)

    def __len__(self) -> int:
        return len(self.pixels)

    def in_camera(self, T_other_this: np.ndarray, K: np.ndarray) -> FeatureSet:
        """The same features as another camera with intrinsics ``K`` sees them, this one's pose
        in its frame being ``T_other_this``: points moved into it, pixels shifted by the change
        of their projections. ORB runs on the colour image: a colour image taken off the depth's
        instant was seen from ``T_depth_colour``, and ``in_camera(T_depth_colour, K)`` gives its
        features as the depth camera, whose pose tracking estimates, would have seen them."""
        if len(self) == 0:
            return self
        R, t = T_other_this[:3, :3], T_other_this[:3, 3]
        moved = self.points_cam @ R.T + t
        shift = project(moved, K) - project(self.points_cam, K)
        return FeatureSet(self.pixels + shift, self.descriptors, moved, self.octave)

    @staticmethod
    def empty() -> FeatureSet:
        return FeatureSet(
            np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros((0, 3)), np.zeros(0, np.int64)
        )


@dataclass
class KeyframeView:
    """What verification needs of a keyframe: ORB features with 3D points, the depth image the
    features' intrinsics ``K`` refer to after scaling, and the tracking-resolution depth."""

    features: FeatureSet
    depth_m: np.ndarray  # tracking resolution
    K: np.ndarray  # intrinsics of ``depth_m``


@dataclass
class Keyframe:
    """A keyframe: frame index, odometry pose and ORB features with 3D points (camera frame);
    keyframes also keep their depth at tracking resolution (with its intrinsics ``K``) for
    loop verification, and ``id``, their number in the run (0, 1, ...)."""

    index: int
    timestamp: float
    T_world_cam: np.ndarray
    features: FeatureSet
    depth_m: np.ndarray | None = None
    K: np.ndarray | None = None
    id: int = -1
    segment: int = 0  # the map segment (tracking run from a fresh start) it belongs to

    def view(self) -> KeyframeView:
        """What loop verification and relocalisation need of this keyframe."""
        assert self.depth_m is not None and self.K is not None, "a keyframe keeps its depth"
        return KeyframeView(self.features, self.depth_m, self.K)

    def to_state(self) -> dict[str, Any]:
        """Plain data and arrays (checkpoints)."""
        f = self.features
        return {
            "index": self.index,
            "timestamp": self.timestamp,
            "T_world_cam": self.T_world_cam,
            "pixels": f.pixels,
            "descriptors": f.descriptors,
            "points_cam": f.points_cam,
            "octave": f.octave,
            "depth_m": self.depth_m,
            "K": self.K,
            "id": self.id,
            "segment": self.segment,
        }

    @staticmethod
    def from_state(d: dict[str, Any]) -> Keyframe:
        return Keyframe(
            int(d["index"]),
            float(d["timestamp"]),
            np.asarray(d["T_world_cam"]),
            FeatureSet(d["pixels"], d["descriptors"], d["points_cam"], d.get("octave")),
            d["depth_m"],
            d["K"],
            int(d["id"]),
            int(d["segment"]),
        )
