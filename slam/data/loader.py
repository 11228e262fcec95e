"""Layout detection: open any supported sequence folder."""

from __future__ import annotations

from pathlib import Path

from slam.data.base import Sequence
from slam.data.layouts import AUTO, LAYOUT_NAMES
from slam.data.sevenscenes import SevenScenesSequence, find_depth_files
from slam.data.tum import TumSequence
from slam.errors import DatasetError

#: The valid ``layout`` values (the table is :mod:`slam.data.layouts`).
LAYOUTS = LAYOUT_NAMES


def detect_layout(path: Path) -> str:
    """``tum`` when ``depth.txt`` is present, ``7scenes`` for frame-XXXXXX.depth.png files."""
    if (path / "depth.txt").is_file():
        return "tum"
    if find_depth_files(path):
        return "7scenes"
    raise DatasetError(
        f"{path}: unknown sequence layout; expected TUM RGB-D (rgb.txt, depth.txt, optional "
        "groundtruth.txt and calibration.yaml) or 7-Scenes (frame-XXXXXX.depth.png, "
        ".color.png/.jpg, .pose.txt, in the folder or in depth/ rgb/ pose/ sub-folders)"
    )


def open_sequence(
    path: str | Path, layout: str = "auto", calibration_overrides: dict | None = None
) -> Sequence:
    """Open a sequence folder; the layout is detected unless given. Errors before any work."""
    path = Path(path).expanduser()
    if path.is_file():
        raise DatasetError(
            f"{path} is a file, not a sequence folder: give the folder that holds rgb.txt and "
            "depth.txt (TUM RGB-D) or the frame-XXXXXX images (7-Scenes)"
        )
    if not path.is_dir():
        raise DatasetError(f"{path}: sequence folder not found")
    if layout not in LAYOUTS:
        raise DatasetError(f"unknown layout {layout!r}; expected one of {LAYOUTS}")
    if layout == AUTO:
        layout = detect_layout(path)
    if layout == "tum":
        return TumSequence(path, calibration_overrides)
    return SevenScenesSequence(path, calibration_overrides)
