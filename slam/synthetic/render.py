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
from slam.synthetic import kinect
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
from slam.synthetic.kinect import SensorMotion
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
    motion: SensorMotion | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Render one RGB-D frame from camera pose ``T_world_cam`` (camera-to-world, OpenCV axes).

    ``scene`` is a :class:`SynthScene` (fast) or the mesh returned by :func:`make_scene` for the
    same ``cfg`` (its renderer is built and cached on first use). ``rng`` drives the noise (only
    used when ``cfg.noise``; default ``np.random.default_rng(cfg.seed)``). With ``cfg.kinect``
    the frame is taken as a hand-held Kinect v1 takes it (:mod:`slam.synthetic.kinect`) while
    the camera moves as ``motion`` says (default: still); ``T_world_cam`` is then the middle
    row's pose.

    Returns ``(color, depth_m)``: HxWx3 uint8 RGB and HxW float32 metres, 0 = no depth.
    """
    cfg.validate()
    sc = _as_synth_scene(scene, cfg)
    W, H = int(cfg.width), int(cfg.height)
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"render_frame: T_world_cam must be a finite 4x4 matrix, got {T.shape}")
    cam = _camera_rays(W, H, float(cfg.fx), float(cfg.fy), float(cfg.cx), float(cfg.cy))
    if rng is None:
        rng = np.random.default_rng(int(cfg.seed))
    if cfg.kinect:
        return _render_kinect(sc, cam, T, cfg, rng, motion or SensorMotion())
    z, hit, obj, normal, d_world = _cast(sc, cam, T)
    color = _shaded_texture(sc, cam, T, z, obj, normal, (H, W)).reshape(H, W, 3)
    z = _drifted(z, cam, cfg)
    if cfg.noise:
        cosang = _incidence(normal, d_world, cam)
        depth = _noisy_depth(z.reshape(H, W), hit.reshape(H, W), cosang.reshape(H, W), cfg, rng)
        color = _colour_noise(color, rng)
    else:
        depth = z.reshape(H, W)
    return _to_images(color, depth, cfg)


def _render_kinect(
    sc: SynthScene,
    cam: _CameraRays,
    T: np.ndarray,
    cfg: SynthConfig,
    rng: np.random.Generator,
    motion: SensorMotion,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`render_frame` as a hand-held Kinect v1 takes it: colour row by row at each row's
    instant, blurred along the motion and scaled by the exposure gain; depth with the Kinect's
    projector shadows, ragged edges, correlated noise and dark-surface dropouts."""
    W, H = int(cfg.width), int(cfg.height)
    T_rows = kinect.row_poses(T, motion.twist, H)
    z_c, _, obj_c, normal_c, d_c, origins_c = _cast_rows(sc, cam, T_rows)
    points_c = (origins_c + z_c[:, None] * d_c.reshape(-1, 3)).reshape(-1, 1, 3)
    color = _shaded_texture(sc, cam, T, z_c, obj_c, normal_c, (H, W), points_c)
    flow = kinect.image_speed(cam.xn, cam.yn, z_c, motion.twist, float(cfg.fx), float(cfg.fy))
    color = kinect.motion_blur(color.reshape(H, W, 3), flow, kinect.COLOUR_EXPOSURE_S)
    color = color * np.float32(motion.gain)
    # depth: one instant (deskewing fr1/rpy's depth rows by the true motion did not bring
    # frame-to-frame ICP nearer the ground truth), lit by the projector beside the camera
    z, hit, obj, normal, d_world = _cast(sc, cam, T)
    z = _drifted(z, cam, cfg)
    if not cfg.noise:
        return _to_images(color, z.reshape(H, W), cfg)
    grey = _shaded_texture(sc, cam, T, z, obj, normal, (H, W)) @ np.array(
        [0.299, 0.587, 0.114], np.float32
    )
    origins = np.broadcast_to(T[:3, 3].astype(np.float32), (len(z), 3))
    points = origins + z[:, None] * d_world.reshape(-1, 3)
    shadow = kinect.projector_shadow(sc.raycaster, T, points, hit)
    drop = shadow | (rng.random(len(z), dtype=np.float32) < kinect.dark_dropout(grey))
    cosang = _incidence(normal, d_world, cam)
    depth = _noisy_depth(
        z.reshape(H, W), hit.reshape(H, W), cosang.reshape(H, W), cfg, rng,
        kinect_drop=drop.reshape(H, W),
    )  # fmt: skip
    return _to_images(_colour_noise(color, rng), depth, cfg)


