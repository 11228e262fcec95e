"""Joint photometric + geometric alignment (own Gauss-Newton, coarse to fine), for sequences
whose colour is registered to depth.

The source frame (depth + grey intensity) is aligned to a target (the model ray-cast, or a
frame) by minimising, over ``T_target_source``,

    sum_i rho(r_geo_i) / s_geo^2  +  w * sum_j rho(r_pho_j) / s_pho^2

with ``r_geo = n . (T p - q)`` the point-to-plane distance to the projectively associated target
vertex ``q`` (normal ``n``), as in :func:`slam.frontend.icp.projective_icp`, and
``r_pho = I_t(pi(T p)) - I_s(p) - b`` the intensity difference at the bilinearly interpolated
projection (``b``: a global brightness offset, re-estimated every iteration, which absorbs
exposure changes). ``rho`` is Huber's loss; ``s_geo``, ``s_pho`` are robust scales (1.4826 x
the median absolute residual) re-estimated every iteration, so the two terms are weighed by
their measured noise, not by units: noisy real depth hands weight to colour, exact synthetic
depth keeps it.

Along the directions the geometric term constrains ``degenerate_ratio`` times worse than its
best (a corridor's length, a wall's plane), its information and gradient are left out and
colour decides alone: what depth says there rests on a few pixels at depth edges and on the
model's bias, and on exact depth its weight would drown colour.

Pixels and intrinsics follow the pinhole convention (pixel (u, v) is the ray
``K^-1 [u, v, 1]``; pyramids are 2x2 box averages, see :func:`slam.camera.scale_intrinsics`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from slam.frontend.icp import IcpResult
from slam.frontend.joint_kernels import (
    geometric_rows,
    photometric_rows,
    warp_accumulate,
    weighted_system,
)
from slam.frontend.rgbd_image import RgbdImage, _SourceLevel, _TargetLevel
from slam.frontend.robust import median, robust_scale
from slam.frontend.weighted_icp import vertex_map, without_blind_directions
from slam.geometry import exp_se3, inv_T

# floors of the robust scales: depth's in metres, colour's in grey levels (of 1)
_MIN_GEO_SCALE_M = 5e-4
_MIN_PHO_SCALE = 2.0 / 255.0


def _sample(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples (N, C) of a float32 (H, W, C) image at pixel coordinates (x, y)."""
    n = len(x)
    cols = 1024
    rows = -(-n // cols)
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n] = x
    my[:n] = y
    out = cv2.remap(
        img,
        mx.reshape(rows, cols),
        my.reshape(rows, cols),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return out.reshape(rows * cols, -1)[:n]


def warp_intensity(
    depth_m: np.ndarray,
    K: np.ndarray,
    T_src_dst: np.ndarray,
    src_intensity: np.ndarray,
    src_depth_m: np.ndarray,
    gate_m: float,
) -> np.ndarray:
    """A source view's intensity seen at the pixels of a destination view of depth ``depth_m``
    (same intrinsics ``K``): each pixel's point moved into the source camera by ``T_src_dst``,
    projected and sampled bilinearly. NaN where the destination has no depth, or the point
    falls outside the source image or the source's depth there differs by more than
    ``gate_m`` (occluded, or not seen)."""
    V = vertex_map(np.asarray(depth_m, np.float32), K).reshape(-1, 3)
    out = _warp_vertices(V, K, T_src_dst, (src_intensity, src_depth_m), gate_m)
    return out.reshape(depth_m.shape)


def _warp_vertices(
    V: np.ndarray, K: np.ndarray, T_src_dst: np.ndarray, src: tuple[np.ndarray, ...], gate_m: float
) -> np.ndarray:
    """:func:`warp_intensity` of the destination's vertices ``V`` (N x 3, z = 0: no depth)
    from ``src`` (intensity, depth): N intensities."""
    total = np.zeros(len(V), np.float32)
    count = np.zeros(len(V), np.float32)
    _warp_into(V, K, T_src_dst, src, gate_m, (total, count))
    return np.where(count > 0, total, np.float32(np.nan))


def _warp_into(
    V: np.ndarray,
    K: np.ndarray,
    T_src_dst: np.ndarray,
    src: tuple[np.ndarray, ...],
    gate_m: float,
    sums: tuple[np.ndarray, np.ndarray],
) -> None:
    """:func:`_warp_vertices` added into ``sums`` (total, count; one compiled pass,
    :func:`slam.frontend.joint_kernels.warp_accumulate`)."""
    src_intensity, src_depth_m = src
    intrinsics = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float32)
    warp_accumulate(
        np.ascontiguousarray(V, np.float32), intrinsics,
        np.ascontiguousarray(T_src_dst[:3, :3], np.float32),
        np.ascontiguousarray(T_src_dst[:3, 3], np.float32),
        np.ascontiguousarray(src_intensity, np.float32),
        np.ascontiguousarray(src_depth_m, np.float32), np.float32(gate_m), *sums,
    )  # fmt: skip


