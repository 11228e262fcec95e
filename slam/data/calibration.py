"""Finding a sequence's calibration: ``calibration.yaml``, TUM defaults by camera, or overrides."""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from slam.data.base import Calibration
from slam.errors import CalibrationError

log = logging.getLogger(__name__)

#: TUM RGB-D's published distortion (k1, k2, p1, p2, k3) of the freiburg1 and freiburg2 colour
#: cameras, to which their depth images are registered; calibrated together with the intrinsics
#: below. Their recordings are distributed as recorded (not undistorted); freiburg3's are
#: undistorted already.
TUM_DISTORTION = {
    "freiburg1": (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    "freiburg2": (0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
}

#: How much later (s) TUM's freiburg1 Kinect took its colour images, relative to its depth
#: images, than their timestamps say: 12 ms, where both shared freiburg1 recordings track and
#: close loops best and where the keyframe features agree with the tracked poses far better
#: than as stamped (docs/decisions.md, "TUM freiburg1's colour delay"). freiburg2's and
#: freiburg3's cameras are not measured.
TUM_COLOUR_DELAY_S = {"freiburg1": 0.012}

#: TUM RGB-D calibrated intrinsics (with their distortion and colour delay), depth scale 5000.
TUM_DEFAULTS = {
    "freiburg1": Calibration(
        640, 480, 517.3, 516.5, 318.6, 255.3, 5000.0, *TUM_DISTORTION["freiburg1"],
        colour_delay_s=TUM_COLOUR_DELAY_S["freiburg1"],
    ),  # fmt: skip
    "freiburg2": Calibration(
        640, 480, 520.9, 521.0, 325.1, 249.7, 5000.0, *TUM_DISTORTION["freiburg2"]
    ),
    "freiburg3": Calibration(640, 480, 535.4, 539.2, 320.1, 247.6, 5000.0),
}

#: Microsoft 7-Scenes (Kinect v1 depth camera), depth in millimetres.
SEVEN_SCENES_DEFAULT = Calibration(640, 480, 585.0, 585.0, 320.0, 240.0, 1000.0)

KEYS = ("width", "height", "fx", "fy", "cx", "cy", "depth_scale")
DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")  # optional in calibration.yaml (default 0)
#: optional keys of calibration.yaml and dataset.calibration: the distortion and the colour delay
OPTIONAL_KEYS = (*DISTORTION_KEYS, "colour_delay_s")


def read_calibration_yaml(path: Path) -> Calibration:
    """Read ``calibration.yaml`` (keys width, height, fx, fy, cx, cy, depth_scale)."""
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise CalibrationError(f"{path}: cannot read calibration: {exc}") from exc
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: expected a mapping with keys {', '.join(KEYS)}")
    missing = [k for k in KEYS if k not in data]
    if missing:
        raise CalibrationError(f"{path}: missing keys {missing}; expected {', '.join(KEYS)}")
    try:
        return Calibration(
            width=int(data["width"]),
            height=int(data["height"]),
            fx=float(data["fx"]),
            fy=float(data["fy"]),
            cx=float(data["cx"]),
            cy=float(data["cy"]),
            depth_scale=float(data["depth_scale"]),
            **{k: float(data[k]) for k in OPTIONAL_KEYS if data.get(k) is not None},
        )
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{path}: non-numeric calibration value: {exc}") from exc


def tum_default_for(folder: Path) -> Calibration | None:
    """TUM default intrinsics when the folder name says freiburg1/2/3 (or fr1/fr2/fr3)."""
    name = folder.resolve().name.lower()
    m = re.search(r"(?:freiburg|fr)([123])", name)
    if m is None:
        return None
    return TUM_DEFAULTS[f"freiburg{m.group(1)}"]


def with_tum_distortion(calib: Calibration) -> Calibration:
    """``calib`` with what TUM's freiburg1 or freiburg2 camera is known to have, where its
    intrinsics are that camera's calibrated ones and it states none of it: TUM's published
    distortion (those intrinsics were estimated together with it; using them without it leaves
    the images' ~2% radial distortion in, which the rigid alignment of tracking partly explains
    by translation) and the camera's colour delay (:data:`TUM_COLOUR_DELAY_S`)."""
    for name, dist in TUM_DISTORTION.items():
        d = TUM_DEFAULTS[name]
        same = (calib.width, calib.height) == (d.width, d.height) and np.allclose(
            [calib.fx, calib.fy, calib.cx, calib.cy], [d.fx, d.fy, d.cx, d.cy], atol=0.05
        )
        if not same:
            continue
        values = calib.to_dict()
        if not calib.has_distortion:
            log.info("intrinsics of TUM's %s camera: undistorting with its published model", name)
            values.update(zip(DISTORTION_KEYS, dist))
        if calib.colour_delay_s is None and name in TUM_COLOUR_DELAY_S:
            values["colour_delay_s"] = TUM_COLOUR_DELAY_S[name]
        return Calibration(**values)
    return calib


def apply_overrides(calib: Calibration, overrides: dict[str, Any] | None) -> Calibration:
    """Replace calibration fields by non-null override values (from config or CLI)."""
    if not overrides:
        return calib
    values = calib.to_dict()
    for key, value in overrides.items():
        if value is None:
            continue
        if key not in values:
            raise CalibrationError(
                f"unknown calibration override {key!r}; expected one of {KEYS + OPTIONAL_KEYS}"
            )
        values[key] = value
    return Calibration(**values)


def from_overrides(overrides: dict[str, Any] | None) -> Calibration | None:
    """A calibration made of the overrides alone when they give every key (:data:`KEYS`), else
    ``None``: how a folder without ``calibration.yaml`` gets its intrinsics from the config."""
    given = {k: v for k, v in (overrides or {}).items() if v is not None}
    if any(k not in given for k in KEYS):
        return None
    unknown = sorted(set(given) - set(KEYS + OPTIONAL_KEYS))
    if unknown:
        raise CalibrationError(
            f"unknown calibration override {unknown[0]!r}; expected one of "
            f"{KEYS + OPTIONAL_KEYS}"
        )
    try:
        return Calibration(
            width=int(given["width"]),
            height=int(given["height"]),
            **{k: float(given[k]) for k in ("fx", "fy", "cx", "cy", "depth_scale")},
            **{k: float(given[k]) for k in OPTIONAL_KEYS if k in given},
        )
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"dataset.calibration: non-numeric value: {exc}") from exc


def missing_overrides(overrides: dict[str, Any] | None) -> list[str]:
    """The calibration keys the overrides do not give (null counts as not given)."""
    return [k for k in KEYS if (overrides or {}).get(k) is None]
