"""The frame and sequence types every loader returns."""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from slam.camera import check_intrinsics
from slam.errors import CalibrationError, FrameError, FrameSizeError
from slam.trajectory import Trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Calibration:
    """Pinhole intrinsics (pixels) and the depth scale (stored depth value / depth_scale = metres).

    ``k1 k2 p1 p2 k3``: lens distortion of the images (OpenCV's radial-tangential model), all 0
    when the images are already undistorted; loaders undistort frames that have it, so every
    frame the pipeline sees is pinhole with intrinsics ``K``. ``colour_delay_s``: how much
    later the colour camera took its images, relative to the depth camera, than their
    timestamps say (a sensor's timing, calibrated like its intrinsics; None: not stated, 0)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float = 5000.0
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    colour_delay_s: float | None = None

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError(f"image size must be positive, got {self.width}x{self.height}")
        values = self.to_dict()
        bad = [k for k, v in values.items() if not np.isfinite(v)]
        if bad:
            raise CalibrationError(
                "calibration values must be finite numbers, got "
                + ", ".join(f"{k}={values[k]}" for k in bad)
            )
        if self.fx <= 0 or self.fy <= 0:
            raise CalibrationError(f"focal lengths must be positive, got fx={self.fx} fy={self.fy}")
        if self.depth_scale <= 0:
            raise CalibrationError(f"depth_scale must be positive, got {self.depth_scale}")
        check_intrinsics(self.K, self.width, self.height, "calibration")
        if self.colour_delay_s is not None and abs(self.colour_delay_s) >= 0.1:
            raise CalibrationError(
                "colour_delay_s is a capture-timing offset of a few milliseconds (|value| < "
                f"0.1 s), got {self.colour_delay_s}"
            )

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distortion(self) -> np.ndarray:
        """OpenCV distortion coefficients ``(k1, k2, p1, p2, k3)``."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.distortion != 0.0))

    def to_dict(self) -> dict:
        return {
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "depth_scale": self.depth_scale,
            "k1": self.k1,
            "k2": self.k2,
            "p1": self.p1,
            "p2": self.p2,
            "k3": self.k3,
            **({} if self.colour_delay_s is None else {"colour_delay_s": self.colour_delay_s}),
        }


@dataclass
class Frame:
    """One RGB-D frame.

    ``color`` is HxWx3 uint8 RGB (or ``None`` for depth-only sequences); ``depth_m`` is HxW float32
    metres with 0 meaning no depth; ``K`` is the 3x3 intrinsic matrix of the depth image;
    ``color_dt_s``: when the colour image was captured, in seconds after the depth image (the
    frame's ``timestamp``); TUM RGB-D pairs images up to 20 ms apart, a moving camera took the
    two from different poses. A malformed frame (``K`` not a pinhole matrix for the image, depth not 2-D, colour of
    another size, a non-finite timestamp) is a :class:`FrameError` or :class:`CalibrationError`
    when it is made; :func:`checked_frame` repeats the check where frames enter the system.
    """

    index: int
    timestamp: float
    color: np.ndarray | None
    depth_m: np.ndarray
    K: np.ndarray
    color_dt_s: float = 0.0

    def __post_init__(self) -> None:
        where = f"frame {self.index}"
        depth = self.depth_m
        if not isinstance(depth, np.ndarray) or depth.ndim != 2 or depth.size == 0:
            shape = getattr(depth, "shape", type(depth).__name__)
            raise FrameError(f"{where}: depth_m must be an HxW array of metres, got {shape}")
        if depth.dtype.kind not in "fiu":
            raise FrameError(
                f"{where}: depth_m must be numeric (float32 metres), got {depth.dtype}"
            )
        if self.color is not None:
            c = self.color
            if not isinstance(c, np.ndarray) or c.shape != (*depth.shape, 3) or c.dtype != np.uint8:
                raise FrameError(
                    f"{where}: color must be None or an HxWx3 uint8 RGB array of the depth's "
                    f"size {depth.shape[1]}x{depth.shape[0]}, got "
                    f"{getattr(c, 'shape', type(c).__name__)} {getattr(c, 'dtype', '')}".rstrip()
                )
        try:
            stamp = float(self.timestamp)
        except (TypeError, ValueError):
            stamp = float("nan")
        if not np.isfinite(stamp):
            raise FrameError(
                f"{where}: timestamp must be a finite number of seconds, got {self.timestamp!r}"
            )
        if not np.isfinite(self.color_dt_s):
            raise FrameError(
                f"{where}: color_dt_s must be a finite number of seconds, got {self.color_dt_s!r}"
            )
        self.K = check_intrinsics(self.K, depth.shape[1], depth.shape[0], f"{where}: K")

    @property
    def height(self) -> int:
        return int(self.depth_m.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth_m.shape[1])