def mean_warped_intensity(
    depth_m: np.ndarray,
    K: np.ndarray,
    T_world_dst: np.ndarray,
    views: list[tuple[RgbdImage, np.ndarray]],
    gate_m: float,
) -> np.ndarray:
    """The mean of several views' intensities (``views``: image and ``T_world_cam``, each
    with registered intensity and the intrinsics ``K`` at level 0) seen at the pixels of a
    destination view of depth ``depth_m`` and pose ``T_world_dst`` (:func:`warp_intensity`);
    each pixel averages the views that see it, NaN where none does."""
    V = vertex_map(np.asarray(depth_m, np.float32), K).reshape(-1, 3)
    total = np.zeros(len(V), np.float32)
    count = np.zeros(len(V), np.float32)
    for image, T_world_src in views:
        assert image.intensity is not None
        T_src_dst = inv_T(T_world_src) @ T_world_dst
        _warp_into(V, K, T_src_dst, (image.intensity[0], image.depth[0]), gate_m, (total, count))
    out = np.full(len(V), np.nan, np.float32)
    np.divide(total, count, out=out, where=count > 0)
    return out.reshape(depth_m.shape)


#: rows per block of a tall matrix product. OpenBLAS multiplies blocks this small on one thread;
#: on tens of thousands of rows it uses its threads, which then spin for a while after the
#: product and slow the next Open3D kernel by about half on two cores (docs/archive/journal.md)
_BLOCK_ROWS = 4096


