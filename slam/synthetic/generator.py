"""Deterministic synthetic RGB-D sequences with exact ground truth, rendered by Open3D raycasting.

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
"""

from __future__ import annotations

import json
import logging
import os
import re
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from slam.data.base import Calibration
from slam.errors import ConfigError, DatasetError
from slam.trajectory import Trajectory, atomic_write_text, write_tum

log = logging.getLogger(__name__)

# ------------------------------------------------------------------------------------------------
# constants

#: Room extent in metres (world frame): x in [-2.5, 2.5], y in [-2, 2], z in [0, 2.6].
ROOM_MIN = np.array([-2.5, -2.0, 0.0])
ROOM_MAX = np.array([2.5, 2.0, 2.6])

FPS = 30.0

#: Depth sensor working range (metres); outside it the sensor returns no depth (always applied).
MIN_DEPTH = 0.3
MAX_DEPTH = 4.0

#: Kinect-v1-like disparity quantisation: baseline 7.5 cm, IR focal length 580 px, 1/8 sub-pixel
#: disparity steps (depth step ~3 mm at 1 m, ~12 mm at 2 m, ~46 mm at 4 m), independent of the
#: rendered image size (it models the native sensor).
KINECT_BASELINE = 0.075
KINECT_FOCAL = 580.0
DISPARITY_SUBPIXEL = 8.0

#: Dropout model (noise=True).
GRAZING_COS = 0.2  # no depth where |cos(angle between ray and surface normal)| < this
EDGE_JUMP = 0.05  # metres; neighbouring depth discontinuity counted as an edge
RANDOM_DROPOUT = 0.01
COLOR_NOISE_SIGMA = 2.0  # grey levels

#: Texture atlas: TEX_SIZE x TEX_SIZE texels, TEX_RES metres per texel (period 6.1 m).
TEX_SIZE = 2048
TEX_RES = 0.003

#: Fixed directional lights (applied to object-local normals, so cloned objects shade alike).
_LIGHTS = (
    (np.array([0.3, 0.5, 1.0]) / np.linalg.norm([0.3, 0.5, 1.0]), 0.45),
    (np.array([-0.6, -0.2, 0.4]) / np.linalg.norm([-0.6, -0.2, 0.4]), 0.25),
)
_AMBIENT = 0.35


@dataclass
class SynthConfig:
    """Parameters of a synthetic sequence. Everything is deterministic for a given ``seed``.

    ``loop``: the camera path is a closed loop (the last frames revisit the first pose) when true,
    an open sweep that never comes back to its start otherwise. ``noise``: Kinect-like depth noise,
    quantisation and dropouts plus colour pixel noise; with ``noise=False`` depth is exact (still
    limited to the sensor range 0.3-4.0 m). ``alias``: the scene contains the same textured
    furniture cluster twice (on opposite walls) to fool place recognition. ``drift_bias``: a
    systematic depth distortion for loop-closure experiments, as uncalibrated Kinects have
    (Herrera et al. 2012, Teichman et al. 2013): depth grows by the factor
    ``1 + drift_bias * r^2`` with ``r^2 = x_n^2 + y_n^2`` the squared normalised image radius
    (0 at the centre, ~0.6 at the corners of a 525 px focal length VGA image). Every frame
    then disagrees slightly with the model built from other viewpoints, so odometry drifts
    steadily; ground truth stays exact. Motion speeds are tuned for ``frames`` around 300 (the path
    is parameterised over the sequence, so fewer frames means faster motion).
    """

    frames: int = 300
    loop: bool = True
    seed: int = 0
    width: int = 640
    height: int = 480
    fx: float = 525.0
    fy: float = 525.0
    cx: float = 319.5
    cy: float = 239.5
    depth_scale: float = 5000.0
    noise: bool = True
    alias: bool = False
    drift_bias: float = 0.0
    render_frames: int | None = None  # render only the first N frames of the trajectory

    @classmethod
    def half_resolution(cls, **overrides) -> SynthConfig:
        """The default camera at 320x240 (focal lengths halved, principal point on the pixel-
        centre convention): a quarter of the pixels, for quick tests and sweeps."""
        d = cls()
        cam = dict(
            width=d.width // 2,
            height=d.height // 2,
            fx=d.fx / 2,
            fy=d.fy / 2,
            cx=(d.cx + 0.5) / 2 - 0.5,
            cy=(d.cy + 0.5) / 2 - 0.5,
        )
        return cls(**{**cam, **overrides})

    def calibration(self) -> Calibration:
        """The :class:`Calibration` of the rendered images (validates the intrinsics)."""
        return Calibration(
            self.width, self.height, self.fx, self.fy, self.cx, self.cy, self.depth_scale
        )

    def validate(self) -> None:
        """Raise :class:`ConfigError` / :class:`CalibrationError` on unusable values."""
        if int(self.frames) < 1:
            raise ConfigError(f"SynthConfig.frames must be >= 1, got {self.frames}")
        self.calibration()


# ------------------------------------------------------------------------------------------------
# scene layout


@dataclass
class _TexParams:
    """Per-object texture parameters: 6 per-face (axis, sign) atlas offsets and a 2-colour palette."""

    offsets: np.ndarray  # (6, 2) texels
    palette: np.ndarray  # (2, 3) RGB in [0, 1]


