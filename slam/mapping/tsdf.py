"""TSDF fusion, ray-casting and marching cubes on Open3D's VoxelBlockGrid (CPU tensor kernels).

The grid stores a truncated signed distance, a weight and (optionally) a colour per voxel and is
updated by the weighted running average of KinectFusion: ``D <- (W D + d) / (W + 1)``,
``W <- W + 1``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import open3d.core as o3c

from slam.config import MappingConfig
from slam.geometry import inv_T
from slam.mapping.range_map import RangeMapBuffer, fragments_bound

log = logging.getLogger(__name__)
_CPU = o3c.Device("CPU:0")
_DEPTH_SCALE = 5000.0  # depth images handed to Open3D's integration: uint16, 0.2 mm units
# Open3D warns when a ray-cast's range map overflowed; RangeMapBuffer sees that it never does
o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)


@dataclass
class Rendering:
    """A ray-cast view of the model: depth (m, 0 = no surface), normals in the camera frame, and
    colour (float RGB in [0, 1]) when the model has colour."""

    depth_m: np.ndarray
    normals_cam: np.ndarray | None
    color: np.ndarray | None


def _pixel_centre_shift(K: np.ndarray, shift_px: float) -> np.ndarray:
    K = np.asarray(K, float).copy()
    K[0, 2] += shift_px
    K[1, 2] += shift_px
    return K


def _range_map_factor(width: int, height: int) -> int:
    """Down-sampling factor of the ray-caster's range map: 8 where it divides the image size.
    Open3D's ray_cast does not return when it does not (seen with 80x60 images and 8)."""
    return next(f for f in (8, 4, 2, 1) if width % f == 0 and height % f == 0)


def _tensor(a: np.ndarray, dtype=None) -> o3c.Tensor:
    return o3c.Tensor(np.ascontiguousarray(a if dtype is None else a.astype(dtype)))


