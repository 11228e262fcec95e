"""Trajectory metrics (ATE / RPE) with numbers identical to evo's, plus a top-view plot.

Everything numeric is delegated to evo's library so that the values match the ``evo_ape`` /
``evo_rpe`` command line tools exactly:

* :func:`associate`  == ``evo.core.sync.associate_trajectories`` (nearest timestamp within
  ``max_diff`` seconds, evo's default 0.01 s)
* :func:`ate`        == ``evo_ape tum GT EST -a`` (``-as`` with ``correct_scale=True``), translation
  part, metres
* :func:`rpe`        == ``evo_rpe tum GT EST -a --delta 1 --delta_unit f`` for ``-r trans_part``
  (metres) and ``-r angle_deg`` (degrees), consecutive pairs (``all_pairs=False``)

The ground truth is always evo's *reference* (first file) and the estimate the second, and the
estimate is the one that gets aligned. Inputs are never modified (evo aligns in place, so this
module works on copies).
"""

from __future__ import annotations

import copy
import logging
import os
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from evo import EvoException
from evo.core import lie_algebra, metrics, sync
from evo.core.metrics import PoseRelation, Unit
from evo.core.trajectory import PoseTrajectory3D

from slam.errors import TrajectoryError
from slam.trajectory import Trajectory, read_tum

logger = logging.getLogger(__name__)

__all__ = [
    "Stats",
    "align_trajectory",
    "associate",
    "ate",
    "evaluate",
    "evaluate_files",
    "plot_trajectories",
    "rpe",
]

#: Minimum number of associated poses for any metric (Umeyama needs 3 points).
MIN_MATCHES = 3

# Tolerance (s) when selecting pose pairs ``delta`` seconds apart: TUM timestamps are written
# with microsecond resolution, so 30 frames at 30 Hz may come out as 0.999999 s.
_SECONDS_TOL = 1e-6


