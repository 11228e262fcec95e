"""Scene kinds that stress tracking, besides the furnished ``room`` of the demo (the scene
matrix, ``benchmarks/matrix.py``, runs each with several seeds and two speeds):

- ``wall``: a bare 6.4 x 5.2 x 2.8 m room with textured walls and two flat posters; the camera
  circles 1 m around a point off-centre looking outwards, panning at 40 deg/s (times
  ``speed``), so one flat textured wall 1.3-2.8 m away fills most of the view: depth alone lets
  ICP slide along it, texture does not.
- ``corridor``: a 30 m long, 2 m wide, 2.5 m high textured corridor; the camera walks along it
  at 0.6 m/s (times ``speed``) looking left and right (+-35 deg). No geometry constrains the
  translation along the corridor (its ends are out of range).
- ``hall``: a 16 x 12 x 5 m hall whose walls are 4-8 m away, with six pillars and a few crates
  2-5 m away; the camera pans like in ``wall``. The sensor range is 8 m (a Kinect's far range:
  depth noise grows as z^2, ~10 cm quantisation steps at 6 m).
- ``desk``: a desk with a monitor, books, a mug, a ball and boxes in the middle of a bare room;
  the camera orbits it 0.6-1 m away at 30 deg/s (times ``speed``), looking at the desk.

``speed`` scales every rate of a path (2 gives 60-90 deg/s pans: the fast rows of the matrix).
Paths are defined by rates, not by the number of frames: more frames is a longer recording.
Every path wobbles smoothly in height, pitch and roll, with phases from the seed, like a hand-
held camera.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from slam.synthetic.config import FPS, SynthConfig
from slam.synthetic.shapes import Layout, box, cylinder, look_rotation, poses_from, sphere

#: Sensor range (metres) of each kind; kinds not listed use the room's 4 m.
SENSOR_MAX_DEPTH_M = {"corridor": 8.0, "hall": 8.0}


def _rng(seed: int, salt: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), salt])


def _poster(L: Layout, rng, name: str, axis: int, at: float, u0, u1, z0, z1) -> None:
    """A flat 1 cm poster on a wall normal to ``axis`` (0: x, 1: y) at coordinate ``at``."""
    inward = -0.01 if at > 0 else 0.01
    lo, hi = [0.0, 0.0, z0], [0.0, 0.0, z1]
    lo[axis], hi[axis] = min(at, at + inward), max(at, at + inward)
    lo[1 - axis], hi[1 - axis] = u0, u1
    L.add(name, box(lo, hi), rng)


@lru_cache(maxsize=8)
def kind_layout(kind: str, seed: int) -> Layout:
    """The objects of a scene kind (not ``room``), textures drawn from ``seed``."""
    rng = _rng(seed, 0x5CE7E)
    L = Layout()
    if kind == "wall":
        L.add_room([-3.2, -2.6, 0.0], [3.2, 2.6, 2.8], rng)
        _poster(L, rng, "poster_x", 0, 3.2, -0.8, 0.4, 1.1, 1.9)
        _poster(L, rng, "poster_y", 1, -2.6, -1.5, -0.5, 1.0, 1.7)
    elif kind == "corridor":
        L.add_room([-15.0, -1.0, 0.0], [15.0, 1.0, 2.5], rng)
    elif kind == "hall":
        L.add_room([-8.0, -6.0, 0.0], [8.0, 6.0, 5.0], rng)
        for i, (x, y) in enumerate([(3, 2.5), (-3, 2.5), (3, -2.5), (-3, -2.5), (0, 4), (0, -4)]):
            L.add(f"pillar{i}", box([x - 0.3, y - 0.3, 0.0], [x + 0.3, y + 0.3, 5.0]), rng)
        L.add("crate0", box([4.5, -0.8, 0.0], [5.3, 0.2, 0.9]), rng)
        L.add("crate1", box([-5.2, 0.5, 0.0], [-4.4, 1.3, 1.2]), rng)
        L.add("crate2", box([1.0, 4.6, 0.0], [2.2, 5.4, 0.7]), rng)
    elif kind == "desk":
        L.add_room([-2.5, -2.0, 0.0], [2.5, 2.0, 2.6], rng)
        L.add("desk_top", box([-0.6, -0.35, 0.72], [0.6, 0.35, 0.75]), rng)
        for i, (x, y) in enumerate([(-0.57, -0.32), (0.54, -0.32), (-0.57, 0.29), (0.54, 0.29)]):
            L.add(f"desk_leg{i}", box([x, y, 0.0], [x + 0.03, y + 0.03, 0.72]), rng)
        L.add("monitor", box([-0.25, 0.15, 0.9], [0.25, 0.18, 1.2]), rng)
        L.add("monitor_stand", cylinder([0.0, 0.17], 0.75, 0.025, 0.15), rng)
        L.add("keyboard", box([-0.2, -0.15, 0.75], [0.2, -0.02, 0.77]), rng)
        L.add("books", box([-0.55, -0.3, 0.75], [-0.33, -0.02, 0.85]), rng)
        L.add("book_top", box([-0.52, -0.25, 0.85], [-0.36, -0.05, 0.88]), rng)
        L.add("mug", cylinder([0.35, -0.15], 0.75, 0.04, 0.1), rng)
        L.add("ball", sphere([0.45, 0.12, 0.82], 0.07), rng)
        L.add("box", box([0.28, -0.32, 0.75], [0.5, -0.22, 0.9]), rng)
        L.add("lamp", cylinder([-0.45, 0.2], 0.75, 0.015, 0.35), rng)
    else:
        raise ValueError(f"no layout for scene kind {kind!r}")
    return L


def kind_poses(cfg: SynthConfig) -> np.ndarray:
    """(frames, 4, 4) ``T_world_cam`` of a scene kind's camera path (see the module doc)."""
    n = int(cfg.frames)
    t = np.arange(n) / FPS
    rng = _rng(cfg.seed, 0x7A7)
    ph = rng.uniform(0, 2 * np.pi, 6)
    s = float(cfg.speed)
    wob_z = 0.04 * np.sin(1.3 * t + ph[0]) + 0.015 * np.sin(3.1 * t + ph[1])
    wob_pitch = np.radians(3.0 * np.sin(0.9 * t + ph[2]))
    roll = np.radians(2.0 * np.sin(1.1 * t + ph[3]) + 0.7 * np.sin(2.9 * t + ph[4]))
    start = rng.uniform(0, 2 * np.pi)
    if cfg.scene in ("wall", "hall"):
        centre = np.array([0.6, 0.3]) if cfg.scene == "wall" else np.array([0.5, -0.5])
        radius = 1.0 if cfg.scene == "wall" else 0.6
        theta = start + np.radians(40.0 * s) * t + 0.05 * np.sin(2.0 * t + ph[5])
        xy = centre + radius * np.stack([np.cos(theta), np.sin(theta)], 1)
        yaw = theta + 0.1 * np.sin(1.7 * t + ph[5])
        pitch = np.radians(-8.0) + wob_pitch
        z = 1.4 + wob_z
    elif cfg.scene == "corridor":
        x = -6.0 + 0.6 * s * t
        xy = np.stack([x, 0.25 * np.sin(0.5 * s * t + ph[5])], 1)
        yaw = np.radians(35.0) * np.sin(2 * np.pi * s * t / 6.0 + start)
        pitch = np.radians(-5.0) + wob_pitch
        z = 1.45 + wob_z
    elif cfg.scene == "desk":
        theta = start + np.radians(30.0 * s) * t
        radius = 0.7 + 0.12 * np.sin(0.8 * t + ph[5])
        xy = radius[:, None] * np.stack([np.cos(theta), np.sin(theta)], 1)
        z = 1.2 + wob_z
        target = np.array([0.0, 0.0, 0.8])
        d = np.stack([target[0] - xy[:, 0], target[1] - xy[:, 1], target[2] - z], 1)
        yaw = np.arctan2(d[:, 1], d[:, 0]) + 0.08 * np.sin(1.9 * t + ph[4])
        pitch = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])) + wob_pitch
    else:
        raise ValueError(f"no camera path for scene kind {cfg.scene!r}")
    forward = np.stack(
        [np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)], axis=1
    )
    position = np.column_stack([xy, z])
    return poses_from(position, look_rotation(forward, roll))
