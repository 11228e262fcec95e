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


class TrajectoryError(SlamError):
    """A trajectory file is malformed or two trajectories cannot be associated."""


class TrackingError(SlamError):
    """Tracking could not estimate a pose."""


class RunFolderError(SlamError):
    """The run folder cannot be used: not a folder, not writable, holds another run, or has no
    complete run (no ``metrics.json``) where one is needed."""
