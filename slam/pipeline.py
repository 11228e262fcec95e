"""The offline SLAM pipeline: a loop of :class:`~slam.system.Slam` over a sequence's frames, with
checkpoints; :func:`slam.run_folder.writer.save_run` writes its result to the run folder."""

from __future__ import annotations

import logging
import resource
import signal
import threading
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
from slam.errors import FrameReadError, RunFolderError, RunInterrupted, SlamError
from slam.kernels import prepare as prepare_kernels
from slam.records import TrackingStatus
from slam.results import RunResult
from slam.run_folder import submaps_dir
from slam.run_folder.checkpoint import CheckpointError, read_checkpoint, write_checkpoint
from slam.saved_map import Map
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
    """The sequence's frames a run processes (``dataset.first_frame``, ``dataset.stride``,
    ``dataset.max_frames``)."""
    idx = list(range(cfg.dataset.first_frame, len(sequence), max(cfg.dataset.stride, 1)))
    if cfg.dataset.max_frames is not None:
        idx = idx[: cfg.dataset.max_frames]
    return idx


class ReadTimes:
    """The reader thread's own work: the time it spent reading (and decoding, undistorting)
    frames, unreadable ones included, measured in that thread. The frame loop only waits for
    frames (``stage_ms["load"]``), which is ~0 when reading keeps ahead of tracking."""

    def __init__(self) -> None:
        self.ms = 0.0
        self.frames = 0

    def read(self, sequence: Sequence, index: int) -> Frame:
        t0 = time.perf_counter()
        try:
            return sequence[index]
        finally:
            self.ms += (time.perf_counter() - t0) * 1e3
            self.frames += 1

    def ms_per_frame(self) -> float | None:
        return round(self.ms / self.frames, 3) if self.frames else None


def prefetch(
    sequence: Sequence, indices: list[int], ahead: int = 2, times: ReadTimes | None = None
) -> Iterator[tuple[int, Future]]:
    """(index, future frame) in order, reading up to ``ahead`` frames in a background thread
    (image decoding releases the GIL, so it overlaps with tracking); ``times`` gets the
    thread's read time per frame."""
    read = (times or ReadTimes()).read
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="slam-read") as pool:
        pending: deque[tuple[int, Future]] = deque()
        todo = iter(indices)
        for i in todo:
            pending.append((i, pool.submit(read, sequence, i)))
            if len(pending) > ahead:
                yield pending.popleft()
        while pending:
            yield pending.popleft()


def color_registered(sequence: Sequence, cfg: SlamConfig) -> bool:
    """Whether colour pixels are depth's rays: ``dataset.color_registered``, else as the
    sequence's layout says."""
    registered = cfg.dataset.color_registered
    return sequence.color_registered if registered is None else registered


def new_system(
    sequence: Sequence, cfg: SlamConfig, spill_dir: str | Path | None, map: Map | None = None
) -> Slam:
    """A fresh :class:`Slam` for ``sequence``; finished submaps wait in ``spill_dir``;
    ``map``: localise in that saved map instead of mapping."""
    return Slam(
        cfg,
        has_color=sequence.has_color,
        spill_dir=None if spill_dir is None else str(spill_dir),
        color_registered=color_registered(sequence, cfg),
        map=map,
    )


def next_frame(system: Slam, sequence: Sequence, index: int, future: Future) -> Frame | None:
    """The frame read ahead by :func:`prefetch`; an unreadable one is recorded as skipped
    (None). The wait counts as the loop's ``load`` time, an unreadable frame's too (seconds,
    fps)."""
    t0 = time.perf_counter()
    try:
        return future.result()
    except FrameReadError as exc:
        system.skip(index, sequence.timestamp(index), str(exc))
        return None
    finally:
        system.stage_ms["load"] += (time.perf_counter() - t0) * 1e3


