"""Image decoding shared by the loaders."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from slam.errors import FrameReadError


def read_color(path: Path, index: int) -> np.ndarray:
    """Read a colour image as HxWx3 uint8 RGB; raise FrameReadError naming file and frame.
    A truncated JPEG is an error too (OpenCV would decode its first part and grey the rest)."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise FrameReadError(f"frame {index}: cannot read colour image {path}: {exc}") from exc
    if data[:2] == b"\xff\xd8" and b"\xff\xd9" not in data[-1024:]:
        raise FrameReadError(
            f"frame {index}: colour image {path} is a truncated JPEG (no end-of-image marker)"
        )
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) if data else None
    if img is None:
        raise FrameReadError(
            f"frame {index}: cannot decode colour image {path} (missing or corrupt)"
        )
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(
    path: Path, index: int, depth_scale: float, invalid_value: int | None = None
) -> np.ndarray:
    """Read a 16-bit depth PNG as float32 metres (0 = no depth)."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise FrameReadError(
            f"frame {index}: cannot decode depth image {path} (missing or corrupt)"
        )
    if raw.ndim != 2:
        raise FrameReadError(
            f"frame {index}: depth image {path} has shape {raw.shape}, expected a single channel"
        )
    if raw.dtype not in (np.uint16, np.float32):
        raise FrameReadError(
            f"frame {index}: depth image {path} has dtype {raw.dtype}, expected uint16 (or float32)"
        )
    if invalid_value is not None and raw.dtype == np.uint16:
        raw = np.where(raw == invalid_value, 0, raw)
    depth = raw.astype(np.float32) / np.float32(depth_scale)
    depth[~np.isfinite(depth)] = 0.0
    return depth


class Undistorter:
    """Resamples frames of a camera with lens distortion onto the pinhole image of the same
    intrinsics ``K`` (OpenCV's radial-tangential model): depth by nearest neighbour (no depth is
    invented between surfaces), colour bilinearly. The maps are built once."""

    def __init__(self, K: np.ndarray, distortion: np.ndarray, width: int, height: int) -> None:
        self.map_x, self.map_y = cv2.initUndistortRectifyMap(
            np.asarray(K, np.float64),
            np.asarray(distortion, np.float64),
            None,
            np.asarray(K, np.float64),
            (int(width), int(height)),
            cv2.CV_32FC1,
        )

    def depth(self, depth_m: np.ndarray) -> np.ndarray:
        return cv2.remap(depth_m, self.map_x, self.map_y, cv2.INTER_NEAREST)

    def color(self, color: np.ndarray) -> np.ndarray:
        return cv2.remap(color, self.map_x, self.map_y, cv2.INTER_LINEAR)