def _tall_times(A: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``A @ M`` for a tall ``A`` (N x k) and a small ``M``, block by block (one thread)."""
    if len(A) <= _BLOCK_ROWS:
        return A @ M
    out = np.empty((len(A), M.shape[1]), np.result_type(A, M))
    for s in range(0, len(A), _BLOCK_ROWS):
        np.matmul(A[s : s + _BLOCK_ROWS], M, out=out[s : s + _BLOCK_ROWS])
    return out


@dataclass
class _Terms:
    """One pyramid level's settings of the two terms of :func:`joint_align`."""

    gate: np.float32  # geometric correspondences farther apart are rejected (m)
    delta_g: float  # Huber delta of the geometric term (m)
    min_geo_scale_m: float
    photometric_weight: float  # 0: depth alone
    min_pho_scale: float
    degenerate_ratio: float  # > 0: depth is left out of the directions it is blind in


def _project(
    points: np.ndarray, T: np.ndarray, fx: np.float32, fy: np.float32, cx: float, cy: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``points`` moved by ``T`` and projected: the moved points, pixel coordinates (u, v) and
    inverse depths (points behind the camera get 1)."""
    Q = _tall_times(points, T[:3, :3].T.astype(np.float32)) + T[:3, 3].astype(np.float32)
    z = Q[:, 2]
    inv_z = np.float32(1.0) / np.where(z > 1e-3, z, np.float32(1.0))
    return Q, fx * Q[:, 0] * inv_z + cx, fy * Q[:, 1] * inv_z + cy, inv_z


_NormalEquations = tuple[np.ndarray, np.ndarray]  # (H, b) of one term
# both terms' equations, the geometric residuals and the correspondences' depths
_Parts = tuple[_NormalEquations, _NormalEquations | None, np.ndarray, np.ndarray | None]


def _term_equations(
    src: _SourceLevel,
    tgt: _TargetLevel,
    K: np.ndarray,
    T: np.ndarray,
    terms: _Terms,
    T_colour: np.ndarray | None = None,
) -> _Parts | None:
    """The two terms of :func:`joint_align` at pose ``T`` (``T_target_source``), apart:
    ``((H_geo, b_geo), (H_pho, b_pho) or None, geometric residuals, depths of the geometric
    correspondences)``; None when fewer than 6 source points correspond. The
    photometric term is None when its weight is 0, either side has no intensity, or fewer than
    6 points are visible. ``T_colour``: the pose of the source's colour camera in the target's
    colour camera, when the colour images were not taken at their depth images' instants
    (None: ``T``). The depths come with the photometric term only. One compiled pass over the
    source points (:mod:`slam.frontend.joint_kernels`) per term."""
    intrinsics = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float32)
    n = len(src.points)
    J = np.empty((n, 6), np.float32)
    r = np.empty(n, np.float32)
    z = np.empty(n, np.float32)
    visible = np.empty(n, np.int64)
    R, t = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)
    _, n_geo, n_vis = geometric_rows(
        src.points, R, t, intrinsics, tgt.depth, tgt.geometry, tgt.shape, terms.gate,
        J, r, z, visible,
    )  # fmt: skip
    if n_geo < 6:  # point-to-plane against the projectively associated target vertex
        return None
    rg, z_geo = r[:n_geo].copy(), z[:n_geo].copy()
    s_g = robust_scale(rg, terms.min_geo_scale_m)
    geometric = weighted_system(J, r, n_geo, 0.0, s_g, terms.delta_g, 1.0)
    photometric = None
    if terms.photometric_weight > 0 and src.intensity is not None and tgt.photo is not None:
        if n_vis >= 6:  # on source points the target surface does not hide
            photometric = _photometric_equations(
                src, visible[:n_vis], T if T_colour is None else T_colour, intrinsics,
                tgt.photo, terms, (J, r),
            )  # fmt: skip
    # the correspondences' depths (to compare rotations with translations), only for the
    # combinations that use them
    return geometric, photometric, rg, (z_geo if photometric is not None else None)


def _photometric_equations(
    src: _SourceLevel,
    visible: np.ndarray,
    T_colour: np.ndarray,
    intrinsics: np.ndarray,
    photo: np.ndarray,
    terms: _Terms,
    scratch: tuple[np.ndarray, np.ndarray],
) -> _NormalEquations:
    """Normal equations of the photometric term: the ``visible`` source points moved by
    ``T_colour`` into the target's colour camera and projected into its ``photo`` (intensity
    and its gradients), residuals less their median (a global brightness offset), Huber
    weights at 1.345 robust scales, times the term's weight (``scratch``: rows to write into)."""
    assert src.intensity is not None
    J, r = scratch
    R, t = T_colour[:3, :3].astype(np.float32), T_colour[:3, 3].astype(np.float32)
    m = photometric_rows(
        src.points, src.intensity, visible, len(visible), R, t, intrinsics, photo, J, r
    )
    if m < 6:
        return np.zeros((6, 6)), np.zeros(6)
    offset = np.float32(median(r[:m]))  # global brightness offset
    s_p = robust_scale(r[:m] - offset, terms.min_pho_scale)
    return weighted_system(J, r, m, offset, s_p, 1.345 * s_p, terms.photometric_weight)


def _joint_equations(parts: _Parts, terms: _Terms) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One Gauss-Newton iteration's normal equations ``(H, b)`` of :func:`joint_align` from its
    two terms (:func:`_term_equations`), and the geometric residuals of its correspondences."""
    geometric, photometric, rg, z_geo = parts
    H, b = geometric
    if photometric is not None:
        if terms.degenerate_ratio > 0:  # where depth is blind, colour decides alone
            assert z_geo is not None
            H, b = without_blind_directions(H, b, median(z_geo), terms.degenerate_ratio)
        H = H + photometric[0]
        b = b + photometric[1]
    # a whisper of damping: directions nothing constrains (sliding along a bare wall) stay put
    # instead of making the system singular
    H[np.diag_indices(6)] += 1e-9 * np.trace(H) + 1e-12
    return H, b, rg


def colour_pose(
    T_target_source: np.ndarray, C_source: np.ndarray | None, C_target: np.ndarray | None
) -> np.ndarray | None:
    """The pose of the source's colour camera in the target's colour camera, from the depth
    cameras' ``T_target_source`` and each colour camera's pose in its depth camera (``C_*``,
    ``T_depth_colour``; None: the same pose). None when both are None (the depth cameras'
    pose is the colour cameras')."""
    if C_source is None and C_target is None:
        return None
    T = T_target_source if C_source is None else T_target_source @ C_source
    return T if C_target is None else inv_T(C_target) @ T


def photometric_costs(
    source: _SourceLevel,
    target: _TargetLevel,
    K: np.ndarray,
    steps: list[tuple[np.ndarray, np.ndarray | None]],
    gate_m: float,
) -> list[float]:
    """What two images say of competing poses, without an alignment: the photometric cost of
    ``source`` against ``target`` (intrinsics ``K``) at each of ``steps``, pairs of
    ``T_target_source`` and the pose of the source's colour camera in the target's (None:
    the same). The cost is the mean Huber loss of the intensity differences, less their median
    (a brightness offset), at 1.345 robust scales of the first step's, over the source points
    every step sees (in front of the target camera, inside its image, and within ``gate_m`` of
    its depth there, so no step is scored on pixels another step has occluded); infinite
    when fewer than 6 are seen by all."""
    assert source.intensity is not None and target.photo is not None
    fx, fy, cx, cy = (np.float32(k) for k in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    h, w = target.shape
    seen = np.ones(len(source.points), bool)
    pixels = []
    for T, T_colour in steps:
        Q, uf, vf, _ = _project(source.points, T, fx, fy, cx, cy)
        if T_colour is not None:
            _, uf_c, vf_c, _ = _project(source.points, T_colour, fx, fy, cx, cy)
        else:
            uf_c, vf_c = uf, vf
        ui, vi = np.rint(uf).astype(np.int64), np.rint(vf).astype(np.int64)
        inside = (Q[:, 2] > 1e-3) & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
        inside &= (uf_c >= 0) & (uf_c <= w - 1) & (vf_c >= 0) & (vf_c <= h - 1)
        zt = target.depth[np.where(inside, vi * w + ui, 0)]
        seen &= inside & (zt > 0) & (np.abs(zt - Q[:, 2]) < gate_m)
        pixels.append((uf_c, vf_c))
    if np.count_nonzero(seen) < 6:
        return [float("inf")] * len(steps)
    residuals = []
    for uf_c, vf_c in pixels:
        r = _sample(target.photo, uf_c[seen], vf_c[seen])[:, 0] - source.intensity[seen]
        residuals.append(r - np.float32(median(r)))
    delta = 1.345 * robust_scale(residuals[0], _MIN_PHO_SCALE)
    costs = []
    for r in residuals:
        a = np.abs(r).astype(np.float64)
        costs.append(float(np.mean(np.where(a <= delta, 0.5 * a * a, delta * (a - 0.5 * delta)))))
    return costs


def joint_align(
    source: RgbdImage,
    target: RgbdImage,
    init_T_target_source: np.ndarray,
    iterations: list[int],
    max_correspondence_m: float = 0.07,
    huber_delta_m: float = 0.05,
    coarse_factor: float = 2.0,
    photometric_weight: float = 1.0,
    min_geo_scale_m: float = _MIN_GEO_SCALE_M,
    min_pho_scale: float = _MIN_PHO_SCALE,
    finest_step: int = 1,
    fitness_depth_max_m: float = float("inf"),
    degenerate_ratio: float = 0.0,
    colour_poses: tuple[np.ndarray | None, np.ndarray | None] = (None, None),
) -> IcpResult:
    """Align ``source`` to ``target`` (see the module docstring); ``iterations`` per level,
    coarse to fine. Correspondence distance and Huber delta of the geometric term grow by
    ``coarse_factor`` per coarser level (as in :func:`projective_icp`). The photometric term is
    used when both images carry intensity and ``photometric_weight`` > 0; ``finest_step`` > 1
    subsamples the source pixels at the finest level. Returns ``T_target_source``, fitness
    (fraction of source points with a geometric correspondence, finest level) and the
    geometric inlier RMSE. The fitness counts source points nearer than ``fitness_depth_max_m``
    (the depth-only ICP's range, so both fitnesses mean the same). With both terms and
    ``degenerate_ratio`` > 0, the geometric term is left out of the directions it constrains
    more than that many times worse than its best
    (:func:`~slam.frontend.weighted_icp.without_blind_directions`): there colour decides alone.
    ``colour_poses``: the source's and the target's ``T_depth_colour``, the pose of each colour
    camera in its depth camera when the two images were not taken at the same instant (a moving
    camera: :func:`slam.frontend.motion.colour_motion`; None: the same pose); the photometric
    term then moves the source's points into the target's colour camera. (Its Jacobian is taken
    at those points, not rotated back into the depth camera: a step of a few milliseconds'
    motion changes how fast it converges, not where to.)"""
    T = np.asarray(init_T_target_source, float).copy()
    C_src, C_tgt = colour_poses
    levels = len(iterations)
    use_pho = (
        photometric_weight > 0 and source.intensity is not None and target.intensity is not None
    )
    fitness, rmse = 0.0, float("inf")
    for level in reversed(range(levels)):
        n_iter = int(iterations[levels - 1 - level])
        if n_iter <= 0:
            continue
        scale = coarse_factor**level
        terms = _Terms(
            np.float32(max_correspondence_m * scale),
            huber_delta_m * scale,
            min_geo_scale_m,
            photometric_weight if use_pho else 0.0,
            min_pho_scale,
            degenerate_ratio,
        )
        src = source.source(level, finest_step if level == 0 else 1)
        tgt = target.target(level)
        in_range = np.count_nonzero(src.points[:, 2] < fitness_depth_max_m) if level == 0 else 0
        for _ in range(n_iter):
            T_colour = colour_pose(T, C_src, C_tgt) if use_pho else None
            parts = _term_equations(src, tgt, target.K[level], T, terms, T_colour)
            if parts is None:
                return IcpResult(np.asarray(init_T_target_source, float).copy(), 0.0, np.inf)
            H, b, rg = _joint_equations(parts, terms)
            T = exp_se3(-np.linalg.solve(H, b)) @ T
            if level == 0:
                fitness = min(1.0, len(rg) / max(in_range, 1))
                rmse = float(np.sqrt(np.mean(rg.astype(np.float64) ** 2)))
    return IcpResult(T, fitness, rmse)
