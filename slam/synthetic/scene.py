"""The synthetic room: furniture layout, procedural tri-planar texture atlas, and the scene
ready for ray casting (:func:`build_scene`)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from functools import lru_cache

import cv2
import numpy as np
import open3d as o3d

from slam.synthetic.config import ROOM_MAX, ROOM_MIN, TEX_RES, TEX_SIZE, SynthConfig
from slam.synthetic.kinds import kind_layout
from slam.synthetic.shapes import Layout, Rz, box, cylinder, rand_tex, sphere

log = logging.getLogger(__name__)

# ------------------------------------------------------------------------------------------------
# scene layout


def _cluster_parts() -> list[tuple[str, tuple[np.ndarray, np.ndarray]]]:
    """The furniture cluster that is cloned when ``alias=True``, in its local frame.

    Local frame: origin on the floor at the wall, +x pointing into the room, y along the wall.
    """
    return [
        ("cluster_cabinet", box([0.005, -0.45, 0.0], [0.48, 0.45, 0.85])),
        ("cluster_drawer1", box([0.48, -0.40, 0.48], [0.50, 0.40, 0.78])),
        ("cluster_drawer2", box([0.48, -0.40, 0.08], [0.50, 0.40, 0.40])),
        ("cluster_box", box([0.08, -0.38, 0.85], [0.36, -0.08, 1.07])),
        ("cluster_can", cylinder([0.25, 0.22], 0.85, 0.08, 0.28)),
        ("cluster_ball", sphere([0.30, 0.02, 0.93], 0.08)),
        ("cluster_poster", box([0.003, -0.40, 1.25], [0.02, 0.40, 1.80])),
    ]


@lru_cache(maxsize=8)
def _room_layout(seed: int, alias: bool) -> Layout:
    """All scene objects (world-frame triangle soups) with their texture parameters."""
    rng = np.random.default_rng([int(seed), 0x5CE7E])
    L = Layout()

    def add(name: str, vt: tuple[np.ndarray, np.ndarray], tex=None, group: int = -1) -> None:
        L.add(name, vt, rng, tex, group)

    L.add_room(ROOM_MIN, ROOM_MAX, rng)
    _clusters(L, add, seed, alias)
    _table(add)
    _shelf_wall(add, seed)
    # wall -x: plant (pot + foliage sphere)
    add("plant_pot", cylinder([-2.15, 1.35], 0.0, 0.17, 0.38))
    add("plant_ball", sphere([-2.15, 1.35, 0.62], 0.27))
    add("plant_poster", box([-2.497, 0.6, 1.2], [-2.48, 1.5, 1.85]))
    _desk_wall(add)
    return L


#: ``add(name, (vertices, triangles), tex=None, group=-1)``: one object into the layout.
Add = Callable[..., None]


def _clusters(L: Layout, add: Add, seed: int, alias: bool) -> None:
    """Wall +x (x = 2.5): cluster A (always present); wall -x (x = -2.5): cluster B (alias:
    an identical clone of A, the revisit detector's trap), else a sofa."""
    cluster = _cluster_parts()
    cluster_rng = np.random.default_rng([int(seed), 0xC1A5])
    cluster_tex = [rand_tex(cluster_rng) for _ in cluster]
    placements = [(np.array([2.5, 0.85, 0.0]), 180.0)]
    if alias:
        placements.append((np.array([-2.5, -0.55, 0.0]), 0.0))
    for gi, (t, yaw) in enumerate(placements):
        R = Rz(yaw)
        T_world_local = np.eye(4)
        T_world_local[:3, :3] = R
        T_world_local[:3, 3] = t
        L.group_T_local_world.append(np.linalg.inv(T_world_local))
        for (name, (v, tri)), tex in zip(cluster, cluster_tex):
            add(f"{name}_{gi}", (v @ R.T + t, tri), tex=tex, group=gi)
    if not alias:
        add("sofa_seat", box([-2.495, -1.35, 0.0], [-1.75, 0.25, 0.45]))
        add("sofa_back", box([-2.495, -1.35, 0.45], [-2.25, 0.25, 0.9]))
        add("sofa_arm1", box([-2.495, -1.55, 0.0], [-1.75, -1.35, 0.62]))
        add("sofa_arm2", box([-2.495, 0.25, 0.0], [-1.75, 0.45, 0.62]))
        add("cushion", box([-2.2, -0.9, 0.45], [-2.05, -0.5, 0.75]))


def _table(add: Add) -> None:
    """A table near wall +x, with a sphere, a box and a can on it."""
    add("table_top", box([1.75, -1.45, 0.72], [2.45, -0.25, 0.76]))
    for i, (x, y) in enumerate([(1.78, -1.42), (2.37, -1.42), (1.78, -0.33), (2.37, -0.33)]):
        add(f"table_leg{i}", box([x, y, 0.0], [x + 0.05, y + 0.05, 0.72]))
    add("table_sphere", sphere([2.05, -1.15, 0.88], 0.12))
    add("table_box", box([1.9, -0.75, 0.76], [2.2, -0.45, 0.95]))
    add("table_can", cylinder([2.3, -1.25], 0.76, 0.05, 0.22))


def _shelf_wall(add: Add, seed: int) -> None:
    """Wall +y (y = 2): a bookshelf with random books, a cabinet, a picture frame, boxes."""
    sx0, sx1, sy0, sy1 = 0.4, 1.45, 1.6, 1.995
    add("shelf_side1", box([sx0, sy0, 0.0], [sx0 + 0.03, sy1, 1.8]))
    add("shelf_side2", box([sx1 - 0.03, sy0, 0.0], [sx1, sy1, 1.8]))
    add("shelf_back", box([sx0 + 0.03, sy1 - 0.02, 0.0], [sx1 - 0.03, sy1, 1.8]))
    for k, z in enumerate([0.0, 0.45, 0.9, 1.35, 1.77]):
        add(f"shelf_board{k}", box([sx0 + 0.03, sy0, z], [sx1 - 0.03, sy1 - 0.02, z + 0.03]))
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
                add(f"book{k}_{x:.2f}", box([x, sy1 - 0.02 - d, z], [x + w, sy1 - 0.02, z + h]))
            x += w + 0.005
    add("cabinet", box([-1.65, 1.5, 0.0], [-0.75, 1.995, 1.1]))
    add("cabinet_door1", box([-1.6, 1.485, 0.1], [-1.22, 1.5, 1.0]))
    add("cabinet_door2", box([-1.18, 1.485, 0.1], [-0.8, 1.5, 1.0]))
    add("cabinet_vase", cylinder([-1.0, 1.75], 1.1, 0.09, 0.3))
    add("frame", box([-0.45, 1.97, 1.15], [0.15, 1.997, 1.75]))
    add("box_stack1", box([1.8, 1.45, 0.0], [2.45, 1.95, 0.5]))
    add("box_stack2", box([1.9, 1.55, 0.5], [2.35, 1.9, 0.85]))


def _desk_wall(add: Add) -> None:
    """Wall -y (y = -2): a desk with a monitor, a chair, a bin, a lamp, a crate."""
    add("desk_top", box([-0.2, -1.995, 0.72], [1.2, -1.4, 0.76]))
    add("desk_drawers", box([0.75, -1.95, 0.0], [1.15, -1.45, 0.72]))
    add("desk_leg1", box([-0.18, -1.95, 0.0], [-0.13, -1.45, 0.72]))
    add("desk_leg2", box([0.7, -1.95, 0.0], [0.75, -1.45, 0.72]))
    add("monitor", box([0.15, -1.9, 0.92], [0.75, -1.85, 1.27]))
    add("monitor_stand", cylinder([0.45, -1.86], 0.76, 0.03, 0.17))
    add("keyboard", box([0.2, -1.7, 0.76], [0.65, -1.55, 0.785]))
    add("chair_seat", box([0.05, -1.35, 0.42], [0.5, -0.9, 0.47]))
    add("chair_back", box([0.05, -0.95, 0.47], [0.5, -0.9, 0.95]))
    add("chair_post", cylinder([0.275, -1.125], 0.0, 0.03, 0.42))
    add("bin", cylinder([-0.7, -1.75], 0.0, 0.15, 0.4))
    add("lamp_pole", cylinder([-1.9, -1.6], 0.0, 0.02, 1.55))
    add("lamp_shade", cylinder([-1.9, -1.6], 1.55, 0.18, 0.25))
    add("lamp_base", cylinder([-1.9, -1.6], 0.0, 0.15, 0.03))
    add("crate", box([-1.55, -1.95, 0.0], [-1.05, -1.5, 0.45]))
    add("wall_panel", box([-1.4, -1.997, 1.2], [-0.6, -1.98, 1.7]))


def _layout(seed: int, alias: bool, scene: str = "room") -> Layout:
    """The objects of a scene: the furnished room (``alias``: with a cloned furniture cluster)
    or another scene kind (:mod:`slam.synthetic.kinds`)."""
    return _room_layout(seed, alias) if scene == "room" else kind_layout(scene, seed)


def make_scene(cfg: SynthConfig) -> o3d.geometry.TriangleMesh:
    """Legacy triangle mesh of the true scene surface (world frame, metres).

    ``triangle_material_ids`` holds each triangle's object index (used by :func:`render_frame`).
    """
    L = _layout(int(cfg.seed), bool(cfg.alias), cfg.scene)
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
    L = _layout(int(cfg.seed), bool(cfg.alias), cfg.scene)
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
