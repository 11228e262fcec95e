"""ATE, RPE and drift with numbers identical to evo's (see :mod:`slam.tools.eval`, which
re-exports everything here): the evo adapter (association, alignment, RPE pair selection) and the
public metric functions. Inputs are never modified (evo aligns in place, so this module works on
copies)."""

from __future__ import annotations

import copy
import logging
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from evo import EvoException
from evo.core import lie_algebra, metrics, sync
from evo.core.metrics import PoseRelation, Unit
from evo.core.trajectory import PoseTrajectory3D

from slam.errors import TrajectoryError
from slam.tools.eval_results import MIN_RPE_PAIRS, DriftResult, EvalResult, RPEResult, Stats
from slam.trajectory import Trajectory, read_tum

logger = logging.getLogger(__name__)

__all__ = [
    "MIN_RPE_PAIRS",
    "align_trajectory",
    "ape_per_pose",
    "associate",
    "ate",
    "drift",
    "evaluate",
    "evaluate_files",
    "evaluate_full",
    "parse_delta",
    "rpe",
]

#: Minimum number of associated poses for any metric (Umeyama needs 3 points).
MIN_MATCHES = 3

# Tolerance (s) when selecting pose pairs ``delta`` seconds apart: TUM timestamps are written
# with microsecond resolution, so 30 frames at 30 Hz may come out as 0.999999 s.
_SECONDS_TOL = 1e-6


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
        if possible < MIN_MATCHES:
            # too few poses to begin with: no tolerance helps (e.g. a run of 1 or 2 frames)
            which = "estimate" if len(est) < MIN_MATCHES else "ground truth"
            raise TrajectoryError(
                f"the {which} has only {possible} pose{'s' if possible != 1 else ''} "
                f"(ground truth {_range(gts)}, estimate {_range(ests)}): ATE, RPE and drift "
                f"need at least {MIN_MATCHES} associated poses (the alignment fits 3 points); "
                + (
                    f"evaluate a run of at least {MIN_MATCHES} tracked frames"
                    if which == "estimate"
                    else "give a ground truth with more poses"
                )
            )
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
            f"Try a larger max_diff (`max_diff=` in Python; on the command line "
            f"`slam eval` / `slam report` --t-max-diff SECONDS, e.g. `slam eval RUN_DIR "
            f"--t-max-diff 0.02` for a run)."
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
    "frame": Unit.frames,
    "f": Unit.frames,
    "meters": Unit.meters,
    "metres": Unit.meters,
    "meter": Unit.meters,
    "metre": Unit.meters,
    "m": Unit.meters,
    "seconds": Unit.seconds,
    "second": Unit.seconds,
    "sec": Unit.seconds,
    "s": Unit.seconds,
}


#: Canonical names of the RPE delta units (evo's ``Unit.meters`` is written "metres" here).
_UNIT_NAMES = {Unit.frames: "frames", Unit.seconds: "seconds", Unit.meters: "metres"}


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


def parse_delta(spec: str | float | tuple[float, str]) -> tuple[float, str]:
    """An RPE delta as ``(value, unit)`` with unit ``frames``, ``seconds`` or ``metres``.

    Accepts ``(1, "frames")``, a bare number (frames) or text such as ``"1f"``, ``"10 frames"``,
    ``"0.5s"``, ``"1m"``, ``"2 metres"``.
    """
    if isinstance(spec, tuple):
        value, unit = spec
        return float(value), _UNIT_NAMES[_parse_unit(unit)]
    if isinstance(spec, (int, float)) and not isinstance(spec, bool):
        return float(spec), "frames"
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([A-Za-z]*)\s*", str(spec))
    if m is None:
        raise TrajectoryError(
            f"cannot read RPE delta {spec!r}: write a number and a unit, e.g. '1f' (frames), "
            f"'1s' (seconds) or '0.5m' (metres)"
        )
    unit = m.group(2) or "frames"
    return float(m.group(1)), _UNIT_NAMES[_parse_unit(unit)]


def _ids_by_time(stamps: np.ndarray, delta: float) -> list[int]:
    """Consecutive pose ids at least ``delta`` seconds apart (like evo's by-path selection)."""
    ids = [0]
    for i in range(1, len(stamps)):
        if stamps[i] - stamps[ids[-1]] >= delta - _SECONDS_TOL:
            ids.append(i)
    return ids


def _rpe_metrics(
    ref: PoseTrajectory3D, est: PoseTrajectory3D, delta: float, unit: Unit
) -> tuple[Stats, Stats, int]:
    """(translation stats m, rotation stats deg, number of pose pairs) of evo's RPE."""
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
    pairs = 0
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
        pairs = len(metric.error)
    return out[0], out[1], pairs


