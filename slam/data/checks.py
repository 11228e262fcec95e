"""Checks of a sequence before any work: image size against the calibration, depth scale."""

from __future__ import annotations

import logging

import numpy as np

from slam.data.base import Sequence
from slam.errors import CalibrationError, DatasetError, FrameReadError, FrameSizeError

log = logging.getLogger(__name__)

#: A plausible median scene depth for an RGB-D camera, metres.
DEPTH_RANGE_M = (0.1, 20.0)
#: Depth scales in common use: TUM (1/5000 m), millimetres, metres, 1/10000 m.
COMMON_DEPTH_SCALES = (5000.0, 1000.0, 1.0, 10000.0)


def suggest_depth_scale(median_raw: float) -> float:
    """The depth_scale under which a median stored depth value ``median_raw`` is a typical
    indoor distance: a common scale if one fits, else the one giving 1.5 m."""
    lo, hi = DEPTH_RANGE_M
    fits = [s for s in COMMON_DEPTH_SCALES if lo <= median_raw / s <= hi]
    if fits:
        return min(fits, key=lambda s: abs(np.log(median_raw / s / 1.5)))
    return float(f"{median_raw / 1.5:.3g}")


def check_sequence(sequence: Sequence, indices: list[int], probe: int = 5) -> None:
    """Read the first readable frames (up to ``probe`` with depth): the first one's depth
    image must have the calibration's size, and their median depth must lie within
    0.1-20 m (else the depth scale is wrong: the error says which one fits). Unreadable frames
    are left for the run to report, unless none of those probed can be read (8-bit depth, a
    wrong folder): then the first one's reason is the error."""
    calib = sequence.calibration
    medians: list[float] = []
    sized = False
    unreadable: list[FrameReadError] = []
    for i in indices[: 4 * probe]:
        try:
            frame = sequence[i]
        except FrameSizeError as exc:
            if not sized:  # the first readable frame: the calibration is wrong, not the frame
                raise CalibrationError(f"{sequence.path}: {exc}") from exc
            continue
        except FrameReadError as exc:
            unreadable.append(exc)
            continue
        sized = True
        valid = frame.depth_m[frame.depth_m > 0]
        if valid.size:
            medians.append(float(np.median(valid)))
        if len(medians) >= probe:
            break
    if not sized and unreadable:
        raise DatasetError(
            f"{sequence.path}: none of the first {len(unreadable)} frames can be read: "
            f"{unreadable[0]}"
        )
    if not medians:
        log.warning(
            "%s: the first frames have no depth at all; frames stay lost until depth appears",
            sequence.path,
        )
        return
    median = float(np.median(medians))
    lo, hi = DEPTH_RANGE_M
    if not lo <= median <= hi:
        scale = calib.depth_scale
        better = suggest_depth_scale(median * scale)
        raise CalibrationError(
            f"{sequence.path}: the median depth of the first {len(medians)} frames is "
            f"{median:.4g} m with depth_scale {scale:g}, outside {lo}-{hi} m: depth_scale is "
            f"likely wrong. depth_scale {better:g} would give {median * scale / better:.2f} m "
            "(common values: 5000 for TUM, 1000 for depth in millimetres, 1 for metres); set "
            "it in the sequence's calibration.yaml or in the config as "
            "dataset.calibration.depth_scale"
        )
