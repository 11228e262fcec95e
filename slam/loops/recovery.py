"""Tracking with loss and recovery: the per-frame state machine around the tracker.

Every frame's tracking is decided on its own. A frame without usable depth, or whose estimate
fails the tracker's checks, is *lost* (not fused, no pose written). Each lost frame is tried,
in order: against the model as after a gap (recovery; not for the frame just lost, which
tracking already tried), relocalised against all keyframes of the map, then against every
surface the model has seen (``tracking.recovery.rescue_min_weight``: a fast pan brings surfaces into
view faster than frames fuse them past the ray-cast's weight threshold). If that keeps failing
for ``tracking.recovery.new_segment_after_lost`` frames with usable depth, a new map segment starts (a
new submap and a new component of the pose graph), joined to the old map later at the first
verified revisits (see :mod:`slam.loops.closer`).

States: *not started* (``segment < 0``) -> *tracking* <-> *lost* -> (new segment) *tracking*.
``run`` counts tracking runs (a run ends where tracking was lost); ``segment`` is the map
segment of the current run.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from slam.config import TrackingConfig
from slam.frontend.frame import PreparedFrame, usable_depth_fraction
from slam.frontend.tracker import Tracker
from slam.loops.closer import KeyframeLink
from slam.loops.relocalisation import Relocaliser
from slam.records import TrackingStatus

log = logging.getLogger(__name__)


class SegmentedMap(Protocol):
    """What the state machine asks of the map: start a submap (a new segment, or beside the
    submap a relocalised frame lands in)."""

    submaps: list[Any]
    active: Any

    def start_submap(self, kf_id: int, T_world_kf: np.ndarray, **kw: Any) -> Any: ...

    def submap_of_keyframe(self, kf_id: int) -> Any: ...


@dataclass
class Outcome:
    """What tracking made of one frame: the pose (None when lost), the tracker's status and,
    for a keyframe that does not follow its predecessor by tracking, how it joins the graph."""

    T_world_cam: np.ndarray | None
    status: TrackingStatus
    link: KeyframeLink | None = None


@dataclass
class LossRecovery:
    """The tracking state machine (see the module docstring)."""

    cfg: TrackingConfig
    tracker: Tracker
    model: SegmentedMap
    relocaliser: Relocaliser
    loop_sigma_m: float  # a relocalisation edge's sigma (backend.loop_sigma_m)
    segment: int = -1  # the current map segment (-1: not started)
    run: int = -1  # the current tracking run
    lost: bool = False
    lost_with_depth: int = 0  # consecutive lost frames that had usable depth
    relocalisations: list[dict[str, Any]] = field(default_factory=list)

    def track(self, frame: PreparedFrame, ratio: float, gap: bool) -> Outcome:
        """The frame's pose by whatever the state calls for: first frame, tracking, or (while
        lost) recovery, relocalisation and at last a new segment. ``ratio``: the time since
        the last frame with a pose over the usual frame interval; ``gap``: the frame follows a
        skipped frame or a timestamp jump (the pose must be verified)."""
        c = self.cfg
        fraction = usable_depth_fraction(frame.frame.depth_m, c.depth_min_m, c.depth_max_m)
        if fraction < c.min_depth_fraction:
            reason = (
                f"no usable depth: {100 * fraction:.1f}% of pixels within "
                f"[{c.depth_min_m}, {c.depth_max_m}] m (min {100 * c.min_depth_fraction:.1f}%)"
            )
            status = self.tracker.lost_status(frame, reason, gap, self.segment)
            out = Outcome(None, status)
            self._lose(out.status)
            return out
        if self.segment < 0:
            return self._new_segment(frame, np.eye(4))
        if self.lost:
            return self._while_lost(frame, ratio)
        T, status = self.tracker.track(
            frame, self.model, verify=gap, dt_ratio=ratio, segment=self.segment
        )
        if T is not None:
            return Outcome(T, status)
        self._lose(status)
        self.lost_with_depth = 1
        found = self._relocalise(frame)
        if found.T_world_cam is None:  # ORB matches verify it only after a gap, as tracking does
            found = self._recover_all_surfaces(frame, ratio, gap, found)
        return found if found.T_world_cam is not None else Outcome(None, status)

    def _while_lost(self, frame: PreparedFrame, ratio: float) -> Outcome:
        """Recover against the model, else relocalise, else recover against every surface the
        model has seen, else (after enough lost frames) start a new map segment where the
        camera was last seen."""
        out = self._recover(frame, ratio)
        if out.T_world_cam is None:
            tracked = out.status
            out = self._relocalise(frame)
            if out.T_world_cam is None:
                out = self._recover_all_surfaces(frame, ratio, True, out)
            if out.T_world_cam is None:
                tracked.reason += "; relocalisation: no keyframe verifies"
                out = Outcome(None, tracked)
        if out.T_world_cam is None:
            if self.lost_with_depth + 1 >= self.cfg.recovery.new_segment_after_lost:
                T_last = self.tracker.state.T_world_prev
                assert T_last is not None
                return self._new_segment(frame, T_last)
            self.lost_with_depth += 1
        return out

    def _lose(self, status: TrackingStatus) -> None:
        if self.segment < 0:
            return  # nothing to lose before the first frame with a pose
        if not self.lost:
            log.info("frame %d: tracking lost (%s); relocalising", status.index, status.reason)
        self.lost = True
        self.tracker.mark_lost()

    def _resume(self) -> None:
        self.lost = False
        self.lost_with_depth = 0

    def _new_segment(self, frame: PreparedFrame, T_world_cam: np.ndarray) -> Outcome:
        """Start a map segment at this frame (the first frame, or after a long loss)."""
        self.segment += 1
        self.run += 1
        self._resume()
        status = self.tracker.reset(frame, T_world_cam, "init", self.segment)
        kf = self.tracker.state.keyframes[-1]
        if self.model.submaps:
            log.warning(
                "frame %d: not relocalised after %d lost frames; starting map segment %d",
                frame.index,
                self.cfg.recovery.new_segment_after_lost,
                self.segment,
            )
            self.model.start_submap(kf.id, kf.T_world_cam, continuous=False)
        else:
            self.model.start_submap(kf.id, kf.T_world_cam)
        return Outcome(kf.T_world_cam.copy(), status, KeyframeLink("segment"))

    def _recover(
        self,
        frame: PreparedFrame,
        ratio: float,
        min_weight: float | None = None,
        verify: bool = True,
    ) -> Outcome:
        """While lost: track the frame against the model as after a gap (prediction
        extrapolated from the last pose over the time since, alternative guesses, and with
        ``verify`` verification by ORB matches), the model rendered down to ``min_weight``
        when given. Tracking goes on in the same run when it verifies."""
        T, status = self.tracker.track(
            frame, self.model, verify=verify, dt_ratio=ratio, segment=self.segment,
            min_weight=min_weight,
        )  # fmt: skip
        if T is None:
            return Outcome(None, status)
        self._resume()
        seen = "" if min_weight is None else f" (every surface fused at least {min_weight:g}x)"
        status.reason = f"recovered against the model{seen} after {ratio:.0f} frame intervals"
        record: dict[str, Any] = {"frame": frame.index, "method": "model"}
        if min_weight is not None:
            record["min_weight"] = min_weight
        self.relocalisations.append(record)
        log.info("frame %d: tracking recovered against the model%s", frame.index, seen)
        return Outcome(T, status)

    def _recover_all_surfaces(
        self, frame: PreparedFrame, ratio: float, verify: bool, failed: Outcome
    ) -> Outcome:
        """A lost frame that no keyframe relocalises (``failed``, returned as it is when
        ``tracking.recovery.rescue_min_weight`` is 0): :meth:`_recover` against every surface the model
        has seen, not only those fused past the ray-cast's weight threshold. ``verify``: the
        pose needs ORB support (the frame follows a gap or lost frames; the frame that was
        just lost follows the last tracked one, and is checked as any tracked frame is)."""
        if self.cfg.recovery.rescue_min_weight <= 0:
            return failed
        return self._recover(frame, ratio, self.cfg.recovery.rescue_min_weight, verify)

    def _relocalise(self, frame: PreparedFrame) -> Outcome:
        """Register the frame against the whole map; on success tracking resumes there."""
        t0 = time.perf_counter()
        found = self.relocaliser.relocalise(
            frame.view(), self.tracker.state.keyframes, self.tracker.state.T_world_prev
        )
        if found is None:
            reason = "lost; relocalisation found no keyframe that verifies"
            status = self.tracker.lost_status(frame, reason, segment=self.segment)
            status.ms = (time.perf_counter() - t0) * 1e3
            return Outcome(None, status)
        match, T, ver = found.keyframe, found.T_world_cam, found.verification
        self.run += 1
        self.segment = match.segment
        self._resume()
        status = self.tracker.reset(frame, T, "reloc", self.segment, evidence=ver)
        kf = self.tracker.state.keyframes[-1]
        home = self.model.submap_of_keyframe(match.id)
        if home is not self.model.active:
            self.model.start_submap(
                kf.id, T, seed_from=home, seed_views=[T, match.T_world_cam], continuous=False
            )
        self.relocalisations.append(
            {"frame": frame.index, "method": "keyframe", "keyframe": match.id,
             "keyframe_frame": match.index}
        )  # fmt: skip
        log.info(
            "frame %d: relocalised against keyframe %d (frame %d), %d candidates tried",
            frame.index,
            match.id,
            match.index,
            found.candidates_tried,
        )
        status.ms += (time.perf_counter() - t0) * 1e3
        info = ver.information / self.loop_sigma_m**2
        return Outcome(
            T, status, KeyframeLink("relocalisation", match.id, ver.T_candidate_query, info)
        )

    # --- checkpoints
    def state_dict(self) -> dict[str, Any]:
        return {
            "segment": self.segment,
            "run": self.run,
            "lost": self.lost,
            "lost_with_depth": self.lost_with_depth,
            "relocalisations": [dict(r) for r in self.relocalisations],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.segment = int(state["segment"])
        self.run = int(state["run"])
        self.lost = bool(state["lost"])
        self.lost_with_depth = int(state["lost_with_depth"])
        self.relocalisations = [dict(r) for r in state["relocalisations"]]
