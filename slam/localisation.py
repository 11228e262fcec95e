"""Localisation against a saved map (:class:`slam.saved_map.Map`): every frame is placed in the
map's world frame, nothing is added to the map.

A frame is first *not localised*: there is no prior pose, so it is registered against the map's
keyframes as a lost frame is relocalised (place recognition over the map's keyframes, then ORB
matches lifted by depth, RANSAC and ICP between the depth images:
:class:`~slam.loops.relocalisation.Relocaliser`). Once one verifies, the next frames are
tracked frame to model against the map's own surface (its TSDF ray-cast at the predicted pose),
with the tracker's usual checks; a frame that fails them is registered against the keyframes
again. A recording of another place is never localised: its frames get no pose, none is made
up. The map is read only (two localisations may share one map at once), and no frame is fused:
localising costs a ray-cast a frame where mapping also fuses.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from slam.config import SlamConfig
from slam.frontend.frame import PreparedFrame, usable_depth_fraction
from slam.frontend.tracker import Tracker
from slam.geometry import inv_T
from slam.loops.closer import KeyframeLink
from slam.loops.recovery import Outcome
from slam.loops.relocalisation import Relocaliser
from slam.loops.verification import LoopVerifier
from slam.mapping.tsdf import Rendering
from slam.saved_map import Map

__all__ = ["Localisation", "MapModel"]

log = logging.getLogger(__name__)


class MapModel:
    """A saved map's TSDF as the tracker's model (:class:`~slam.frontend.model.TrackingModel`):
    rendered from a pose in the map's world frame, never fused into."""

    def __init__(self, saved: Map) -> None:
        self.volume = saved.volume
        self.T_volume_world = inv_T(saved.T_world_volume)
        self.min_weight = saved.min_weight

    @property
    def depth_max_m(self) -> float:
        return self.volume.depth_max_m

    def raycast(
        self, K: np.ndarray, width: int, height: int, T_world_cam: np.ndarray, *args, **kw
    ) -> Rendering:
        """:meth:`TSDFVolume.raycast <slam.mapping.tsdf.TSDFVolume.raycast>` from a pose in
        the map's world frame, surfaces fused at least ``min_weight`` (default the map's)."""
        if kw.get("min_weight") is None:
            kw["min_weight"] = self.min_weight
        return self.volume.raycast(K, width, height, self.T_volume_world @ T_world_cam, *args, **kw)


@dataclass
class Localisation:
    """The per-frame state machine of a localisation run (see the module docstring)."""

    cfg: SlamConfig
    tracker: Tracker
    saved: Map
    verifier: LoopVerifier
    localised: bool = False  # the previous frame has a pose in the map
    run: int = -1  # tracking runs (each starts at a registration against the keyframes)
    first_localised: int | None = None  # the first frame with a pose (sequence index)
    registrations: list[dict[str, Any]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.model = MapModel(self.saved)
        loop = self.cfg.loop
        t = self.cfg.tracking
        self.relocaliser = Relocaliser(
            self.verifier, self.saved.place_index(loop), t.recovery.relocalisation_candidates,
            loop.exclude_recent_keyframes, t.motion.hypothesis_overlap, t.depth_max_m,
        )  # fmt: skip

    def track(self, frame: PreparedFrame, ratio: float, gap: bool) -> Outcome:
        """The frame's pose in the map (None: not localised), tracked from the previous one
        when that had a pose, else registered against the map's keyframes."""
        c = self.cfg.tracking
        fraction = usable_depth_fraction(frame.frame.depth_m, c.depth_min_m, c.depth_max_m)
        if fraction < c.min_depth_fraction:
            reason = f"no usable depth ({100 * fraction:.1f}% of pixels in range)"
            return self._lost(frame, reason, gap)
        if self.localised:
            T, status = self.tracker.track(frame, self.model, verify=gap, dt_ratio=ratio)
            if T is not None:
                return Outcome(T, status)
            log.info("frame %d: tracking in the map lost (%s)", frame.frame.index, status.reason)
            self.localised = False
            self.tracker.mark_lost()
        return self._register(frame)

    def _register(self, frame: PreparedFrame) -> Outcome:
        """Register the frame against the map's keyframes; tracking starts there."""
        found = self.relocaliser.relocalise(frame.view(), self.saved.keyframes, None)
        if found is None:
            return self._lost(frame, "not localised: no keyframe of the map verifies", False)
        T, ver = found.T_world_cam, found.verification
        self.localised = True
        self.run += 1
        if self.first_localised is None:
            self.first_localised = frame.frame.index
        status = self.tracker.reset(frame, T, "reloc", 0, evidence=ver)
        self.registrations.append(
            {"frame": frame.frame.index, "method": "map keyframe", "keyframe": found.keyframe.id,
             "keyframe_frame": found.keyframe.index}
        )  # fmt: skip
        log.info(
            "frame %d: localised against the map's keyframe %d (frame %d)",
            frame.frame.index, found.keyframe.id, found.keyframe.index,
        )  # fmt: skip
        return Outcome(T.copy(), status, KeyframeLink("relocalisation"))

    def _lost(self, frame: PreparedFrame, reason: str, gap: bool) -> Outcome:
        if self.localised:
            self.localised = False
            self.tracker.mark_lost()
        return Outcome(None, self.tracker.lost_status(frame, reason, gap))
