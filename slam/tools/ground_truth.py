"""The ground truth a run is evaluated against: one definition for ``metrics.json``
(:func:`slam.run`) and ``slam eval RUN_DIR`` / ``slam report`` (:func:`load_run_ground_truth`)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from slam.errors import ConfigError, SlamError, TrajectoryError
from slam.run_folder import CONFIG_FILE, METRICS_FILE, RunFolder
from slam.trajectory import Trajectory, read_tum

log = logging.getLogger(__name__)

__all__ = ["GROUND_TRUTH_FILE", "load_run_ground_truth", "sequence_ground_truth"]

#: The ground-truth file of a sequence folder (TUM layout; the one evo is given).
GROUND_TRUTH_FILE = "groundtruth.txt"

_GT_HINT = "give the ground-truth file with --gt FILE"


def sequence_ground_truth(
    seq_dir: str | Path,
    sequence: Any = None,
    layout: str = "auto",
    calibration: dict[str, Any] | None = None,
) -> tuple[Trajectory | None, str]:
    """The ground truth runs of a sequence are evaluated against, and where it came from.

    One definition for ``metrics.json`` (:func:`slam.run`) and ``slam eval RUN_DIR``
    (:func:`load_run_ground_truth`), evo's: the folder's ``groundtruth.txt`` as it is (raw
    poses, associated with the estimate by nearest timestamp within ``max_diff`` when
    evaluating, as ``evo_ape`` does; not interpolated at the frame times), else the sequence
    loader's ground truth (e.g. 7-Scenes ``*.pose.txt``; ``sequence`` when already open, else
    the folder is opened with ``layout`` and ``calibration``). ``(None, why)`` when there is
    none; unreadable files raise :class:`slam.errors.SlamError` subclasses.
    """
    seq_dir = Path(seq_dir)
    gt_file = seq_dir / GROUND_TRUTH_FILE
    if gt_file.is_file():
        return read_tum(gt_file, skip_non_finite=True), str(gt_file)
    if sequence is None:
        from slam.data.loader import open_sequence

        sequence = open_sequence(seq_dir, layout, calibration)
    gt = sequence.ground_truth
    if gt is None or len(gt) == 0:
        why = f"{seq_dir}: the sequence has no ground truth (no {GROUND_TRUTH_FILE} or poses)"
        return None, why
    return gt, f"{seq_dir} ({type(sequence).__name__} ground truth)"


def load_run_ground_truth(
    run_dir: str | Path | RunFolder, gt_path: str | Path | None = None
) -> tuple[Trajectory, str]:
    """The ground truth of the sequence a run folder was made from, and where it was found.

    ``gt_path`` (a TUM file) wins when given. Otherwise the sequence folder is ``dataset.path`` in
    the run's ``config.yaml``, else ``sequence`` in its ``metrics.json`` (relative paths: to the
    working directory, then to the run folder), and its ground truth is
    :func:`sequence_ground_truth` (``groundtruth.txt``, the file evo would read, else the sequence
    loader's), the same that ``slam run`` evaluated ``metrics.json`` against.
    Raises :class:`TrajectoryError` saying what is missing and suggesting ``--gt``.
    """
    run = run_dir if isinstance(run_dir, RunFolder) else RunFolder(run_dir)
    if gt_path is not None:
        return read_tum(gt_path, skip_non_finite=True), str(gt_path)
    try:
        cfg = run.config()
    except ConfigError as exc:  # e.g. a key a later version dropped: evaluate all the same
        log.warning(
            "%s: the run's config is not this version's (%s); reading the sequence "
            "folder from %s and its layout by detection",
            run.path,
            exc,
            METRICS_FILE,
        )
        cfg = None
    seq_path = cfg.dataset.path if cfg is not None and cfg.dataset.path else run.recorded_sequence()
    if not seq_path:
        raise TrajectoryError(
            f"{run.path}: no ground truth: neither {CONFIG_FILE} (dataset.path) nor "
            f"{METRICS_FILE} (sequence) names the sequence folder; {_GT_HINT}"
        )
    seq_dir = run.sequence_dir()
    if seq_dir is None:
        raise TrajectoryError(
            f"{run.path}: the sequence folder recorded for the run ({seq_path}) does not exist "
            f"here; {_GT_HINT}"
        )
    dataset = cfg.dataset if cfg is not None else None
    try:
        gt, source = sequence_ground_truth(
            seq_dir,
            layout=(dataset.layout if dataset is not None else None) or "auto",
            calibration=(dataset.calibration if dataset is not None else None) or None,
        )
    except TrajectoryError:
        raise
    except SlamError as exc:
        raise TrajectoryError(
            f"{run.path}: cannot read the ground truth of {seq_dir}: {exc}; {_GT_HINT}"
        ) from exc
    if gt is None:
        raise TrajectoryError(f"{source}; {_GT_HINT}")
    return gt, source