#: With automatic checkpoints (``checkpoint_every=None`` and a run folder), writing them costs
#: about this fraction of the run's time: the next one is due once the run has spent
#: 1 / fraction times the last one's cost since it (the first after :data:`FIRST_CHECKPOINT`
#: frames). A checkpoint costs a little more than the one before (the state grows), so 1.5%
#: keeps the total under the 2% promised: 2.00% on tum-fr1-xyz at 2%, 6 checkpoints.
CHECKPOINT_BUDGET = 0.015
FIRST_CHECKPOINT = 100


class Checkpoints:
    """The run's checkpoints: when the next is due (every ``every`` frames, or with ``every``
    None within :data:`CHECKPOINT_BUDGET` of the run time, from what each one cost) and
    writing them (a failed write is a warning: the run goes on, the last one stands)."""

    def __init__(self, run_dir: str | Path | None, every: int | None) -> None:
        self.run_dir = run_dir
        self.every = 0 if run_dir is None else every
        self.t_last = time.perf_counter()
        self.last_cost_s: float | None = None
        self.count, self.ms = 0, 0.0

    def due(self, done: int, start: int) -> bool:
        if self.every is not None:
            return self.every > 0 and done % self.every == 0
        if self.last_cost_s is None:
            return done - start >= FIRST_CHECKPOINT
        return time.perf_counter() - self.t_last >= self.last_cost_s / CHECKPOINT_BUDGET

    def written(self, cost_s: float) -> None:
        self.last_cost_s, self.t_last = cost_s, time.perf_counter()
        self.ms += cost_s * 1e3

    def save(self, system: Slam, done: int, total: int) -> bool:
        """Write the state after ``done`` of ``total`` frames; False when it failed."""
        assert self.run_dir is not None
        t1 = time.perf_counter()
        every = -1 if self.every is None else self.every  # -1: automatic
        try:
            write_checkpoint(self.run_dir, system.state_dict(), done, every)
            self.count += 1
            return True
        except OSError as exc:  # e.g. a full disk: an error, shown under --quiet too
            log.error(
                "checkpoint at frame %d of %d not written (%s); the run goes on, and "
                "--resume would continue from the previous checkpoint",
                done, total, exc,
            )  # fmt: skip
            return False
        finally:
            self.written(time.perf_counter() - t1)


