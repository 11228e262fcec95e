"""Robust statistics of residuals, shared by the alignments: the median (by one partition),
the MAD scale and Huber's weights."""

from __future__ import annotations

import numpy as np

#: the MAD's factor to a normal distribution's standard deviation
MAD = 1.4826


def median(a: np.ndarray) -> float:
    """``np.median`` of a 1-D array, the same value, by a single-pivot partition: ``np.median``
    partitions around the two middle elements at once, which is ten times slower on the
    tens of thousands of residuals of one alignment iteration."""
    a = np.asarray(a).ravel()
    n = len(a)
    if n == 0:
        return float("nan")
    k = n // 2
    p = np.partition(a, k)
    if n % 2:
        return float(p[k])
    return float((p[:k].max() + p[k]) / 2)


def robust_scale(r: np.ndarray, floor: float) -> float:
    """``MAD`` times the median absolute residual, at least ``floor`` (``floor`` when there is
    no residual)."""
    if len(r) == 0:
        return floor
    return max(MAD * median(np.abs(r)), floor)


def huber_weights(r: np.ndarray, delta: float) -> np.ndarray:
    """Huber's IRLS weights (float32) of residuals ``r`` at ``delta``."""
    a = np.abs(r)
    return np.where(a <= delta, np.float32(1.0), np.float32(delta) / np.maximum(a, 1e-12))