@dataclass
class _Layout:
    vertices: list[np.ndarray] = field(default_factory=list)  # world frame, per object
    triangles: list[np.ndarray] = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    tex: list[_TexParams] = field(default_factory=list)
    group: list[int] = field(default_factory=list)  # -1: textured in world frame
    group_T_local_world: list[np.ndarray] = field(default_factory=list)


def _rand_tex(rng: np.random.Generator) -> _TexParams:
    offsets = rng.uniform(0.0, TEX_SIZE, size=(6, 2))
    # two related but distinct colours, moderately saturated
    base = rng.uniform(0.35, 1.0, size=3)
    other = np.clip(base + rng.uniform(-0.45, 0.45, size=3), 0.25, 1.0)
    return _TexParams(offsets.astype(np.float32), np.stack([base, other]).astype(np.float32))


def _box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    m = o3d.geometry.TriangleMesh.create_box(*(hi - lo))
    return np.asarray(m.vertices) + lo, np.asarray(m.triangles).copy()


def _cylinder(center_xy, z0, radius, height, resolution=32) -> tuple[np.ndarray, np.ndarray]:
    split = max(1, int(np.ceil(height / 0.1)))  # avoid very skinny side triangles
    m = o3d.geometry.TriangleMesh.create_cylinder(
        radius, height, resolution=resolution, split=split
    )
    v = np.asarray(m.vertices) + np.array([center_xy[0], center_xy[1], z0 + height / 2.0])
    return v, np.asarray(m.triangles).copy()


def _sphere(center, radius, resolution=20) -> tuple[np.ndarray, np.ndarray]:
    m = o3d.geometry.TriangleMesh.create_sphere(radius, resolution=resolution)
    return np.asarray(m.vertices) + np.asarray(center, float), np.asarray(m.triangles).copy()


def _Rz(deg: float) -> np.ndarray:
    return Rotation.from_euler("z", deg, degrees=True).as_matrix()


def _cluster_parts() -> list[tuple[str, tuple[np.ndarray, np.ndarray]]]:
    """The furniture cluster that is cloned when ``alias=True``, in its local frame.

    Local frame: origin on the floor at the wall, +x pointing into the room, y along the wall.
    """
    return [
        ("cluster_cabinet", _box([0.005, -0.45, 0.0], [0.48, 0.45, 0.85])),
        ("cluster_drawer1", _box([0.48, -0.40, 0.48], [0.50, 0.40, 0.78])),
        ("cluster_drawer2", _box([0.48, -0.40, 0.08], [0.50, 0.40, 0.40])),
        ("cluster_box", _box([0.08, -0.38, 0.85], [0.36, -0.08, 1.07])),
        ("cluster_can", _cylinder([0.25, 0.22], 0.85, 0.08, 0.28)),
        ("cluster_ball", _sphere([0.30, 0.02, 0.93], 0.08)),
        ("cluster_poster", _box([0.003, -0.40, 1.25], [0.02, 0.40, 1.80])),
    ]