def _drifted(z: np.ndarray, cam: _CameraRays, cfg: SynthConfig) -> np.ndarray:
    """Depth grown radially by ``cfg.drift_bias`` (an uncalibrated Kinect's distortion)."""
    if not cfg.drift_bias:
        return z
    r2 = cam.xn * cam.xn + cam.yn * cam.yn
    return z * (np.float32(1.0) + np.float32(cfg.drift_bias) * r2)


def _incidence(normal: np.ndarray, d_world: np.ndarray, cam: _CameraRays) -> np.ndarray:
    """|cos| between each ray and the surface normal it hits (for grazing-angle dropouts)."""
    ray_dot = cv2.transform(normal * d_world, np.ones((1, 3), np.float32)).reshape(-1)
    return np.abs(ray_dot) * cam.inv_len


def _colour_noise(color: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Grey (channel-correlated) Gaussian pixel noise added to an (N, 3) or (H, W, 3) image."""
    h, w = (color.shape[0], 1) if color.ndim == 2 else color.shape[:2]
    noise = rng.standard_normal((h, w, 1), dtype=np.float32) * np.float32(COLOR_NOISE_SIGMA)
    return color + noise.reshape(color.shape[:-1] + (1,))


def _to_images(
    color: np.ndarray, depth: np.ndarray, cfg: SynthConfig
) -> tuple[np.ndarray, np.ndarray]:
    """uint8 colour (rounded, saturated) and the depth inside the sensor's range."""
    H, W = depth.shape
    max_depth = np.float32(SENSOR_MAX_DEPTH_M.get(cfg.scene, MAX_DEPTH))
    depth = np.where((depth >= MIN_DEPTH) & (depth <= max_depth), depth, np.float32(0.0))
    color = np.ascontiguousarray(color.reshape(H, W, 3), dtype=np.float32)
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


def _cast_rows(
    sc: SynthScene, cam: _CameraRays, T_rows: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_cast` with each row's rays from its own pose (``T_rows``: (H, 4, 4), a rolling
    shutter); also returns each ray's origin ((N, 3) float32). z is each row's own depth."""
    H = len(T_rows)
    N = len(cam.xn)
    R = T_rows[:, :3, :3].astype(np.float32)
    d_world = np.einsum("hij,hwj->hwi", R, cam.d_cam.reshape(H, -1, 3)).reshape(N, 1, 3)
    origins = np.repeat(T_rows[:, :3, 3].astype(np.float32), N // H, axis=0)
    rays = np.concatenate([origins, d_world.reshape(N, 3)], axis=1)
    ans = sc.raycaster.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)))
    t_hit = ans["t_hit"].numpy()
    prim = ans["primitive_ids"].numpy()
    normal = ans["primitive_normals"].numpy().reshape(N, 1, 3)
    hit = np.isfinite(t_hit)
    z = np.where(hit, t_hit, np.float32(0.0))
    obj = np.take(sc.tri_obj, np.where(hit, prim, sc.n_tri))
    return z, hit, obj, normal, d_world, origins


def _shaded_texture(
    sc: SynthScene, cam: _CameraRays, T: np.ndarray, z: np.ndarray, obj: np.ndarray,
    normal: np.ndarray, size: tuple[int, int], p_world: np.ndarray | None = None,
) -> np.ndarray:  # fmt: skip
    """(N, 3) float32 colour of the hit points of an image of ``size`` (H, W): each object's
    tri-planar texture in its own frame (the world's, or its cluster's), Lambertian-shaded by
    fixed lights, through the object's albedo palette. ``p_world``: the hit points ((N, 1, 3)
    float32) when they are not the back-projections of ``z`` from ``T`` (a rolling shutter)."""
    N = len(z)
    # --- hit points and normals in each object's texture frame (world, or its cluster's frame)
    if p_world is None:
        pc = cv2.merge([cam.xn * z, cam.yn * z, z]).reshape(N, 1, 3)  # camera-frame points
        p = cv2.transform(pc, T[:3, :].astype(np.float32))
    else:
        p = p_world
    n = normal
    if sc.group_T:
        grp = np.take(sc.obj_group, obj)
        for g, Tg in enumerate(sc.group_T):
            m = grp == g
            if m.any():
                m3 = m[:, None, None]
                if p_world is None:
                    Tl = (Tg.astype(np.float64) @ T)[:3, :].astype(np.float32)
                    p = np.where(m3, cv2.transform(pc, Tl), p)
                else:
                    p = np.where(m3, cv2.transform(p_world, Tg[:3, :].astype(np.float32)), p)
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
    kinect_drop: np.ndarray | None = None,
) -> np.ndarray:
    """Kinect-like depth: axial Gaussian noise, disparity quantisation and dropouts. With
    ``kinect_drop`` (``cfg.kinect``: the pixels :mod:`slam.synthetic.kinect` leaves without
    depth) also ragged edges and correlated and fixed-pattern disparity noise."""
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
    white = rng.standard_normal((H, W), dtype=np.float32)
    if kinect_drop is None:
        zn = z + sigma * white
    else:
        zn = _kinect_noise(z, sigma, white, cfg, rng)
        z_bled, ragged = kinect.ragged_edges(np.where(hit, zn, np.float32(0.0)), edge, rng)
        zn, edge = np.where(hit, z_bled, zn), ragged | kinect_drop
    # disparity quantisation (Kinect v1: 1/8 pixel steps), then the depth-image grid
    bf = np.float32(KINECT_BASELINE * KINECT_FOCAL * DISPARITY_SUBPIXEL)
    valid = hit & (zn > 0.05)
    disp = np.round(bf / np.where(valid, zn, np.float32(1.0)))
    zq = bf / np.maximum(disp, np.float32(1.0))
    zq = np.round(zq * np.float32(cfg.depth_scale)) / np.float32(cfg.depth_scale)
    drop = grazing | edge | (rng.random((H, W), dtype=np.float32) < RANDOM_DROPOUT) | ~valid
    return np.where(drop, np.float32(0.0), zq).astype(np.float32)


def _kinect_noise(
    z: np.ndarray,
    sigma: np.ndarray,
    white: np.ndarray,
    cfg: SynthConfig,
    rng: np.random.Generator,
) -> np.ndarray:
    """Depth with the axial noise's variance split between white and spatially correlated
    noise, plus the device's fixed disparity pattern."""
    H, W = z.shape
    corr = cv2.GaussianBlur(rng.standard_normal((H, W), dtype=np.float32), (0, 0),
                            kinect.CORRELATION_PX)  # fmt: skip
    corr *= np.float32(1.0 / max(float(corr.std()), 1e-6))
    c = np.float32(kinect.CORRELATED_SHARE)
    zn = z + sigma * (np.sqrt(np.float32(1.0) - c) * white + np.sqrt(c) * corr)
    disparity_px = kinect.fixed_pattern(int(cfg.seed), H, W)
    # a disparity error of d pixels moves depth by z^2 d / (baseline * focal length)
    return zn + zn * zn * disparity_px / np.float32(KINECT_BASELINE * KINECT_FOCAL)
