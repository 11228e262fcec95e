"""Offline RGB-D SLAM: KinectFusion-style tracking and TSDF mapping with a loop-closure backend.

Quick use::

    import slam
    seq = slam.open_sequence("path/to/tum_sequence")
    result = slam.run(seq, slam.SlamConfig())
    print(result.metrics["ate_rmse_m"])
"""

from slam.api import resume_run, run_sequence
from slam.config import SlamConfig, config_from_dict, load_config
from slam.data import Calibration, Frame, Sequence, open_sequence
from slam.errors import (
    CalibrationError,
    ConfigError,
    DatasetError,
    FrameReadError,
    RunFolderError,
    SlamError,
    TrackingError,
    TrajectoryError,
)
from slam.pipeline import RunResult, run
from slam.run_folder.writer import save_run
from slam.system import FrameResult, Slam
from slam.trajectory import Trajectory, read_tum, write_tum

__version__ = "0.1.0"

__all__ = [
    "Calibration",
    "CalibrationError",
    "ConfigError",
    "DatasetError",
    "Frame",
    "FrameReadError",
    "FrameResult",
    "RunFolderError",
    "RunResult",
    "Slam",
    "Sequence",
    "SlamConfig",
    "SlamError",
    "TrackingError",
    "Trajectory",
    "TrajectoryError",
    "config_from_dict",
    "load_config",
    "open_sequence",
    "read_tum",
    "resume_run",
    "run",
    "run_sequence",
    "save_run",
    "write_tum",
]
