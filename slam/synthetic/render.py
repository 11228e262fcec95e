"""Rendering a frame of the synthetic room: Open3D ray casting for depth and textured, shaded
colour, then the sensor model (Kinect-like disparity quantisation, dropouts, colour noise)."""

from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
import open3d as o3d

from slam.errors import ConfigError
from slam.synthetic.config import (
    _AMBIENT,
    _LIGHTS,
    COLOR_NOISE_SIGMA,
    DISPARITY_SUBPIXEL,
    EDGE_JUMP,
    GRAZING_COS,
    KINECT_BASELINE,
    KINECT_FOCAL,
    MAX_DEPTH,
    MIN_DEPTH,
    RANDOM_DROPOUT,
    TEX_RES,
    SynthConfig,
)
from slam.synthetic.kinds import SENSOR_MAX_DEPTH_M
from slam.synthetic.scene import _layout, _texture, make_scene

log = logging.getLogger(__name__)

# ------------------------------------------------------------------------------------------------
# rendering


class SynthScene:
    """Everything :func:`render_frame` needs: mesh, raycasting scene, per-object tables, texture."""

    def __init__(self, mesh: o3d.geometry.TriangleMesh, cfg: SynthConfig):
        layout = _layout(int(cfg.seed), bool(cfg.alias), cfg.scene)
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
        self.kind = cfg.scene
        # extra "object" n_obj for rays that hit nothing
        self.tri_obj = np.append(tri_obj, n_obj).astype(np.int32)
        self.n_tri = n_tri
        self.obj_group = np.append(np.asarray(layout.group, np.int32), -1)
        self.group_T = [np.asarray(T, np.float32) for T in layout.group_T_local_world]
        self.offsets = np.concatenate(
            [np.stack([t.offsets for t in layout.tex]), np.zeros((1, 6, 2), np.float32)]
        ).reshape(-1, 2)  # (n_obj+1)*6 rows, indexed obj*6 + face
        self.albedo_lut = _albedo_lut(self.seed, self.alias, self.kind)
        self.texture = _texture(self.seed)
        self.raycaster = o3d.t.geometry.RaycastingScene()
        self.raycaster.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))


def build_scene(cfg: SynthConfig) -> SynthScene:
    """Build the renderable scene (mesh from :func:`make_scene` plus textures and raycaster)."""
    return SynthScene(make_scene(cfg), cfg)


_scene_cache: OrderedDict[int, SynthScene] = OrderedDict()


def _as_synth_scene(scene, cfg: SynthConfig) -> SynthScene:
    if isinstance(scene, SynthScene):
        if (scene.seed, scene.alias, scene.kind) != (int(cfg.seed), bool(cfg.alias), cfg.scene):
            raise ConfigError("render_frame: scene was built with a different seed/alias/scene")
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
            or cached.kind != cfg.scene
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
def _albedo_lut(seed: int, alias: bool, scene: str) -> np.ndarray:
    """((n_obj + 1) * 256, 3) float32: albedo of object k at colour-mix level m is row k*256+m."""
    layout = _layout(seed, alias, scene)
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
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"render_frame: T_world_cam must be a finite 4x4 matrix, got {T.shape}")
    cam = _camera_rays(W, H, float(cfg.fx), float(cfg.fy), float(cfg.cx), float(cfg.cy))
    z, hit, obj, normal, d_world = _cast(sc, cam, T)
    color = _shaded_texture(sc, cam, T, z, obj, normal, (H, W)).reshape(H, W, 3)
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
    max_depth = np.float32(SENSOR_MAX_DEPTH_M.get(cfg.scene, MAX_DEPTH))
    depth = np.where((depth >= MIN_DEPTH) & (depth <= max_depth), depth, np.float32(0.0))
    color_u8 = cv2.convertScaleAbs(np.maximum(color, 0.0, out=color))  # rounds and saturates
    return color_u8, depth.astype(np.float32, copy=False)


def _cast(
    sc: SynthScene, cam: _CameraRays, T: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The camera's rays cast into the scene: z depth (0 where nothing is hit), the hit mask,
    the object each pixel sees (``n_obj`` where none), the surface normal (world frame, (N, 1,
    3)) and the ray directions (world frame, (N, 1, 3))."""
    N = len(cam.xn)
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
    return z, hit, obj, normal, d_world


def _shaded_texture(
    sc: SynthScene, cam: _CameraRays, T: np.ndarray, z: np.ndarray, obj: np.ndarray,
    normal: np.ndarray, size: tuple[int, int],
) -> np.ndarray:  # fmt: skip
    """(N, 3) float32 colour of the hit points of an image of ``size`` (H, W): each object's
    tri-planar texture in its own frame (the world's, or its cluster's), Lambertian-shaded by
    fixed lights, through the object's albedo palette."""
    N = len(z)
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
        sc.texture, mapx.reshape(size), mapy.reshape(size), cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_WRAP,
    ).reshape(N, 2)  # fmt: skip

    # --- shading (Lambertian, fixed lights, object-local normals) and albedo palette
    shade = np.full(N, _AMBIENT, np.float32)
    for ldir, w in _LIGHTS:
        lx, ly, lz = (np.float32(w * c) for c in ldir)
        shade += np.abs(nx * lx + ny * ly + nz * lz)
    lum = tex[:, 0] * shade
    lut_index: np.ndarray = obj * 256 + tex[:, 1].astype(np.int32)
    albedo = np.take(sc.albedo_lut, lut_index, axis=0)
    return np.multiply(albedo, lum[:, None], out=albedo)


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