@lru_cache(maxsize=8)
def _layout(seed: int, alias: bool) -> _Layout:
    """All scene objects (world-frame triangle soups) with their texture parameters."""
    rng = np.random.default_rng([int(seed), 0x5CE7E])
    L = _Layout()

    def add(
        name: str, vt: tuple[np.ndarray, np.ndarray], tex: _TexParams | None = None, group: int = -1
    ) -> None:
        L.vertices.append(np.asarray(vt[0], float))
        L.triangles.append(np.asarray(vt[1], np.int64))
        L.names.append(name)
        L.tex.append(tex if tex is not None else _rand_tex(rng))
        L.group.append(group)

    # room: an inward-facing box (triangle winding flipped so normals point inside)
    rv, rt = _box(ROOM_MIN, ROOM_MAX)
    add("room", (rv, rt[:, ::-1]))

    # --- wall +x (x = 2.5): cluster A (always present) and a table
    # --- wall -x (x = -2.5): cluster B (alias: identical clone of A; else a sofa)
    cluster = _cluster_parts()
    cluster_rng = np.random.default_rng([int(seed), 0xC1A5])
    cluster_tex = [_rand_tex(cluster_rng) for _ in cluster]
    placements = [(np.array([2.5, 0.85, 0.0]), 180.0)]
    if alias:
        placements.append((np.array([-2.5, -0.55, 0.0]), 0.0))
    for gi, (t, yaw) in enumerate(placements):
        R = _Rz(yaw)
        T_world_local = np.eye(4)
        T_world_local[:3, :3] = R
        T_world_local[:3, 3] = t
        L.group_T_local_world.append(np.linalg.inv(T_world_local))
        for (name, (v, tri)), tex in zip(cluster, cluster_tex):
            add(f"{name}_{gi}", (v @ R.T + t, tri), tex=tex, group=gi)
    if not alias:
        add("sofa_seat", _box([-2.495, -1.35, 0.0], [-1.75, 0.25, 0.45]))
        add("sofa_back", _box([-2.495, -1.35, 0.45], [-2.25, 0.25, 0.9]))
        add("sofa_arm1", _box([-2.495, -1.55, 0.0], [-1.75, -1.35, 0.62]))
        add("sofa_arm2", _box([-2.495, 0.25, 0.0], [-1.75, 0.45, 0.62]))
        add("cushion", _box([-2.2, -0.9, 0.45], [-2.05, -0.5, 0.75]))

    # table near wall +x
    add("table_top", _box([1.75, -1.45, 0.72], [2.45, -0.25, 0.76]))
    for i, (x, y) in enumerate([(1.78, -1.42), (2.37, -1.42), (1.78, -0.33), (2.37, -0.33)]):
        add(f"table_leg{i}", _box([x, y, 0.0], [x + 0.05, y + 0.05, 0.72]))
    add("table_sphere", _sphere([2.05, -1.15, 0.88], 0.12))
    add("table_box", _box([1.9, -0.75, 0.76], [2.2, -0.45, 0.95]))
    add("table_can", _cylinder([2.3, -1.25], 0.76, 0.05, 0.22))

    # wall +y (y = 2): bookshelf, cabinet, picture frame
    sx0, sx1, sy0, sy1 = 0.4, 1.45, 1.6, 1.995
    add("shelf_side1", _box([sx0, sy0, 0.0], [sx0 + 0.03, sy1, 1.8]))
    add("shelf_side2", _box([sx1 - 0.03, sy0, 0.0], [sx1, sy1, 1.8]))
    add("shelf_back", _box([sx0 + 0.03, sy1 - 0.02, 0.0], [sx1 - 0.03, sy1, 1.8]))
    for k, z in enumerate([0.0, 0.45, 0.9, 1.35, 1.77]):
        add(f"shelf_board{k}", _box([sx0 + 0.03, sy0, z], [sx1 - 0.03, sy1 - 0.02, z + 0.03]))
    book_rng = np.random.default_rng([int(seed), 0xB00C])
    for k, z in enumerate([0.03, 0.48, 0.93, 1.38]):
        x = sx0 + 0.05
        while True:
            w = float(book_rng.uniform(0.03, 0.09))
            if x + w > sx1 - 0.06:
                break
            h = float(book_rng.uniform(0.2, 0.38))
            d = float(book_rng.uniform(0.18, 0.3))
            if book_rng.random() < 0.8:
                add(f"book{k}_{x:.2f}", _box([x, sy1 - 0.02 - d, z], [x + w, sy1 - 0.02, z + h]))
            x += w + 0.005
    add("cabinet", _box([-1.65, 1.5, 0.0], [-0.75, 1.995, 1.1]))
    add("cabinet_door1", _box([-1.6, 1.485, 0.1], [-1.22, 1.5, 1.0]))
    add("cabinet_door2", _box([-1.18, 1.485, 0.1], [-0.8, 1.5, 1.0]))
    add("cabinet_vase", _cylinder([-1.0, 1.75], 1.1, 0.09, 0.3))
    add("frame", _box([-0.45, 1.97, 1.15], [0.15, 1.997, 1.75]))
    add("box_stack1", _box([1.8, 1.45, 0.0], [2.45, 1.95, 0.5]))
    add("box_stack2", _box([1.9, 1.55, 0.5], [2.35, 1.9, 0.85]))

    # wall -x: plant (pot + foliage sphere)
    add("plant_pot", _cylinder([-2.15, 1.35], 0.0, 0.17, 0.38))
    add("plant_ball", _sphere([-2.15, 1.35, 0.62], 0.27))
    add("plant_poster", _box([-2.497, 0.6, 1.2], [-2.48, 1.5, 1.85]))

    # wall -y (y = -2): desk with monitor, chair, bin, lamp
    add("desk_top", _box([-0.2, -1.995, 0.72], [1.2, -1.4, 0.76]))
    add("desk_drawers", _box([0.75, -1.95, 0.0], [1.15, -1.45, 0.72]))
    add("desk_leg1", _box([-0.18, -1.95, 0.0], [-0.13, -1.45, 0.72]))
    add("desk_leg2", _box([0.7, -1.95, 0.0], [0.75, -1.45, 0.72]))
    add("monitor", _box([0.15, -1.9, 0.92], [0.75, -1.85, 1.27]))
    add("monitor_stand", _cylinder([0.45, -1.86], 0.76, 0.03, 0.17))
    add("keyboard", _box([0.2, -1.7, 0.76], [0.65, -1.55, 0.785]))
    add("chair_seat", _box([0.05, -1.35, 0.42], [0.5, -0.9, 0.47]))
    add("chair_back", _box([0.05, -0.95, 0.47], [0.5, -0.9, 0.95]))
    add("chair_post", _cylinder([0.275, -1.125], 0.0, 0.03, 0.42))
    add("bin", _cylinder([-0.7, -1.75], 0.0, 0.15, 0.4))
    add("lamp_pole", _cylinder([-1.9, -1.6], 0.0, 0.02, 1.55))
    add("lamp_shade", _cylinder([-1.9, -1.6], 1.55, 0.18, 0.25))
    add("lamp_base", _cylinder([-1.9, -1.6], 0.0, 0.15, 0.03))
    add("crate", _box([-1.55, -1.95, 0.0], [-1.05, -1.5, 0.45]))
    add("wall_panel", _box([-1.4, -1.997, 1.2], [-0.6, -1.98, 1.7]))
    return L


