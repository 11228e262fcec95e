"""The camera: intrinsics ``K`` (3x3, pixel-centre convention), projection of camera-frame points
to pixels, back-projection of depth to points, intrinsics of a resized image, and the depth
sensor's axial noise (:class:`DepthNoise`). Shared by tracking, mapping, loop verification and
bundle adjustment."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.errors import CalibrationError


@dataclass(frozen=True)
class DepthNoise:
    """Axial depth noise ``sigma(z) = sigma0_m + quadratic * (z - z0_m)^2`` in metres: a
    structured-light sensor's (Nguyen, Izadi, Lovell 2012, Kinect v1): tracking weighs depth's
    information by it (the constraint analysis) and scales its overlap checks."""

    sigma0_m: float = 0.0012
    quadratic: float = 0.0019
    z0_m: float = 0.4

    def sigma(self, z: np.ndarray) -> np.ndarray:
        z = np.asarray(z, np.float32)
        return np.float32(self.sigma0_m) + np.float32(self.quadratic) * (
            z - np.float32(self.z0_m)
        ) ** 2


def backproject(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Vertex map HxWx3 in the camera frame: ``v = depth * K^-1 [u, v, 1]``; zero where no depth."""
    h, w = depth_m.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = (np.arange(w, dtype=np.float32) - cx) / fx
    v = (np.arange(h, dtype=np.float32) - cy) / fy
    z = depth_m.astype(np.float32)
    return np.stack([z * u[None, :], z * v[:, None], z], axis=-1)


def project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) of camera-frame points (N, 3) with z > 0."""
    z = points[:, 2]
    return np.stack(
        [K[0, 0] * points[:, 0] / z + K[0, 2], K[1, 1] * points[:, 1] / z + K[1, 2]], axis=-1
    )


def scale_intrinsics(K: np.ndarray, factor: float) -> np.ndarray:
    """Intrinsics of an image resized by 1/factor (pixel-centre convention)."""
    if factor == 1:
        return K.copy()
    Ks = K.astype(float).copy()
    Ks[0, 0] /= factor
    Ks[1, 1] /= factor
    Ks[0, 2] = (K[0, 2] + 0.5) / factor - 0.5
    Ks[1, 2] = (K[1, 2] + 0.5) / factor - 0.5
    return Ks


#: The fields of view a pinhole depth camera can have (degrees, along either image axis): a
#: focal length outside gives a matrix no sensor has, and K's inverse overflows near 0.
MIN_FOV_DEG = 1.0
MAX_FOV_DEG = 170.0


def check_intrinsics(K: object, width: int, height: int, where: str = "K") -> np.ndarray:
    """``K`` as a float 3x3 array when it is a pinhole intrinsic matrix for a ``width`` x
    ``height`` image: finite, ``fx, fy > 0``, no skew, last row ``0 0 1``, principal point
    inside the image. Otherwise a :class:`~slam.errors.CalibrationError` that names ``where``,
    the value seen and the expected form."""
    form = "[[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels"
    try:
        arr = np.array(K, dtype=float)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(
            f"{where}: not a numeric 3x3 matrix ({exc}); expected {form}"
        ) from exc
    if arr.shape != (3, 3):
        raise CalibrationError(
            f"{where}: intrinsic matrix of shape {arr.shape}, expected 3x3 {form}"
        )
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{where}: non-finite entries in {arr.tolist()}; expected {form}")
    fx, fy, cx, cy = arr[0, 0], arr[1, 1], arr[0, 2], arr[1, 2]
    if fx <= 0 or fy <= 0:
        raise CalibrationError(
            f"{where}: focal lengths must be positive, got fx={fx:g} fy={fy:g}; expected {form}"
        )
    for f, size, axis in ((fx, width, "fx"), (fy, height, "fy")):
        fov_deg = float(np.degrees(2.0 * np.arctan(size / (2.0 * f))))
        if not MIN_FOV_DEG <= fov_deg <= MAX_FOV_DEG:
            raise CalibrationError(
                f"{where}: {axis}={f:g} px gives a field of view of {fov_deg:.3g} degrees across "
                f"{size} px; a pinhole depth camera's is between {MIN_FOV_DEG:g} and "
                f"{MAX_FOV_DEG:g} degrees: are the focal lengths in pixels, for this image size?"
            )
    if not np.array_equal(arr[2], [0.0, 0.0, 1.0]) or arr[0, 1] != 0 or arr[1, 0] != 0:
        raise CalibrationError(
            f"{where}: expected {form} (no skew, last row [0, 0, 1]), got {arr.tolist()}"
        )
    if not (-0.5 <= cx <= width - 0.5 and -0.5 <= cy <= height - 0.5):
        raise CalibrationError(
            f"{where}: principal point (cx={cx:g}, cy={cy:g}) lies outside the {width}x{height} "
            "image; cx and cy are pixel coordinates (about width/2 and height/2)"
        )
    return arr