class StopOnSignal:
    """While active (in the main thread only), the first SIGINT (Ctrl-C) or SIGTERM asks the
    run to stop after the frame it is on (``requested``); a second one stops at once, as
    without this (the last checkpoint stands)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.requested: int | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopOnSignal:
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        self.requested = signum
        for sig, handler in self._previous.items():  # a second signal: the usual behaviour
            signal.signal(sig, handler)
        log.warning(
            "%s: stopping after this frame and saving the state, or finishing the run if its "
            "frames are done (again to stop at once)",
            signal.Signals(signum).name,
        )

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}


class DeferSignals(StopOnSignal):
    """While active (in the main thread only), SIGINT and SIGTERM wait: what runs (writing a
    finished run's results) completes, then the signal is reported (``requested``) instead of
    killing the process half way through the files."""

    def _handle(self, signum: int, frame: Any) -> None:
        self.requested = signum
        log.warning(
            "%s: the run is finished; writing its results first", signal.Signals(signum).name
        )


def _interrupted(
    signum: int, done: int, total: int, run_dir: str | Path | None, saved: bool
) -> RunInterrupted:
    name = signal.Signals(signum).name
    if saved:
        where = (
            f"the state after frame {done} of {total} is saved in {Path(run_dir or '')}: continue "
            f"with `slam run --resume {run_dir}` (or slam.resume_run)"
        )
    elif run_dir is not None:
        where = f"the state could not be saved in {run_dir} (see the warning above)"
    else:
        where = "nothing was saved (no run folder: pass run_dir to make a run resumable)"
    return RunInterrupted(
        f"run interrupted by {name} after frame {done} of {total}: {where}", signum
    )


def run(
    sequence: Sequence,
    config: SlamConfig | None = None,
    progress: ProgressCallback | None = None,
    run_dir: str | Path | None = None,
    checkpoint_every: int | None = None,
    resume: bool = False,
    on_frame: FrameCallback | None = None,
    map: Map | None = None,  # noqa: A002 - the public name of the argument
) -> RunResult:
    """Run SLAM over a sequence. Ground truth, if the sequence has it, is used only to evaluate.

    ``run_dir``: the run folder, where finished submaps wait and checkpoints go (default: a
    temporary folder, no checkpoints). ``checkpoint_every``: write the state to
    ``run_dir/checkpoint/`` every N frames (0: never; None: automatically, within
    :data:`CHECKPOINT_BUDGET` of the run time, or when resuming as the interrupted run did).
    ``resume``: continue from that checkpoint (the same sequence and config as the interrupted
    run). Called from the main thread, a first SIGINT (Ctrl-C) or SIGTERM stops the run after
    the current frame, saves the state (with a run folder) and raises
    :class:`~slam.errors.RunInterrupted`, whose message says how to resume.
    ``map``: localise the sequence in this saved map (:meth:`slam.saved_map.Map.load`)
    instead of mapping it (no checkpoints: a localisation run is cheap to run again).
    """
    cfg = (config or SlamConfig()).validate()
    if map is not None:
        if resume:
            raise SlamError(
                "a localisation run (map=...) has no checkpoint to resume: run it again"
            )
        checkpoint_every = 0
    if (checkpoint_every or resume) and run_dir is None:
        raise SlamError("checkpoints need a run folder: pass run_dir")
    if checkpoint_every is not None and checkpoint_every < 0:
        raise SlamError(f"checkpoint_every must be >= 0 frames, got {checkpoint_every}")
    indices = frame_indices(sequence, cfg)
    if not indices:
        raise SlamError(
            f"{sequence.path}: no frames to process (check dataset.first_frame/max_frames/stride)"
        )
    system = new_system(sequence, cfg, None if run_dir is None else submaps_dir(run_dir), map)
    start = 0
    if resume:
        assert run_dir is not None
        start, checkpoint_every = _resume(system, Path(run_dir), checkpoint_every, len(indices))
        log.info("resuming %s at frame %d of %d", run_dir, start, len(indices))
    else:
        check_sequence(sequence, indices)
    checkpoints = Checkpoints(run_dir, checkpoint_every)
    total = len(indices)
    reads = ReadTimes()
    prepare_kernels()  # compiled once per machine, before the first frame, not during it
    with StopOnSignal() as stop:
        for done, (i, future) in enumerate(
            prefetch(sequence, indices[start:], times=reads), start + 1
        ):
            frame = next_frame(system, sequence, i, future)
            if frame is None:
                if progress:
                    progress(done, total, None)
                continue
            step = system.step(frame)
            if on_frame:
                on_frame(frame, step)
            if progress:
                progress(done, total, step.status)
            if stop.requested is not None:
                saved = run_dir is not None and checkpoints.save(system, done, total)
                raise _interrupted(stop.requested, done, total, run_dir, saved)
            if done < total and checkpoints.due(done, start):
                checkpoints.save(system, done, total)
        # a first signal from here on lets the run finish (its results are then complete)
        result = system.finish()
    _complete_metrics(result, sequence, checkpoints, reads, start if resume else None)
    log.info("%s: %s", sequence.name, summary_line(result.metrics))
    return result


def _resume(
    system: Slam, run_dir: Path, checkpoint_every: int | None, total: int
) -> tuple[int, int | None]:
    """Load the run folder's checkpoint into ``system``: the number of frames it had done (of
    ``total``; a position the state does not hold is refused), and the checkpoint interval to
    go on with (the interrupted run's when none is given)."""
    state, start = read_checkpoint(run_dir)
    try:
        if checkpoint_every is None:
            every = state.get("checkpoint_every", 0)
            checkpoint_every = None if every is None or every < 0 else int(every)
        system.load_state_dict(state)
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, OverflowError,
            RuntimeError) as exc:  # fmt: skip
        # RuntimeError: Open3D refusing arrays of the wrong shape
        raise CheckpointError(
            f"{run_dir}: the checkpoint does not hold a complete state of this version "
            f"({type(exc).__name__}: {exc}); start the run again with --overwrite"
        ) from exc
    stepped = len(system.statuses) + len(system.skipped)
    if not 0 < start <= total or start != stepped:
        raise RunFolderError(
            f"{run_dir}: damaged checkpoint: its position says {start} frames were done, its "
            f"state holds {stepped} of the sequence's {total}; start the run again with "
            "--overwrite"
        )
    return start, checkpoint_every


