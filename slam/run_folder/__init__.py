"""The run folder: one run's results, written so that a folder never misrepresents a run.

- :func:`prepare_run_dir` is called before the first frame: the folder must be creatable and
  writable, and must not hold another run unless ``overwrite`` (which deletes the old run's
  outputs first).
- Results are written atomically, ``metrics.json`` last: its presence marks a complete run, and
  ``slam eval`` / ``slam report`` refuse a folder without it (:func:`require_complete`).
- Working state (checkpoints, spilled submaps) lives in the folder while the run goes on and is
  removed once the results are written.

This package is the one owner of the folder: :mod:`~slam.run_folder.layout` names every file
(no other module spells them), :mod:`~slam.run_folder.writer` writes the results
(:func:`save_run`), :mod:`~slam.run_folder.reader` reads them back (:class:`RunFolder`),
:mod:`~slam.run_folder.tracking_csv` converts ``tracking.csv`` both ways and
:mod:`~slam.run_folder.checkpoint` holds the checkpoints.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

from slam.errors import RunFolderError
from slam.run_folder.layout import (
    CHECKPOINT_DIR,
    CHUNKS_DIR,
    CHUNKS_FILE,
    CONFIG_FILE,
    ERROR_PNG,
    LOOPS_FILE,
    MESH_FILE,
    METRICS_FILE,
    ODOMETRY_FILE,
    OUTPUT_DIRS,
    POSE_GRAPH_FILE,
    RECORDING_FILE,
    REPORT_FILE,
    REPORT_PNG_GLOB,
    RUN_FILES,
    RUN_GLOBS,
    SEGMENT_GLOB,
    SUBMAPS_DIR,
    TIMING_PNG,
    TOPVIEW_PNG,
    TRACKING_FILE,
    TRAJECTORY_FILE,
    WORK_DIRS,
    segment_file,
    segment_number,
)
from slam.run_folder.reader import RunFolder
from slam.run_folder.writer import save_run, write_config

__all__ = [
    "CHECKPOINT_DIR",
    "CHUNKS_DIR",
    "CHUNKS_FILE",
    "CONFIG_FILE",
    "ERROR_PNG",
    "LOOPS_FILE",
    "MESH_FILE",
    "METRICS_FILE",
    "ODOMETRY_FILE",
    "POSE_GRAPH_FILE",
    "RECORDING_FILE",
    "REPORT_FILE",
    "REPORT_PNG_GLOB",
    "RUN_FILES",
    "RUN_GLOBS",
    "SEGMENT_GLOB",
    "SUBMAPS_DIR",
    "TIMING_PNG",
    "TOPVIEW_PNG",
    "TRACKING_FILE",
    "TRAJECTORY_FILE",
    "WORK_DIRS",
    "make_run_dir",
    "submaps_dir",
    "RunFolder",
    "check_writable",
    "clear_run_dir",
    "prepare_run_dir",
    "remove_work_dirs",
    "require_complete",
    "run_outputs",
    "save_run",
    "segment_file",
    "segment_number",
    "write_config",
]


def run_outputs(run_dir: Path) -> list[Path]:
    """The run outputs and working folders present in ``run_dir``."""
    found = [run_dir / n for n in RUN_FILES + OUTPUT_DIRS + WORK_DIRS if (run_dir / n).exists()]
    for pattern in RUN_GLOBS:
        found += sorted(run_dir.glob(pattern))
    return found


def clear_run_dir(run_dir: Path) -> None:
    """Delete a run's outputs and working folders (nothing else in the folder)."""
    for p in run_outputs(run_dir):
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()


def check_writable(run_dir: Path) -> None:
    try:
        with tempfile.NamedTemporaryFile(dir=run_dir, prefix=".write-test-"):
            pass
    except OSError as exc:
        raise RunFolderError(f"run folder {run_dir} is not writable: {exc}") from exc


def prepare_run_dir(out: str | Path, overwrite: bool = False) -> Path:
    """Make ``out`` ready for a new run (see the module docstring); returns it."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise RunFolderError(
            f"--out {out} is a file, not a folder: give a folder for the run's results"
        )
    if out.is_dir():
        existing = run_outputs(out)
        if existing and not overwrite:
            names = ", ".join(p.name for p in existing[:5])
            raise RunFolderError(
                f"{out} already holds a run ({names}); pass --overwrite (Python: "
                "overwrite=True) to replace it (its outputs are deleted first), --resume "
                f"{out} (Python: slam.resume_run) to continue an interrupted run, or choose "
                "another --out"
            )
        if overwrite:
            clear_run_dir(out)
    return make_run_dir(out)


def make_run_dir(out: str | Path) -> Path:
    """``out`` as a writable folder (created when missing); what it holds is not checked."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise RunFolderError(
            f"--out {out} is a file, not a folder: give a folder for the run's results"
        )
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RunFolderError(f"cannot create the run folder {out}: {exc}") from exc
    check_writable(out)
    return out


def require_complete(run_dir: str | Path) -> Path:
    """``run_dir`` if it holds a complete run (``metrics.json``), else a
    :class:`RunFolderError` saying what is there instead."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunFolderError(f"{run_dir}: run folder not found")
    if not (run_dir / METRICS_FILE).is_file():
        if (run_dir / CHECKPOINT_DIR).is_dir():
            why = f"the run did not finish; continue it with `slam run --resume {run_dir}`"
        elif (run_dir / CONFIG_FILE).is_file():
            why = "the run did not finish (it was stopped or is still running)"
        else:
            why = "it is not a run folder of `slam run`"
        raise RunFolderError(f"{run_dir}: no {METRICS_FILE}, so no complete run: {why}")
    _check_metrics(run_dir / METRICS_FILE)
    return run_dir


def _check_metrics(path: Path) -> None:
    """``metrics.json`` must be a JSON object (an empty or garbage file passed for a complete
    run)."""
    try:
        data = json.loads(path.read_text())
    except RecursionError:
        data = None
        why = "nested too deeply"
    except (OSError, ValueError) as exc:
        data, why = None, type(exc).__name__
    else:
        why = "not a JSON object"
    if not isinstance(data, dict):
        raise RunFolderError(
            f"{path}: not a run's metrics ({why}); the folder is damaged: run the sequence again"
        )


def submaps_dir(run_dir: str | Path) -> Path:
    """Where a run's finished submaps wait on disk while it goes on (kept for resuming)."""
    return Path(run_dir) / SUBMAPS_DIR


def remove_work_dirs(run_dir: Path) -> None:
    """Remove checkpoints and spilled submaps once the run's results are written."""
    for name in WORK_DIRS:
        shutil.rmtree(run_dir / name, ignore_errors=True)
