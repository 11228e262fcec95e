"""Compiled per-pixel passes over depth images, each one walk instead of numpy's full-size
temporaries, with numpy's arithmetic type for type (``tests/frontend/test_depth_kernels.py``):

- :func:`agreement`: :func:`slam.frontend.icp.projective_agreement`, the overlap score every
  alignment is verified and ranked by (float64 points, pixels rounded half to even as
  ``np.round``, the noise gate in float32 as :meth:`slam.camera.DepthNoise.sigma` computes it):
  the same score, the RMSE to float rounding;
- :func:`downsample`: :func:`slam.frontend.pointcloud.downsample_depth`, a depth pyramid's
  next level (every target of every ICP builds its pyramid): the same values;
- :func:`geometry`: vertices and normals (:func:`slam.frontend.pointcloud.geometry_rows`):
  the same values;
- :func:`information`: the point-to-plane information of a frame's own depth
  (:func:`slam.frontend.weighted_icp.depth_information`, every frame): to float rounding.

Compiled on first use and cached on disk by numba, as :mod:`slam.frontend.joint_kernels`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["agreement", "downsample", "geometry", "information"]


@njit(cache=True, nogil=True)
def _vertex(depth, u, v, fx, fy, cx, cy):  # pragma: no cover - compiled
    z = np.float64(depth[v, u])
    return (u - cx) * z / fx, (v - cy) * z / fy, z


@njit(cache=True, nogil=True)
def _plane_residual(depth, p, u, v, K):  # pragma: no cover - compiled
    """The distance of ``p`` (target frame) to the target surface's tangent plane at pixel
    (u, v), its normal from the central differences of the neighbours' vertices; NaN where
    the pixel is on the border or a neighbour has no depth."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    h, w = depth.shape
    if not (u > 0 and u < w - 1 and v > 0 and v < h - 1):
        return np.nan
    rx, ry, rz = _vertex(depth, u + 1, v, fx, fy, cx, cy)
    lx, ly, lz = _vertex(depth, u - 1, v, fx, fy, cx, cy)
    dx, dy, dz = _vertex(depth, u, v + 1, fx, fy, cx, cy)
    ux, uy, uz = _vertex(depth, u, v - 1, fx, fy, cx, cy)
    ax, ay, az = rx - lx, ry - ly, rz - lz
    bx, by, bz = dx - ux, dy - uy, dz - uz
    nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
    if not (norm > 1e-12 and rz > 0 and lz > 0 and dz > 0 and uz > 0):
        return np.nan
    qx, qy, qz = _vertex(depth, u, v, fx, fy, cx, cy)
    return ((p[0] - qx) * nx + (p[1] - qy) * ny + (p[2] - qz) * nz) / norm


