"""The results of trajectory evaluation (:mod:`slam.tools.eval`): error statistics as evo computes
them, RPE per delta, final-position drift, and everything of one evaluation, JSON-ready."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

__all__ = ["MIN_RPE_PAIRS", "DriftResult", "EvalResult", "RPEResult", "Stats", "json_ready"]

#: Minimum number of pose pairs for an RPE row to be shown: with fewer, a handful of relative
#: motions stand for the whole trajectory and one bad pair sets the RMSE (a 1 m delta on a 3 m
#: path gives 3 pairs), so the row is left out, with the reason, rather than shown as solid as
#: the others. At 10, no single pair carries more than a tenth of the mean.
MIN_RPE_PAIRS = 10


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


@dataclass
class RPEResult:
    """RPE over consecutive pose pairs ``delta`` ``unit`` apart (``unit``: frames, seconds or
    metres), from ``pairs`` pose pairs. ``trans`` in metres, ``rot`` in degrees (evo's
    statistics); both ``None`` and ``error`` set when no pair could be formed (e.g. a 1 m delta
    on a 0.5 m trajectory). With fewer than ``min_pairs`` pairs the row is *left out*
    (:attr:`left_out`): its statistics stay here, as evo computes them, but the JSON
    (:meth:`as_dict`), the headline, ``slam eval`` and ``slam report`` give the pair count and
    the reason instead of numbers."""

    delta: float
    unit: str
    pairs: int
    trans: Stats | None
    rot: Stats | None
    error: str | None = None
    min_pairs: int = 1

    @property
    def left_out(self) -> str | None:
        """Why this row has no numbers to show (no pair at all, or fewer than ``min_pairs``);
        ``None`` when it has."""
        if self.trans is None or self.rot is None:
            return self.error or "no pose pair"
        if self.pairs < self.min_pairs:
            return (
                f"only {self.pairs} pose pair{'' if self.pairs == 1 else 's'} {self.label} "
                f"apart (at least {self.min_pairs} are needed for a statistic that no single "
                f"pair dominates): use a smaller delta or a longer trajectory"
            )
        return None

    @property
    def label(self) -> str:
        """Short human label: ``1 frame``, ``5 frames``, ``1 s``, ``0.5 m``."""
        value = f"{self.delta:g}"
        if self.unit == "frames":
            return f"{value} frame" + ("" if self.delta == 1 else "s")
        return f"{value} {'s' if self.unit == 'seconds' else 'm'}"

    def as_dict(self) -> dict[str, Any]:
        """``trans_m`` / ``rot_deg`` null and ``error`` the reason when the row is left out."""
        out = self.left_out
        return {
            "delta": self.delta,
            "unit": self.unit,
            "pairs": self.pairs,
            "trans_m": None if out or self.trans is None else self.trans.as_dict(),
            "rot_deg": None if out or self.rot is None else self.rot.as_dict(),
            "error": out,
        }


@dataclass
class DriftResult:
    """Final-position drift: ``final_error_m`` is the distance between the last associated
    estimated position (after ``alignment``) and the ground-truth position at the same time,
    ``path_length_m`` the length of the associated ground-truth path (sum of distances between
    consecutive associated poses) and ``percent = 100 * final_error_m / path_length_m`` (NaN for a
    zero-length path)."""

    final_error_m: float
    path_length_m: float
    percent: float
    alignment: str
    final_timestamp: float

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class EvalResult:
    """Everything :func:`evaluate_full` computes for one estimate against one ground truth.

    ``alignment`` is how the estimate was aligned for ATE and RPE: ``se3`` (Umeyama, evo ``-a``),
    ``sim3`` (``-as``), ``scale`` (``-s``) or ``none``; ``scale`` is the Sim(3) scale applied
    (1 unless corrected). ``rpe`` has one entry per requested delta, in order.
    """

    matched_poses: int
    alignment: str
    scale: float
    max_diff: float
    ate: Stats
    rpe: list[RPEResult]
    drift: DriftResult

    def headline(self) -> dict[str, Any]:
        """The flat dict of :func:`evaluate` (RPE from the first delta; ``None`` if it failed or
        is left out: too few pairs)."""
        first = self.rpe[0] if self.rpe and not self.rpe[0].left_out else None
        return {
            "ate_rmse_m": self.ate.rmse,
            "ate_mean_m": self.ate.mean,
            "ate_median_m": self.ate.median,
            "ate_std_m": self.ate.std,
            "ate_max_m": self.ate.max,
            "rpe_trans_rmse_m": None if first is None or first.trans is None else first.trans.rmse,
            "rpe_rot_rmse_deg": None if first is None or first.rot is None else first.rot.rmse,
            "matched_poses": self.matched_poses,
            "drift_percent": self.drift.percent,
            "path_length_m": self.drift.path_length_m,
        }

    def as_dict(self) -> dict[str, Any]:
        """Headline keys (as :func:`evaluate`, plus ``ate_min_m``) and the full detail nested
        under ``ate``, ``rpe`` and ``drift``; JSON-ready (NaN becomes ``None``)."""
        out: dict[str, Any] = self.headline()
        out["ate_min_m"] = self.ate.min
        out["drift_final_error_m"] = self.drift.final_error_m
        out.update(
            alignment=self.alignment,
            scale=self.scale,
            max_diff_s=self.max_diff,
            ate=self.ate.as_dict(),
            rpe=[r.as_dict() for r in self.rpe],
            drift=self.drift.as_dict(),
        )
        return json_ready(out)


def json_ready(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
