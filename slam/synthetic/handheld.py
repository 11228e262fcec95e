"""Recorded hand-held camera motion for the synthetic camera paths (``SynthConfig.handheld``).

A real hand does not move a camera along a smooth curve: it jerks, shakes and turns in bursts,
and those accelerations are what a constant-velocity prediction and the checks built on it
meet. The folder ``handheld/`` holds motion-capture ground truth of TUM RGB-D's hand-held
``freiburg1`` recordings (Kinect v1 held by a person; CC BY 4.0, Sturm et al. IROS 2012),
resampled at 30 Hz by ``datasets/handheld_trajectories.py``.

A scene kind's path is designed to cover its scene (a wall panned, a corridor walked, a desk
circled); a recording's path covers the room it was made in, and replayed whole in another
scene it would leave it or face nothing. So the recording lends its *hand*: its motion around
its own smoothed path (:data:`SMOOTH_S`), every acceleration, jerk and fast turn above about
half a hertz as recorded, is applied in the camera frame on top of the kind's path. A constant
velocity prediction then departs from the synthetic camera as it did from the recorded one
(tests/synthetic/test_handheld.py).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from slam.errors import ConfigError
from slam.geometry import inv_T

#: The recordings, one TUM file each (``timestamp tx ty tz qx qy qz qw``, 30 Hz from 0 s).
HANDHELD_DIR = Path(__file__).resolve().parent / "handheld"
RECORDINGS = tuple(sorted(p.stem for p in HANDHELD_DIR.glob("*.txt")))

#: Gaussian sigma (s) of the smoothing that separates the recording's slow path (left to the
#: scene kind) from the hand's motion around it (applied). At 0.6 s the synthetic camera's
#: departures from constant velocity are the recording's (median and 99th percentile within
#: 10%, rotation and translation; 0.3 s kept only 80-85% of the translation's), for a hand that
#: strays up to 8-18 cm and 12-24 degrees from the kind's path.
SMOOTH_S = 0.6


@lru_cache(maxsize=8)
def recording(name: str) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (s, from 0) and (N, 4, 4) ``T_world_cam`` of a recording in :data:`RECORDINGS`."""
    if name not in RECORDINGS:
        raise ConfigError(f"SynthConfig.handheld must be one of {RECORDINGS}, got {name!r}")
    data = np.loadtxt(HANDHELD_DIR / f"{name}.txt", comments="#", ndmin=2)
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(data[:, 4:8]).as_matrix()
    poses[:, :3, 3] = data[:, 1:4]
    return data[:, 0], poses


def smoothed(poses: np.ndarray, sigma_frames: float) -> np.ndarray:
    """The path smoothed by a Gaussian of ``sigma_frames``: positions filtered, rotations as
    sign-continuous quaternions filtered and normalised (a faithful mean for the few degrees a
    hand turns within the window)."""
    out = poses.copy()
    out[:, :3, 3] = gaussian_filter1d(poses[:, :3, 3], sigma_frames, axis=0, mode="nearest")
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    flip = np.cumprod(np.where(np.sum(q[1:] * q[:-1], axis=1) < 0, -1.0, 1.0))
    q[1:] *= flip[:, None]
    q = gaussian_filter1d(q, sigma_frames, axis=0, mode="nearest")
    out[:, :3, :3] = Rotation.from_quat(q / np.linalg.norm(q, axis=1, keepdims=True)).as_matrix()
    return out


def hand_motion(name: str, t_s: np.ndarray, start_s: float = 0.0) -> np.ndarray:
    """(len(t_s), 4, 4): the recording's camera relative to its own smoothed path,
    ``S(t)^-1 R(t)``, at times ``t_s`` from ``start_s`` into it (played backwards from its
    end: a path longer than the recording turns round there, as a hand does)."""
    stamps, poses = recording(name)
    dt = float(stamps[-1] - stamps[0]) / (len(stamps) - 1)
    hand = np.einsum("nij,njk->nik", inv_T(smoothed(poses, SMOOTH_S / dt)), poses)
    index = np.round((np.asarray(t_s, float) + start_s) / dt).astype(int) % (2 * len(hand) - 2)
    return hand[np.where(index < len(hand), index, 2 * len(hand) - 2 - index)]