def _color_at_surface(
    color: np.ndarray, depth: np.ndarray, K: np.ndarray, R_world_cam: np.ndarray, shift_m: float
) -> np.ndarray:
    """Undo the half-voxel shift of the rendered colour. The ray-caster is handed a camera moved
    by ``shift_m`` on every world axis (see :meth:`TSDFVolume.raycast`), which puts the rendered
    *surface* right, but Open3D reads the colour field without the TSDF's offset, so pixel u shows
    the colour of its surface point X(u) moved by s = shift_m (1, 1, 1) (world): a sideways shift
    of the texture in the image (~0.9 px at 2 m, 1 cm voxels, 320x240). The colour of X(u) is
    shown at the pixel whose point is X(u) - s, i.e. at pi(X(u) - s): resample there."""
    h, w = depth.shape
    s = R_world_cam.T @ np.full(3, shift_m)  # camera frame
    u = np.arange(w, dtype=np.float32)[None, :]
    v = np.arange(h, dtype=np.float32)[:, None]
    z = depth.astype(np.float32)
    x = (u - np.float32(K[0, 2])) * z / np.float32(K[0, 0]) - np.float32(s[0])
    y = (v - np.float32(K[1, 2])) * z / np.float32(K[1, 1]) - np.float32(s[1])
    zz = z - np.float32(s[2])
    ok = (z > 0) & (zz > 1e-3)
    zz = np.where(ok, zz, np.float32(1.0))
    mx = np.where(ok, np.float32(K[0, 0]) * x / zz + np.float32(K[0, 2]), u)
    my = np.where(ok, np.float32(K[1, 1]) * y / zz + np.float32(K[1, 2]), v)
    out = cv2.remap(
        np.ascontiguousarray(color, np.float32),
        mx.astype(np.float32),
        my.astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return out


class TSDFVolume:
    """A TSDF volume in world coordinates (metres)."""

    def __init__(
        self, cfg: MappingConfig, has_color: bool = True, block_count: int | None = None
    ) -> None:
        self.cfg = cfg
        self.has_color = has_color and cfg.integrate_color
        names = self._attribute_names()
        dtypes = [o3c.float32] * len(names)
        channels = [[3] if n == "color" else [1] for n in names]
        self.vbg = o3d.t.geometry.VoxelBlockGrid(
            names,
            dtypes,
            channels,
            cfg.voxel_size_m,
            cfg.block_resolution,
            cfg.block_count if block_count is None else block_count,
            _CPU,
        )
        self.n_integrated = 0
        self.mesh_weight_threshold = cfg.mesh_weight_threshold
        self._last_blocks: o3c.Tensor | None = None
        self._range_map = RangeMapBuffer()

    @property
    def voxel_size(self) -> float:
        return self.cfg.voxel_size_m

    def integrate(
        self,
        depth_m: np.ndarray,
        color: np.ndarray | None,
        K: np.ndarray,
        T_world_cam: np.ndarray,
    ) -> None:
        """Fuse one frame (depth in metres, colour HxWx3 uint8 RGB or None) seen from a pose.
        A frame without any depth in range changes nothing."""
        if not np.any((depth_m > 0) & (depth_m < self.cfg.depth_max_m)):
            return  # Open3D raises "No block is touched" on it
        # uint16 depth (0.2 mm steps) and uint8 colour: the kernel's native input pair, which
        # avoids converting every colour pixel to float
        depth_u16 = np.clip(np.round(depth_m * _DEPTH_SCALE), 0, 65535).astype(np.uint16)
        depth = o3d.t.geometry.Image(o3c.Tensor(depth_u16))
        # Open3D's integration reads, for a voxel projecting to (u, v), pixel (int(u), int(v)):
        # truncation, so pixel (i, j) would stand for the rays through [i, i+1) x [j, j+1) and
        # the fused surface would sit half a pixel off the pinhole convention used everywhere
        # else (pixel (u, v) <-> ray K^-1 [u, v, 1]). Shifting the principal point by +0.5 px
        # turns the truncation into rounding: nearest-pixel lookup, no offset.
        K_t = _tensor(_pixel_centre_shift(K, 0.5), np.float64)
        extrinsic = _tensor(inv_T(T_world_cam), np.float64)
        trunc = float(self.cfg.trunc_voxels)
        depth_max = float(self.cfg.depth_max_m)
        blocks = self._touched_blocks(depth, K_t, extrinsic, _DEPTH_SCALE, depth_max)
        if blocks is None:
            log.debug("frame fuses nothing: its depth misses the pixels Open3D samples")
            return
        if self.has_color and color is not None:
            col = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(color, np.uint8)))
            self.vbg.integrate(
                blocks, depth, col, K_t, K_t, extrinsic, _DEPTH_SCALE, depth_max, trunc
            )
        else:
            self.vbg.integrate(blocks, depth, K_t, extrinsic, _DEPTH_SCALE, depth_max, trunc)
        self._last_blocks = blocks
        self.n_integrated += 1

    def _touched_blocks(
        self,
        depth: o3d.t.geometry.Image,
        K: o3c.Tensor,
        extrinsic: o3c.Tensor,
        scale: float,
        depth_max: float,
    ) -> o3c.Tensor | None:
        """The blocks a depth image (Open3D image, ``scale`` units a metre) touches from a pose
        within the truncation band; None when it touches none (no depth before ``depth_max``
        at the pixels Open3D samples: every 4th, so NaN rows or a wrong depth scale leave it
        nothing), where Open3D raises."""
        try:
            return self.vbg.compute_unique_block_coordinates(
                depth, K, extrinsic, scale, depth_max, float(self.cfg.trunc_voxels)
            )
        except RuntimeError as exc:
            if "No block is touched" not in str(exc):
                raise
            return None

    def _weight_threshold(self, threshold: float) -> float:
        # early on every voxel has few observations; do not demand more than there can be
        return float(min(threshold, max(self.n_integrated, 1)))

    @property
    def depth_max_m(self) -> float:
        """Depth beyond this is never fused (``mapping.depth_max_m``)."""
        return float(self.cfg.depth_max_m)

    def raycast(
        self,
        K: np.ndarray,
        width: int,
        height: int,
        T_world_cam: np.ndarray,
        with_normals: bool = True,
        with_color: bool = False,
        depth_min_m: float = 0.1,
        depth_max_m: float | None = None,
        frustum_depth_m: np.ndarray | None = None,
        min_weight: float | None = None,
    ) -> Rendering:
        """Render depth (and normals, colour) of the model as seen from ``T_world_cam``.

        Rays are bounded by a range map built from a set of blocks: those a depth image
        ``frustum_depth_m`` (same intrinsics) would touch from this pose when given (tracking
        passes the new frame's depth), else the blocks last integrated. Surfaces fused with
        less weight than ``min_weight`` (default ``mapping.raycast_weight_threshold``) are
        not rendered.
        """
        depth_max = self.cfg.depth_max_m if depth_max_m is None else depth_max_m
        weight = self._weight_threshold(
            self.cfg.raycast_weight_threshold if min_weight is None else min_weight
        )
        # Open3D's ray-caster reads voxel (i, j, k) as if its value sat half a voxel lower than
        # where integration measured it, so surfaces render shifted by -voxel/2 on every world
        # axis (measured: +7 mm depth bias at 1 cm voxels, 0 with this correction; the
        # marching-cubes mesh has no such offset). Rendering from a camera moved by +voxel/2
        # cancels it; uncorrected, frame-to-model tracking drifts along (1, 1, 1).
        T_world_shifted = T_world_cam.copy()
        T_world_shifted[:3, 3] += 0.5 * self.cfg.voxel_size_m
        blocks = self._ray_blocks(K, T_world_shifted, frustum_depth_m, depth_max)
        if blocks is None or blocks.shape[0] == 0:
            return Rendering(np.zeros((height, width), np.float32), None, None)
        attrs = ["depth"] + (["normal"] if with_normals else [])
        if with_color and self.has_color:
            attrs.append("color")
        depth_range = (depth_min_m, depth_max)
        out = self._march(blocks, K, T_world_shifted, (width, height), attrs, depth_range, weight)
        depth = out["depth"].numpy()[..., 0].astype(np.float32)
        bad = ~np.isfinite(depth)
        if bad.any():
            log.debug("ray-cast produced %d non-finite depths", int(bad.sum()))
            depth[bad] = 0.0
        normals = None
        if with_normals:
            # Open3D returns camera-frame normals pointing into the surface; flip to face the camera
            normals = -out["normal"].numpy().astype(np.float32)
            normals[depth <= 0] = 0.0
        color = None
        if "color" in attrs:
            color = _color_at_surface(
                out["color"].numpy(), depth, K, T_world_shifted[:3, :3], 0.5 * self.cfg.voxel_size_m
            )
        return Rendering(depth, normals, color)

    def _ray_blocks(
        self,
        K: np.ndarray,
        T_world_cam: np.ndarray,
        frustum_depth_m: np.ndarray | None,
        depth_max_m: float,
    ) -> o3c.Tensor | None:
        """The blocks a ray-cast from ``T_world_cam`` may hit: those ``frustum_depth_m`` (same
        intrinsics) touches from there when given, else the blocks last integrated."""
        if frustum_depth_m is None or self.n_integrated == 0:
            return self._last_blocks
        return self._touched_blocks(
            o3d.t.geometry.Image(_tensor(frustum_depth_m, np.float32)),
            _tensor(K, np.float64),
            _tensor(inv_T(T_world_cam), np.float64),
            1.0,
            depth_max_m,
        )

    def _march(
        self,
        blocks: o3c.Tensor,
        K: np.ndarray,
        T_world_cam: np.ndarray,
        size: tuple[int, int],
        attrs: list[str],
        depth_range: tuple[float, float],
        weight: float,
    ) -> dict:
        """Open3D's ray-cast of ``blocks`` (``size``: width, height), its range map grown to
        what the blocks need first (else Open3D drops blocks from it)."""
        width, height = size
        T_cam_world = inv_T(T_world_cam)
        down = _range_map_factor(width, height)
        block_m = self.cfg.voxel_size_m * self.cfg.block_resolution
        needed = fragments_bound(blocks.numpy(), K, T_cam_world, width, height, down, block_m)
        self._range_map.ensure(self.vbg, needed)
        return self.vbg.ray_cast(
            blocks, _tensor(K, np.float64), _tensor(T_cam_world, np.float64), width, height,
            attrs, 1.0, *depth_range, weight, self.cfg.trunc_voxels, down,
        )  # fmt: skip

    def render(
        self,
        K: np.ndarray,
        width: int,
        height: int,
        T_world_cam: np.ndarray,
        with_normals: bool = True,
    ) -> Rendering:
        """Render depth, colour and (optionally) normals from any pose, marching through all
        allocated blocks."""
        saved = self._last_blocks
        try:
            self._last_blocks = self.active_block_coords()
            return self.raycast(K, width, height, T_world_cam, with_normals, True)
        finally:
            self._last_blocks = saved

    def active_block_coords(self) -> o3c.Tensor:
        hashmap = self.vbg.hashmap()
        return hashmap.key_tensor()[hashmap.active_buf_indices().to(o3c.int64)]

    def extract_mesh(self, weight_threshold: float | None = None) -> o3d.geometry.TriangleMesh:
        """Marching cubes over the whole volume: a legacy Open3D mesh (vertex colours if any)."""
        thr = self.mesh_weight_threshold if weight_threshold is None else weight_threshold
        mesh = self.vbg.extract_triangle_mesh(self._weight_threshold(thr)).to_legacy()
        mesh.compute_vertex_normals()
        return mesh

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The allocated blocks as numpy arrays (copies): ``keys`` (N, 3) int32 block
        coordinates, per attribute (``tsdf``, ``weight``, ``color`` when fused) an (N, r, r, r, channels) float32 array, r = block resolution, and ``n_integrated``
        (0-d). ``np.savez`` of this dict is the file format of :meth:`save`."""
        hashmap = self.vbg.hashmap()
        idx = hashmap.active_buf_indices().numpy().astype(np.int64)
        out = {
            "keys": hashmap.key_tensor().numpy()[idx],
            "n_integrated": np.array(self.n_integrated),
        }
        for i, name in enumerate(self._attribute_names()):
            out[name] = hashmap.value_tensor(i).numpy()[idx]
        return out

    @classmethod
    def from_arrays(
        cls,
        arrays: dict[str, np.ndarray],
        cfg: MappingConfig,
        has_color: bool = True,
    ) -> TSDFVolume:
        """A volume holding the blocks of :meth:`to_arrays` (its ``n_integrated``, the frames
        fused into it, caps the weight thresholds early on; 1 when absent)."""
        keys = np.ascontiguousarray(arrays["keys"], np.int32)
        vol = cls(cfg, has_color, block_count=max(int(1.5 * len(keys)), 1000))
        if len(keys):
            values = [o3c.Tensor(np.ascontiguousarray(arrays[n])) for n in vol._attribute_names()]
            vol.vbg.hashmap().insert(o3c.Tensor(keys), values)
        vol.n_integrated = int(arrays.get("n_integrated", 1))
        return vol

    def _attribute_names(self) -> list[str]:
        return ["tsdf", "weight"] + (["color"] if self.has_color else [])

    def save(self, path: str | Path) -> None:
        """Save the blocks (uncompressed ``.npz`` of :meth:`to_arrays`) for checkpointing."""
        np.savez(path, **self.to_arrays())

    @classmethod
    def load(cls, path: str | Path, cfg: MappingConfig, has_color: bool = True) -> TSDFVolume:
        """A volume saved with :meth:`save` (or its arrays written with ``np.savez``)."""
        with np.load(path) as z:
            return cls.from_arrays({k: z[k] for k in z.files}, cfg, has_color)

    @property
    def n_blocks(self) -> int:
        return int(self.vbg.hashmap().size())


def write_mesh(path: str | Path, mesh: o3d.geometry.TriangleMesh) -> None:
    """Write a PLY mesh atomically (temporary file in the same folder, then rename)."""
    import os

    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    ok = o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False, compressed=False)
    # Open3D reports success on a truncated file (a full disk): check the size the header
    # promises before the file takes the final name
    want, got = _ply_size(tmp), tmp.stat().st_size if tmp.exists() else 0
    if not ok or want is None or got != want:
        tmp.unlink(missing_ok=True)
        raise OSError(
            f"{path}: the mesh could not be written whole ({got} of {want or '?'} bytes; is the "
            "disk full?)"
        )
    os.replace(tmp, path)


def _ply_size(path: Path) -> int | None:
    """The size in bytes a binary PLY file of triangles must have by its header (None when the
    header is unreadable)."""
    from slam.mapping.ply import read_ply_header

    try:
        return read_ply_header(path).triangle_mesh_bytes()
    except (OSError, ValueError):
        return None