@dataclass
class Stats:
    """Error statistics as evo computes them (``std`` is the population standard deviation)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


# ----------------------------------------------------------------------------------------------
# conversions


def _to_evo(traj: Trajectory, what: str) -> PoseTrajectory3D:
    """Copy a :class:`Trajectory` into an evo ``PoseTrajectory3D`` (never shares memory)."""
    if not isinstance(traj, Trajectory):
        raise TrajectoryError(f"{what}: expected a slam.trajectory.Trajectory, got {type(traj)!r}")
    if len(traj) == 0:
        raise TrajectoryError(f"{what} trajectory is empty")
    if not np.all(np.isfinite(traj.timestamps)):
        raise TrajectoryError(f"{what} trajectory has non-finite timestamps")
    if not np.all(np.isfinite(traj.poses)):
        bad = int(np.flatnonzero(~np.isfinite(traj.poses).reshape(len(traj), -1).all(axis=1))[0])
        raise TrajectoryError(
            f"{what} trajectory has a non-finite pose (first at index {bad}, "
            f"t={traj.timestamps[bad]:.6f})"
        )
    poses = np.array(traj.poses, dtype=float, copy=True)
    return PoseTrajectory3D(
        poses_se3=list(poses), timestamps=np.array(traj.timestamps, dtype=float), name=what
    )


def _from_evo(traj: PoseTrajectory3D) -> Trajectory:
    return Trajectory(np.array(traj.timestamps, dtype=float), np.array(traj.poses_se3, dtype=float))


def _stats(metric: metrics.PE) -> Stats:
    s = metric.get_all_statistics()
    return Stats(
        rmse=float(s["rmse"]),
        mean=float(s["mean"]),
        median=float(s["median"]),
        std=float(s["std"]),
        min=float(s["min"]),
        max=float(s["max"]),
    )


def _range(stamps: np.ndarray) -> str:
    return f"[{stamps.min():.6f}, {stamps.max():.6f}] s ({len(stamps)} poses)"


# ----------------------------------------------------------------------------------------------
# association and alignment (evo objects)


def _associate_evo(
    gt: Trajectory, est: Trajectory, max_diff: float
) -> tuple[PoseTrajectory3D, PoseTrajectory3D]:
    if not (np.isfinite(max_diff) and max_diff >= 0):
        raise TrajectoryError(f"max_diff must be a non-negative number of seconds, got {max_diff}")
    ref = _to_evo(gt, "ground truth")
    est_e = _to_evo(est, "estimate")
    try:
        ref_s, est_s = sync.associate_trajectories(ref, est_e, max_diff=max_diff)
        matched = ref_s.num_poses
    except sync.SyncException:
        matched = 0
    if matched < MIN_MATCHES:
        possible = min(len(gt), len(est))
        gts, ests = gt.timestamps, est.timestamps
        overlap = min(gts.max(), ests.max()) - max(gts.min(), ests.min())
        hint = ""
        if overlap < -max_diff:
            hint = (
                " The time ranges do not overlap: are both trajectories in the same clock "
                "(e.g. one uses sequence-relative seconds, the other Unix time)?"
            )
        raise TrajectoryError(
            f"only {matched} of {possible} possible poses could be associated by timestamp "
            f"(need at least {MIN_MATCHES}) with max_diff={max_diff} s: "
            f"ground truth {_range(gts)}, estimate {_range(ests)}.{hint} "
            f"Try a larger max_diff (CLI option --t-max-diff)."
        )
    logger.debug(
        "associated %d of %d possible poses (max_diff=%g s)",
        matched,
        min(len(gt), len(est)),
        max_diff,
    )
    return ref_s, est_s


def _align_evo(
    ref: PoseTrajectory3D, est: PoseTrajectory3D, align: bool, correct_scale: bool
) -> np.ndarray:
    """Align ``est`` to ``ref`` in place exactly as evo_ape/evo_rpe do; returns the Sim(3) used."""
    only_scale = correct_scale and not align
    if not (align or correct_scale):
        return np.eye(4)
    try:
        r, t, s = est.align(ref, correct_scale, only_scale)
    except EvoException as exc:
        raise TrajectoryError(
            f"cannot align the estimate to the ground truth ({exc}); the estimated or ground "
            f"truth positions are degenerate (all identical or collinear?)"
        ) from exc
    logger.debug("alignment: scale=%.6f t=%s", s, np.round(t, 6))
    if only_scale:
        return lie_algebra.sim3(np.eye(3), np.zeros(3), s)
    return lie_algebra.sim3(r, t, s)


def _ape_stats(ref: PoseTrajectory3D, est: PoseTrajectory3D) -> Stats:
    metric = metrics.APE(PoseRelation.translation_part)
    metric.process_data((ref, est))
    return _stats(metric)


_UNITS = {
    "frames": Unit.frames,
    "f": Unit.frames,
    "meters": Unit.meters,
    "metres": Unit.meters,
    "m": Unit.meters,
    "seconds": Unit.seconds,
    "s": Unit.seconds,
}


def _parse_unit(delta_unit: str | Unit) -> Unit:
    if isinstance(delta_unit, Unit):
        unit = delta_unit
    else:
        unit = _UNITS.get(str(delta_unit).lower())
    if unit not in (Unit.frames, Unit.meters, Unit.seconds):
        raise TrajectoryError(
            f"unsupported RPE delta_unit {delta_unit!r}: use 'frames', 'meters' or 'seconds'"
        )
    return unit


def _ids_by_time(stamps: np.ndarray, delta: float) -> list[int]:
    """Consecutive pose ids at least ``delta`` seconds apart (like evo's by-path selection)."""
    ids = [0]
    for i in range(1, len(stamps)):
        if stamps[i] - stamps[ids[-1]] >= delta - _SECONDS_TOL:
            ids.append(i)
    return ids


def _rpe_stats(
    ref: PoseTrajectory3D, est: PoseTrajectory3D, delta: float, unit: Unit
) -> tuple[Stats, Stats]:
    if not (np.isfinite(delta) and delta > 0):
        raise TrajectoryError(f"RPE delta must be a positive number, got {delta}")
    if unit is Unit.frames and float(delta) != int(delta):
        raise TrajectoryError(f"RPE delta must be a whole number of frames, got {delta}")
    if unit is Unit.seconds:
        # evo has no time-based pair selection: pick the ids here (on the estimate's stamps, as
        # evo picks path-based pairs on the estimate), then evo's consecutive-frame RPE on the
        # reduced trajectories evaluates exactly those pairs.
        ids = _ids_by_time(np.asarray(est.timestamps), float(delta))
        if len(ids) < 2:
            raise TrajectoryError(
                f"RPE delta = {delta} s is longer than the associated trajectory "
                f"({est.timestamps[-1] - est.timestamps[0]:.3f} s): use a smaller delta"
            )
        ref, est = copy.deepcopy(ref), copy.deepcopy(est)
        ref.reduce_to_ids(ids)
        est.reduce_to_ids(ids)
        delta, unit = 1, Unit.frames
    out = []
    for relation in (PoseRelation.translation_part, PoseRelation.rotation_angle_deg):
        metric = metrics.RPE(relation, delta=delta, delta_unit=unit, all_pairs=False)
        try:
            metric.process_data((ref, est))
        except EvoException as exc:
            raise TrajectoryError(
                f"RPE failed for delta = {delta} {unit.value} on {est.num_poses} associated poses "
                f"({est.path_length:.3f} m of path): {exc}"
            ) from exc
        out.append(_stats(metric))
    return out[0], out[1]


# ----------------------------------------------------------------------------------------------
# public API


def associate(
    gt: Trajectory, est: Trajectory, max_diff: float = 0.01
) -> tuple[Trajectory, Trajectory]:
    """Match poses by nearest timestamp (evo's ``associate_trajectories``).

    Returns copies ``(gt_matched, est_matched)`` of equal length. Raises :class:`TrajectoryError`
    when fewer than 3 poses match.
    """
    ref, est_s = _associate_evo(gt, est, max_diff)
    return _from_evo(ref), _from_evo(est_s)


def ate(
    gt: Trajectory,
    est: Trajectory,
    align: bool = True,
    correct_scale: bool = False,
    max_diff: float = 0.01,
) -> Stats:
    """Absolute trajectory error, translation part in metres.

    ``align=True`` == ``evo_ape tum GT EST -a`` (SE(3) Umeyama); with ``correct_scale=True`` ==
    ``-as`` (Sim(3)); ``align=False, correct_scale=True`` == ``-s`` (scale only).
    """
    ref, est_s = _associate_evo(gt, est, max_diff)
    _align_evo(ref, est_s, align, correct_scale)
    return _ape_stats(ref, est_s)


def rpe(
    gt: Trajectory,
    est: Trajectory,
    delta: float = 1,
    delta_unit: str = "frames",
    align: bool = True,
    max_diff: float = 0.01,
    correct_scale: bool = False,
) -> tuple[Stats, Stats]:
    """Relative pose error over consecutive pairs ``delta`` apart.

    Returns ``(translation stats in metres, rotation stats in degrees)``, equal to
    ``evo_rpe tum GT EST -a --delta 1 --delta_unit f`` with ``-r trans_part`` and ``-r angle_deg``.
    ``delta_unit`` is ``"frames"``, ``"meters"`` (evo's ``Unit.meters``: travelled path of the
    estimate) or ``"seconds"`` (not in evo: pairs at least ``delta`` s apart on the estimate's
    timestamps, then evo's RPE on those pairs).
    """
    unit = _parse_unit(delta_unit)
    ref, est_s = _associate_evo(gt, est, max_diff)
    _align_evo(ref, est_s, align, correct_scale)
    return _rpe_stats(ref, est_s, delta, unit)


def align_trajectory(
    gt: Trajectory, est: Trajectory, correct_scale: bool = False, max_diff: float = 0.01
) -> Trajectory:
    """The whole estimate (all its poses) mapped by the Umeyama alignment that :func:`ate` uses.

    Handy for plotting an estimate over the ground truth.
    """
    ref, est_s = _associate_evo(gt, est, max_diff)
    S = _align_evo(ref, est_s, True, correct_scale)
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))
    R, t = S[:3, :3] / s, S[:3, 3]
    poses = np.array(est.poses, dtype=float, copy=True)
    out = np.empty_like(poses)
    out[:, :3, :3] = R @ poses[:, :3, :3]
    out[:, :3, 3] = s * poses[:, :3, 3] @ R.T + t
    out[:, 3, :] = (0.0, 0.0, 0.0, 1.0)
    return Trajectory(np.array(est.timestamps, copy=True), out)


