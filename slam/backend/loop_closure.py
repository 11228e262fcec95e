"""Loop closure: keyframes go into the pose graph with odometry edges; each new keyframe queries
the place-recognition index for revisits, candidates are verified geometrically and checked
against the current estimate, accepted loops become robust graph edges and the graph is
optimised. :func:`elastic_correction` then bends every frame pose with its keyframes.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from slam.backend.pose_graph import Edge, PoseGraph
from slam.config import BackendConfig, LoopConfig
from slam.frontend.loop_verification import (
    KeyframeView,
    LoopVerifier,
    Verification,
    registration_information,
)
from slam.frontend.place_recognition import KeyframeDatabase
from slam.frontend.tracker import Keyframe
from slam.geometry import exp_se3, inv_T, log_se3, rotation_angle_deg, translation_norm

log = logging.getLogger(__name__)


def _view(kf: Keyframe) -> KeyframeView:
    assert kf.depth_m is not None and kf.K is not None
    return KeyframeView(kf.features, kf.depth_m, kf.K)


@dataclass
class LoopCloser:
    """Owns the keyframe pose graph, the revisit index and the loop records."""

    loop_cfg: LoopConfig
    backend_cfg: BackendConfig
    depth_max_m: float = 4.0
    graph: PoseGraph = field(init=False)
    database: KeyframeDatabase = field(init=False)
    keyframes: list[Keyframe] = field(default_factory=list)
    path_length_m: list[float] = field(default_factory=list)  # along the keyframe chain
    records: list[dict[str, Any]] = field(default_factory=list)
    ms: dict[str, float] = field(
        default_factory=lambda: {"loop_detection": 0.0, "optimisation": 0.0, "graph": 0.0}
    )
    optimisations: int = 0

    def __post_init__(self) -> None:
        self.graph = PoseGraph(self.backend_cfg)
        self.database = KeyframeDatabase(
            self.loop_cfg.vocabulary_words, self.loop_cfg.vocabulary_keyframes
        )
        self.verifier = LoopVerifier(self.loop_cfg, self.depth_max_m)

    @property
    def loops_accepted(self) -> int:
        return sum(r["accepted"] for r in self.records)

    @property
    def loops_rejected(self) -> int:
        return sum(not r["accepted"] for r in self.records)

    def T_world_kf(self, kf_id: int) -> np.ndarray:
        """Current (corrected) estimate of a keyframe's pose."""
        return self.graph.nodes[kf_id]

    # --- graph building
    def _odometry_information(self, prev: Keyframe, kf: Keyframe, T_prev_kf: np.ndarray):
        c = self.backend_cfg
        sigma = c.odometry_sigma_m + c.odometry_drift_per_m * (
            translation_norm(T_prev_kf) + np.radians(rotation_angle_deg(T_prev_kf))
        )
        if kf.depth_m is None or prev.depth_m is None or kf.K is None:
            return np.eye(6) / sigma**2
        info, n = registration_information(
            kf.depth_m, prev.depth_m, kf.K, T_prev_kf, 0.03, self.depth_max_m
        )
        if n < 10:  # nothing overlaps: a weak isotropic edge keeps the chain connected
            return np.eye(6) / (10 * sigma) ** 2
        return info / sigma**2

    def add_keyframe(self, kf: Keyframe) -> list[dict[str, Any]]:
        """Add a keyframe (odometry pose in ``kf.T_world_cam``): graph node and odometry edge,
        then revisit detection. Returns the loop records of this keyframe."""
        t0 = time.perf_counter()
        if not self.keyframes:
            self.graph.add_node(kf.id, kf.T_world_cam)
            self.path_length_m.append(0.0)
        else:
            prev = self.keyframes[-1]
            T_prev_kf = inv_T(prev.T_world_cam) @ kf.T_world_cam
            self.graph.add_node(kf.id, self.graph.nodes[prev.id] @ T_prev_kf)
            info = self._odometry_information(prev, kf, T_prev_kf)
            self.graph.add_edge(Edge(prev.id, kf.id, T_prev_kf, info, "odometry"))
            self.path_length_m.append(self.path_length_m[-1] + translation_norm(T_prev_kf))
        self.keyframes.append(kf)
        self.ms["graph"] += (time.perf_counter() - t0) * 1e3

        records: list[dict[str, Any]] = []
        cfg = self.loop_cfg
        if not cfg.enabled or len(kf.features) == 0 or kf.depth_m is None:
            return records
        t0 = time.perf_counter()
        self.database.observe(kf.features.descriptors)
        candidates = self.database.query(kf.features.descriptors, cfg.max_candidates, cfg.min_score)
        accepted = []
        for cand_id, score in candidates:
            cand = self.keyframes[cand_id]
            ver = self.verifier.verify(_view(kf), _view(cand))
            if ver.accepted:
                self._check_consistency(cand, kf, ver)
            rec = {
                "query_kf": kf.id,
                "match_kf": cand.id,
                "query_frame": kf.index,
                "match_frame": cand.index,
                "query_timestamp": kf.timestamp,
                "match_timestamp": cand.timestamp,
                "score": round(score, 4),
                **ver.summary(),
            }
            records.append(rec)
            log.log(
                logging.INFO if ver.accepted else logging.DEBUG,
                "loop candidate frame %d -> %d (keyframes %d -> %d, score %.3f): %s",
                kf.index,
                cand.index,
                kf.id,
                cand.id,
                score,
                ver.reason,
            )
            if ver.accepted:
                accepted.append((cand, ver))
        # index the keyframe that just left the "recent" window
        old = len(self.keyframes) - 1 - cfg.exclude_recent_keyframes
        if old >= 0:
            k_old = self.keyframes[old]
            self.database.add(k_old.id, k_old.features.descriptors)
        self.ms["loop_detection"] += (time.perf_counter() - t0) * 1e3
        self.records.extend(records)

        if accepted:
            s = self.backend_cfg.loop_sigma_m
            for cand, ver in accepted:
                tag = (
                    len(self.records)
                    - len(records)
                    + next(k for k, r in enumerate(records) if r["match_kf"] == cand.id)
                )
                self.add_loop(cand.id, kf.id, ver.T_candidate_query, ver.information / s**2, tag)
            self.optimize()
        return records

    def _check_consistency(self, cand: Keyframe, kf: Keyframe, ver: Verification) -> None:
        """Reject a loop whose relative pose disagrees with the current estimate by more than
        odometry could have drifted along the path between the two keyframes."""
        c = self.loop_cfg
        T_pred = inv_T(self.T_world_kf(cand.id)) @ self.T_world_kf(kf.id)
        err = inv_T(T_pred) @ ver.T_candidate_query
        path = self.path_length_m[kf.id] - self.path_length_m[cand.id]
        tol_m = c.consistency_m + c.consistency_per_m * path
        tol_deg = c.consistency_deg + c.consistency_deg_per_m * path
        if translation_norm(err) > tol_m or rotation_angle_deg(err) > tol_deg:
            ver.accepted = False
            ver.reason = (
                f"inconsistent with odometry: {translation_norm(err):.2f} m / "
                f"{rotation_angle_deg(err):.1f} deg off after {path:.1f} m of path "
                f"(tolerance {tol_m:.2f} m / {tol_deg:.1f} deg)"
            )

    def add_loop(
        self, i: int, j: int, T_i_j: np.ndarray, information: np.ndarray, tag: int = -1
    ) -> None:
        """Add a loop edge (robust noise model) between keyframes ``i`` and ``j``."""
        self.graph.add_edge(Edge(i, j, T_i_j, information, "loop", tag))

    def optimize(self) -> None:
        """Optimise; then, while the worst loop edge still disagrees with the optimised graph by
        more than ``loop_prune_sigma`` (the robust kernel kept it from bending the graph, so its
        residual stays large), remove it and optimise again."""
        thr = self.backend_cfg.loop_prune_sigma
        while True:
            report = self.graph.optimize()
            self.ms["optimisation"] += report.ms
            self.optimisations += 1
            loops = [e for e in self.graph.edges if e.kind == "loop"]
            if not loops:
                return
            r, worst = max((self.graph.whitened_residual(e), k) for k, e in enumerate(loops))
            if r <= thr:
                return
            edge = loops[worst]
            self.graph.remove_edge(edge)
            log.warning(
                "loop keyframes %d -> %d removed: residual %.1f sigma after optimisation (max %.1f)",
                edge.j,
                edge.i,
                r,
                thr,
            )
            if 0 <= edge.tag < len(self.records):
                rec = self.records[edge.tag]
                rec["accepted"] = False
                rec["reason"] = (
                    f"rejected by the pose graph: residual {r:.1f} sigma after optimisation "
                    f"(max {thr})"
                )

    def loops_json(self) -> dict[str, Any]:
        return {"candidates": self.records}


