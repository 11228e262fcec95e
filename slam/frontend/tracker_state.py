"""What tracking carries from one frame to the next: :class:`TrackerState`.

The previous frame (pose, depth, pyramids, features, timestamp), the motion model's velocity,
the keyframes made so far, the recent overlaps (for the suspect-overlap check) and the colour
references (the last keyframes' images, which the joint alignment against the model warps into
the model's view).
:class:`~slam.frontend.tracker.Tracker` owns one and its stages update it;
:meth:`TrackerState.to_dict` / :meth:`TrackerState.from_dict` are its checkpoint form (plain
data and arrays).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from slam.errors import SlamError
from slam.frontend.frame import PreparedFrame
from slam.frontend.pointcloud import depth_pyramid
from slam.frontend.rgbd_image import RgbdImage
from slam.keyframe import FeatureSet, Keyframe

__all__ = ["TrackerState"]


@dataclass
class TrackerState:
    """What tracking carries from frame to frame (saved/restored for checkpoints)."""

    T_world_prev: np.ndarray | None = None
    prev_features: Keyframe | None = None  # the previous frame's features, when it computed them
    prev_depth: np.ndarray | None = None  # the previous frame's depth at tracking resolution
    prev_pyramid: list[np.ndarray] | None = None  # ... and its ICP pyramid (not saved)
    prev_frame: PreparedFrame | None = None  # ... the prepared frame itself (saved: its grey)
    t_prev: float | None = None  # ... and its timestamp
    velocity: np.ndarray = field(default_factory=lambda: np.eye(4))  # T_prev_cur of last step
    keyframes: list[Keyframe] = field(default_factory=list)
    recent_overlaps: list[float] = field(default_factory=list)  # of the last tracked frames
    # the last frames' departures from the prediction (of the estimates kept), as m/s^2
    recent_accelerations: list[float] = field(default_factory=list)
    # the last keyframes' depth and grey pyramids and poses, oldest first: the colour frames
    # are aligned to against the model (tracking.colour.photometric_reference: keyframe); empty
    # without colour
    references: list[tuple[RgbdImage, np.ndarray]] = field(default_factory=list)

    @property
    def velocity_known(self) -> bool:
        """A step has been tracked since tracking (re)started: before it, the camera's motion
        is unknown, not zero (a sequence may start mid-pan)."""
        return len(self.recent_overlaps) > 0

    def ransac_candidates(self, n_keyframes: int) -> list[Keyframe]:
        """What RANSAC tries against: the previous frame, then the ``n_keyframes`` most recent
        keyframes (newest first)."""
        return ([self.prev_features] if self.prev_features else []) + list(
            reversed(self.keyframes[-n_keyframes:])
        )

    def restart(self, p: PreparedFrame, T_world_cam: np.ndarray, feats: FeatureSet | None) -> None:
        """Tracking starts again at a frame with a known pose, from rest (the colour
        references start again with it: a new segment's world is not the old one's)."""
        self.T_world_prev = T_world_cam
        self.references = []
        self.velocity = np.eye(4)
        self.prev_depth = p.depth_m
        self.prev_pyramid = None
        self.prev_frame = p
        self.t_prev = p.timestamp
        self.recent_overlaps = []
        self.recent_accelerations = []
        self.prev_features = _features_keyframe(p, T_world_cam, feats)

    def advance(
        self,
        p: PreparedFrame,
        T_world_cam: np.ndarray,
        velocity: np.ndarray,
        overlap: float,
        feats: FeatureSet | None,
    ) -> None:
        """A tracked frame becomes the previous one (``velocity``: its motion per usual frame
        interval; ``overlap``: with the model, for the suspect-overlap check of the next)."""
        self.recent_overlaps = (self.recent_overlaps + [float(overlap)])[-10:]
        self.velocity = velocity
        self.T_world_prev = T_world_cam
        self.prev_depth = p.depth_m
        self.prev_pyramid = p.pyramid
        self.prev_frame = p
        self.t_prev = p.timestamp
        self.prev_features = _features_keyframe(p, T_world_cam, feats)

    def record_departure(self, acceleration_m_s2: float, window: int) -> None:
        """A tracked frame's departure from the prediction, as an acceleration: the last
        ``window`` of them are the recording's motion pattern."""
        self.recent_accelerations = (self.recent_accelerations + [acceleration_m_s2])[-window:]

    def forget_previous(self) -> None:
        """The previous frame cannot be aligned to any more; pose and velocity stay."""
        self.prev_depth = None
        self.prev_pyramid = None
        self.prev_frame = None
        self.prev_features = None

    def add_keyframe(
        self, p: PreparedFrame, T_world_cam: np.ndarray, feats: FeatureSet | None, segment: int
    ) -> Keyframe:
        """The frame as the next keyframe (numbered in order), with its tracking depth."""
        feats = feats or FeatureSet.empty()
        K = p.K_track.copy()
        kf = Keyframe(
            p.index,
            p.timestamp,
            T_world_cam.copy(),
            feats,
            p.depth_m,
            K,
            len(self.keyframes),
            segment,
        )
        self.keyframes.append(kf)
        return kf

    def to_dict(self) -> dict[str, Any]:
        """Plain data and arrays; keyframes by id (their owner saves them once). The arrays
        are never modified in place (each frame replaces them), so this is a snapshot."""
        prev = self.prev_features
        return {
            "T_world_prev": self.T_world_prev,
            "references": [
                {"depth_m": im.depth[0], "grey": im.intensity[0], "K": im.K[0], "T_world_cam": T}
                for im, T in self.references
            ],
            "velocity": self.velocity,
            "prev_depth": self.prev_depth,
            "prev_features": None if prev is None else prev.to_state(),
            "recent_overlaps": list(self.recent_overlaps),
            "recent_accelerations": list(self.recent_accelerations),
            "t_prev": self.t_prev,
            "keyframes": [kf.id for kf in self.keyframes],
            "prev_frame": _frame_state(self.prev_frame),
        }

    @staticmethod
    def from_dict(
        d: dict[str, Any], keyframes_by_id: dict[int, Keyframe], levels: int
    ) -> TrackerState:
        """The state :meth:`to_dict` saved; the ICP pyramid of the previous depth (``levels``
        levels), the references' pyramids and the previous frame's grey pyramids (the joint
        alignment's target of the next frame) are rebuilt."""
        missing = [i for i in d["keyframes"] if int(i) not in keyframes_by_id]
        if missing:
            raise SlamError(
                f"tracker state refers to keyframes {missing[:5]} that were not loaded; pass "
                "every keyframe of the checkpoint (Keyframe.from_state) in keyframes_by_id"
            )
        prev_depth, prev = d["prev_depth"], d["prev_features"]
        prev_pyramid = None if prev_depth is None else depth_pyramid(prev_depth, levels)
        # a state saved before tracking.colour.photometric_keyframes held one "reference"
        refs = d.get("references", [r for r in [d.get("reference")] if r is not None])
        return TrackerState(
            references=[
                (RgbdImage(r["depth_m"], r["grey"], r["K"], levels), r["T_world_cam"]) for r in refs
            ],
            T_world_prev=d["T_world_prev"],
            prev_features=None if prev is None else Keyframe.from_state(prev),
            prev_depth=prev_depth,
            prev_pyramid=prev_pyramid,
            prev_frame=_frame_from_state(d.get("prev_frame"), prev_depth, prev_pyramid, levels),
            velocity=d["velocity"],
            keyframes=[keyframes_by_id[int(i)] for i in d["keyframes"]],
            recent_overlaps=list(d["recent_overlaps"]),
            recent_accelerations=[float(a) for a in d.get("recent_accelerations", [])],
            t_prev=d.get("t_prev"),
        )


