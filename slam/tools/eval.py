"""Trajectory metrics (ATE / RPE) with numbers identical to evo's, and the evaluation of a run
folder. The metrics are in :mod:`slam.tools.eval_metrics` (their results in
:mod:`slam.tools.eval_results`), the ground-truth lookup in :mod:`slam.tools.ground_truth`; all
are re-exported here. The trajectory plot is in :mod:`slam.tools.plots` (:func:`plot_trajectories`
and :func:`save_figure` are re-exported here too, imported when first used: importing this module
loads no plotting).

Everything numeric is delegated to evo's library so that the values match the ``evo_ape`` /
``evo_rpe`` command line tools exactly:

* :func:`associate`  == ``evo.core.sync.associate_trajectories`` (nearest timestamp within
  ``max_diff`` seconds, evo's default 0.01 s)
* :func:`ate`        == ``evo_ape tum GT EST -a`` (``-as`` with ``correct_scale=True``), translation
  part, metres
* :func:`rpe`        == ``evo_rpe tum GT EST -a --delta 1 --delta_unit f`` for ``-r trans_part``
  (metres) and ``-r angle_deg`` (degrees), consecutive pairs (``all_pairs=False``)

* :func:`drift`      final-position error in % of the ground-truth path length (defined there)
* :func:`evaluate_full` all of the above (any number of RPE deltas) as one :class:`EvalResult`;
  an RPE delta with fewer than :data:`MIN_RPE_PAIRS` pose pairs is left out with the reason
  (:attr:`RPEResult.left_out`);
  :func:`evaluate` its flat headline dict; :func:`evaluate_run` both trajectories of a run folder
  (``trajectory.txt`` and ``odometry.txt``) against the sequence's ground truth

The ground truth is always evo's *reference* (first file) and the estimate the second, and the
estimate is the one that gets aligned. Inputs are never modified.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from slam.errors import RunFolderError, SlamError
from slam.run_folder import ODOMETRY_FILE, RunFolder
from slam.run_folder.reader import same_trajectory
from slam.tools.eval_metrics import (
    MIN_RPE_PAIRS,
    align_trajectory,
    alignment,
    ape_per_pose,
    associate,
    ate,
    drift,
    evaluate,
    evaluate_files,
    evaluate_full,
    parse_delta,
    rpe,
    transformed,
)
from slam.tools.eval_results import DriftResult, EvalResult, RPEResult, Stats, json_ready
from slam.tools.ground_truth import (
    GROUND_TRUTH_FILE,
    load_run_ground_truth,
    sequence_ground_truth,
)
from slam.trajectory import Trajectory

if TYPE_CHECKING:
    from slam.tools.plots import (
        PlotPlane,
        plot_plane,
        plot_trajectories,
        save_figure,
        trajectory_plane,
    )

logger = logging.getLogger(__name__)

__all__ = [
    "GROUND_TRUTH_FILE",
    "MIN_RPE_PAIRS",
    "DriftResult",
    "EvalResult",
    "RPEResult",
    "RunEvaluation",
    "Stats",
    "align_trajectory",
    "ape_per_pose",
    "associate",
    "ate",
    "drift",
    "evaluate",
    "evaluate_files",
    "evaluate_full",
    "evaluate_run",
    "map_frame_ate",
    "load_run_ground_truth",
    "localisation_summary",
    "parse_delta",
    "PlotPlane",
    "plot_plane",
    "plot_trajectories",
    "rpe",
    "save_figure",
    "sequence_ground_truth",
    "trajectory_plane",
]


def map_frame_ate(gt: Trajectory, est: Trajectory, map_run: str | Path) -> float:
    """The ATE RMSE (m) of a localisation run's trajectory ``est`` in its map's world frame:
    the map run's own alignment to its ground truth applied (that run's trajectory and its
    sequence's ground truth, as recorded in ``map_run``), and no alignment of ``est``'s own,
    so a localisation that lands 20 cm off the map reads 20 cm."""
    run = RunFolder(map_run)
    seq_dir = run.sequence_dir()
    if seq_dir is None:
        raise RunFolderError(
            f"{map_run}: the map run's sequence folder ({run.sequence_path()}) is not found, so "
            "its alignment to the ground truth is unknown"
        )
    map_gt, source = sequence_ground_truth(seq_dir)
    if map_gt is None:
        raise RunFolderError(f"{map_run}: the map run's sequence has no ground truth ({source})")
    S = alignment(map_gt, run.trajectory())
    return ate(gt, transformed(est, S), align=False).rmse


#: Names of :mod:`slam.tools.plots` re-exported here, imported on first use.
_PLOTTING = ("PlotPlane", "plot_plane", "plot_trajectories", "save_figure", "trajectory_plane")


def __getattr__(name: str) -> Any:
    if name in _PLOTTING:
        from slam.tools import plots

        return getattr(plots, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@dataclass
class RunEvaluation:
    """Both trajectories of a run folder against the sequence's ground truth.

    ``final`` evaluates ``trajectory.txt`` (after loop closure), ``odometry`` ``odometry.txt``
    (frontend only; ``None`` when the file is absent). ``ground_truth`` says where the ground truth
    came from; ``odometry_identical`` is true when no pose was corrected.
    """

    run_dir: Path
    ground_truth: str
    final: EvalResult
    odometry: EvalResult | None
    odometry_identical: bool
    loops_accepted: int | None = None
    # a localisation run (slam run --map): frames placed in the map, frames not placed, the
    # first placed, and the ATE in the map's frame (or why it could not be measured)
    localisation: dict[str, Any] | None = None

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "run_dir": str(self.run_dir),
            "localisation": self.localisation,
            "ground_truth": self.ground_truth,
            "loops_accepted": self.loops_accepted,
            "odometry_identical": self.odometry_identical,
            "final": self.final.as_dict(),
            "odometry": None if self.odometry is None else self.odometry.as_dict(),
        }
        if self.odometry is not None:
            out["ate_rmse_change_m"] = self.final.ate.rmse - self.odometry.ate.rmse
        return json_ready(out)


def _loops_accepted(run: RunFolder) -> int | None:
    """``loops_accepted`` of the run's metrics (``None`` when absent or unreadable)."""
    try:
        value = run.metrics().get("loops_accepted")
    except RunFolderError:
        return None
    return int(value) if isinstance(value, (int, float)) else None


