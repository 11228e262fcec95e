"""Synthetic bundle-adjustment problems with exact ground truth (tests and benchmarks).

A camera moves on a circle of radius 1 m inside a 5 x 4 x 2.6 m room, looking outwards and
slightly down, for one or more laps (later laps revisit the first: tracks span the loop); the
landmarks are random points on the room's walls, floor and ceiling. Each keyframe observes the
landmarks in its view (640x480, fx = fy = 525), with Gaussian pixel noise and depth noise
growing as z^2 (a structured-light sensor), optionally with a fraction of outliers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from slam.backend.ba_problem import BAProblem
from slam.geometry import exp_se3, inv_T, make_T
from slam.keyframe import SCALE_FACTOR

K_VGA = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
ROOM = np.array([[-2.5, -2.0, 0.0], [2.5, 2.0, 2.6]])


@dataclass
class SyntheticBA:
    """A problem plus its truth: ``poses_true``/``points_true`` (by keyframe id / landmark
    index), ``poses_init`` (perturbed), ``outlier`` (mask of corrupted observations)."""

    problem: BAProblem
    poses_true: dict[int, np.ndarray]
    points_true: np.ndarray
    poses_init: dict[int, np.ndarray]
    outlier: np.ndarray


def room_points(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` random points on the inner faces of the room box."""
    lo, hi = ROOM
    size = hi - lo
    areas = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]]) * 2
    face = rng.choice(6, size=n, p=np.repeat(areas / areas.sum(), 2) / 2)
    p = lo + rng.random((n, 3)) * size
    axis = face // 2
    side = face % 2
    p[np.arange(n), axis] = np.where(side == 0, lo[axis], hi[axis])
    return p


def circle_poses(n: int, laps: float = 1.0, radius: float = 1.0) -> list[np.ndarray]:
    """Camera poses (OpenCV camera, z forward) on a circle at 1.3 m height, looking outwards
    and 15 degrees down."""
    out = []
    for k in range(n):
        a = 2 * np.pi * laps * k / n
        forward = np.array([np.cos(a), np.sin(a), -np.tan(np.radians(15))])
        forward /= np.linalg.norm(forward)
        x = np.cross(forward, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(forward, x)
        R = np.stack([x, y, forward], axis=1)
        out.append(make_T(R, [radius * np.cos(a), radius * np.sin(a), 1.3]))
    return out


def perturb(T: np.ndarray, rng: np.random.Generator, trans_m: float, rot_deg: float) -> np.ndarray:
    """``T`` moved by a random translation of ``trans_m`` and rotation of ``rot_deg``."""
    t = rng.normal(size=3)
    w = rng.normal(size=3)
    xi = np.concatenate(
        [np.radians(rot_deg) * w / np.linalg.norm(w), trans_m * t / np.linalg.norm(t)]
    )
    return T @ exp_se3(xi)


def make_problem(
    n_keyframes: int = 20,
    n_points: int = 2000,
    laps: float = 1.0,
    max_observations: int = 300,
    pixel_sigma: float = 0.5,
    depth_sigma: float = 0.002,
    outlier_fraction: float = 0.0,
    pyramid_levels: int = 0,
    trans_m: float = 0.03,
    rot_deg: float = 2.0,
    seed: int = 0,
) -> SyntheticBA:
    """Keyframes on the circle (``laps`` laps), landmarks on the walls; each keyframe observes
    up to ``max_observations`` visible landmarks (depth 0.3-4 m) with pixel noise
    ``pixel_sigma`` and depth noise ``depth_sigma`` * z^2; ``outlier_fraction`` of the
    observations get a random pixel (and a depth off by up to 50%). With ``pyramid_levels``
    > 0 each observation is a keypoint of a random ORB pyramid level below it, its pixel noise
    ``pixel_sigma * SCALE_FACTOR**level`` (recorded in ``problem.level``). Initial poses: all
    but the first perturbed by ``trans_m`` / ``rot_deg``."""
    rng = np.random.default_rng(seed)
    points = room_points(n_points, rng)
    poses = circle_poses(n_keyframes, laps)
    kf_l, lm_l, uv_l, z_l, lv_l = [], [], [], [], []
    for k, T in enumerate(poses):
        pc = (points - T[:3, 3]) @ T[:3, :3]
        z = pc[:, 2]
        u = K_VGA[0, 0] * pc[:, 0] / np.maximum(z, 1e-6) + K_VGA[0, 2]
        v = K_VGA[1, 1] * pc[:, 1] / np.maximum(z, 1e-6) + K_VGA[1, 2]
        vis = np.flatnonzero((z > 0.3) & (z < 4.0) & (u > 0) & (u < 639) & (v > 0) & (v < 479))
        if len(vis) > max_observations:
            vis = rng.choice(vis, max_observations, replace=False)
        kf_l.append(np.full(len(vis), k))
        lm_l.append(vis)
        level = np.zeros(len(vis), np.int64)
        if pyramid_levels > 0:
            level = rng.integers(0, pyramid_levels, len(vis))
        sigma = pixel_sigma * SCALE_FACTOR ** level.astype(float)
        lv_l.append(level)
        noise = rng.normal(0, 1, (len(vis), 2)) * sigma[:, None]
        uv_l.append(np.stack([u[vis], v[vis]], 1) + noise)
        z_l.append(z[vis] + rng.normal(0, 1, len(vis)) * depth_sigma * z[vis] ** 2)
    kf = np.concatenate(kf_l)
    lm = np.concatenate(lm_l)
    uv = np.concatenate(uv_l)
    z = np.concatenate(z_l)
    lv = np.concatenate(lv_l)
    outlier = rng.random(len(kf)) < outlier_fraction
    n_out = int(outlier.sum())
    uv[outlier] = rng.random((n_out, 2)) * [640, 480]
    z[outlier] *= 1 + rng.uniform(-0.5, 0.5, n_out)
    # keep landmarks seen at least twice
    counts = np.bincount(lm, minlength=n_points)
    keep = counts[lm] >= 2
    kf, lm, uv, z, lv, outlier = kf[keep], lm[keep], uv[keep], z[keep], lv[keep], outlier[keep]
    ids, compact = np.unique(lm, return_inverse=True)
    problem = BAProblem(K_VGA.copy(), kf, np.arange(len(kf)), compact, ids, uv, z, lv)
    truth = {k: T for k, T in enumerate(poses)}
    init = {
        k: (T.copy() if k == 0 else perturb(T, rng, trans_m, rot_deg)) for k, T in truth.items()
    }
    return SyntheticBA(problem, truth, points[ids], init, outlier)


def pose_errors(
    est: dict[int, np.ndarray], truth: dict[int, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Per keyframe: translation error (m) and rotation error (deg) of ``est`` vs ``truth``."""
    keys = sorted(est)
    d = [inv_T(truth[k]) @ est[k] for k in keys]
    trans = np.array([np.linalg.norm(T[:3, 3]) for T in d])
    rot = np.array([np.degrees(Rotation.from_matrix(T[:3, :3]).magnitude()) for T in d])
    return trans, rot
