"""The offline SLAM pipeline: read frames, track against the model, fuse, mesh, evaluate."""

from __future__ import annotations

import csv
import io
import json
import logging
import resource
import time
from collections import Counter, deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d

from slam.backend.loop_closure import LoopCloser, elastic_correction
from slam.config import SlamConfig
from slam.data.base import Sequence
from slam.errors import FrameReadError, SlamError
from slam.frontend.tracker import Tracker, TrackingStatus
from slam.mapping.submaps import SubmapMap
from slam.mapping.tsdf import write_mesh
from slam.trajectory import Trajectory, atomic_write_text, write_tum

log = logging.getLogger(__name__)

#: Called after every frame with (frames done, frames total, status of the frame).
ProgressCallback = Callable[[int, int, TrackingStatus | None], None]


@dataclass
class RunResult:
    """What a run produces. ``trajectory`` is the final estimate, ``odometry`` the frontend-only
    one (identical until loop closure corrects poses)."""

    trajectory: Trajectory
    odometry: Trajectory
    mesh: o3d.geometry.TriangleMesh | None
    metrics: dict[str, Any]
    tracking: list[TrackingStatus] = field(default_factory=list)
    config: SlamConfig | None = None
    model: SubmapMap | None = None  # the submaps (odometry frame), for re-meshing and inspection
    loop_closer: LoopCloser | None = None  # keyframes, pose graph and loop records

    @property
    def poses(self) -> np.ndarray:
        return self.trajectory.poses

    @property
    def timestamps(self) -> np.ndarray:
        return self.trajectory.timestamps


def _frame_indices(sequence: Sequence, cfg: SlamConfig) -> list[int]:
    idx = list(range(0, len(sequence), max(cfg.dataset.stride, 1)))
    if cfg.dataset.max_frames is not None:
        idx = idx[: cfg.dataset.max_frames]
    return idx


def _prefetch(
    sequence: Sequence, indices: list[int], ahead: int = 2
) -> Iterator[tuple[int, Future]]:
    """(index, future frame) in order, reading up to ``ahead`` frames in a background thread
    (image decoding releases the GIL, so it overlaps with tracking)."""
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="slam-read") as pool:
        pending: deque[tuple[int, Future]] = deque()
        todo = iter(indices)
        for i in todo:
            pending.append((i, pool.submit(sequence.__getitem__, i)))
            if len(pending) > ahead:
                yield pending.popleft()
        while pending:
            yield pending.popleft()


