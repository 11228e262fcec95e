"""Dataset loaders: TUM RGB-D layout and 7-Scenes layout (the synthetic generator is slam.synthetic).

The names below are imported when first used, so ``slam.data.layouts`` (the table of layouts)
can be read without loading the image decoders."""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from slam.data.base import Calibration, Frame, Sequence
    from slam.data.loader import detect_layout, open_sequence
    from slam.data.sevenscenes import SevenScenesSequence
    from slam.data.tum import TumSequence

_WHERE = {
    "Calibration": "slam.data.base",
    "Frame": "slam.data.base",
    "Sequence": "slam.data.base",
    "SevenScenesSequence": "slam.data.sevenscenes",
    "TumSequence": "slam.data.tum",
    "detect_layout": "slam.data.loader",
    "open_sequence": "slam.data.loader",
}

__all__ = [
    "Calibration",
    "Frame",
    "Sequence",
    "SevenScenesSequence",
    "TumSequence",
    "detect_layout",
    "open_sequence",
]


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        value = getattr(import_module(_WHERE[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
