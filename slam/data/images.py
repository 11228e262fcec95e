"""Image decoding shared by the loaders. An image's header is read before it is decoded: a
frame declaring a size it must not have is refused without allocating its pixels."""

from __future__ import annotations

import os
import stat
import struct
from pathlib import Path

import cv2
import numpy as np

from slam.errors import FrameReadError, FrameSizeError

#: No image of an RGB-D sequence has more pixels than this (8K video is 33 MP); a header that
#: declares more is damaged or hostile, and decoding it could take gigabytes.
MAX_IMAGE_PIXELS = 40_000_000

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (they carry the image size): C0-CF but C4 (DHT), C8 (JPG), CC (DAC)
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def declared_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) an image's header declares, read without decoding: PNG (the IHDR chunk,
    bytes 16-24) and JPEG (the start-of-frame segment); ``None`` for other formats or a header
    too damaged to say (the decoder then reports it)."""
    if data[:8] == _PNG_SIGNATURE:
        if len(data) < 24 or data[12:16] != b"IHDR":
            return None
        width, height = struct.unpack(">II", data[16:24])
        return int(width), int(height)
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            i += 2
            continue
        if marker == 0xDA:  # start of scan before any frame header
            return None
        if marker in _JPEG_SOF:
            if i + 9 > len(data):
                return None
            height, width = struct.unpack(">HH", data[i + 5 : i + 9])
            return int(width), int(height)
        i += 2 + struct.unpack(">H", data[i + 2 : i + 4])[0]
    return None


def _check_declared_size(
    data: bytes, path: Path, index: int, what: str, expected: tuple[int, int] | None = None
) -> None:
    """Refuse an image whose header declares more than :data:`MAX_IMAGE_PIXELS` (a
    :class:`FrameReadError`), or a size other than ``expected`` (width, height; a
    :class:`FrameSizeError`), before decoding it."""
    size = declared_size(data)
    if size is None:
        return
    w, h = size
    if w * h > MAX_IMAGE_PIXELS:
        raise FrameReadError(
            f"frame {index}: {what} image {path} declares {w}x{h} pixels in its header "
            f"(more than {MAX_IMAGE_PIXELS // 1_000_000} million); not decoded: the file is "
            "damaged or not a frame of this sequence"
        )
    if expected is not None and (w, h) != tuple(expected):
        raise FrameSizeError(
            f"frame {index}: {what} image is {w}x{h} but the calibration says "
            f"{expected[0]}x{expected[1]} (declared in the header of {path}; not decoded); fix "
            "width/height (and fx, fy, cx, cy) in the sequence's calibration.yaml or in the "
            "config's dataset.calibration"
        )


#: the largest image file read (bytes): an uncompressed 3-channel image of MAX_IMAGE_PIXELS
#: with room for headers; anything larger is not a frame (a link to /dev/zero read 4.3 GB)
MAX_IMAGE_BYTES = 3 * MAX_IMAGE_PIXELS + 1_000_000


def _read_bytes(path: Path, index: int, what: str) -> bytes:
    """The file's bytes: a regular file (following links) of at most :data:`MAX_IMAGE_BYTES`;
    a device, a FIFO (a read that never ends) or a larger file is a FrameReadError."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # a FIFO must not block the open
    except OSError as exc:
        raise FrameReadError(f"frame {index}: cannot read {what} image {path}: {exc}") from exc
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise FrameReadError(
                f"frame {index}: {what} image {path} is not a regular file (a device, FIFO or "
                "socket): images must be files"
            )
        if st.st_size > MAX_IMAGE_BYTES:
            raise FrameReadError(
                f"frame {index}: {what} image {path} is {st.st_size} bytes, more than any frame "
                f"({MAX_IMAGE_BYTES}): damaged or not an image"
            )
        with os.fdopen(fd, "rb", closefd=True) as f:
            fd = -1
            return f.read(MAX_IMAGE_BYTES + 1)
    except OSError as exc:
        raise FrameReadError(f"frame {index}: cannot read {what} image {path}: {exc}") from exc
    finally:
        if fd >= 0:
            os.close(fd)


def read_color(path: Path, index: int) -> np.ndarray:
    """Read a colour image as HxWx3 uint8 RGB; raise FrameReadError naming file and frame.
    A truncated JPEG is an error too (OpenCV would decode its first part and grey the rest),
    so is a header declaring more than :data:`MAX_IMAGE_PIXELS` (refused before decoding)."""
    data = _read_bytes(path, index, "colour")
    _check_declared_size(data, path, index, "colour")
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
    path: Path,
    index: int,
    depth_scale: float,
    invalid_value: int | None = None,
    size: tuple[int, int] | None = None,
) -> np.ndarray:
    """Read a 16-bit depth PNG as float32 metres (0 = no depth). ``size``: the (width, height)
    the image must have (the calibration's): a header declaring another size is a
    :class:`FrameSizeError` before any pixel is decoded."""
    data = _read_bytes(path, index, "depth")
    _check_declared_size(data, path, index, "depth", size)
    raw = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
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
    depth[~(depth > 0) | ~np.isfinite(depth)] = 0.0  # NaN, inf, negative: no depth
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


#: a colour image whose width/height ratio differs from the depth's by more than this fraction
#: is not the same view at another resolution
ASPECT_TOLERANCE = 0.02


def fit_color(color: np.ndarray, depth_shape: tuple[int, ...]) -> tuple[np.ndarray, str | None]:
    """``color`` at the depth image's size (bilinear), and a warning when the resize cannot
    keep colour and depth registered: another width/height ratio (a 1x1 image stretched to
    640x480), or a colour image under a quarter of the depth's width (None otherwise)."""
    h, w = depth_shape[:2]
    ch, cw = color.shape[:2]
    if (ch, cw) == (h, w):
        return color, None
    warning = None
    if abs((cw / ch) / (w / h) - 1.0) > ASPECT_TOLERANCE or 4 * cw < w:
        warning = (
            f"its colour image is {cw}x{ch} and its depth image {w}x{h}: not the same view at "
            f"another resolution, so colour stretched to {w}x{h} does not line up with depth"
        )
    return cv2.resize(color, (w, h), interpolation=cv2.INTER_LINEAR), warning