@njit(cache=True, nogil=True)
def agreement(
    source, target, K, T, threshold, step, noise, source_max, residuals, samples
):  # pragma: no cover - compiled
    """``(fraction, rmse)`` of :func:`slam.frontend.icp.projective_agreement`: the source
    depth's every ``step``-th pixel (nearer than ``source_max``) moved by ``T`` and projected
    into ``target`` (same intrinsics ``K``, float64); it agrees within ``threshold`` or, with
    ``noise`` = (sigma0, quadratic, z0, sigmas) and sigmas >= 0 (-1: no noise model), that
    many noise sigmas of its depth. The RMSE of the point-to-plane residuals of the agreeing pixels (at most about
    ``samples`` of them, evenly spaced) when ``residuals``, else NaN; NaN when none agrees."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    h, w = target.shape
    sigma0, quadratic = np.float32(noise[0]), np.float32(noise[1])
    z0, sigmas = np.float32(noise[2]), np.float32(noise[3])
    threshold32 = np.float32(threshold)
    n_src = 0
    good = np.empty((source.shape[0] // step + 1) * (source.shape[1] // step + 1), np.int64)
    n_good = 0
    for v in range(0, source.shape[0], step):
        for u in range(0, source.shape[1], step):
            d = source[v, u]
            if not (d > 0 and d <= source_max):
                continue
            n_src += 1
            x, y, z = _vertex(source, u, v, fx, fy, cx, cy)
            pz = T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]
            if not pz > 1e-6:
                continue
            px = T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3]
            py = T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3]
            ut = int(np.rint(fx * px / pz + cx))
            vt = int(np.rint(fy * py / pz + cy))
            if not (ut >= 0 and ut < w and vt >= 0 and vt < h):
                continue
            zt = np.float64(target[vt, ut])
            if sigmas >= 0:
                dz = np.float32(pz) - z0
                gate = np.float64(max(threshold32, sigmas * (sigma0 + quadratic * (dz * dz))))
            else:
                gate = threshold
            if zt > 0 and abs(zt - pz) < gate:
                good[n_good] = v * source.shape[1] + u
                n_good += 1
    if n_src == 0:
        return 0.0, np.nan
    fraction = n_good / n_src
    if not residuals or n_good == 0:
        return fraction, np.nan
    stride = n_good // samples if n_good > samples else 1
    total = 0.0
    n = 0
    p = np.empty(3)
    for k in range(0, n_good, stride):
        v, u = divmod(good[k], source.shape[1])
        x, y, z = _vertex(source, u, v, fx, fy, cx, cy)
        for i in range(3):
            p[i] = T[i, 0] * x + T[i, 1] * y + T[i, 2] * z + T[i, 3]
        ut = int(np.rint(fx * p[0] / p[2] + cx))
        vt = int(np.rint(fy * p[1] / p[2] + cy))
        r = _plane_residual(target, p, ut, vt, K)
        if not np.isnan(r):
            total += r * r
            n += 1
    return fraction, np.sqrt(total / n) if n else np.nan


@njit(cache=True, nogil=True)
def downsample(depth, max_diff):  # pragma: no cover - compiled
    """Half resolution (float32): each 2x2 block's mean of its top-left value and the others
    that have depth and lie within ``max_diff`` of it, summed in that order; 0 where the
    top-left value has none (or is NaN)."""
    h, w = depth.shape[0] // 2, depth.shape[1] // 2
    out = np.zeros((h, w), np.float32)
    one = np.float32(1.0)
    for v in range(h):
        for u in range(w):
            ref = depth[2 * v, 2 * u]
            if not ref > 0:
                continue
            total, count = ref, one
            for x in (
                depth[2 * v, 2 * u + 1],
                depth[2 * v + 1, 2 * u],
                depth[2 * v + 1, 2 * u + 1],
            ):
                if abs(x - ref) < max_diff and x > 0:
                    total += x
                    count += one
            out[v, u] = total / count
    return out


@njit(cache=True, nogil=True)
def information(geometry, width, noise):  # pragma: no cover - compiled
    """``(H, depths)`` of :func:`slam.frontend.weighted_icp.depth_information` from a depth
    image's geometry rows (:func:`geometry`, ``width``
    pixels a row): ``sum w J J^T`` (float64) over the pixels of even column whose normal is
    known, ``J = [p x n, n]``, ``w = 1 / sigma(z)^2`` with ``sigma`` in float32 from
    ``noise`` = (sigma0, quadratic, z0); and those pixels' depths."""
    sigma0, quadratic, z0 = np.float32(noise[0]), np.float32(noise[1]), np.float32(noise[2])
    H = np.zeros((6, 6))
    depths = np.empty(geometry.shape[0], np.float64)
    n = 0
    j = np.empty(6)
    for k in range(geometry.shape[0]):
        if k % width % 2 or geometry[k, 6] == 0:
            continue
        # (numba's float() keeps a float32 a float32: np.float64 widens it)
        px, py, pz = (
            np.float64(geometry[k, 0]),
            np.float64(geometry[k, 1]),
            np.float64(geometry[k, 2]),
        )
        nx, ny, nz = (
            np.float64(geometry[k, 4]),
            np.float64(geometry[k, 5]),
            np.float64(geometry[k, 6]),
        )
        j[0], j[1], j[2] = py * nz - pz * ny, pz * nx - px * nz, px * ny - py * nx
        j[3], j[4], j[5] = nx, ny, nz
        dz = np.float32(pz) - z0
        s = np.float64(sigma0 + quadratic * (dz * dz))  # float32, as DepthNoise.sigma
        w = 1.0 / (s * s)
        for a in range(6):
            wa = w * j[a]
            for b in range(a + 1):
                H[a, b] += wa * j[b]
        depths[n] = pz
        n += 1
    for a in range(6):
        for b in range(a):
            H[b, a] = H[a, b]
    return H, depths[:n]


@njit(cache=True, nogil=True)
def geometry(depth, xs, ys, jump, slope):  # pragma: no cover - compiled
    """The rows of :attr:`slam.frontend.rgbd_image._TargetLevel.geometry` of a depth image
    (H x W float32): vertex ``z * (xs[u], ys[v], 1)`` (``xs``, ``ys``: float32 ray slopes), 0,
    the normal of :func:`slam.frontend.pointcloud.geometry_rows` (central differences over one
    pixel each side, 0 across a depth step over ``max(jump, slope * z)`` or next to a pixel
    without depth; oriented towards the camera), and 1 where the normal is known. The
    arithmetic is numpy's, type for type (float32, the orientation's division in float64)."""
    h, w = depth.shape
    out = np.zeros((h * w, 8), np.float32)
    for v in range(h):
        for u in range(w):
            z = depth[v, u]
            k = v * w + u
            out[k, 0], out[k, 1], out[k, 2] = z * xs[u], z * ys[v], z
    tiny = np.float32(1e-12)
    for v in range(1, h - 1):
        for u in range(1, w - 1):
            k = v * w + u
            r, le, d, up = k + 1, k - 1, k + w, k - w
            dxx, dxy, dxz = out[r, 0] - out[le, 0], out[r, 1] - out[le, 1], out[r, 2] - out[le, 2]
            dyx, dyy, dyz = out[d, 0] - out[up, 0], out[d, 1] - out[up, 1], out[d, 2] - out[up, 2]
            cx = dxy * dyz - dxz * dyy
            cy = dxz * dyx - dxx * dyz
            cz = dxx * dyy - dxy * dyx
            norm = np.sqrt(cx * cx + cy * cy + cz * cz)
            zc = out[k, 2]
            step = max(jump, slope * zc)
            if not (
                zc > 0 and norm > 1e-12 and out[r, 2] > 0 and out[le, 2] > 0
                and out[d, 2] > 0 and out[up, 2] > 0 and abs(dxz) < step and abs(dyz) < step
            ):  # fmt: skip
                continue
            facing = cx * out[k, 0] + cy * out[k, 1] + cz * zc
            inv = (-1.0 if facing > 0 else 1.0) / np.float64(max(norm, tiny))
            nx, ny, nz = np.float32(cx * inv), np.float32(cy * inv), np.float32(cz * inv)
            out[k, 4], out[k, 5], out[k, 6] = nx, ny, nz
            out[k, 7] = 1.0 if (nx != 0 or ny != 0 or nz != 0) else 0.0
    return out
