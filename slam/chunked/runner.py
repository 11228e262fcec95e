"""A parallel run of one sequence (``slam run SEQ --workers N``): plan the chunks, run them
(finished ones are kept in the run folder and not redone), join them, finish.

Steps of :func:`run_chunked`: ``plan`` (:func:`~slam.chunked.plan.plan_chunks`, written to
``chunks/plan.json`` so ``--resume`` continues with the same chunks), ``track`` (the chunks in
parallel, :func:`~slam.chunked.executor.run_tasks`), ``join`` (:class:`~slam.chunked.join.Joiner`),
``finish`` (:meth:`Slam.finish <slam.system.Slam.finish>` on the joined system) and the
metrics; ``chunks.json`` records the chunks, their joins and the times.
"""

from __future__ import annotations

import json
import logging
import os
import resource
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from slam.chunked.executor import run_tasks
from slam.chunked.join import Joiner
from slam.chunked.plan import Chunk, plan_chunks
from slam.chunked.worker import PROGRESS_EVERY_S, chunk_dir, frames_done
from slam.config import SlamConfig
from slam.data.base import Sequence
from slam.data.checks import check_sequence
from slam.errors import RunFolderError, SlamError
from slam.pipeline import (
    ProgressCallback,
    color_registered,
    evaluate_against_ground_truth,
    frame_indices,
    new_system,
    summary_line,
)
from slam.records import RunMetrics
from slam.results import RunResult
from slam.run_folder.checkpoint import read_checkpoint
from slam.run_folder.layout import CHUNKS_DIR, CHUNKS_FILE
from slam.run_metrics import real_time_factor
from slam.system import Slam
from slam.trajectory import atomic_write_text

log = logging.getLogger(__name__)

PLAN_FILE = "plan.json"
#: default overlap of consecutive chunks, in frames (a second of a 30 Hz sensor)
OVERLAP = 30


def plan_path(run_dir: str | Path) -> Path:
    return Path(run_dir) / CHUNKS_DIR / PLAN_FILE


def is_chunked(run_dir: str | Path) -> bool:
    """Whether the run folder holds an unfinished parallel run (``--resume`` continues it)."""
    return plan_path(run_dir).is_file()


def read_plan(run_dir: str | Path) -> dict[str, Any]:
    """``chunks/plan.json``, checked: a RunFolderError names what is wrong with a damaged one."""
    path = plan_path(run_dir)
    try:
        raw = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise RunFolderError(_plan_advice(path, str(exc))) from exc
    except RecursionError:
        raise RunFolderError(_plan_advice(path, "nested too deeply")) from None
    problem = _plan_problem(raw)
    if problem:
        raise RunFolderError(_plan_advice(path, problem))
    return {**raw, "chunks": [Chunk(**c) for c in raw["chunks"]]}


def _plan_advice(path: Path, problem: str) -> str:
    return f"{path}: not a readable chunk plan ({problem}); start the run again with --overwrite"


def _is_count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _plan_problem(raw: Any) -> str | None:
    """What makes ``raw`` not a plan :func:`_plan` writes (None when it is one)."""
    if not isinstance(raw, dict):
        return f"a {type(raw).__name__}, not an object"
    for key in ("workers", "overlap"):
        if not _is_count(raw.get(key)):
            return f"{key!r} is {raw.get(key)!r}, not a count"
    frames, chunks = raw.get("frames"), raw.get("chunks")
    if not isinstance(frames, list) or not all(_is_count(f) for f in frames):
        return "'frames' is not a list of frame indices"
    if not isinstance(chunks, list) or not chunks:
        return "'chunks' is not a list of chunks"
    fields = set(Chunk.__dataclass_fields__)
    for k, c in enumerate(chunks):
        if not isinstance(c, dict) or set(c) != fields or not all(map(_is_count, c.values())):
            return f"chunk {k} is not an object of the counts {sorted(fields)}"
        if not (c["number"] == k and c["start"] < c["keep_stop"] <= c["stop"] <= len(frames)):
            return f"chunk {k} ({c}) does not fit the plan's {len(frames)} frames"
    return None