def evaluate(
    gt: Trajectory,
    est: Trajectory,
    max_diff: float = 0.01,
    align: bool = True,
    correct_scale: bool = False,
) -> dict[str, Any]:
    """All headline numbers in one flat dict.

    Keys: ``ate_rmse_m, ate_mean_m, ate_median_m, ate_std_m, ate_max_m`` (as :func:`ate`),
    ``rpe_trans_rmse_m, rpe_rot_rmse_deg`` (as :func:`rpe` with delta = 1 frame, same alignment),
    ``matched_poses``, ``path_length_m`` (of the associated ground truth) and ``drift_percent``
    (error of the last associated position after alignment / ``path_length_m`` * 100; NaN for a
    zero-length path).
    """
    ref, est_s = _associate_evo(gt, est, max_diff)
    _align_evo(ref, est_s, align, correct_scale)
    a = _ape_stats(ref, est_s)
    rt, rr = _rpe_stats(ref, est_s, 1, Unit.frames)
    path = float(ref.path_length)
    final_err = float(np.linalg.norm(est_s.positions_xyz[-1] - ref.positions_xyz[-1]))
    if path > 0:
        drift = final_err / path * 100.0
    else:
        logger.warning("ground truth path length is zero: drift_percent is undefined (NaN)")
        drift = float("nan")
    result = {
        "ate_rmse_m": a.rmse,
        "ate_mean_m": a.mean,
        "ate_median_m": a.median,
        "ate_std_m": a.std,
        "ate_max_m": a.max,
        "rpe_trans_rmse_m": rt.rmse,
        "rpe_rot_rmse_deg": rr.rmse,
        "matched_poses": int(ref.num_poses),
        "drift_percent": float(drift),
        "path_length_m": path,
    }
    logger.info(
        "ATE rmse %.4f m, RPE %.4f m / %.3f deg, %d poses matched, drift %.2f %%",
        a.rmse,
        rt.rmse,
        rr.rmse,
        result["matched_poses"],
        drift,
    )
    return result


