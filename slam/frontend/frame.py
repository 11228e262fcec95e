"""TEMPORARY shim (replaced by the tracker's prepared frame)."""

from __future__ import annotations

from functools import cached_property
from typing import Any

from slam.camera import scale_intrinsics
from slam.data.base import Frame
from slam.keyframe import FeatureSet, KeyframeView


class PreparedFrame:
    def __init__(self, frame: Frame, tracker: Any) -> None:
        self.frame = frame
        self.index = frame.index
        self._tracker = tracker

    @cached_property
    def depth(self):
        return self._tracker._tracking_depth(self.frame.depth_m)

    @cached_property
    def features(self):
        return self._tracker._features(self.frame)

    def view(self) -> KeyframeView:
        return KeyframeView(
            self.features or FeatureSet.empty(),
            self.depth,
            scale_intrinsics(self.frame.K, self._tracker.cfg.downsample),
        )
