"""Dataset loaders: TUM RGB-D layout, 7-Scenes layout, (the synthetic generator is slam.synthetic)."""

from slam.data.base import Calibration, Frame, Sequence
from slam.data.loader import detect_layout, open_sequence
from slam.data.sevenscenes import SevenScenesSequence
from slam.data.tum import TumSequence

__all__ = [
    "Calibration",
    "Frame",
    "Sequence",
    "SevenScenesSequence",
    "TumSequence",
    "detect_layout",
    "open_sequence",
]
