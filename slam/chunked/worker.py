"""One chunk of a parallel run, in its own worker: the ordinary :class:`~slam.system.Slam`
over the chunk's frames, its state written to ``RUN_DIR/chunks/chunk_NNN/`` (a checkpoint, so
the join reads it from disk and a finished chunk is never redone) with ``chunk.json`` last.

The task and the report are plain data (they travel to Ray tasks and worker processes).
"""

from __future__ import annotations

import json
import logging
import os
import resource
import shutil
import time
from pathlib import Path
from typing import Any

from slam.run_folder import submaps_dir
from slam.run_folder.layout import CHUNKS_DIR

log = logging.getLogger(__name__)

CHUNK_FILE = "chunk.json"
#: frames the chunk's worker has stepped so far (rewritten at most every PROGRESS_EVERY_S)
PROGRESS_FILE = "progress"
PROGRESS_EVERY_S = 0.5


def chunk_dir(run_dir: str | Path, number: int) -> Path:
    return Path(run_dir) / CHUNKS_DIR / f"chunk_{number:03d}"


def finished_report(run_dir: str | Path, number: int, n_frames: int) -> dict[str, Any] | None:
    """The report of a chunk already finished in this run folder (None: it must run)."""
    path = chunk_dir(run_dir, number) / CHUNK_FILE
    try:
        report = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(report, dict) or report.get("frames") != n_frames:
        return None
    return report


def frames_done(run_dir: str | Path, number: int) -> int:
    """How many of its frames chunk ``number`` has stepped, as its worker last wrote (all of
    them once it finished; 0 before it starts, or when the file is being replaced)."""
    folder = chunk_dir(run_dir, number)
    try:
        if (folder / CHUNK_FILE).is_file():
            return int(json.loads((folder / CHUNK_FILE).read_text())["frames"])
        return int((folder / PROGRESS_FILE).read_text())
    except (OSError, ValueError, KeyError, TypeError):
        return 0


def set_kernel_threads(threads: int) -> None:
    """The worker's kernel threads: Open3D's (TBB: ``open3d.utility.set_max_threads``), OpenCV's
    and OpenMP's (``OMP_NUM_THREADS``, read when a library loads: the executors call this first
    in a fresh process)."""
    threads = max(int(threads), 1)
    os.environ["OMP_NUM_THREADS"] = str(threads)
    import cv2
    import open3d as o3d

    o3d.utility.set_max_threads(threads)
    cv2.setNumThreads(threads)


def run_chunk(task: dict[str, Any]) -> dict[str, Any]:
    """Run one chunk. ``task``: ``run_dir``, ``number``, ``indices`` (the sequence's frame
    indices of the chunk), ``config`` (the run's config as a dict), ``threads``. Returns the
    report written to ``chunk.json``: frame count, wall time, the worker's process id."""
    set_kernel_threads(task["threads"])
    from slam.config import config_from_dict
    from slam.data.loader import open_sequence
    from slam.pipeline import new_system, next_frame, prefetch
    from slam.run_folder.checkpoint import write_checkpoint
    from slam.trajectory import atomic_write_text

    run_dir, number, indices = task["run_dir"], int(task["number"]), list(task["indices"])
    done = finished_report(run_dir, number, len(indices))
    if done is not None:
        return done
    t0 = time.perf_counter()
    folder = chunk_dir(run_dir, number)
    shutil.rmtree(folder, ignore_errors=True)  # what a killed attempt left
    folder.mkdir(parents=True)
    (folder / "worker.pid").write_text(str(os.getpid()))
    cfg = config_from_dict(task["config"])
    seq = open_sequence(cfg.dataset.path, cfg.dataset.layout, cfg.dataset.calibration)
    system = new_system(seq, cfg, submaps_dir(folder))
    written = time.monotonic()
    for k, (i, future) in enumerate(prefetch(seq, indices)):
        frame = next_frame(system, seq, i, future)
        if frame is not None:
            system.step(frame)
        if time.monotonic() - written >= PROGRESS_EVERY_S:  # for the driver's progress bar
            atomic_write_text(folder / PROGRESS_FILE, str(k + 1))
            written = time.monotonic()
    write_checkpoint(folder, system.state_dict(), len(indices), 0)
    report = {
        "number": number,
        "frames": len(indices),
        "first_frame": indices[0],
        "last_frame": indices[-1],
        "seconds": round(time.perf_counter() - t0, 3),
        "frame_loop_seconds": round(system.elapsed_s + system.stage_ms["load"] / 1e3, 3),
        "keyframes": len(system.closer.keyframes),
        "loops_accepted": system.closer.loops_accepted,
        "worker_pid": os.getpid(),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
        "threads": int(task["threads"]),
    }
    atomic_write_text(folder / CHUNK_FILE, json.dumps(report, indent=1) + "\n")
    log.info("chunk %d: %d frames in %.1f s", number, len(indices), report["seconds"])
    return report
