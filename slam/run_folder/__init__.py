"""The run folder: one run's results, written so that a folder never misrepresents a run.

- :func:`prepare_run_dir` is called before the first frame: the folder must be creatable and
  writable, and must not hold another run unless ``overwrite`` (which deletes the old run's
  outputs first).
- Results are written atomically, ``metrics.json`` last: its presence marks a complete run, and
  ``slam eval`` / ``slam report`` refuse a folder without it (:func:`require_complete`).
- Working state (checkpoints, spilled submaps) lives in the folder while the run goes on and is
  removed once the results are written.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from slam.errors import RunFolderError

#: Files a run writes (and ``slam report`` adds); their presence means the folder holds a run.
RUN_FILES = (
    "metrics.json",
    "trajectory.txt",
    "odometry.txt",
    "mesh.ply",
    "config.yaml",
    "tracking.csv",
    "loops.json",
    "pose_graph.g2o",
    "report.md",
    "recording.rrd",
)
RUN_GLOBS = ("report_*.png", "segment_*.txt")
#: Working folders of a run in progress.
WORK_DIRS = ("checkpoint", "submaps")


def run_outputs(run_dir: Path) -> list[Path]:
    """The run outputs and working folders present in ``run_dir``."""
    found = [run_dir / n for n in RUN_FILES + WORK_DIRS if (run_dir / n).exists()]
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
                f"{out} already holds a run ({names}); pass --overwrite to replace it (its "
                f"outputs are deleted first), --resume {out} to continue an interrupted run, "
                "or choose another --out"
            )
        if overwrite:
            clear_run_dir(out)
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
    if not (run_dir / "metrics.json").is_file():
        if (run_dir / "checkpoint").is_dir():
            why = f"the run did not finish; continue it with `slam run --resume {run_dir}`"
        elif (run_dir / "config.yaml").is_file():
            why = "the run did not finish (it was stopped or is still running)"
        else:
            why = "it is not a run folder of `slam run`"
        raise RunFolderError(f"{run_dir}: no metrics.json, so no complete run: {why}")
    return run_dir


def submaps_dir(run_dir: str | Path) -> Path:
    """Where a run's finished submaps wait on disk while it goes on (kept for resuming)."""
    return Path(run_dir) / "submaps"


def remove_work_dirs(run_dir: Path) -> None:
    """Remove checkpoints and spilled submaps once the run's results are written."""
    for name in WORK_DIRS:
        shutil.rmtree(run_dir / name, ignore_errors=True)
