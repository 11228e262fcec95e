"""The offline SLAM pipeline: a loop of :class:`~slam.system.Slam` over a sequence's frames, with
checkpoints; :func:`slam.run_folder.writer.save_run` writes its result to the run folder."""

from __future__ import annotations

import logging
import resource
import time
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from slam.config import SlamConfig
from slam.data.base import Frame, Sequence
from slam.data.checks import check_sequence
from slam.errors import FrameReadError, RunFolderError, SlamError
from slam.records import TrackingStatus
from slam.results import RunResult
from slam.run_folder import submaps_dir
from slam.run_folder.checkpoint import read_checkpoint, write_checkpoint
from slam.system import FrameResult, Slam
from slam.trajectory import Trajectory, as_written

__all__ = ["FrameCallback", "ProgressCallback", "RunResult", "run"]

log = logging.getLogger(__name__)

#: Called after every frame with (frames done, frames total, status of the frame; None for a
#: frame that could not be read).
ProgressCallback = Callable[[int, int, TrackingStatus | None], None]
#: Called after every frame that was read with the frame and what the system made of it (a
#: viewer or logger hooks in here).
FrameCallback = Callable[[Frame, FrameResult], None]


def frame_indices(sequence: Sequence, cfg: SlamConfig) -> list[int]:
    """The sequence's frames a run processes (``dataset.stride``, ``dataset.max_frames``)."""
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
    run_dir: str | Path | None = None,
    checkpoint_every: int | None = None,
    resume: bool = False,
    on_frame: FrameCallback | None = None,
) -> RunResult:
    """Run SLAM over a sequence. Ground truth, if the sequence has it, is used only to evaluate.

    ``run_dir``: the run folder, where finished submaps wait and checkpoints go (default: a
    temporary folder, no checkpoints). ``checkpoint_every``: write the state to
    ``run_dir/checkpoint/`` every N frames (0: never; None: 0, or when resuming the
    interrupted run's N). ``resume``: continue from that checkpoint (the same sequence and
    config as the interrupted run).
    """
    cfg = (config or SlamConfig()).validate()
    if (checkpoint_every or resume) and run_dir is None:
        raise SlamError("checkpoints need a run folder: pass run_dir")
    if checkpoint_every is not None and checkpoint_every < 0:
        raise SlamError(f"checkpoint_every must be >= 0 frames, got {checkpoint_every}")
    indices = frame_indices(sequence, cfg)
    if not indices:
        raise SlamError(f"{sequence.path}: no frames to process (check dataset.max_frames/stride)")
    registered = cfg.dataset.color_registered
    registered = sequence.color_registered if registered is None else registered
    system = Slam(
        cfg,
        has_color=sequence.has_color,
        spill_dir=None if run_dir is None else str(submaps_dir(run_dir)),
        color_registered=registered,
    )
    start = 0
    if resume:
        assert run_dir is not None
        state, start = read_checkpoint(run_dir)
        if checkpoint_every is None:
            checkpoint_every = int(state.get("checkpoint_every", 0))
        try:
            system.load_state_dict(state)
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise RunFolderError(
                f"{run_dir}: the checkpoint does not hold a complete state of this version "
                f"({type(exc).__name__}: {exc}); start the run again with --overwrite"
            ) from exc
        log.info("resuming %s at frame %d of %d", run_dir, start, len(indices))
    else:
        check_sequence(sequence, indices)
    checkpoint_every = checkpoint_every or 0
    n_checkpoints, checkpoint_ms = 0, 0.0
    for done, (i, future) in enumerate(_prefetch(sequence, indices[start:]), start + 1):
        t0 = time.perf_counter()
        try:
            frame = future.result()
        except FrameReadError as exc:
            system.skip(i, sequence.timestamp(i), str(exc))
            if progress:
                progress(done, len(indices), None)
            continue
        system.stage_ms["load"] += (time.perf_counter() - t0) * 1e3
        result = system.step(frame)
        if on_frame:
            on_frame(frame, result)
        if progress:
            progress(done, len(indices), result.status)
        if checkpoint_every and done % checkpoint_every == 0 and done < len(indices):
            assert run_dir is not None
            t1 = time.perf_counter()
            try:
                write_checkpoint(run_dir, system.state_dict(), done, checkpoint_every)
                n_checkpoints += 1
            except OSError as exc:  # e.g. a full disk: the run goes on, the last one stands
                log.warning(
                    "checkpoint at frame %d of %d not written (%s); the run goes on, and "
                    "--resume would continue from the previous checkpoint",
                    done, len(indices), exc,
                )  # fmt: skip
            checkpoint_ms += (time.perf_counter() - t1) * 1e3
    result = system.finish()
    m = result.metrics
    m.sequence = str(sequence.path)
    m.checkpoints = n_checkpoints
    m.checkpoint_ms = round(checkpoint_ms, 1)
    if resume:
        m.resumed_at_frame = start
    m.peak_rss_mb = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)
    m.update(
        evaluate_against_ground_truth(
            sequence, result.trajectory, result.odometry, result.pose_graph
        )
    )
    log.info("%s: %s", sequence.name, summary_line(m))
    return result