def evaluate_files(gt_path: str | Path, est_path: str | Path, **kw: Any) -> dict[str, Any]:
    """:func:`evaluate` on two TUM files (read with :func:`slam.trajectory.read_tum`)."""
    return evaluate(read_tum(gt_path), read_tum(est_path), **kw)


# ----------------------------------------------------------------------------------------------
# plotting

_AXIS_NAMES = "xyz"
# Tie-break when extents are equal: prefer x, then z, then y (a top view for y-down cameras).
_AXIS_PREFERENCE = {0: 0, 2: 1, 1: 2}


def _plot_axes(points: np.ndarray) -> tuple[int, int]:
    if len(points) == 0:
        return 0, 2
    extent = np.ptp(points, axis=0)
    extent = np.where(np.isfinite(extent), extent, 0.0)
    if not np.any(extent > 0):
        return 0, 2
    best = sorted(range(3), key=lambda a: (-round(float(extent[a]), 12), _AXIS_PREFERENCE[a]))
    a, b = sorted(best[:2])
    return a, b


def plot_trajectories(
    path_png: str | Path,
    gt: Trajectory | None,
    trajectories: dict[str, Trajectory],
    title: str = "",
) -> None:
    """Top view of the ground truth and any number of trajectories, saved as a PNG.

    The plane is spanned by the two axes along which the ground truth (or, without one, all
    trajectories) extends most; x-z when undecided. Trajectories are plotted as given (use
    :func:`align_trajectory` first to overlay an estimate on the ground truth). Written atomically.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    trajectories = dict(trajectories or {})
    if gt is None and not trajectories:
        raise TrajectoryError(
            "plot_trajectories: nothing to plot (no ground truth, no trajectories)"
        )
    if gt is not None and len(gt):
        ref_points = gt.positions
    else:
        ref_points = np.concatenate(
            [t.positions for t in trajectories.values() if len(t)] or [np.zeros((0, 3))]
        )
    a, b = _plot_axes(ref_points)

    fig = Figure(figsize=(8, 7), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if gt is not None and len(gt):
        p = gt.positions
        ax.plot(
            p[:, a], p[:, b], color="black", linestyle="--", linewidth=1.5, label="ground truth"
        )
        ax.plot(p[0, a], p[0, b], marker="o", color="black", markersize=5, linestyle="none")
    for name, traj in trajectories.items():
        if len(traj) == 0:
            logger.warning("plot_trajectories: trajectory %r is empty, skipped", name)
            continue
        p = traj.positions
        (line,) = ax.plot(p[:, a], p[:, b], linewidth=1.2, label=str(name))
        ax.plot(
            p[0, a], p[0, b], marker="o", color=line.get_color(), markersize=4, linestyle="none"
        )
    ax.set_xlabel(f"{_AXIS_NAMES[a]} [m]")
    ax.set_ylabel(f"{_AXIS_NAMES[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")
    if title:
        ax.set_title(title)
    fig.tight_layout()

    path = Path(path_png)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            fig.savefig(f, format="png")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    logger.debug("wrote trajectory plot %s", path)
