"""Offline RGB-D SLAM: KinectFusion-style tracking and TSDF mapping with a loop-closure backend.

Quick use::

    import slam
    seq = slam.open_sequence("path/to/tum_sequence")
    result = slam.run(seq, slam.SlamConfig())
    print(result.metrics["ate_rmse_m"])

The public names below load on first use (``import slam`` itself loads no Open3D or GTSAM);
the layers behind them are described in docs/architecture.md.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

#: public name -> the module that defines it
_EXPORTS = {
    "Calibration": "slam.data.base",
    "Frame": "slam.data.base",
    "Sequence": "slam.data.base",
    "open_sequence": "slam.data.loader",
    "SlamConfig": "slam.config",
    "config_from_dict": "slam.config",
    "load_config": "slam.config",
    "CalibrationError": "slam.errors",
    "ConfigError": "slam.errors",
    "DatasetError": "slam.errors",
    "FrameReadError": "slam.errors",
    "RunFolderError": "slam.errors",
    "SlamError": "slam.errors",
    "TrackingError": "slam.errors",
    "TrajectoryError": "slam.errors",
    "RunResult": "slam.results",
    "run": "slam.pipeline",
    "save_run": "slam.run_folder.writer",
    "resume_run": "slam.api",
    "run_sequence": "slam.api",
    "Map": "slam.saved_map",
    "MapError": "slam.saved_map",
    "FrameResult": "slam.system",
    "Slam": "slam.system",
    "Trajectory": "slam.trajectory",
    "read_tum": "slam.trajectory",
    "write_tum": "slam.trajectory",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'slam' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # for type checkers and editors: the same names, imported eagerly
    from slam.api import resume_run, run_sequence
    from slam.config import SlamConfig, config_from_dict, load_config
    from slam.data.base import Calibration, Frame, Sequence
    from slam.data.loader import open_sequence
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
    from slam.pipeline import run
    from slam.results import RunResult
    from slam.run_folder.writer import save_run
    from slam.system import FrameResult, Slam
    from slam.trajectory import Trajectory, read_tum, write_tum