def summary_line(m: dict[str, Any]) -> str:
    """One line: frames, speed, lost and skipped frames, loops, ATE."""
    line = (
        f"{m['frames']} frames, {m['fps'] or 0:.1f} fps, {len(m['lost_frames'])} lost, "
        f"{m['frames_skipped']} skipped, {m['relocalisations']} relocalisations, "
        f"{m['loops_accepted']} loops closed"
    )
    if len(m.get("map_segments", [])) > 1:
        line += f", {len(m['map_segments'])} map segments (not joined)"
    if "ate_rmse_m" in m:
        line += f", ATE RMSE {m['ate_rmse_m']:.4f} m (odometry {m['ate_rmse_odometry_m']:.4f} m)"
    return line


def evaluate_against_ground_truth(
    sequence: Sequence,
    traj: Trajectory,
    odometry: Trajectory,
    pose_graph: Trajectory | None = None,
) -> dict[str, Any]:
    """The ``metrics.json`` accuracy keys: ``ate_rmse_m``, ``ate_rmse_odometry_m``,
    ``ate_rmse_pose_graph_m`` (the pose graph alone, before bundle adjustment, evaluated as the
    final trajectory is),
    ``rpe_trans_rmse_m``, ``rpe_rot_rmse_deg``, ``matched_poses``, ``drift_percent`` (``{}``
    without ground truth; ``evaluation_error`` when it fails).

    The same numbers as ``slam eval RUN_DIR`` (``final`` and ``odometry`` ATE RMSE, RPE over
    1 frame, matched poses, drift): the same ground truth (:func:`slam.tools.eval.sequence_ground_truth`,
    evo's definition: ``groundtruth.txt`` associated by nearest timestamp within 0.01 s), and
    the trajectories as they are written to the run folder (TUM text precision).
    """
    from slam.tools import eval as slam_eval

    try:
        gt, source = slam_eval.sequence_ground_truth(sequence.path, sequence)
        if gt is None:
            log.debug("no evaluation: %s", source)
            return {}
        final = slam_eval.evaluate(gt, as_written(traj))
        same = len(traj) == len(odometry) and np.array_equal(traj.poses, odometry.poses)
        odo_rmse = final["ate_rmse_m"] if same else slam_eval.ate(gt, as_written(odometry)).rmse
        pg_rmse = (
            final["ate_rmse_m"]
            if pose_graph is None or np.array_equal(pose_graph.poses, traj.poses)
            else slam_eval.ate(gt, as_written(pose_graph)).rmse
        )
    except SlamError as exc:
        log.warning("evaluation against ground truth failed: %s", exc)
        return {"evaluation_error": str(exc)}
    out = {
        "ate_rmse_m": final["ate_rmse_m"],
        "ate_rmse_odometry_m": odo_rmse,
        "ate_rmse_pose_graph_m": pg_rmse,
        "rpe_trans_rmse_m": final["rpe_trans_rmse_m"],
        "rpe_rot_rmse_deg": final["rpe_rot_rmse_deg"],
        "matched_poses": final["matched_poses"],
        "drift_percent": final["drift_percent"],  # NaN (no path) is written as null
    }
    return {k: None if isinstance(v, float) and not np.isfinite(v) else v for k, v in out.items()}
