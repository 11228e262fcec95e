"""SE(3) helpers. Convention: 4x4 homogeneous matrices, ``T_a_b`` maps points in frame b to frame a.

Camera poses are ``T_world_cam`` (camera-to-world). Quaternions are ``(qx, qy, qz, qw)`` as in TUM.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build a 4x4 transform from a 3x3 rotation and a translation vector."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (or a stack of them, shape (..., 4, 4))."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points of shape (..., 3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def pose_to_tum(T: np.ndarray) -> np.ndarray:
    """4x4 pose -> ``[tx, ty, tz, qx, qy, qz, qw]`` (scalar-last quaternion, qw >= 0)."""
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    if q[3] < 0:
        q = -q
    return np.concatenate([T[:3, 3], q])


def tum_to_pose(v: np.ndarray) -> np.ndarray:
    """``[tx, ty, tz, qx, qy, qz, qw]`` -> 4x4 pose. The quaternion is normalised."""
    v = np.asarray(v, dtype=float)
    q = v[3:7] / np.linalg.norm(v[3:7])
    return make_T(Rotation.from_quat(q).as_matrix(), v[:3])


# Rodrigues' formulas in closed form: scipy's Rotation takes 50-150 us a call, which tracking
# (a few dozen exp/log a frame) felt as ~2% of its time


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """Exponential map: twist ``[wx, wy, wz, vx, vy, vz]`` (rotation first) -> 4x4 transform."""
    xi = np.asarray(xi, dtype=float)
    w, v = xi[:3], xi[3:]
    theta = float(np.sqrt(w @ w))
    W = skew(w)
    WW = W @ W
    if theta < 1e-2:  # series expansions avoid cancellation near zero (terms to theta^4)
        t2 = theta**2
        s = 1.0 - t2 / 6.0 + t2**2 / 120.0  # sin(theta) / theta
        a = 0.5 - t2 / 24.0 + t2**2 / 720.0
        b = 1.0 / 6.0 - t2 / 120.0 + t2**2 / 5040.0
    else:
        s = np.sin(theta) / theta
        a, b = (1 - np.cos(theta)) / theta**2, (theta - np.sin(theta)) / theta**3
    T = np.eye(4)
    T[:3, :3] += s * W + a * WW
    T[:3, 3] = (np.eye(3) + a * W + b * WW) @ v
    return T


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis times angle, radians) of a 3x3 rotation matrix."""
    R = np.asarray(R, dtype=float)
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    if c < -0.99:  # near half a turn the antisymmetric part vanishes: the quaternion route
        return Rotation.from_matrix(R).as_rotvec()
    s = 0.5 * float(np.sqrt(axis @ axis))  # sin(theta)
    theta = float(np.arctan2(s, c))
    if theta < 1e-4:  # theta / sin(theta) by its series
        return 0.5 * (1.0 + theta**2 / 6.0) * axis
    return 0.5 * theta / s * axis


def log_se3(T: np.ndarray) -> np.ndarray:
    """Logarithm map, inverse of :func:`exp_se3`: 4x4 transform -> twist (rotation first)."""
    w = log_so3(T[:3, :3])
    theta = float(np.sqrt(w @ w))
    W = skew(w)
    if theta < 1e-2:  # the closed form cancels to ~1e-8 relative error at theta = 1e-4
        t2 = theta**2
        a = 1.0 / 12.0 + t2 / 720.0 + t2**2 / 30240.0
    else:
        a = (1 - theta / 2 * np.sin(theta) / (1 - np.cos(theta))) / theta**2
    V_inv = np.eye(3) - 0.5 * W + a * (W @ W)
    return np.concatenate([w, V_inv @ T[:3, 3]])


def skew(v: np.ndarray) -> np.ndarray:
    """3x3 cross-product matrix of a 3-vector."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rotation_angle_deg(T: np.ndarray) -> float:
    """Angle of the rotation part of a transform, in degrees."""
    R = T[:3, :3]
    # atan2 form: accurate for small angles even when R is not exactly orthonormal
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arctan2(s, c)))


def translation_norm(T: np.ndarray) -> float:
    """Length of the translation part of a transform."""
    return float(np.linalg.norm(T[:3, 3]))


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """Nearest rigid transform (rotation re-projected onto SO(3) by SVD)."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return make_T(R, T[:3, 3])
