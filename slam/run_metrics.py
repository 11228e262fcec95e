"""The numbers of a finished run (:class:`~slam.records.RunMetrics`, written as ``metrics.json``)
from what the stepwise system recorded."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from slam.records import FrameLog, RunMetrics, TrackingStatus


@dataclass
class RunRecord:
    """What the system hands over for the metrics (all of it recorded while stepping)."""

    statuses: list[TrackingStatus]
    frames: FrameLog
    skipped: list[dict[str, Any]]
    relocalisations: list[dict[str, Any]]
    stage_ms: dict[str, float]  # per stage, including the end's (meshing, reintegration)
    loop_s: float  # the frame loop's wall time
    seconds: float  # the whole run's wall time


def map_components(
    frames: FrameLog, root: Callable[[int], int], main_root: int
) -> list[dict[str, Any]]:
    """``metrics.json``'s ``map_segments``: each map component (joined segments) with its
    frames; ``root`` gives the component of a segment."""
    members: dict[int, list[int]] = {}
    for seg in sorted(set(frames.segment)):
        members.setdefault(root(seg), []).append(seg)
    out = []
    for r, segs in members.items():
        rows = [k for k, s in enumerate(frames.segment) if root(s) == r]
        out.append(
            {
                "id": r,
                "segments": segs,
                "frames": len(rows),
                "first_frame": frames.index[rows[0]],
                "last_frame": frames.index[rows[-1]],
                "in_trajectory": r == main_root,
            }
        )
    return out


def run_metrics(
    rec: RunRecord,
    closer: Any,
    keyframes: int,
    submaps: int,
    ba_summary: dict[str, Any],
    frames_in_trajectory: int,
    main_root: int,
    mesh_vertices: int,
    map_blocks: int,
) -> RunMetrics:
    """The run's metrics (see docs/usage.md, "metrics.json keys"); ``closer``: the loop closer
    (loop counts, joins, its timings)."""
    statuses = rec.statuses
    n = len(statuses)
    lost = [s.index for s in statuses if not s.ok]
    tracked = [s for s in statuses if s.ok and s.path not in ("init", "reloc")]
    ms = rec.stage_ms
    per_frame = {k: v for k, v in ms.items() if k not in ("meshing", "reintegration")}
    return RunMetrics(
        frames=n,
        frames_tracked=len(rec.frames),
        frames_in_trajectory=frames_in_trajectory,
        frames_skipped=len(rec.skipped),
        skipped=list(rec.skipped),
        lost_frames=lost,
        relocalisations=len(rec.relocalisations),
        relocalisation_frames=[r["frame"] for r in rec.relocalisations],
        map_segments=map_components(rec.frames, closer.segment_root, main_root),
        segment_joins=list(closer.joins),
        seconds=round(rec.seconds, 3),
        # every frame the loop went through (read, or skipped as unreadable) over its time
        fps=round((n + len(rec.skipped)) / rec.loop_s, 3) if rec.loop_s > 0 else None,
        fps_tracking_fusion=round(n / max((ms["tracking"] + ms["integration"]) / 1e3, 1e-9), 3),
        real_time_factor=real_time_factor([s.timestamp for s in statuses], rec.loop_s),
        stage_ms_per_frame={k: round(v / max(n, 1), 3) for k, v in per_frame.items()},
        stage_ms_total={
            **{k: round(v, 1) for k, v in ms.items()},
            **{k: round(v, 1) for k, v in closer.ms.items()},
        },
        tracking_failures=len(lost),
        tracking_paths=dict(Counter(s.path for s in statuses)),
        colour_frames=sum(1 for s in tracked if s.photometric),
        keyframes=keyframes,
        submaps=submaps,
        loops_accepted=closer.loops_accepted,
        loops_rejected=closer.loops_rejected,
        loop_detection_ms=round(closer.ms["loop_detection"], 1),
        optimisation_ms=round(closer.ms["optimisation"], 1),
        optimisations=closer.optimisations,
        ba=ba_summary,
        icp_fitness_mean=round(float(np.mean([s.icp_fitness for s in tracked] or [0])), 4),
        icp_rmse_mean_m=_finite_mean([s.icp_rmse_m for s in tracked]),
        mesh_vertices=mesh_vertices,
        map_blocks=map_blocks,
    )


def real_time_factor(timestamps: list[float], loop_s: float) -> float | None:
    """How much faster than the sensor the run was: the recording's duration (first to last
    frame, plus one frame interval) over the frame loop's time; >= 1 keeps up with a live
    sensor. None without two distinct timestamps or any time."""
    t = np.unique(np.asarray([x for x in timestamps if np.isfinite(x)], float))
    if len(t) < 2 or loop_s <= 0:
        return None
    duration = (t[-1] - t[0]) * len(t) / (len(t) - 1)
    return round(float(duration / loop_s), 3)


def _finite_mean(values: list[float]) -> float:
    """Mean of the finite values (0 without any), rounded to the micrometre."""
    finite = [v for v in values if np.isfinite(v)]
    return round(float(np.mean(finite)), 6) if finite else 0.0
