"""Synthetic RGB-D sequences with exact ground truth (the demo, unit tests, the scene matrix),
and test tooling: damaged copies of recordings (:mod:`slam.synthetic.damage`) and a synthetic
bundle-adjustment problem (:mod:`slam.synthetic.ba_problem`).

Deterministic synthetic RGB-D sequences with exact ground truth, rendered by Open3D raycasting.

The scene is an indoor room (about 5 x 4 x 2.6 m, world frame z up, floor at z = 0, room centred
on x = y = 0) furnished with boxes, cylinders and spheres. Every surface carries a procedural,
high-contrast texture that is a function of the 3D hit point (tri-planar lookup into a periodic
texture atlas generated once per seed), so it is consistent across views and rich in ORB corners.

Camera convention: OpenCV camera frame (x right, y down, z forward); poses are ``T_world_cam``
(camera-to-world). Pixel ``(u, v)`` (column, row) is the ray through ``K^-1 [u, v, 1]``, so the
usual back-projection ``z * K^-1 [u, v, 1]`` of a rendered depth lands exactly on the surface.

Typical use::

    cfg = SynthConfig(frames=300, seed=0)
    path = generate_sequence("/tmp/synth", cfg)   # TUM RGB-D layout + scene.ply + .complete

or, in memory::

    scene = build_scene(cfg)          # (make_scene(cfg) returns its mesh only)
    traj = make_trajectory(cfg)
    color, depth_m = render_frame(scene, traj.poses[0], cfg, np.random.default_rng(0))

Modules: ``config`` (parameters, sensor constants), ``scene`` (layout, texture), ``render``
(ray casting + sensor noise), ``trajectory`` (camera path), ``writer`` (files on disk).
"""

from slam.synthetic.config import COLOR_NOISE_SIGMA, FPS, SynthConfig
from slam.synthetic.render import SynthScene, build_scene, render_frame
from slam.synthetic.scene import alias_clusters, make_scene
from slam.synthetic.trajectory import make_trajectory
from slam.synthetic.writer import generate_sequence, is_complete

__all__ = [
    "COLOR_NOISE_SIGMA",
    "FPS",
    "SynthConfig",
    "SynthScene",
    "alias_clusters",
    "build_scene",
    "generate_sequence",
    "is_complete",
    "make_scene",
    "make_trajectory",
    "render_frame",
]