def _rpe_stats(
    ref: PoseTrajectory3D, est: PoseTrajectory3D, delta: float, unit: Unit
) -> tuple[Stats, Stats]:
    t, r, _ = _rpe_metrics(ref, est, delta, unit)
    return t, r


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


def alignment(gt: Trajectory, est: Trajectory, max_diff: float = 0.01) -> np.ndarray:
    """The SE(3) Umeyama alignment (4x4) that :func:`ate` applies to ``est`` (evo's ``-a``)."""
    ref, est_s = _associate_evo(gt, est, max_diff)
    return _align_evo(ref, est_s, True, False)


def transformed(traj: Trajectory, T: np.ndarray) -> Trajectory:
    """Every pose of ``traj`` moved by the rigid transform ``T`` (T @ pose)."""
    return Trajectory(np.array(traj.timestamps, copy=True), np.asarray(T, float) @ traj.poses)


def _alignment_name(align: bool, correct_scale: bool) -> str:
    if align:
        return "sim3" if correct_scale else "se3"
    return "scale" if correct_scale else "none"


_DRIFT_ALIGNMENTS = ("se3", "sim3", "scale", "none", "origin")


def _drift_evo(ref: PoseTrajectory3D, est: PoseTrajectory3D, alignment: str) -> DriftResult:
    """Drift of an associated (and, unless ``origin``, already aligned) estimate."""
    if alignment == "origin":
        est = copy.deepcopy(est)
        est.align_origin(ref)
    path = float(ref.path_length)
    final_err = float(np.linalg.norm(est.positions_xyz[-1] - ref.positions_xyz[-1]))
    if path > 0:
        pct = final_err / path * 100.0
    else:
        logger.warning("ground truth path length is zero: drift percent is undefined (NaN)")
        pct = float("nan")
    return DriftResult(
        final_error_m=final_err,
        path_length_m=path,
        percent=float(pct),
        alignment=alignment,
        final_timestamp=float(est.timestamps[-1]),
    )


def drift(
    gt: Trajectory, est: Trajectory, alignment: str = "se3", max_diff: float = 0.01
) -> DriftResult:
    """Final-position drift of ``est`` in % of the ground-truth path length.

    The poses are associated by timestamp (as :func:`associate`); the estimate is then aligned to
    the ground truth by ``alignment``: ``se3`` (the Umeyama fit over all associated positions that
    :func:`ate` uses, evo ``-a``), ``sim3`` (``-as``), ``scale`` (``-s``), ``origin`` (the rigid
    motion that puts the first associated estimated pose exactly on the first ground-truth pose,
    evo ``--align_origin``: all the error accumulated from the start shows at the end) or ``none``.
    ``final_error_m`` is the distance between the last associated positions and ``percent`` =
    100 * ``final_error_m`` / ground-truth path length over the associated poses.
    """
    if alignment not in _DRIFT_ALIGNMENTS:
        raise TrajectoryError(
            f"unknown drift alignment {alignment!r}; use one of {', '.join(_DRIFT_ALIGNMENTS)}"
        )
    ref, est_s = _associate_evo(gt, est, max_diff)
    if alignment in ("se3", "sim3", "scale"):
        _align_evo(ref, est_s, alignment != "scale", alignment != "se3")
    return _drift_evo(ref, est_s, alignment)


