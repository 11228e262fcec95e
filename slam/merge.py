"""A map grown by a new recording (``slam run SEQ --map RUN_DIR --extend``): the new recording is
mapped as any run is, then joined to the saved map.

1. **Links**: each new keyframe is verified against the old keyframes place recognition ranks
   highest (the loop verifier: ORB matches lifted by depth, RANSAC, ICP between the depth
   images); every accepted pair is a loop edge between the two maps.
2. **One pose graph**: the old keyframes (held by a prior on the first, and to each other by
   their saved relative poses, stiffly: the old map was optimised already), the new keyframes
   (held to each other by their relative poses with a frontend's drift between keyframes, so
   links at both ends bend the new recording as a loop closure would) and the links (robust
   loop edges, as the loop closer weighs them), solved by GTSAM; the new keyframes start where
   the first link puts them.
3. **Poses and surface**: the new frames follow their keyframes (the elastic correction); the
   new map's volume is rendered from the new frames' views (every ``reintegration_stride``-th)
   and fused, where the solution moves each view, into the old map's volume: the merged mesh
   and map.

A recording that never meets the old map (no link) stays its own segment, in its own frame: the
result is the new run as it was, reported as not joined, and no merged map is written.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np

from slam.backend.finalise import elastic_correction
from slam.backend.pose_graph import Edge, PoseGraph
from slam.camera import scale_intrinsics
from slam.config import SlamConfig
from slam.geometry import inv_T
from slam.keyframe import Keyframe
from slam.loops.verification import LoopVerifier
from slam.mapping.tsdf import TSDFVolume
from slam.results import RunResult
from slam.saved_map import Map
from slam.trajectory import Trajectory

__all__ = ["MergeReport", "extend_map"]

log = logging.getLogger(__name__)

#: how stiffly the old map holds its keyframes together (sigma: rad, m): it was optimised
_STIFF_ROT_RAD, _STIFF_M = np.deg2rad(0.05), 0.0005
#: how the new recording's keyframes hold together: a frontend's drift between keyframes
#: (sigma: rad, m), so links at both ends of it can bend it as the loop closer would
_ODOMETRY_ROT_RAD, _ODOMETRY_M = np.deg2rad(0.3), 0.005
#: old keyframes each new keyframe is verified against
_CANDIDATES = 3


@dataclass
class MergeReport:
    """How a new recording joined a saved map: ``joined`` (at least one verified link), the
    links as (new keyframe frame, old keyframe frame) pairs, the pairs tried, and how far the
    solution moved the old keyframes (m; the old map is held stiffly, so ~0)."""

    joined: bool
    links: list[tuple[int, int]] = field(default_factory=list)
    pairs_tried: int = 0
    old_moved_m: float = 0.0

    def as_json(self) -> dict:
        return {
            "joined": self.joined, "links": len(self.links), "pairs_tried": self.pairs_tried,
            "linked_frames": [list(p) for p in self.links], "old_map_moved_m": self.old_moved_m,
        }  # fmt: skip


def _information(sigma_rad: float, sigma_m: float) -> np.ndarray:
    return np.diag([1 / sigma_rad**2] * 3 + [1 / sigma_m**2] * 3)


def _links(
    old: Map, new: list[Keyframe], cfg: SlamConfig, verifier: LoopVerifier
) -> tuple[list[tuple[Keyframe, Keyframe, np.ndarray, np.ndarray]], int]:
    """Verified (new, old, T_old_new, information) pairs, and the number of pairs tried."""
    db = old.place_index(cfg.loop)
    by_id = {kf.id: kf for kf in old.keyframes}
    out, tried = [], 0
    for kf in new:
        # a small old map has no vocabulary yet: every keyframe of it is a candidate
        ranked = (
            [by_id[i] for i, _ in db.query(kf.features.descriptors, _CANDIDATES)]
            if db.trained
            else old.keyframes
        )
        for cand in ranked:
            tried += 1
            ver = verifier.verify(kf.view(), cand.view())
            if ver.accepted:
                info = ver.information / cfg.backend.loop_sigma_m**2
                out.append((kf, cand, ver.T_candidate_query, info))
                break
    return out, tried


def _solve(
    old: Map, new: list[Keyframe], links: list, cfg: SlamConfig
) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """The pose graph of both maps and their links: final poses of the old keyframes and of the
    new ones (by id), in the old map's frame."""
    graph = PoseGraph(cfg.backend)
    offset = max(kf.id for kf in old.keyframes) + 1
    kf_new, kf_old, T_old_new, _ = links[0]
    T_align = kf_old.T_world_cam @ T_old_new @ inv_T(kf_new.T_world_cam)
    for kf in old.keyframes:
        graph.add_node(kf.id, kf.T_world_cam)
    for kf in new:
        graph.add_node(offset + kf.id, T_align @ kf.T_world_cam)
    chains = (
        (old.keyframes, 0, _information(_STIFF_ROT_RAD, _STIFF_M)),
        (new, offset, _information(_ODOMETRY_ROT_RAD, _ODOMETRY_M)),
    )
    for chain, key, info in chains:
        for a, b in zip(chain, chain[1:]):
            rel = inv_T(a.T_world_cam) @ b.T_world_cam
            graph.add_edge(Edge(key + a.id, key + b.id, rel, info, "odometry"))
    for kf, cand, T, info in links:
        graph.add_edge(Edge(cand.id, offset + kf.id, T, info, "loop"))
    graph.anchors = {old.keyframes[0].id}
    graph.optimize()
    return (
        {kf.id: graph.nodes[kf.id] for kf in old.keyframes},
        {kf.id: graph.nodes[offset + kf.id] for kf in new},
    )