def run(
    sequence: Sequence,
    config: SlamConfig | None = None,
    progress: ProgressCallback | None = None,
) -> RunResult:
    """Run SLAM over a sequence. Ground truth, if the sequence has it, is used only to evaluate."""
    cfg = config or SlamConfig()
    indices = _frame_indices(sequence, cfg)
    if not indices:
        raise SlamError(f"{sequence.path}: no frames to process (check dataset.max_frames/stride)")
    use_color = sequence.has_color
    registered = cfg.dataset.color_registered
    registered = sequence.color_registered if registered is None else registered
    tracker = Tracker(cfg.tracking, use_color=use_color, color_registered=registered)
    model = SubmapMap(cfg.mapping, with_color=use_color)
    closer = LoopCloser(cfg.loop, cfg.backend, cfg.tracking.depth_max_m)
    kf_rows: list[int] = []  # row of each keyframe in ``poses``

    stamps: list[float] = []
    poses: list[np.ndarray] = []
    statuses: list[TrackingStatus] = []
    skipped: list[dict[str, Any]] = []
    stage_ms: dict[str, float] = {"load": 0.0, "tracking": 0.0, "integration": 0.0, "loop": 0.0}
    t_start = time.perf_counter()
    for n_done, (i, future) in enumerate(_prefetch(sequence, indices), 1):
        t0 = time.perf_counter()
        try:
            frame = future.result()
        except FrameReadError as exc:
            log.error("skipping frame %d: %s", i, exc)
            skipped.append({"index": i, "error": str(exc)})
            if progress:
                progress(n_done, len(indices), None)
            continue
        t1 = time.perf_counter()
        T_world_cam, status = tracker.track(frame, model)
        t2 = time.perf_counter()
        if status.keyframe:
            kf = tracker.state.keyframes[-1]
            kf_rows.append(len(poses))
            model.on_keyframe(kf.id, kf.T_world_cam)
            closer.add_keyframe(kf)
        t3 = time.perf_counter()
        if status.ok:
            model.integrate(frame.depth_m, frame.color, frame.K, T_world_cam)
        t4 = time.perf_counter()
        stage_ms["load"] += (t1 - t0) * 1e3
        stage_ms["tracking"] += (t2 - t1) * 1e3
        stage_ms["loop"] += (t3 - t2) * 1e3
        stage_ms["integration"] += (t4 - t3) * 1e3
        stamps.append(frame.timestamp)
        poses.append(T_world_cam)
        statuses.append(status)
        if progress:
            progress(n_done, len(indices), status)
    if not poses:
        raise SlamError(f"{sequence.path}: every frame failed to load; see the log for reasons")
    t_loop = time.perf_counter() - t_start

    # elastic correction: every frame follows its keyframes' optimised poses
    odometry = Trajectory(np.array(stamps), np.stack(poses))
    kfs = closer.keyframes
    corrected = closer.graph.n_loops > 0
    if corrected:
        final = elastic_correction(
            odometry.poses,
            kf_rows,
            [kf.T_world_cam for kf in kfs],
            [closer.T_world_kf(kf.id) for kf in kfs],
        )
        traj = Trajectory(odometry.timestamps.copy(), final)
    else:
        traj = Trajectory(odometry.timestamps.copy(), odometry.poses.copy())

    mesh = None
    map_blocks = model.n_blocks
    t0 = time.perf_counter()
    if cfg.output.save_mesh:
        anchors = (
            {sm.id: closer.T_world_kf(sm.anchor_kf) for sm in model.submaps} if corrected else None
        )
        if len(model.submaps) > 1:
            volume = model.rebuild(anchors)
            map_blocks = volume.n_blocks
            stage_ms["reintegration"] = (time.perf_counter() - t0) * 1e3
            t0 = time.perf_counter()
            mesh = volume.extract_mesh()
        else:
            mesh = model.extract_mesh(anchors)
    stage_ms["meshing"] = (time.perf_counter() - t0) * 1e3
    seconds = time.perf_counter() - t_start
    n = len(poses)
    paths = Counter(s.path for s in statuses)
    metrics: dict[str, Any] = {
        "sequence": str(sequence.path),
        "frames": n,
        "frames_skipped": len(skipped),
        "skipped": skipped,
        "seconds": round(seconds, 3),
        "fps": round(n / t_loop, 3) if t_loop > 0 else None,
        "fps_tracking_fusion": round(
            n / max((stage_ms["tracking"] + stage_ms["integration"]) / 1e3, 1e-9), 3
        ),
        "stage_ms_per_frame": {
            k: round(v / n, 3) for k, v in stage_ms.items() if k not in ("meshing", "reintegration")
        },
        "stage_ms_total": {
            **{k: round(v, 1) for k, v in stage_ms.items()},
            **{k: round(v, 1) for k, v in closer.ms.items()},
        },
        "tracking_failures": int(paths.get("lost", 0)),
        "tracking_paths": dict(paths),
        "keyframes": len(tracker.state.keyframes),
        "submaps": len(model.submaps),
        "loops_accepted": closer.loops_accepted,
        "loops_rejected": closer.loops_rejected,
        "loop_detection_ms": round(closer.ms["loop_detection"], 1),
        "optimisation_ms": round(closer.ms["optimisation"], 1),
        "optimisations": closer.optimisations,
        "icp_fitness_mean": round(float(np.mean([s.icp_fitness for s in statuses[1:]] or [0])), 4),
        "icp_rmse_mean_m": round(float(np.mean([s.icp_rmse_m for s in statuses[1:]] or [0])), 6),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
        "mesh_vertices": len(mesh.vertices) if mesh is not None else 0,
        "map_blocks": map_blocks,
    }
    gt = sequence.ground_truth
    if gt is not None:
        metrics.update(_evaluate(gt, traj, odometry))
    log.info(
        "%s: %d frames in %.1f s (%.1f fps), %d tracking failures%s",
        sequence.name,
        n,
        seconds,
        metrics["fps"] or 0,
        metrics["tracking_failures"],
        f", ATE {metrics['ate_rmse_m']:.4f} m" if "ate_rmse_m" in metrics else "",
    )
    return RunResult(traj, odometry, mesh, metrics, statuses, cfg, model, closer)


def _evaluate(gt: Trajectory, traj: Trajectory, odometry: Trajectory) -> dict[str, Any]:
    from slam import eval as slam_eval

    out: dict[str, Any] = {}
    try:
        final = slam_eval.evaluate(gt, traj)
        same = np.array_equal(traj.poses, odometry.poses)  # no correction applied (yet)
        odo_rmse = final["ate_rmse_m"] if same else slam_eval.ate(gt, odometry).rmse
    except SlamError as exc:
        log.warning("evaluation against ground truth failed: %s", exc)
        return {"evaluation_error": str(exc)}
    out["ate_rmse_m"] = final["ate_rmse_m"]
    out["ate_rmse_odometry_m"] = odo_rmse
    out["rpe_trans_rmse_m"] = final["rpe_trans_rmse_m"]
    out["rpe_rot_rmse_deg"] = final["rpe_rot_rmse_deg"]
    out["matched_poses"] = final["matched_poses"]
    return out


def save_run(result: RunResult, out_dir: str | Path) -> Path:
    """Write the run folder: trajectory.txt, odometry.txt, mesh.ply, metrics.json, config.yaml,
    tracking.csv, pose_graph.g2o, loops.json. Every file is written atomically."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_tum(out / "trajectory.txt", result.trajectory)
    write_tum(out / "odometry.txt", result.odometry)
    if result.mesh is not None and len(result.mesh.vertices) > 0:
        write_mesh(out / "mesh.ply", result.mesh)
    elif result.mesh is not None:
        log.warning("%s: the map is empty (no surface seen with enough weight); no mesh.ply", out)
    if result.config is not None:
        atomic_write_text(out / "config.yaml", result.config.to_yaml())
    if result.tracking and (result.config is None or result.config.output.save_tracking_log):
        buf = io.StringIO()
        rows = [s.as_row() for s in result.tracking]
        writer = csv.DictWriter(buf, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
        atomic_write_text(out / "tracking.csv", buf.getvalue())
    if result.loop_closer is not None:
        result.loop_closer.graph.write_g2o(out / "pose_graph.g2o")
        atomic_write_text(
            out / "loops.json", json.dumps(result.loop_closer.loops_json(), indent=1) + "\n"
        )
    atomic_write_text(out / "metrics.json", json.dumps(result.metrics, indent=2) + "\n")
    return out