def make_scene(cfg: SynthConfig) -> o3d.geometry.TriangleMesh:
    """Legacy triangle mesh of the true scene surface (world frame, metres).

    ``triangle_material_ids`` holds each triangle's object index (used by :func:`render_frame`).
    """
    L = _layout(int(cfg.seed), bool(cfg.alias))
    verts, tris, ids = [], [], []
    n = 0
    for k, (v, t) in enumerate(zip(L.vertices, L.triangles)):
        verts.append(v)
        tris.append(t + n)
        ids.append(np.full(len(t), k, np.int32))
        n += len(v)
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.concatenate(verts)),
        o3d.utility.Vector3iVector(np.concatenate(tris).astype(np.int32)),
    )
    mesh.triangle_material_ids = o3d.utility.IntVector(np.concatenate(ids))
    mesh.compute_triangle_normals()
    return mesh


def alias_clusters(cfg: SynthConfig) -> list[np.ndarray]:
    """``T_world_cluster`` of each copy of the clonable furniture cluster (2 with ``alias``, else 1).

    The copies are identical in shape and texture in their local frames, so a camera pose
    ``T_world_cam`` looking at copy 0 sees the same image of the cluster as the pose
    ``clusters[1] @ inv(clusters[0]) @ T_world_cam`` looking at copy 1.
    """
    L = _layout(int(cfg.seed), bool(cfg.alias))
    return [np.linalg.inv(T) for T in L.group_T_local_world]


# ------------------------------------------------------------------------------------------------
# texture


def _upsample_periodic(grid: np.ndarray, cell: int, size: int) -> np.ndarray:
    """Smoothly upsample a periodic (n, n) grid by ``cell`` to (size, size), seamless when tiled."""
    pad = 2
    g = np.pad(grid, pad, mode="wrap")
    up = cv2.resize(g, (g.shape[1] * cell, g.shape[0] * cell), interpolation=cv2.INTER_CUBIC)
    return up[pad * cell : pad * cell + size, pad * cell : pad * cell + size]