def run_chunked(
    sequence: Sequence,
    config: SlamConfig,
    run_dir: str | Path,
    workers: int,
    overlap: int | None = None,
    executor: str = "auto",
    ray_address: str | None = None,
    resume: bool = False,
    threads: int | None = None,
    progress: ProgressCallback | None = None,
) -> RunResult:
    """Run SLAM over ``sequence`` in ``workers`` chunks at once (see the module docstring).
    ``run_dir`` is required: the chunks' states and submaps wait there until the join.
    ``overlap``: frames tracked by both of two consecutive chunks (default :data:`OVERLAP`).
    ``resume``: continue the parallel run in ``run_dir`` (its plan; finished chunks are
    kept). ``threads``: kernel threads per worker (default: the machine's cores over
    ``workers``, at least 1). ``progress(done, total, None)``: called from a watcher thread
    about twice a second while the chunks run, with the frames the workers have stepped
    (the overlaps counted once), and once with ``done == total`` before the join."""
    cfg = config.validate()
    if workers < 1:
        raise SlamError(f"--workers must be >= 1, got {workers}")
    t0 = time.perf_counter()
    overlap = OVERLAP if overlap is None else overlap
    indices = frame_indices(sequence, cfg)
    if not indices:
        raise SlamError(f"{sequence.path}: no frames to process (check dataset.max_frames/stride)")
    if not resume:
        check_sequence(sequence, indices)
    chunks = _plan(run_dir, indices, workers, overlap, resume)
    threads = threads or max(1, (os.cpu_count() or 1) // workers)
    tasks = [
        {"run_dir": str(run_dir), "number": c.number, "indices": indices[c.start : c.stop],
         "config": cfg.to_dict(), "threads": threads}
        for c in chunks
    ]  # fmt: skip
    log.info("%d frames in %d chunks (overlap %d) on %d workers", len(indices), len(chunks),
             overlap, workers)  # fmt: skip
    with _watch(run_dir, chunks, len(indices), progress):
        reports = run_tasks(tasks, workers, executor, ray_address)
    if progress is not None:
        progress(len(indices), len(indices), None)
    t_tracked = time.perf_counter()
    joiner = Joiner(cfg, sequence.has_color, color_registered(sequence, cfg))
    for c in chunks:
        cut = indices[c.keep_stop] if c.keep_stop < len(indices) else float("inf")
        joiner.add(c, _load_part(run_dir, c, sequence, cfg), cut)
    t_joined = time.perf_counter()
    result = joiner.system.finish()
    t_end = time.perf_counter()
    m = result.metrics
    _add_metrics(m, sequence, result, len(chunks), reports, t_end - t0)
    summary = {
        "workers": workers,
        "overlap": overlap,
        "chunks": [
            {**c.as_json(), "first_frame": indices[c.start], "last_frame": indices[c.stop - 1],
             "worker": r}
            for c, r in zip(chunks, reports)
        ],
        "joins": [j.as_json() for j in joiner.reports],
        "seconds": {
            "chunks": round(t_tracked - t0, 3),
            "join": round(t_joined - t_tracked, 3),
            "finish": round(t_end - t_joined, 3),
            "total": round(t_end - t0, 3),
        },
    }  # fmt: skip
    atomic_write_text(Path(run_dir) / CHUNKS_FILE, json.dumps(summary, indent=1) + "\n")
    log.info("%s (%d workers): %s", sequence.name, len(chunks), summary_line(m.as_json()))
    return result


def _add_metrics(
    m: RunMetrics,
    sequence: Sequence,
    result: RunResult,
    n_chunks: int,
    reports: list[dict[str, Any]],
    wall: float,
) -> None:
    """The joined run's wall-clock figures (over all workers; peak memory: the largest
    process's) and its evaluation against ground truth."""
    m.sequence, m.workers = str(sequence.path), n_chunks
    m.seconds = round(wall, 3)
    m.fps = round((m.frames + m.frames_skipped) / wall, 3)
    m.real_time_factor = real_time_factor([s.timestamp for s in result.tracking], wall)
    m.peak_rss_mb = max(
        [round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)]
        + [r.get("peak_rss_mb", 0.0) for r in reports]
    )
    m.update(evaluate_against_ground_truth(
        sequence, result.trajectory, result.odometry, result.pose_graph
    ))  # fmt: skip


@contextmanager
def _watch(
    run_dir: str | Path, chunks: list[Chunk], total: int, progress: ProgressCallback | None
) -> Iterator[None]:
    """While the block runs, report the chunks' frames done to ``progress`` (every
    :data:`~slam.chunked.worker.PROGRESS_EVERY_S`): the workers write them to their chunk
    folders, on whatever machine they run."""
    if progress is None:
        yield
        return
    stop = threading.Event()
    stepped = sum(c.frames for c in chunks)

    def watch() -> None:
        while not stop.wait(PROGRESS_EVERY_S):
            done = sum(min(frames_done(run_dir, c.number), c.frames) for c in chunks)
            progress(min(round(done * total / stepped), total - 1), total, None)

    watcher = threading.Thread(target=watch, name="chunk-progress", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        stop.set()
        watcher.join()


def _plan(
    run_dir: str | Path, indices: list[int], workers: int, overlap: int, resume: bool
) -> list[Chunk]:
    """The chunks: a resumed run's own (its frames must be the same), else a new plan,
    written before any chunk runs."""
    if resume:
        plan = read_plan(run_dir)
        if plan.get("frames") != indices:
            raise RunFolderError(
                f"{plan_path(run_dir)}: the plan's frames are not this sequence's frames; "
                "start the run again with --overwrite"
            )
        return list(plan["chunks"])
    chunks = plan_chunks(len(indices), workers, overlap)
    plan = {"workers": workers, "overlap": overlap, "frames": indices,
            "chunks": [c.as_json() for c in chunks]}  # fmt: skip
    atomic_write_text(plan_path(run_dir), json.dumps(plan) + "\n")
    return chunks


def _load_part(run_dir: str | Path, chunk: Chunk, sequence: Sequence, cfg: SlamConfig) -> Slam:
    """A finished chunk's system, from its state in the run folder."""
    state, position = read_checkpoint(chunk_dir(run_dir, chunk.number))
    if position != chunk.frames:
        raise RunFolderError(
            f"{chunk_dir(run_dir, chunk.number)}: the chunk's state stops after {position} of "
            f"its {chunk.frames} frames; run `slam run --resume {run_dir}` to finish it"
        )
    part = new_system(sequence, cfg, None)
    part.load_state_dict(state)
    return part