def _complete_metrics(
    result: RunResult,
    sequence: Sequence,
    checkpoints: Checkpoints,
    reads: ReadTimes,
    resumed_at: int | None,
) -> None:
    """What only the loop over the sequence knows, added to the run's metrics: the sequence,
    checkpoints, where a resumed run started, peak memory, reading time, and the evaluation
    against the sequence's ground truth (when it has one)."""
    m = result.metrics
    m.sequence = str(sequence.path)
    m.unpaired_images = dict(sequence.unpaired_images)
    m.calibration_source = sequence.calibration_source
    m.checkpoints = checkpoints.count
    m.checkpoint_ms = round(checkpoints.ms, 1)
    if resumed_at is not None:
        m.resumed_at_frame = resumed_at
    m.peak_rss_mb = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)
    m.read_ms_per_frame = reads.ms_per_frame()
    if len(result.trajectory) == 0:
        return  # nothing to evaluate (a localisation that placed no frame)
    m.update(
        evaluate_against_ground_truth(
            sequence, result.trajectory, result.odometry, result.pose_graph
        )
    )
    if m.get("map") is not None:
        m.update(evaluate_in_map_frame(sequence, result.trajectory, m["map"]))


def _real_time(m: dict[str, Any]) -> str:
    rtf = m.get("real_time_factor")
    return "" if rtf is None else f" ({rtf:.2f}x real time)"


def summary_line(m: dict[str, Any]) -> str:
    """One line: frames, speed, lost and skipped frames, loops, ATE."""
    frames = "1 frame" if m["frames"] == 1 else f"{m['frames']} frames"
    line = (
        f"{frames}, {m['fps'] or 0:.1f} fps{_real_time(m)}, "
        f"{len(m['lost_frames'])} lost, "
        f"{m['frames_skipped']} skipped, {m['relocalisations']} relocalisations, "
        f"{m['loops_accepted']} loops closed"
    )
    if len(m.get("map_segments", [])) > 1:
        line += f", {len(m['map_segments'])} map segments (not joined)"
    if "ate_rmse_m" in m:
        line += f", ATE RMSE {m['ate_rmse_m']:.4f} m (odometry {m['ate_rmse_odometry_m']:.4f} m)"
    return line


def evaluate_in_map_frame(sequence: Sequence, traj: Trajectory, map_run: str) -> dict[str, Any]:
    """A localisation run's ``ate_rmse_map_frame_m`` (:func:`slam.tools.eval.map_frame_ate`),
    or ``map_frame_error`` saying why it could not be measured; ``{}`` without ground truth."""
    from slam.tools import eval as slam_eval

    try:
        gt, _ = slam_eval.sequence_ground_truth(sequence.path, sequence)
        if gt is None:
            return {}
        return {"ate_rmse_map_frame_m": slam_eval.map_frame_ate(gt, as_written(traj), map_run)}
    except SlamError as exc:
        log.warning("evaluation in the map's frame failed: %s", exc)
        return {"map_frame_error": str(exc)}


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