def _frame_state(p: PreparedFrame | None) -> dict[str, Any] | None:
    """What the next frame reads of the previous one besides its depth: its grey image (the
    joint alignment's target), index, instants and where its colour camera was."""
    if p is None:
        return None
    rgbd = p.photometric_image(len(p.pyramid))
    return {
        "index": p.index,
        "timestamp": p.timestamp,
        "color_dt_s": p.frame.color_dt_s,
        "K_track": p.K_track,
        "icp_depth_max_m": p.icp_depth_max_m,
        "constraint_ratio": p.constraint_ratio,
        "T_depth_colour": p.T_depth_colour,
        "grey": None if rgbd is None or rgbd.intensity is None else rgbd.intensity[0],
    }


def _frame_from_state(
    d: dict[str, Any] | None,
    depth_m: np.ndarray | None,
    pyramid: list[np.ndarray] | None,
    levels: int,
) -> PreparedFrame | None:
    """The previous frame as :func:`_frame_state` kept it: at tracking resolution, without
    its full-resolution images (its features are ``prev_features``)."""
    if d is None or depth_m is None or pyramid is None:
        return None
    from slam.data.base import Frame

    K = np.asarray(d["K_track"], float)
    frame = Frame(int(d["index"]), float(d["timestamp"]), None, depth_m, K,
                  float(d["color_dt_s"]))  # fmt: skip
    grey = d["grey"]
    p = PreparedFrame(
        frame, depth_m, pyramid, K, float(d["icp_depth_max_m"]),
        rgbd=None if grey is None else RgbdImage(pyramid, grey, K, levels),
        colour_registered=grey is not None, constraint_ratio=float(d["constraint_ratio"]),
    )  # fmt: skip
    p.T_depth_colour = d["T_depth_colour"]
    return p


def _features_keyframe(
    p: PreparedFrame, T_world_cam: np.ndarray, feats: FeatureSet | None
) -> Keyframe | None:
    """The frame as the next frame's RANSAC candidate (None without features)."""
    if feats is None or len(feats) == 0:
        return None
    return Keyframe(p.index, p.timestamp, T_world_cam.copy(), feats)
