"""Typed exceptions. Every error the library raises on purpose is a :class:`SlamError`."""

from __future__ import annotations


class SlamError(Exception):
    """Base class of all errors raised by the ``slam`` package."""


class ConfigError(SlamError):
    """A configuration file or value is invalid."""


class DatasetError(SlamError):
    """A sequence folder cannot be read: unknown layout, missing list, image or file."""


class CalibrationError(DatasetError):
    """Intrinsics or depth scale cannot be determined or are invalid."""


class FrameReadError(DatasetError):
    """A single frame cannot be decoded (corrupt or missing image). The pipeline skips it."""


class FrameSizeError(FrameReadError):
    """A frame's depth image does not have the calibration's size."""


class FrameError(SlamError):
    """A frame handed to the system is malformed: depth not an HxW array, colour of another
    size or type, a non-finite timestamp (a bad ``K`` is a :class:`CalibrationError`)."""


class TrajectoryError(SlamError):
    """A trajectory file is malformed or two trajectories cannot be associated."""


class TrackingError(SlamError):
    """Tracking could not estimate a pose."""


class RunFolderError(SlamError):
    """The run folder cannot be used: not a folder, not writable, holds another run, or has no
    complete run (no ``metrics.json``) where one is needed."""


class RunInterrupted(SlamError):
    """A run stopped by a signal (Ctrl-C: SIGINT, or SIGTERM) between two frames. Its message
    says where the state was saved and how to continue; ``signal_number`` is the signal."""

    def __init__(self, message: str, signal_number: int) -> None:
        super().__init__(message)
        self.signal_number = signal_number
