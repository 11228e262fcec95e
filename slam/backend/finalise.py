"""The end of a run: the final keyframe poses (pose graph, then bundle adjustment) and every
frame bent onto them (:func:`elastic_correction`)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial import cKDTree

from slam.geometry import exp_se3, inv_T, log_se3
from slam.keyframe import Keyframe

if TYPE_CHECKING:
    from slam.backend.adjuster import BundleAdjuster
    from slam.backend.pose_graph import PoseGraph


def elastic_correction(
    odometry: np.ndarray,
    kf_positions: list[int],
    T_world_kf_odometry: list[np.ndarray],
    T_world_kf_corrected: list[np.ndarray],
    runs: np.ndarray | None = None,
) -> np.ndarray:
    """Corrected poses of every frame from the corrected keyframe poses.

    ``odometry`` (N, 4, 4): frontend poses of all frames; ``kf_positions``: the row of each
    keyframe in ``odometry`` (increasing). A frame between keyframes a and b keeps its odometry
    pose relative to each of them, giving two estimates ``T_a' T_a^-1 T`` and ``T_b' T_b^-1 T``;
    it takes their SE(3) interpolation at its fraction of the way from a to b, so the
    trajectory bends smoothly and keyframes land exactly on their optimised poses.

    ``runs`` (N,): the tracking run of each frame (a run ends where tracking was lost). Frames
    follow keyframes of their own run only: odometry says nothing across a loss. Every run
    starts with a keyframe.
    """
    out = odometry.copy()
    if not kf_positions:
        return out
    runs = np.zeros(len(odometry), int) if runs is None else np.asarray(runs)
    corr = [Tc @ inv_T(To) for Tc, To in zip(T_world_kf_corrected, T_world_kf_odometry)]
    n = len(odometry)
    for f in range(0, kf_positions[0]):
        out[f] = corr[0] @ odometry[f]
    for k, a in enumerate(kf_positions):
        nxt = kf_positions[k + 1] if k + 1 < len(kf_positions) else n
        same_run = k + 1 < len(kf_positions) and runs[nxt] == runs[a]
        for f in range(a, nxt):
            Ta = corr[k] @ odometry[f]
            if not same_run:
                out[f] = Ta
                continue
            Tb = corr[k + 1] @ odometry[f]
            s = (f - a) / (nxt - a)
            out[f] = Ta @ exp_se3(s * log_se3(inv_T(Ta) @ Tb))
    return out


@dataclass
class FinalPoses:
    """Every frame's pose three ways (N x 4 x 4, rows as the frame log's) and the keyframe
    poses the final trajectory follows (the anchors of re-fusion)."""

    odometry: np.ndarray  # the frontend's
    pose_graph: np.ndarray  # following the pose graph's keyframes (before BA)
    final: np.ndarray  # following the final keyframes (after BA)
    T_world_kf: dict[int, np.ndarray]  # final keyframe poses by keyframe id
    corrected: bool  # the final poses differ from the odometry
    ba_ms: float | None = None  # the final bundle adjustment's time, when it ran


def final_poses(
    odometry: np.ndarray,
    runs: np.ndarray,
    kf_rows: list[int],
    keyframes: list[Keyframe],
    graph: PoseGraph,
    adjuster: BundleAdjuster | None,
    graph_adjusted: bool,
    corrected: bool,
) -> FinalPoses:
    """The end-of-run solution. ``graph_adjusted``: a mid-run BA left its poses in the graph's
    nodes, so the pose graph alone is solved again (the trajectory of the pose graph alone, and
    where the final BA starts from). ``adjuster``: a final bundle adjustment from there (None:
    none). ``corrected``: loops were closed or segments joined (the pose graph moved the
    keyframes). Every frame then follows its keyframes (:func:`elastic_correction`)."""
    if graph_adjusted:
        graph.optimize()
    pose_graph_kf = {kf.id: graph.nodes[kf.id] for kf in keyframes}
    final_kf = dict(pose_graph_kf)
    ba_ms = None
    if adjuster is not None:
        t0 = time.perf_counter()
        res = adjuster.optimise(graph.nodes, graph.edges, reason="finish")
        ba_ms = (time.perf_counter() - t0) * 1e3
        final_kf.update(res.poses)

    def follow(poses: dict[int, np.ndarray]) -> np.ndarray:
        odo_kf = [kf.T_world_cam for kf in keyframes]
        return elastic_correction(
            odometry, kf_rows, odo_kf, [poses[kf.id] for kf in keyframes], runs
        )

    pose_graph_all = follow(pose_graph_kf) if corrected else odometry.copy()
    adjusted = any(not np.array_equal(final_kf[k], pose_graph_kf[k]) for k in final_kf)
    final_all = follow(final_kf) if adjusted else pose_graph_all
    return FinalPoses(odometry, pose_graph_all, final_all, final_kf, corrected or adjusted, ba_ms)


@dataclass
class FinalMesh:
    mesh: Any  # open3d TriangleMesh, or None when no mesh is made
    map_blocks: int
    reintegration_ms: float | None  # re-fusion of several submaps into one volume
    meshing_ms: float
    volume: Any  # the global model: a TSDFVolume (one submap's own, or the re-fused one)
    T_world_volume: np.ndarray  # where that volume sits in the world frame
    rebuilt: bool  # re-fused from rendered views: each surface carries one view's weight


def view_correction(odometry: np.ndarray, final: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """How a fused view moves from its odometry pose to its final one: the correction
    (``final @ odometry^-1``) of the frame whose odometry pose it is (``odometry``, ``final``:
    N x 4 x 4, one row a frame; the frame found by its position, which a view shares with the
    frame it was fused from up to float rounding)."""
    tree = cKDTree(odometry[:, :3, 3])
    corrections = final @ np.linalg.inv(odometry)

    def correct(T_world_view: np.ndarray) -> np.ndarray:
        _, i = tree.query(T_world_view[:3, 3])
        return corrections[int(i)] @ T_world_view

    return correct


def final_mesh(
    model: Any,
    T_world_anchors: dict[int, np.ndarray] | None,
    include: set[int] | None,
    mesh: bool = True,
    correct_view: Callable[[np.ndarray], np.ndarray] | None = None,
) -> FinalMesh:
    """The global model, and marching cubes on it (``mesh``): the submaps in ``include``
    (None: all) re-fused into one volume, each view where ``correct_view`` moves it (the
    trajectory's correction; :func:`view_correction`) or, without it, each submap under its
    corrected anchor pose (``T_world_anchors`` by submap id; None: as fused)
    (:meth:`slam.mapping.submaps.SubmapMap.rebuild`). A single submap that nothing corrects
    inside is its own volume, moved rigidly."""
    t0 = time.perf_counter()
    chosen = [sm for sm in model.submaps if include is None or sm.id in include]
    if len(chosen) == 1 and correct_view is None:
        sm = chosen[0]
        volume, blocks, reintegration_ms = model.volume(sm), model.n_blocks, None
        T_world_volume = np.asarray((T_world_anchors or {}).get(sm.id, sm.T_world_anchor), float)
    else:
        volume = model.rebuild(T_world_anchors, include, correct_view)
        blocks, T_world_volume = volume.n_blocks, np.eye(4)
        reintegration_ms = (time.perf_counter() - t0) * 1e3
    t1 = time.perf_counter()
    out = volume.extract_mesh().transform(T_world_volume) if mesh else None
    meshing_ms = (time.perf_counter() - t1) * 1e3 if mesh else 0.0
    return FinalMesh(
        out, blocks, reintegration_ms, meshing_ms, volume, T_world_volume,
        len(chosen) != 1 or correct_view is not None,
    )  # fmt: skip