def _fuse(
    target: TSDFVolume,
    part: Map,
    views: list[tuple[np.ndarray, np.ndarray]],
    downsample: int,
) -> None:
    """Fuse ``part``'s surface into ``target``: rendered from each of ``views`` (the view's
    pose in ``part``'s world frame, then where to fuse it in ``target``'s)."""
    K = scale_intrinsics(part.K, downsample)
    w, h = part.size[0] // downsample, part.size[1] // downsample
    T_volume_world = inv_T(part.T_world_volume)
    for T_part_view, T_target_view in views:
        r = part.volume.render(K, w, h, T_volume_world @ T_part_view, with_normals=False)
        if (r.depth_m > 0).any():
            color = None
            if r.color is not None:
                color = np.clip(r.color * 255.0 + 0.5, 0, 255).astype(np.uint8)
            target.integrate(r.depth_m, color, K, T_target_view)


def _start_from(
    old: Map, cfg: SlamConfig, poses: dict[int, np.ndarray], downsample: int
) -> TSDFVolume:
    """The merged volume's start: the old map's own volume, copied, when it sits in the world
    frame (a re-fused map: re-rendering it from its keyframes alone would thin it: demo mesh
    median 1.33 -> 1.66 mm); else the old surface rendered from its keyframes."""
    if np.allclose(old.T_world_volume, np.eye(4)):
        volume = TSDFVolume.from_arrays(old.volume.to_arrays(), cfg.mapping, old.volume.has_color)
    else:
        volume = TSDFVolume(cfg.mapping, old.has_color)
        _fuse(volume, old, [(kf.T_world_cam, poses[kf.id]) for kf in old.keyframes], downsample)
    volume.mesh_weight_threshold = 1.0
    return volume


def extend_map(old: Map, new: RunResult, cfg: SlamConfig) -> tuple[RunResult, MergeReport]:
    """Join a finished mapping run ``new`` (with its map, ``new.map``) to the saved map ``old``
    (see the module docstring): the new run's result moved into the old map's frame, its mesh
    and map the merged ones; or, with no link, ``new`` as it was."""
    if new.map is None or not new.map.keyframes or not old.keyframes:
        return new, MergeReport(False)
    verifier = LoopVerifier(
        cfg.loop, cfg.tracking.depth_max_m, features_on_depth=old.color_registered
    )
    links, tried = _links(old, new.map.keyframes, cfg, verifier)
    if not links:
        log.warning(
            "the new recording never meets the map of %s (no keyframe of it verifies against "
            "the map's, %d pairs tried): it stays its own segment, in its own frame",
            old.source, tried,
        )  # fmt: skip
        return new, MergeReport(False, [], tried)
    poses_old, poses_new = _solve(old, new.map.keyframes, links, cfg)
    report = MergeReport(
        True, [(kf.index, c.index) for kf, c, _, _ in links], tried,
        max(float(np.linalg.norm(poses_old[k.id][:3, 3] - k.T_world_cam[:3, 3])) for k in old.keyframes),
    )  # fmt: skip
    log.info("joined the new recording to the map: %d links, %d pairs tried", len(links), tried)
    # the new frames follow their keyframes
    traj = new.trajectory
    rows = [int(np.argmin(np.abs(traj.timestamps - kf.timestamp))) for kf in new.map.keyframes]
    order = np.argsort(rows)
    kfs = [new.map.keyframes[i] for i in order]
    moved = elastic_correction(
        traj.poses, [rows[i] for i in order], [kf.T_world_cam for kf in kfs],
        [poses_new[kf.id] for kf in kfs],
    )  # fmt: skip
    T_align = poses_new[kfs[0].id] @ inv_T(kfs[0].T_world_cam)
    odometry = Trajectory(new.odometry.timestamps.copy(), T_align @ new.odometry.poses)
    # one surface: the old map's, and the new one's rendered from the new frames (every
    # reintegration_stride-th, as the end of a run re-fuses) where the solution moves them
    down = max(int(cfg.mapping.reintegration_downsample), 1)
    merged = _start_from(old, cfg, poses_old, down)
    stride = max(int(cfg.mapping.reintegration_stride), 1)
    views = list(zip(traj.poses[::stride], moved[::stride]))
    _fuse(merged, new.map, views, down)
    offset = max(kf.id for kf in old.keyframes) + 1
    keyframes = [dataclasses.replace(kf, T_world_cam=poses_old[kf.id]) for kf in old.keyframes]
    keyframes += [
        dataclasses.replace(kf, id=offset + kf.id, T_world_cam=poses_new[kf.id]) for kf in kfs
    ]
    saved = Map(
        keyframes, merged, np.eye(4), 1.0, old.K, old.size, old.has_color, old.color_registered
    )
    mesh = merged.extract_mesh() if new.mesh is not None else None
    result = dataclasses.replace(
        new, trajectory=Trajectory(traj.timestamps.copy(), moved), odometry=odometry,
        mesh=mesh, map=saved, segments={}, pose_graph=None,
    )  # fmt: skip
    return result, report
