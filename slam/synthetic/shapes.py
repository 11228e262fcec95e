"""Building blocks of the synthetic scenes and camera paths: textured objects (boxes, cylinders,
spheres as world-frame triangle soups with per-face texture offsets), the scene layout they are
collected in, and the look-at camera rotation."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from slam.synthetic.config import TEX_SIZE


@dataclass
class TexParams:
    """Per-object texture parameters: 6 per-face (axis, sign) atlas offsets and a 2-colour
    palette."""

    offsets: np.ndarray  # (6, 2) texels
    palette: np.ndarray  # (2, 3) RGB in [0, 1]


@dataclass
class Layout:
    """All objects of a scene with their texture parameters (the renderer's tables)."""

    vertices: list[np.ndarray] = field(default_factory=list)  # world frame, per object
    triangles: list[np.ndarray] = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    tex: list[TexParams] = field(default_factory=list)
    group: list[int] = field(default_factory=list)  # -1: textured in world frame
    group_T_local_world: list[np.ndarray] = field(default_factory=list)

    def add(
        self,
        name: str,
        vt: tuple[np.ndarray, np.ndarray],
        rng: np.random.Generator,
        tex: TexParams | None = None,
        group: int = -1,
    ) -> None:
        """Add an object (vertices, triangles); its texture is drawn from ``rng`` unless
        given."""
        self.vertices.append(np.asarray(vt[0], float))
        self.triangles.append(np.asarray(vt[1], np.int64))
        self.names.append(name)
        self.tex.append(tex if tex is not None else rand_tex(rng))
        self.group.append(group)

    def add_room(self, lo, hi, rng: np.random.Generator, name: str = "room") -> None:
        """An inward-facing box (triangle winding flipped so normals point inside)."""
        v, t = box(lo, hi)
        self.add(name, (v, t[:, ::-1]), rng)


def rand_tex(rng: np.random.Generator) -> TexParams:
    offsets = rng.uniform(0.0, TEX_SIZE, size=(6, 2))
    # two related but distinct colours, moderately saturated
    base = rng.uniform(0.35, 1.0, size=3)
    other = np.clip(base + rng.uniform(-0.45, 0.45, size=3), 0.25, 1.0)
    return TexParams(offsets.astype(np.float32), np.stack([base, other]).astype(np.float32))


def box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    m = o3d.geometry.TriangleMesh.create_box(*(hi - lo))
    return np.asarray(m.vertices) + lo, np.asarray(m.triangles).copy()


def cylinder(center_xy, z0, radius, height, resolution=32) -> tuple[np.ndarray, np.ndarray]:
    split = max(1, int(np.ceil(height / 0.1)))  # avoid very skinny side triangles
    m = o3d.geometry.TriangleMesh.create_cylinder(
        radius, height, resolution=resolution, split=split
    )
    v = np.asarray(m.vertices) + np.array([center_xy[0], center_xy[1], z0 + height / 2.0])
    return v, np.asarray(m.triangles).copy()


def sphere(center, radius, resolution=20) -> tuple[np.ndarray, np.ndarray]:
    m = o3d.geometry.TriangleMesh.create_sphere(radius, resolution=resolution)
    return np.asarray(m.vertices) + np.asarray(center, float), np.asarray(m.triangles).copy()


def Rz(deg: float) -> np.ndarray:
    return Rotation.from_euler("z", deg, degrees=True).as_matrix()


def look_rotation(forward: np.ndarray, roll: np.ndarray) -> np.ndarray:
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


def poses_from(position: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(N, 4, 4) ``T_world_cam`` from (N, 3) positions and (N, 3, 3) rotations."""
    poses = np.tile(np.eye(4), (len(position), 1, 1))
    poses[:, :3, :3] = R
    poses[:, :3, 3] = position
    return poses
