"""Offline RGB-D SLAM: KinectFusion-style tracking and TSDF mapping with a loop-closure backend."""

from slam.errors import (
    CalibrationError,
    ConfigError,
    DatasetError,
    FrameReadError,
    SlamError,
    TrackingError,
    TrajectoryError,
)

__version__ = "0.1.0"

__all__ = [
    "CalibrationError",
    "ConfigError",
    "DatasetError",
    "FrameReadError",
    "SlamError",
    "TrackingError",
    "TrajectoryError",
]
