"""Loop closure: keyframes go into the pose graph with odometry edges; each new keyframe queries
the place-recognition index for revisits, candidates are verified geometrically and checked
against the current estimate, accepted loops become robust graph edges and the graph is
optimised. :func:`slam.backend.finalise.elastic_correction` then bends every frame pose with its
keyframes. Revisits between map segments join them (:mod:`slam.loops.segments`): the joined
segment is moved rigidly into the other's frame, its prior dropped, and the graph optimised.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from types import MappingProxyType
from typing import Any

import numpy as np

from slam.backend.pose_graph import Edge, PoseGraph
from slam.config import BackendConfig, LoopConfig
from slam.geometry import inv_T, rotation_angle_deg, translation_norm
from slam.keyframe import Keyframe
from slam.loops.place_recognition import KeyframeDatabase
from slam.loops.segments import Join, MapSegments, PendingJoin
from slam.loops.verification import LoopVerifier, Verification, registration_information
from slam.records import LoopRecord

log = logging.getLogger(__name__)


@dataclass
class KeyframeLink:
    """How a keyframe that does not follow its predecessor by tracking joins the graph:
    ``relocalisation`` (an edge to keyframe ``other`` with the registration ``T_other_kf``) or
    ``segment`` (the first keyframe of a new map segment: no edge, its own prior)."""

    kind: str
    other: int = -1
    T_other_kf: np.ndarray | None = None
    information: np.ndarray | None = None


@dataclass
class LoopCloser:
    """Owns the keyframe pose graph, the revisit index and the loop records."""

    loop_cfg: LoopConfig
    backend_cfg: BackendConfig
    depth_max_m: float = 4.0
    color_registered: bool = True  # features' 3D points from registered depth (verification)
    graph: PoseGraph = field(init=False)
    database: KeyframeDatabase = field(init=False)
    keyframes: list[Keyframe] = field(default_factory=list)
    path_length_m: list[float] = field(default_factory=list)  # along the keyframe chain
    records: list[LoopRecord] = field(default_factory=list)
    ms: dict[str, float] = field(
        default_factory=lambda: {"loop_detection": 0.0, "optimisation": 0.0, "graph": 0.0}
    )
    optimisations: int = 0
    # every verification's outcome by (query frame, candidate frame), as the verifier gave it:
    # a replay of the same keyframes (the join of a parallel run) does not verify them again
    verified: dict[tuple[int, int], Verification] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.graph = PoseGraph(self.backend_cfg)
        self.database = KeyframeDatabase(
            self.loop_cfg.vocabulary_words, self.loop_cfg.vocabulary_keyframes
        )
        self.verifier = LoopVerifier(
            self.loop_cfg, self.depth_max_m, features_on_depth=self.color_registered
        )
        self.segments = MapSegments(self.loop_cfg)

    @property
    def joins(self) -> list[dict[str, Any]]:
        """The map segments joined so far (``metrics.json``'s ``segment_joins``)."""
        return self.segments.joins

    @property
    def loops_accepted(self) -> int:
        return sum(r.accepted for r in self.records)

    @property
    def loops_rejected(self) -> int:
        return sum(not r.accepted for r in self.records)

    def keyframe_poses(self) -> Mapping[int, np.ndarray]:
        """The current (corrected) keyframe poses by id: a read-only view of the graph's."""
        return MappingProxyType(self.graph.nodes)

    def adopt_poses(self, poses: Mapping[int, np.ndarray]) -> None:
        """Take keyframe poses solved elsewhere (bundle adjustment) as the current estimate:
        later loop checks and track matching start from them."""
        self.graph.nodes.update(poses)

    def T_world_kf(self, kf_id: int) -> np.ndarray:
        """Current (corrected) estimate of a keyframe's pose."""
        return self.graph.nodes[kf_id]

    # --- map segments
    def segment_root(self, segment: int) -> int:
        """The segment id that stands for all segments joined with ``segment``."""
        return self.segments.root(segment)

    def same_map(self, a: Keyframe, b: Keyframe) -> bool:
        """Whether two keyframes lie in one map component (their segments are joined)."""
        return self.segments.same_map(a, b)

    def add_keyframe(self, kf: Keyframe, link: KeyframeLink | None = None) -> list[LoopRecord]:
        """Add a keyframe (odometry pose in ``kf.T_world_cam``): graph node and its edge (from
        the previous keyframe by odometry, or as ``link`` says), then revisit detection, loop
        edges, segment joins and optimisation. Returns the loop records of this keyframe."""
        self._add_to_graph(kf, link)
        cfg = self.loop_cfg
        if not cfg.enabled or len(kf.features) == 0 or kf.depth_m is None:
            return []
        records, accepted, joining = self._detect(kf)
        join = self.segments.find_join(self.T_world_kf) if joining else None
        if join is not None:
            self._join(join)
        s = self.backend_cfg.loop_sigma_m
        for tag, ver in accepted:
            rec = self.records[tag]
            self.add_loop(rec.match_kf, kf.id, ver.T_candidate_query, ver.information / s**2, tag)
        if accepted or join is not None:
            self.optimize()
        return records

    def _add_to_graph(self, kf: Keyframe, link: KeyframeLink | None) -> None:
        t0 = time.perf_counter()
        self.segment_root(kf.segment)
        if not self.keyframes or (link is not None and link.kind == "segment"):
            self.graph.add_node(kf.id, kf.T_world_cam)
            self.graph.anchors.add(kf.id)  # a prior holds the new segment until it is joined
            self.path_length_m.append(self.path_length_m[-1] if self.path_length_m else 0.0)
        else:
            prev = self.keyframes[-1]
            T_prev_kf = inv_T(prev.T_world_cam) @ kf.T_world_cam
            if link is not None and link.kind == "relocalisation":
                assert link.T_other_kf is not None and link.information is not None
                self.graph.add_node(kf.id, self.graph.nodes[link.other] @ link.T_other_kf)
                self.graph.add_edge(
                    Edge(link.other, kf.id, link.T_other_kf, link.information, "relocalisation")
                )
            else:
                self.graph.add_node(kf.id, self.graph.nodes[prev.id] @ T_prev_kf)
                info = odometry_information(prev, kf, T_prev_kf, self.backend_cfg, self.depth_max_m)
                self.graph.add_edge(Edge(prev.id, kf.id, T_prev_kf, info, "odometry"))
            self.path_length_m.append(self.path_length_m[-1] + translation_norm(T_prev_kf))
        self.keyframes.append(kf)
        self.ms["graph"] += (time.perf_counter() - t0) * 1e3

    def _detect(
        self, kf: Keyframe
    ) -> tuple[list[LoopRecord], list[tuple[int, Verification]], bool]:
        """Revisit candidates of ``kf`` from place recognition, each verified and (in the same
        map) checked against odometry; verified revisits across map segments wait to join
        them. Returns (this keyframe's records, the accepted ones as (position in
        ``self.records``, verification), whether a revisit across segments was verified)."""
        t0 = time.perf_counter()
        cfg = self.loop_cfg
        self.database.observe(kf.features.descriptors)
        candidates = self.database.query(kf.features.descriptors, cfg.max_candidates, cfg.min_score)
        records: list[LoopRecord] = []
        accepted: list[tuple[int, Verification]] = []
        joining = False
        for cand_id, score in candidates:
            cand = self.keyframes[cand_id]
            ver = self._verify(kf, cand)
            across = ver.accepted and not self.same_map(cand, kf)
            if across:
                ver.accepted = False
                ver.reason = (
                    f"verified across map segments {cand.segment} and {kf.segment}: waits for "
                    f"{cfg.join_verifications} agreeing revisits to join them"
                )
            elif ver.accepted:
                T_pred = inv_T(self.T_world_kf(cand.id)) @ self.T_world_kf(kf.id)
                path = self.path_length_m[kf.id] - self.path_length_m[cand.id]
                check_consistency(ver, T_pred, path, cfg)
            rec = ver.record(kf, cand, score)
            self.records.append(rec)
            records.append(rec)
            log.log(
                logging.INFO if ver.accepted else logging.DEBUG,
                "loop candidate frame %d -> %d (keyframes %d -> %d, score %.3f): %s",
                kf.index, cand.index, kf.id, cand.id, score, ver.reason,
            )  # fmt: skip
            if ver.accepted:
                accepted.append((len(self.records) - 1, ver))
            elif across:
                self.segments.pending.append(PendingJoin(cand, kf, ver, len(self.records) - 1))
                joining = True
        # index the keyframe that just left the "recent" window
        old = len(self.keyframes) - 1 - cfg.exclude_recent_keyframes
        if old >= 0:
            k_old = self.keyframes[old]
            self.database.add(k_old.id, k_old.features.descriptors)
        self.ms["loop_detection"] += (time.perf_counter() - t0) * 1e3
        return records, accepted, joining

    def _verify(self, kf: Keyframe, cand: Keyframe) -> Verification:
        """The verifier's outcome for the pair (remembered: see ``verified``); a copy, which
        the checks that follow may reject."""
        known = self.verified.get((kf.index, cand.index))
        if known is None:
            known = self.verified[(kf.index, cand.index)] = self.verifier.verify(
                kf.view(), cand.view()
            )
        return replace(known)

    def remember(self, other: LoopCloser) -> None:
        """Take the verifications ``other`` made (a chunk of a parallel run, the same frames)."""
        self.verified.update(other.verified)

    def _join(self, join: Join) -> None:
        """Move segment ``b``'s keyframes rigidly into ``a``'s frame, drop its prior, add the
        agreeing revisits as loop edges and mark their records accepted."""
        members = {kf.id for kf in self.keyframes if self.segment_root(kf.segment) == join.b_root}
        for key in members:
            self.graph.nodes[key] = join.T_ab @ self.graph.nodes[key]
        self.graph.anchors -= members
        s = self.backend_cfg.loop_sigma_m
        for p in join.evidence:
            ver, tag = p.verification, p.record
            self.add_loop(p.candidate.id, p.query.id, ver.T_candidate_query,
                          ver.information / s**2, tag)  # fmt: skip
            if 0 <= tag < len(self.records):
                self.records[tag].accepted = True
                self.records[tag].reason = (
                    f"accepted: joins map segment {p.query.segment} to segment "
                    f"{p.candidate.segment}"
                )
        self.segments.joined(join)
        log.info(
            "map segment %d joined to segment %d by %d agreeing revisits",
            join.b_root, join.a_root, len(join.evidence),
        )  # fmt: skip

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
                rec.accepted = False
                rec.reason = (
                    f"rejected by the pose graph: residual {r:.1f} sigma after optimisation "
                    f"(max {thr})"
                )

    def loops_json(self) -> dict[str, Any]:
        """The ``loops.json`` object: every verified candidate, in order."""
        return {"candidates": [r.as_json() for r in self.records]}

    # --- checkpoints
    def state_dict(self) -> dict[str, Any]:
        """The graph, loop records, path lengths, segment joins and the place-recognition
        index; keyframes are saved by the caller (they are shared with the tracker) and named
        here by id."""
        return {
            "graph": self.graph.state_dict(),
            "database": self.database.state_dict(),
            "keyframes": [kf.id for kf in self.keyframes],
            "path_length_m": list(self.path_length_m),
            "records": [asdict(r) for r in self.records],
            "ms": dict(self.ms),
            "optimisations": self.optimisations,
            "segments": self.segments.state_dict(),
            "verifier": self.verifier.state_dict(),
            "verified": [[q, c, asdict(v)] for (q, c), v in self.verified.items()],
        }

    def load_state_dict(self, state: dict[str, Any], keyframes: dict[int, Keyframe]) -> None:
        self.graph = PoseGraph.from_state_dict(self.backend_cfg, state["graph"])
        self.database = KeyframeDatabase.from_state_dict(state["database"])
        self.keyframes = [keyframes[i] for i in state["keyframes"]]
        self.path_length_m = list(state["path_length_m"])
        self.records = [LoopRecord(**r) for r in state["records"]]
        self.ms = dict(state["ms"])
        self.optimisations = state["optimisations"]
        self.segments.load_state_dict(state["segments"], keyframes)
        self.verifier.load_state_dict(state["verifier"])
        self.verified = {(int(q), int(c)): Verification(**v) for q, c, v in state["verified"]}


def odometry_information(
    prev: Keyframe, kf: Keyframe, T_prev_kf: np.ndarray, c: BackendConfig, depth_max_m: float
) -> np.ndarray:
    """The information of the odometry edge ``prev -> kf``: the shape of the two keyframes'
    depth registration (which motions their overlap constrains), scaled by a sigma that grows
    with the motion the edge spans."""
    sigma = c.odometry_sigma_m + c.odometry_drift_per_m * (
        translation_norm(T_prev_kf) + np.radians(rotation_angle_deg(T_prev_kf))
    )
    if kf.depth_m is None or prev.depth_m is None or kf.K is None:
        return np.eye(6) / sigma**2
    info, n = registration_information(
        kf.depth_m, prev.depth_m, kf.K, T_prev_kf, c.odometry_information_threshold_m, depth_max_m
    )
    if n < 10:  # nothing overlaps: a weak isotropic edge keeps the chain connected
        return np.eye(6) / (10 * sigma) ** 2
    return info / sigma**2


def check_consistency(ver: Verification, T_pred: np.ndarray, path_m: float, c: LoopConfig) -> None:
    """Reject a verified loop whose relative pose disagrees with the current estimate
    ``T_pred`` (candidate -> query) by more than odometry could have drifted along the
    ``path_m`` travelled between the two keyframes."""
    err = inv_T(T_pred) @ ver.T_candidate_query
    tol_m = c.consistency_m + c.consistency_per_m * path_m
    tol_deg = c.consistency_deg + c.consistency_deg_per_m * path_m
    if translation_norm(err) > tol_m or rotation_angle_deg(err) > tol_deg:
        ver.accepted = False
        ver.reason = (
            f"inconsistent with odometry: {translation_norm(err):.2f} m / "
            f"{rotation_angle_deg(err):.1f} deg off after {path_m:.1f} m of path "
            f"(tolerance {tol_m:.2f} m / {tol_deg:.1f} deg)"
        )