def ape_per_pose(
    gt: Trajectory,
    est: Trajectory,
    align: bool = True,
    correct_scale: bool = False,
    max_diff: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pose translation error (m) after the alignment :func:`ate` uses.

    Returns ``(timestamps of the associated estimated poses, errors)``; the errors are evo's APE
    ``error`` array, so their statistics are exactly :func:`ate`'s.
    """
    ref, est_s = _associate_evo(gt, est, max_diff)
    _align_evo(ref, est_s, align, correct_scale)
    metric = metrics.APE(PoseRelation.translation_part)
    metric.process_data((ref, est_s))
    return np.array(est_s.timestamps, dtype=float), np.array(metric.error, dtype=float)


def evaluate_full(
    gt: Trajectory,
    est: Trajectory,
    max_diff: float = 0.01,
    align: bool = True,
    correct_scale: bool = False,
    rpe_deltas: Sequence[str | float | tuple[float, str]] = ((1, "frames"),),
    drift_alignment: str | None = None,
    min_rpe_pairs: int = MIN_RPE_PAIRS,
) -> EvalResult:
    """ATE, RPE for each of ``rpe_deltas`` and drift of ``est`` against ``gt``.

    One association and one alignment (as :func:`ate`: SE(3) Umeyama by default, Sim(3) with
    ``correct_scale``) serve every metric, so the numbers equal :func:`ate`, :func:`rpe` and
    :func:`drift` called separately with the same options. ``rpe_deltas`` entries are anything
    :func:`parse_delta` reads (``"1f"``, ``"1s"``, ``"0.5m"``, ``(1, "frames")``); a delta that
    yields no pose pair is recorded with its ``error`` instead of raising. One with fewer than
    ``min_rpe_pairs`` pairs (:data:`MIN_RPE_PAIRS`) keeps evo's statistics but is *left out*
    (:attr:`RPEResult.left_out` says why): the headline, ``as_dict`` (the JSON), ``slam eval``
    and ``slam report`` show its pair count and the reason instead of numbers.
    ``drift_alignment`` ``None`` uses the ATE alignment, else any :func:`drift` alignment
    (e.g. ``"origin"``).
    """
    deltas = [parse_delta(d) for d in rpe_deltas]
    if drift_alignment is not None and drift_alignment not in _DRIFT_ALIGNMENTS:
        raise TrajectoryError(
            f"unknown drift alignment {drift_alignment!r}; "
            f"use one of {', '.join(_DRIFT_ALIGNMENTS)}"
        )
    ref, est_s = _associate_evo(gt, est, max_diff)
    unaligned = copy.deepcopy(est_s) if drift_alignment is not None else None
    S = _align_evo(ref, est_s, align, correct_scale)
    scale = float(np.cbrt(np.linalg.det(S[:3, :3])))
    a = _ape_stats(ref, est_s)
    rpes: list[RPEResult] = []
    for value, unit_name in deltas:
        try:
            t, r, pairs = _rpe_metrics(ref, est_s, value, _parse_unit(unit_name))
            rp = RPEResult(value, unit_name, pairs, t, r, min_pairs=min_rpe_pairs)
        except TrajectoryError as exc:
            rp = RPEResult(value, unit_name, 0, None, None, str(exc), min_rpe_pairs)
        if rp.left_out:
            logger.info("RPE over %s left out: %s", rp.label, rp.left_out)
        rpes.append(rp)
    name = _alignment_name(align, correct_scale)
    if drift_alignment is None or drift_alignment == name:
        dr = _drift_evo(ref, est_s, name)
    else:
        assert unaligned is not None
        if drift_alignment in ("se3", "sim3", "scale"):
            _align_evo(ref, unaligned, drift_alignment != "scale", drift_alignment != "se3")
        dr = _drift_evo(ref, unaligned, drift_alignment)
    result = EvalResult(
        matched_poses=int(ref.num_poses),
        alignment=name,
        scale=scale,
        max_diff=float(max_diff),
        ate=a,
        rpe=rpes,
        drift=dr,
    )
    first = rpes[0] if rpes else None
    logger.info(
        "ATE rmse %.4f m, RPE %s, %d poses matched, drift %.2f %%",
        a.rmse,
        "n/a"
        if first is None or first.left_out or first.trans is None or first.rot is None
        else f"{first.trans.rmse:.4f} m / {first.rot.rmse:.3f} deg",
        result.matched_poses,
        dr.percent,
    )
    return result


def evaluate(
    gt: Trajectory,
    est: Trajectory,
    max_diff: float = 0.01,
    align: bool = True,
    correct_scale: bool = False,
) -> dict[str, Any]:
    """All headline numbers in one flat dict.

    Keys: ``ate_rmse_m, ate_mean_m, ate_median_m, ate_std_m, ate_max_m`` (as :func:`ate`),
    ``rpe_trans_rmse_m, rpe_rot_rmse_deg`` (as :func:`rpe` with delta = 1 frame, same alignment;
    ``None`` with fewer than :data:`MIN_RPE_PAIRS` pairs, i.e. under 11 matched poses: left out),
    ``matched_poses``, ``path_length_m`` (of the associated ground truth) and ``drift_percent``
    (error of the last associated position after the same alignment / ``path_length_m`` * 100,
    see :func:`drift`; NaN for a zero-length path). :func:`evaluate_full` has the full detail.
    """
    return evaluate_full(gt, est, max_diff, align, correct_scale).headline()


def evaluate_files(gt_path: str | Path, est_path: str | Path, **kw: Any) -> dict[str, Any]:
    """:func:`evaluate` on two TUM files (read with :func:`slam.trajectory.read_tum`)."""
    return evaluate(read_tum(gt_path, skip_non_finite=True), read_tum(est_path), **kw)
