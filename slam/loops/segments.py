"""Map segments and their joins.

When tracking is lost and cannot be relocalised, a new map segment starts: its first keyframe
has no edge to the old ones and its own prior. A verified revisit between two segments cannot
be checked against odometry (there is none between them), so segments are joined only when
``loop.join_verifications`` such revisits agree on where one segment lies in the other.
:class:`MapSegments` keeps which segments are joined (a union-find: a joined segment resolves
to the root of its component), the revisits waiting to join two segments, and the record of
each join; the loop closer moves the graph when a join is found.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from slam.config import LoopConfig
from slam.geometry import inv_T, rotation_angle_deg, translation_norm
from slam.keyframe import Keyframe
from slam.loops.verification import Verification


@dataclass
class PendingJoin:
    """A verified revisit between two map segments: ``query`` (the new keyframe) seen from
    ``candidate``; ``record``: its loop record's position in the closer's records."""

    candidate: Keyframe
    query: Keyframe
    verification: Verification
    record: int


@dataclass
class Join:
    """Segment ``b_root``'s component goes into ``a_root``'s: its graph frame lies at ``T_ab``
    in a's, as the agreeing revisits ``evidence`` say."""

    a_root: int
    b_root: int
    T_ab: np.ndarray
    evidence: list[PendingJoin]


@dataclass
class MapSegments:
    """Which map segments are joined, and the revisits that may join more (see the module
    docstring)."""

    cfg: LoopConfig
    parent: dict[int, int] = field(default_factory=dict)  # union-find of joined segments
    joins: list[dict[str, Any]] = field(default_factory=list)  # metrics.json segment_joins
    pending: list[PendingJoin] = field(default_factory=list)

    def root(self, segment: int) -> int:
        """The segment id that stands for all segments joined with ``segment``."""
        self.parent.setdefault(segment, segment)
        while self.parent[segment] != segment:
            segment = self.parent[segment]
        return segment

    def same_map(self, a: Keyframe, b: Keyframe) -> bool:
        """Whether two keyframes lie in one map component (their segments are joined)."""
        return self.root(a.segment) == self.root(b.segment)

    def find_join(self, T_world_kf: Callable[[int], np.ndarray]) -> Join | None:
        """Two components to join: enough pending revisits between them agree on the transform
        that puts one into the other's frame (``T_world_kf``: the current keyframe poses)."""
        c = self.cfg
        # pairs whose segments were joined meanwhile are dropped
        self.pending = [p for p in self.pending if not self.same_map(p.candidate, p.query)]

        def roots(p: PendingJoin) -> tuple[int, int]:
            return self.root(p.candidate.segment), self.root(p.query.segment)

        for a_root, b_root in {roots(p) for p in self.pending}:
            group = [p for p in self.pending if roots(p) == (a_root, b_root)]
            # where segment b's graph frame lies in segment a's, by each revisit
            moves = [
                T_world_kf(p.candidate.id)
                @ p.verification.T_candidate_query
                @ inv_T(T_world_kf(p.query.id))
                for p in group
            ]
            for T_ab in moves:
                agree = [
                    j
                    for j, T in enumerate(moves)
                    if translation_norm(inv_T(T_ab) @ T) < c.consistency_m
                    and rotation_angle_deg(inv_T(T_ab) @ T) < c.consistency_deg
                ]
                if len(agree) >= c.join_verifications:
                    return Join(a_root, b_root, T_ab, [group[j] for j in agree])
        return None

    def joined(self, join: Join) -> None:
        """Record a join the closer has applied to the graph."""
        self.parent[join.b_root] = join.a_root
        self.joins.append(
            {
                "segment": join.b_root,
                "into": join.a_root,
                "keyframe": max(p.query.id for p in join.evidence),
                "revisits": len(join.evidence),
            }
        )
        self.pending = [p for p in self.pending if not self.same_map(p.candidate, p.query)]

    # --- checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Plain data; keyframes by id, verifications as their fields."""
        return {
            "parent": dict(self.parent),
            "joins": [dict(j) for j in self.joins],
            "pending": [
                (p.candidate.id, p.query.id, dict(vars(p.verification)), p.record)
                for p in self.pending
            ],
        }

    def load_state_dict(self, state: dict[str, Any], keyframes: dict[int, Keyframe]) -> None:
        self.parent = {int(k): int(v) for k, v in state["parent"].items()}
        self.joins = [dict(j) for j in state["joins"]]
        self.pending = [
            PendingJoin(keyframes[c], keyframes[k], Verification(**v), int(tag))
            for c, k, v, tag in state["pending"]
        ]
