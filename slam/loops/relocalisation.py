"""Relocalisation: find where a frame is in the map after tracking was lost.

With colour, the frame is verified against keyframes exactly as a loop candidate is (ORB
matches lifted by depth, RANSAC, then ICP between the depth images: the loop verifier), trying
the keyframes that place recognition ranks highest over the whole map, then the most recent ones
(not yet in the place-recognition index) ranked by descriptor matches. Without colour
(depth-only sequences) the recent keyframes are tried by ICP from the last known pose, and a
pose is accepted only with a high depth overlap.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from slam.frontend.features import match_descriptors
from slam.frontend.icp import projective_icp, projective_overlap
from slam.geometry import inv_T
from slam.keyframe import Keyframe, KeyframeView
from slam.loops.place_recognition import KeyframeDatabase
from slam.loops.verification import (
    ICP_ITERATIONS,
    LoopVerifier,
    Verification,
    registration_information,
)

log = logging.getLogger(__name__)


@dataclass
class Relocalisation:
    """A verified pose: ``keyframe`` is the one the frame was registered to and
    ``verification.T_candidate_query`` the frame's pose in that keyframe's camera frame."""

    keyframe: Keyframe
    verification: Verification
    candidates_tried: int

    @property
    def T_world_cam(self) -> np.ndarray:
        """The frame's pose in the keyframe's (odometry) frame."""
        return self.keyframe.T_world_cam @ self.verification.T_candidate_query


class Relocaliser:
    """Registers a lost frame against the map's keyframes (see the module docstring)."""

    def __init__(
        self,
        verifier: LoopVerifier,
        database: KeyframeDatabase,
        max_candidates: int = 5,
        recent_keyframes: int = 8,
        depth_only_overlap: float = 0.75,
        depth_max_m: float = 4.0,
    ) -> None:
        self.verifier = verifier
        self.database = database
        self.max_candidates = max_candidates
        self.recent_keyframes = recent_keyframes
        self.depth_only_overlap = depth_only_overlap
        self.depth_max_m = depth_max_m

    def candidates(self, view: KeyframeView, keyframes: list[Keyframe]) -> list[Keyframe]:
        """Keyframes to verify, best first: alternately the recent keyframes with the most
        descriptor matches and place recognition's best over the indexed (older) ones."""
        desc = view.features.descriptors
        by_id = {kf.id: kf for kf in keyframes}
        indexed = [by_id[i] for i, _ in self.database.query(desc, self.max_candidates)]
        recent = keyframes[-self.recent_keyframes :]
        if not self.database.trained:
            recent = keyframes  # nothing is indexed yet: few keyframes, rank them all
        counts = [len(match_descriptors(desc, kf.features.descriptors)) for kf in recent]
        ranked = [kf for _, kf in sorted(zip(counts, recent), key=lambda p: -p[0]) if _ > 0]
        out: list[Keyframe] = []
        for pair in zip(ranked + [None] * len(indexed), indexed + [None] * len(ranked)):
            for kf in pair:
                if kf is not None and all(kf.id != k.id for k in out):
                    out.append(kf)
        return out[: self.max_candidates]

    def relocalise(
        self,
        view: KeyframeView,
        keyframes: list[Keyframe],
        T_world_last: np.ndarray | None = None,
    ) -> Relocalisation | None:
        """The first candidate keyframe that verifies, or None. ``T_world_last``: the last
        known pose (used by the depth-only search)."""
        if not keyframes:
            return None
        if len(view.features) == 0:
            return self._depth_only(view, keyframes, T_world_last)
        tried = 0
        for kf in self.candidates(view, keyframes):
            tried += 1
            ver = self.verifier.verify(view, kf.view())
            log.debug("relocalisation against keyframe %d: %s", kf.id, ver.reason)
            if ver.accepted:
                return Relocalisation(kf, ver, tried)
        return None

    def _depth_only(
        self, view: KeyframeView, keyframes: list[Keyframe], T_world_last: np.ndarray | None
    ) -> Relocalisation | None:
        if T_world_last is None:
            return None
        recent = list(reversed(keyframes[-self.recent_keyframes :]))
        for tried, kf in enumerate(recent, 1):
            init = inv_T(kf.T_world_cam) @ T_world_last
            c = self.verifier.cfg  # the checks of loop verification, on depth alone
            icp = projective_icp(
                view.depth_m,
                kf.depth_m,
                view.K,
                init,
                ICP_ITERATIONS,
                self.depth_max_m,
                c.icp_max_correspondence_m,
                c.icp_huber_delta_m,
            )
            T = icp.T_target_source
            overlap = projective_overlap(view.depth_m, kf.depth_m, view.K, T, c.overlap_threshold_m)
            if overlap >= self.depth_only_overlap:
                info, _ = registration_information(
                    view.depth_m, kf.depth_m, view.K, T, c.overlap_threshold_m, self.depth_max_m
                )
                ver = Verification(
                    True,
                    "accepted",
                    icp_fitness=float(icp.fitness),
                    overlap=overlap,
                    T_candidate_query=T,
                    information=info,
                )
                return Relocalisation(kf, ver, tried)
        return None