def elastic_correction(
    odometry: np.ndarray,
    kf_positions: list[int],
    T_world_kf_odometry: list[np.ndarray],
    T_world_kf_corrected: list[np.ndarray],
) -> np.ndarray:
    """Corrected poses of every frame from the corrected keyframe poses.

    ``odometry`` (N, 4, 4): frontend poses of all frames; ``kf_positions``: the row of each
    keyframe in ``odometry`` (increasing). A frame between keyframes a and b keeps its odometry
    pose relative to each of them, giving two estimates ``T_a' T_a^-1 T`` and ``T_b' T_b^-1 T``;
    it takes their SE(3) interpolation at its fraction of the way from a to b, so the
    trajectory bends smoothly and keyframes land exactly on their optimised poses.
    """
    out = odometry.copy()
    if not kf_positions:
        return out
    corr = [Tc @ inv_T(To) for Tc, To in zip(T_world_kf_corrected, T_world_kf_odometry)]
    n = len(odometry)
    first, last = kf_positions[0], kf_positions[-1]
    for f in range(0, first):
        out[f] = corr[0] @ odometry[f]
    for f in range(last, n):
        out[f] = corr[-1] @ odometry[f]
    for k in range(len(kf_positions) - 1):
        a, b = kf_positions[k], kf_positions[k + 1]
        for f in range(a, b):
            Ta = corr[k] @ odometry[f]
            Tb = corr[k + 1] @ odometry[f]
            s = (f - a) / (b - a)
            out[f] = Ta @ exp_se3(s * log_se3(inv_T(Ta) @ Tb))
    return out