def checked_frame(frame: Frame) -> Frame:
    """``frame`` as the system takes it: checked again (a frame's fields can be replaced after
    it was made), depth as float32 with NaN, infinite and negative values set to 0 (no depth;
    a debug log says how many). The caller's arrays are not changed. Anything but a
    :class:`Frame` is a :class:`FrameError`."""
    if not isinstance(frame, Frame):
        raise FrameError(
            f"step() takes a slam.Frame(index, timestamp, color, depth_m, K), got "
            f"{type(frame).__name__}"
        )
    frame = replace(frame)  # runs the checks of Frame.__post_init__ on the current fields
    depth = frame.depth_m
    if depth.dtype != np.float32:
        depth = depth.astype(np.float32)
    bad = ~(depth >= 0) | ~np.isfinite(depth)  # NaN compares false
    if bad.any():
        log.debug(
            "frame %d: %d depth values NaN, infinite or negative set to 0 (no depth)",
            frame.index, int(bad.sum()),
        )  # fmt: skip
        depth = np.where(bad, np.float32(0.0), depth)
    if depth is not frame.depth_m:
        frame = replace(frame, depth_m=depth)
    return frame


class Sequence(ABC):
    """A recorded RGB-D sequence: ``len()``, indexing, iteration, calibration, optional ground truth.

    Indexing may raise :class:`slam.errors.FrameReadError` for a corrupt frame; iteration does too,
    so callers that want to skip bad frames index explicitly.
    """

    path: Path
    calibration: Calibration
    #: where the calibration came from, in words (a calibration.yaml, defaults, the config)
    calibration_source: str = "the loader's defaults"
    #: a colour image that cannot line up with depth was reported (once per sequence)
    _misfit_reported: bool = False

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def ground_truth(self) -> Trajectory | None:
        """Ground-truth trajectory (camera-to-world) when the sequence has one, for evaluation only."""
        return None

    @property
    def has_color(self) -> bool:
        return True

    @property
    def color_registered(self) -> bool:
        """Whether colour pixel (u, v) and depth pixel (u, v) see the same ray (depth registered
        to colour, as TUM RGB-D's). False for two unregistered cameras (7-Scenes): features
        lifted by depth are then only approximately placed (bundle adjustment weakens its depth
        term)."""
        return self.has_color

    @property
    def unpaired_images(self) -> dict[str, int]:
        """Images of the recording left out because they have no partner (by kind: ``rgb``,
        ``depth``): a depth image without a colour image near it in time is not a frame."""
        return {}

    def _fit_color(self, color: np.ndarray, depth: np.ndarray, index: int) -> np.ndarray:
        """``color`` at ``depth``'s size; a colour image that cannot line up with depth after
        the resize is reported once per sequence (:func:`~slam.data.images.fit_color`)."""
        from slam.data.images import fit_color

        color, warning = fit_color(color, depth.shape)
        if warning is not None and not self._misfit_reported:
            self._misfit_reported = True
            log.warning(
                "%s: frame %d: %s; check the folder's colour images (later frames like it "
                "are not reported)", self.path, index, warning,
            )  # fmt: skip
        return color

    @abstractmethod
    def __len__(self) -> int: ...

    @abstractmethod
    def timestamp(self, index: int) -> float:
        """Timestamp of frame ``index`` in seconds, without reading images."""

    @abstractmethod
    def _read(self, index: int) -> Frame: ...

    def __getitem__(self, index: int) -> Frame:
        n = len(self)
        if index < 0:
            index += n
        if not 0 <= index < n:
            raise IndexError(f"frame index {index} out of range for {n} frames")
        frame = self._read(index)
        c = self.calibration
        if frame.depth_m.shape != (c.height, c.width):
            h, w = frame.depth_m.shape[:2]
            raise FrameSizeError(
                f"frame {index}: depth image is {w}x{h} but the calibration says "
                f"{c.width}x{c.height}; fix width/height (and fx, fy, cx, cy) in the sequence's "
                "calibration.yaml or in the config's dataset.calibration"
            )
        return frame

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def timestamps(self) -> np.ndarray:
        return np.array([self.timestamp(i) for i in range(len(self))])