@lru_cache(maxsize=4)
def _texture(seed: int) -> np.ndarray:
    """Periodic texture atlas (TEX_SIZE, TEX_SIZE, 2) uint8: channel 0 luminance, 1 colour mix."""
    rng = np.random.default_rng([int(seed), 0x7E7])
    N = TEX_SIZE
    lum = np.zeros((N, N), np.float32)
    for cell, amp in ((256, 0.30), (64, 0.30), (16, 0.25), (4, 0.15)):
        g = rng.random((N // cell, N // cell), dtype=np.float32)
        lum += amp * _upsample_periodic(g, cell, N)
    lum = (lum - lum.min()) / max(float(lum.max() - lum.min()), 1e-6)
    lum_u8 = np.ascontiguousarray(np.clip(60 + 140 * lum, 0, 255).astype(np.uint8))
    mix = np.zeros((N, N), np.float32)
    for cell, amp in ((128, 0.6), (32, 0.4)):
        mix += amp * _upsample_periodic(
            rng.random((N // cell, N // cell), dtype=np.float32), cell, N
        )
    mix_u8 = np.ascontiguousarray(np.clip(255 * mix, 0, 255).astype(np.uint8))

    def level() -> tuple[int, int]:
        lv = int(rng.integers(10, 60)) if rng.random() < 0.5 else int(rng.integers(195, 250))
        return lv, int(rng.integers(0, 256))

    # high-contrast shapes (corners for FAST/ORB); sizes 3-25 cm
    area_m2 = (N * TEX_RES) ** 2
    n_shapes = int(60 * area_m2)
    for _ in range(n_shapes):  # loop over shapes drawn into the atlas once, not over pixels
        kind = rng.integers(0, 4)
        cx, cy = rng.uniform(0, N, 2)
        r = float(np.exp(rng.uniform(np.log(5), np.log(40))))
        lv, mv = level()
        if kind == 0:
            c = (int(cx), int(cy))
            cv2.circle(lum_u8, c, int(r), lv, -1, cv2.LINE_AA)
            cv2.circle(mix_u8, c, int(r), mv, -1, cv2.LINE_AA)
        else:
            nv = 3 if kind == 1 else 4
            ang = rng.uniform(0, 2 * np.pi) + np.arange(nv) * 2 * np.pi / nv
            ang = ang + rng.uniform(-0.3, 0.3, nv)
            rr = r * rng.uniform(0.6, 1.3, nv)
            pts = np.stack([cx + rr * np.cos(ang), cy + rr * np.sin(ang)], 1)
            pts = np.round(pts * 16).astype(np.int32)  # 4 bits of sub-pixel precision
            cv2.fillConvexPoly(lum_u8, pts, lv, cv2.LINE_AA, 4)
            cv2.fillConvexPoly(mix_u8, pts, mv, cv2.LINE_AA, 4)
    # checkerboard and stripe patches (vectorised per patch)
    n_patches = int(3 * area_m2)
    for _ in range(n_patches):
        h, w = (int(v) for v in rng.integers(50, 160, 2))
        y0, x0 = int(rng.integers(0, N - h)), int(rng.integers(0, N - w))
        yy, xx = np.mgrid[0:h, 0:w]
        period = int(rng.integers(6, 20))
        if rng.random() < 0.5:
            pattern = ((yy // period + xx // period) % 2).astype(bool)
        else:
            a = rng.uniform(0, np.pi)
            pattern = ((xx * np.cos(a) + yy * np.sin(a)) // period % 2).astype(bool)
        lo, hi = int(rng.integers(10, 70)), int(rng.integers(185, 250))
        lum_u8[y0 : y0 + h, x0 : x0 + w] = np.where(pattern, hi, lo).astype(np.uint8)
        mix_u8[y0 : y0 + h, x0 : x0 + w] = int(rng.integers(0, 256))
    # slight blur: limits aliasing when the texture is seen from far away
    tex = np.dstack([lum_u8, mix_u8])
    return cv2.GaussianBlur(tex, (3, 3), 0.6)


# ------------------------------------------------------------------------------------------------
# rendering


class SynthScene:
    """Everything :func:`render_frame` needs: mesh, raycasting scene, per-object tables, texture."""

    def __init__(self, mesh: o3d.geometry.TriangleMesh, cfg: SynthConfig):
        layout = _layout(int(cfg.seed), bool(cfg.alias))
        n_obj = len(layout.names)
        tri_obj = np.asarray(mesh.triangle_material_ids, dtype=np.int32)
        n_tri = len(mesh.triangles)
        if len(tri_obj) != n_tri or (n_tri and (tri_obj.min() < 0 or tri_obj.max() >= n_obj)):
            raise ConfigError(
                "render_frame: the mesh does not come from make_scene() with this config "
                f"(seed={cfg.seed}, alias={cfg.alias})"
            )
        self.mesh = mesh
        self.seed = int(cfg.seed)
        self.alias = bool(cfg.alias)
        # extra "object" n_obj for rays that hit nothing
        self.tri_obj = np.append(tri_obj, n_obj).astype(np.int32)
        self.n_tri = n_tri
        self.obj_group = np.append(np.asarray(layout.group, np.int32), -1)
        self.group_T = [np.asarray(T, np.float32) for T in layout.group_T_local_world]
        self.offsets = np.concatenate(
            [np.stack([t.offsets for t in layout.tex]), np.zeros((1, 6, 2), np.float32)]
        ).reshape(-1, 2)  # (n_obj+1)*6 rows, indexed obj*6 + face
        self.albedo_lut = _albedo_lut(self.seed, self.alias)
        self.texture = _texture(self.seed)
        self.raycaster = o3d.t.geometry.RaycastingScene()
        self.raycaster.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))


def build_scene(cfg: SynthConfig) -> SynthScene:
    """Build the renderable scene (mesh from :func:`make_scene` plus textures and raycaster)."""
    return SynthScene(make_scene(cfg), cfg)


_scene_cache: OrderedDict[int, SynthScene] = OrderedDict()


def _as_synth_scene(scene, cfg: SynthConfig) -> SynthScene:
    if isinstance(scene, SynthScene):
        if scene.seed != int(cfg.seed) or scene.alias != bool(cfg.alias):
            raise ConfigError("render_frame: scene was built with a different seed/alias")
        return scene
    if isinstance(scene, o3d.geometry.TriangleMesh):
        key = id(scene)
        cached = _scene_cache.get(key)
        # the cache entry keeps the mesh alive, so its id cannot be reused while cached
        if (
            cached is None
            or cached.mesh is not scene
            or cached.seed != int(cfg.seed)
            or (cached.alias != bool(cfg.alias))
        ):
            cached = SynthScene(scene, cfg)
            _scene_cache[key] = cached
            while len(_scene_cache) > 2:
                _scene_cache.popitem(last=False)
        return cached
    raise TypeError(
        f"render_frame: expected SynthScene or TriangleMesh, got {type(scene).__name__}"
    )


@dataclass(frozen=True)
class _CameraRays:
    d_cam: np.ndarray  # (N, 1, 3) float32 camera-frame ray directions with z = 1
    xn: np.ndarray  # (N,) float32 (u - cx) / fx
    yn: np.ndarray  # (N,) float32 (v - cy) / fy
    inv_len: np.ndarray  # (N,) float32 1 / |d_cam|


@lru_cache(maxsize=8)
def _camera_rays(w: int, h: int, fx: float, fy: float, cx: float, cy: float) -> _CameraRays:
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    xn = ((u - cx) / fx).reshape(-1)
    yn = ((v - cy) / fy).reshape(-1)
    d = np.stack([xn, yn, np.ones_like(xn)], axis=-1).astype(np.float32).reshape(-1, 1, 3)
    inv_len = 1.0 / np.sqrt(xn**2 + yn**2 + 1.0)
    return _CameraRays(d, xn.astype(np.float32), yn.astype(np.float32), inv_len.astype(np.float32))


@lru_cache(maxsize=8)
def _albedo_lut(seed: int, alias: bool) -> np.ndarray:
    """((n_obj + 1) * 256, 3) float32: albedo of object k at colour-mix level m is row k*256+m."""
    layout = _layout(seed, alias)
    pal = np.concatenate(
        [np.stack([t.palette for t in layout.tex]), np.zeros((1, 2, 3), np.float32)]
    )  # (n_obj+1, 2, 3); the extra object (ray miss) is black
    m = (np.arange(256, dtype=np.float32) / 255.0)[None, :, None]
    lut = pal[:, :1, :] + (pal[:, 1:, :] - pal[:, :1, :]) * m
    return np.ascontiguousarray(lut.reshape(-1, 3), dtype=np.float32)


def render_frame(
    scene: SynthScene | o3d.geometry.TriangleMesh,
    T_world_cam: np.ndarray,
    cfg: SynthConfig,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Render one RGB-D frame from camera pose ``T_world_cam`` (camera-to-world, OpenCV axes).

    ``scene`` is a :class:`SynthScene` (fast) or the mesh returned by :func:`make_scene` for the
    same ``cfg`` (its renderer is built and cached on first use). ``rng`` drives the noise (only
    used when ``cfg.noise``; default ``np.random.default_rng(cfg.seed)``).

    Returns ``(color, depth_m)``: HxWx3 uint8 RGB and HxW float32 metres, 0 = no depth.
    """
    cfg.validate()
    sc = _as_synth_scene(scene, cfg)
    W, H = int(cfg.width), int(cfg.height)
    N = W * H
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"render_frame: T_world_cam must be a finite 4x4 matrix, got {T.shape}")
    cam = _camera_rays(W, H, float(cfg.fx), float(cfg.fy), float(cfg.cx), float(cfg.cy))
    R = np.ascontiguousarray(T[:3, :3], dtype=np.float32)
    origin = T[:3, 3].astype(np.float32)
    d_world = cv2.transform(cam.d_cam, R)  # (N, 1, 3)
    rays = cv2.merge([np.full((N, 1, 3), origin, np.float32), d_world.reshape(N, 1, 3)])
    rays = rays.reshape(N, 6)
    ans = sc.raycaster.cast_rays(o3d.core.Tensor.from_numpy(rays))
    t_hit = ans["t_hit"].numpy()  # = z depth, since camera-frame directions have z = 1
    prim = ans["primitive_ids"].numpy()
    normal = ans["primitive_normals"].numpy().reshape(N, 1, 3)  # world frame
    hit = np.isfinite(t_hit)
    z = np.where(hit, t_hit, np.float32(0.0))
    obj = np.take(sc.tri_obj, np.where(hit, prim, sc.n_tri))

    # --- hit points and normals in each object's texture frame (world, or its cluster's frame)
    pc = cv2.merge([cam.xn * z, cam.yn * z, z]).reshape(N, 1, 3)  # camera-frame points
    p = cv2.transform(pc, T[:3, :].astype(np.float32))
    n = normal
    if sc.group_T:
        grp = np.take(sc.obj_group, obj)
        for g, Tg in enumerate(sc.group_T):
            m = grp == g
            if m.any():
                m3 = m[:, None, None]
                Tl = (Tg.astype(np.float64) @ T)[:3, :].astype(np.float32)
                p = np.where(m3, cv2.transform(pc, Tl), p)
                n = np.where(m3, cv2.transform(normal, Tg[:3, :3]), n)
    px, py, pz = cv2.split(p)
    nx, ny, nz = cv2.split(n)
    px, py, pz, nx, ny, nz = (a.reshape(-1) for a in (px, py, pz, nx, ny, nz))

    # --- tri-planar texture lookup: project on the plane of the dominant local normal axis
    ax, ay, az = np.abs(nx), np.abs(ny), np.abs(nz)
    along_x = (ax >= ay) & (ax >= az)
    along_z = (az > ax) & (az > ay)
    axis = np.where(along_x, 0, np.where(along_z, 2, 1))
    positive = np.where(along_x, nx, np.where(along_z, nz, ny)) > 0
    face = obj * 6 + axis * 2 + positive
    tu = np.where(along_x, py, px)
    tv = np.where(along_z, py, pz)
    scale = np.float32(1.0 / TEX_RES)
    # no explicit modulo: BORDER_WRAP wraps any coordinate, and |coordinate| < TEX_SIZE + room
    # size / TEX_RES stays far inside remap's int16 fixed-point range
    mapx = tu * scale + np.take(sc.offsets[:, 0], face)
    mapy = tv * scale + np.take(sc.offsets[:, 1], face)
    tex = cv2.remap(
        sc.texture,
        mapx.reshape(H, W),
        mapy.reshape(H, W),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_WRAP,
    ).reshape(N, 2)

    # --- shading (Lambertian, fixed lights, object-local normals) and albedo palette
    shade = np.full(N, _AMBIENT, np.float32)
    for ldir, w in _LIGHTS:
        lx, ly, lz = (np.float32(w * c) for c in ldir)
        shade += np.abs(nx * lx + ny * ly + nz * lz)
    lum = tex[:, 0] * shade
    lut_index: np.ndarray = obj * 256 + tex[:, 1].astype(np.int32)
    albedo = np.take(sc.albedo_lut, lut_index, axis=0)
    color = np.multiply(albedo, lum[:, None], out=albedo).reshape(H, W, 3)

    if cfg.drift_bias:
        r2 = cam.xn * cam.xn + cam.yn * cam.yn
        z = z * (np.float32(1.0) + np.float32(cfg.drift_bias) * r2)
    if cfg.noise:
        if rng is None:
            rng = np.random.default_rng(int(cfg.seed))
        # |cos| between ray and surface normal (world frame), for grazing-angle dropouts
        ray_dot = cv2.transform(normal * d_world, np.ones((1, 3), np.float32)).reshape(-1)
        cosang = np.abs(ray_dot) * cam.inv_len
        depth = _noisy_depth(z.reshape(H, W), hit.reshape(H, W), cosang.reshape(H, W), cfg, rng)
        # grey (channel-correlated) Gaussian pixel noise
        noise = rng.standard_normal((H, W, 1), dtype=np.float32) * np.float32(COLOR_NOISE_SIGMA)
        color += noise
    else:
        depth = z.reshape(H, W)
    depth = np.where((depth >= MIN_DEPTH) & (depth <= MAX_DEPTH), depth, np.float32(0.0))
    color_u8 = cv2.convertScaleAbs(np.maximum(color, 0.0, out=color))  # rounds and saturates
    return color_u8, depth.astype(np.float32, copy=False)


def _noisy_depth(
    z: np.ndarray,
    hit: np.ndarray,
    cosang: np.ndarray,
    cfg: SynthConfig,
    rng: np.random.Generator,
) -> np.ndarray:
    """Kinect-like depth: axial Gaussian noise, disparity quantisation and dropouts."""
    H, W = z.shape
    grazing = cosang < GRAZING_COS

    # depth edges: neighbouring discontinuity > EDGE_JUMP (misses count as far), dilated 1 px
    zc = np.where(hit, z, np.float32(100.0))
    jump_x = np.abs(np.diff(zc, axis=1)) > EDGE_JUMP
    jump_y = np.abs(np.diff(zc, axis=0)) > EDGE_JUMP
    edge = np.zeros((H, W), np.uint8)
    edge[:, 1:] |= jump_x
    edge[:, :-1] |= jump_x
    edge[1:, :] |= jump_y
    edge[:-1, :] |= jump_y
    edge = cv2.dilate(edge, np.ones((3, 3), np.uint8)).astype(bool)

    # axial noise (Nguyen et al. 2012), in metres
    sigma = np.float32(0.0012) + np.float32(0.0019) * (z - np.float32(0.4)) ** 2
    zn = z + sigma * rng.standard_normal((H, W), dtype=np.float32)
    # disparity quantisation (Kinect v1: 1/8 pixel steps), then the depth-image grid
    bf = np.float32(KINECT_BASELINE * KINECT_FOCAL * DISPARITY_SUBPIXEL)
    valid = hit & (zn > 0.05)
    disp = np.round(bf / np.where(valid, zn, np.float32(1.0)))
    zq = bf / np.maximum(disp, np.float32(1.0))
    zq = np.round(zq * np.float32(cfg.depth_scale)) / np.float32(cfg.depth_scale)
    drop = grazing | edge | (rng.random((H, W), dtype=np.float32) < RANDOM_DROPOUT) | ~valid
    return np.where(drop, np.float32(0.0), zq).astype(np.float32)


# ------------------------------------------------------------------------------------------------
# trajectory


def _look_rotation(forward: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """(N, 3, 3) camera-to-world rotations (OpenCV axes) looking along ``forward``, world z up."""
    f = forward / np.linalg.norm(forward, axis=1, keepdims=True)
    up = np.array([0.0, 0.0, 1.0])
    right = np.cross(f, up)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(f, right)
    R = np.stack([right, down, f], axis=2)  # columns: x right, y down, z forward
    c, s = np.cos(roll), np.sin(roll)
    Rroll = np.zeros((len(roll), 3, 3))
    Rroll[:, 0, 0] = c
    Rroll[:, 0, 1] = -s
    Rroll[:, 1, 0] = s
    Rroll[:, 1, 1] = c
    Rroll[:, 2, 2] = 1.0
    return R @ Rroll


def make_trajectory(cfg: SynthConfig) -> Trajectory:
    """Smooth hand-held-like camera path inside the room, ``T_world_cam``, timestamps ``i / 30``.

    The camera circles an ellipse (semi-axes 0.8 x 0.6 m) around the room centre at ~1.35 m
    height, looking outwards and ~20 deg down at the furniture along the walls, with sinusoidal
    wobble of speed, height, yaw, pitch and roll (phases from the seed). ``loop=True``: one full
    closed turn (infinitely smooth, the pose after the last frame is the first one again).
    ``loop=False``: an open 0.55-turn sweep.
    """
    cfg.validate()
    n = int(cfg.frames)
    rng = np.random.default_rng([int(cfg.seed), 0x7A7])
    ph = rng.uniform(0, 2 * np.pi, 8)
    amp = rng.uniform(0.7, 1.0, 6)
    turns = 1.0 if cfg.loop else 0.55
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
    R = _look_rotation(forward, roll)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = R
    poses[:, :3, 3] = np.stack([x, y, z], axis=1)
    return Trajectory(np.arange(n) / FPS, poses)


# ------------------------------------------------------------------------------------------------
# sequence writer


def _calibration_yaml(cfg: SynthConfig) -> str:
    return (
        "# pinhole intrinsics of the depth camera, pixels; depth PNG value / depth_scale = metres;"
        " 0 = no depth\n"
        f"width: {int(cfg.width)}\n"
        f"height: {int(cfg.height)}\n"
        f"fx: {float(cfg.fx)!r}\n"
        f"fy: {float(cfg.fy)!r}\n"
        f"cx: {float(cfg.cx)!r}\n"
        f"cy: {float(cfg.cy)!r}\n"
        f"depth_scale: {float(cfg.depth_scale)!r}\n"
    )


def _imwrite(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise DatasetError(f"{path}: cv2.imwrite failed")


def generate_sequence(
    out_dir: str | Path,
    cfg: SynthConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Render a synthetic sequence into ``out_dir`` in the TUM RGB-D layout and return its path.
    ``progress(frames done, frames total)`` is called after every rendered frame.

    Writes ``rgb/NNNNNN.png``, ``depth/NNNNNN.png`` (uint16, metres * depth_scale, 0 = none),
    ``rgb.txt``, ``depth.txt``, ``groundtruth.txt`` (camera-to-world), ``calibration.yaml``,
    ``scene.ply`` (true surface) and, last, ``.complete`` (JSON of the config). A folder without
    ``.complete`` is an interrupted generation; an existing marker is removed first.
    """
    cfg = SynthConfig() if cfg is None else cfg
    cfg.validate()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    marker = out / ".complete"
    marker.unlink(missing_ok=True)
    (out / "rgb").mkdir(exist_ok=True)
    (out / "depth").mkdir(exist_ok=True)

    t0 = time.perf_counter()
    scene = build_scene(cfg)
    traj = make_trajectory(cfg)
    if cfg.render_frames is not None:
        n = max(1, min(int(cfg.render_frames), len(traj)))
        traj = Trajectory(traj.timestamps[:n], traj.poses[:n])
    rng = np.random.default_rng(int(cfg.seed))
    log.info(
        "generating synthetic sequence %s: %d frames %dx%d seed=%d loop=%s noise=%s alias=%s",
        out,
        cfg.frames,
        cfg.width,
        cfg.height,
        cfg.seed,
        cfg.loop,
        cfg.noise,
        cfg.alias,
    )
    names = [f"{i:06d}.png" for i in range(len(traj))]
    t_render = 0.0
    pending: list[Future] = []
    with ThreadPoolExecutor(max_workers=2) as pool:  # PNG encoding overlaps with rendering
        for i, T in enumerate(traj.poses):
            t1 = time.perf_counter()
            color, depth = render_frame(scene, T, cfg, rng)
            t_render += time.perf_counter() - t1
            d16 = np.clip(np.round(depth * cfg.depth_scale), 0, 65535).astype(np.uint16)
            pending.append(pool.submit(_imwrite, out / "rgb" / names[i], color[..., ::-1].copy()))
            pending.append(pool.submit(_imwrite, out / "depth" / names[i], d16))
            while len(pending) > 8:
                pending.pop(0).result()
            if (i + 1) % 100 == 0:
                log.debug("rendered %d/%d frames", i + 1, len(traj))
            if progress is not None:
                progress(i + 1, len(traj))
        for fut in pending:
            fut.result()

    stamps = [f"{t:.6f}" for t in traj.timestamps]
    atomic_write_text(
        out / "rgb.txt",
        "# color images (synthetic, slam.synthetic)\n# timestamp filename\n"
        + "".join(f"{s} rgb/{nm}\n" for s, nm in zip(stamps, names)),
    )
    atomic_write_text(
        out / "depth.txt",
        "# depth maps (synthetic, slam.synthetic)\n# timestamp filename\n"
        + "".join(f"{s} depth/{nm}\n" for s, nm in zip(stamps, names)),
    )
    write_tum(out / "groundtruth.txt", traj)
    atomic_write_text(out / "calibration.yaml", _calibration_yaml(cfg))
    tmp_ply = out / ".scene.tmp.ply"
    # str path: accepted by every supported Open3D (0.18 takes str only, newer stubs say PathLike)
    if not o3d.io.write_triangle_mesh(str(tmp_ply), scene.mesh, write_ascii=False):  # type: ignore[arg-type]
        raise DatasetError(f"{tmp_ply}: writing the scene mesh failed")
    os.replace(tmp_ply, out / "scene.ply")
    # frames left over from an earlier, longer generation into the same folder
    frame_re = re.compile(r"^(\d{6})\.png$")
    for sub in ("rgb", "depth"):
        for p in (out / sub).iterdir():
            m = frame_re.match(p.name)
            if m and int(m.group(1)) >= len(traj):
                p.unlink()
    atomic_write_text(marker, json.dumps(asdict(cfg), sort_keys=True) + "\n")
    dt = time.perf_counter() - t0
    log.info(
        "synthetic sequence %s done: %d frames in %.1f s (render %.1f ms/frame)",
        out,
        len(traj),
        dt,
        1000 * t_render / max(len(traj), 1),
    )
    return out


def is_complete(out_dir: str | Path) -> bool:
    """True when ``out_dir`` holds a fully written synthetic sequence (``.complete`` marker)."""
    return (Path(out_dir) / ".complete").is_file()
