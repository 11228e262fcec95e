"""The synthetic camera path: a smooth loop around the room looking at its furniture."""

from __future__ import annotations

import logging

import numpy as np

from slam.synthetic.config import FPS, SynthConfig
from slam.synthetic.handheld import hand_motion
from slam.synthetic.kinds import kind_poses
from slam.synthetic.shapes import look_rotation, poses_from
from slam.trajectory import Trajectory

log = logging.getLogger(__name__)

#: Seconds into the recorded hand's motion (``SynthConfig.handheld``) per seed.
HANDHELD_START_S = 7.0

# ------------------------------------------------------------------------------------------------
# trajectory


def make_trajectory(cfg: SynthConfig) -> Trajectory:
    """Smooth hand-held-like camera path inside the room, ``T_world_cam``, timestamps ``i / 30``.

    The camera circles an ellipse (semi-axes 0.8 x 0.6 m) around the room centre at ~1.35 m
    height, looking outwards and ~20 deg down at the furniture along the walls, with sinusoidal
    wobble of speed, height, yaw, pitch and roll (phases from the seed). ``loop=True``: one full
    closed turn (infinitely smooth, the pose after the last frame is the first one again).
    ``loop=False``: an open 0.55-turn sweep. Other scene kinds follow their own paths
    (:func:`slam.synthetic.kinds.kind_poses`); ``cfg.handheld`` adds a recorded hand's motion
    (:func:`slam.synthetic.handheld.hand_motion`) to any of them.
    """
    cfg.validate()
    n = int(cfg.frames)
    t = np.arange(n) / FPS
    poses = kind_poses(cfg) if cfg.scene != "room" else _room_poses(cfg)
    if cfg.handheld:  # the recorded hand's motion, in the camera frame
        hand = hand_motion(cfg.handheld, t, HANDHELD_START_S * int(cfg.seed))
        poses = np.einsum("nij,njk->nik", poses, hand)
    return Trajectory(t, poses)


def _room_poses(cfg: SynthConfig) -> np.ndarray:
    """(frames, 4, 4) ``T_world_cam`` of the furnished room's loop (see :func:`make_trajectory`)."""
    n = int(cfg.frames)
    rng = np.random.default_rng([int(cfg.seed), 0x7A7])
    ph = rng.uniform(0, 2 * np.pi, 8)
    amp = rng.uniform(0.7, 1.0, 6)
    turns = (1.0 if cfg.loop else 0.55) * float(cfg.speed)
    s = np.arange(n) / n * turns  # fraction of a full turn
    th0 = rng.uniform(0, 2 * np.pi)  # starting angle on the ellipse
    w = 2 * np.pi * s
    theta = th0 + w + 0.10 * amp[0] * (np.sin(2 * w + ph[0]) - np.sin(ph[0]))
    x = 0.8 * np.cos(theta) + 0.06 * amp[1] * np.sin(3 * w + ph[1])
    y = 0.6 * np.sin(theta) + 0.06 * amp[2] * np.cos(2 * w + ph[2])
    z = 1.35 + 0.08 * amp[3] * np.sin(2 * w + ph[3]) + 0.03 * np.sin(5 * w + ph[4])
    yaw = theta + 0.15 * amp[4] * np.sin(2 * w + ph[5])
    pitch = np.radians(-20.0 + 4.0 * amp[5] * np.sin(3 * w + ph[6]))
    roll = np.radians(3.0 * np.sin(2 * w + ph[7]) + 1.0 * np.sin(5 * w + ph[0]))
    forward = np.stack(
        [np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)], axis=1
    )
    return poses_from(np.stack([x, y, z], axis=1), look_rotation(forward, roll))