_LOCALISATION_KEYS = ("map", "frames_localised", "frames_not_localised", "first_localised_frame")


def localisation_summary(run: RunFolder, gt: Trajectory | None = None) -> dict[str, Any] | None:
    """A localisation run's counts from its ``metrics.json`` (None for a mapping run) and,
    given its ground truth ``gt`` and with frames placed, ``ate_rmse_map_frame_m``
    (:func:`map_frame_ate`; ``map_frame_error`` when it cannot be measured)."""
    try:
        metrics = run.metrics()
    except RunFolderError:
        return None
    if metrics.get("map") is None:
        return None
    out = {k: metrics.get(k) for k in _LOCALISATION_KEYS}
    if gt is not None and out["frames_localised"]:
        try:
            out["ate_rmse_map_frame_m"] = map_frame_ate(gt, run.trajectory(), out["map"])
        except SlamError as exc:
            out["map_frame_error"] = str(exc)
    return out


def evaluate_run(
    run_dir: str | Path | RunFolder,
    gt_path: str | Path | None = None,
    max_diff: float = 0.01,
    correct_scale: bool = False,
    rpe_deltas: Sequence[str | float | tuple[float, str]] = ((1, "frames"),),
    drift_alignment: str | None = None,
) -> RunEvaluation:
    """Evaluate a run folder's ``trajectory.txt`` and ``odometry.txt`` against its ground truth
    (found by :func:`load_run_ground_truth`), each with its own alignment, same options as
    :func:`evaluate_full`. Raises :class:`RunFolderError` when the folder holds no complete run
    and :class:`slam.errors.TrajectoryError` when its trajectory is missing."""
    run = run_dir if isinstance(run_dir, RunFolder) else RunFolder(run_dir)
    run.require_complete()
    est = run.trajectory()
    gt, source = load_run_ground_truth(run, gt_path)
    kw: dict[str, Any] = dict(
        max_diff=max_diff,
        correct_scale=correct_scale,
        rpe_deltas=rpe_deltas,
        drift_alignment=drift_alignment,
    )
    final = evaluate_full(gt, est, **kw)
    odo = run.odometry()
    odometry = None
    identical = True
    if odo is not None:
        identical = same_trajectory(odo, est)
        odometry = final if identical else evaluate_full(gt, odo, **kw)
    else:
        logger.warning("%s: no %s; only the final trajectory is evaluated", run.path, ODOMETRY_FILE)
    return RunEvaluation(
        run.path, source, final, odometry, identical, _loops_accepted(run),
        localisation_summary(run, gt),
    )  # fmt: skip
