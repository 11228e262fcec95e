"""Compiled per-point passes of the joint photometric + geometric alignment
(:func:`slam.frontend.photometric.joint_align`): each pass walks the source points once,
without the dozen full-size temporaries the same arithmetic takes in numpy.

- :func:`geometric_rows`: the source points moved by ``T`` and projectively associated with
  the target; the point-to-plane residuals and Jacobian rows of the correspondences, and which
  points the target surface does not hide (where colour is compared);
- :func:`photometric_rows`: the intensity residuals and Jacobian rows of those points;
- :func:`weighted_system`: the Huber-weighted normal equations of such rows;
- :func:`warp_accumulate`: a reference view's intensity warped into the model's view (the
  target's colour, :func:`slam.frontend.photometric.mean_warped_intensity`).

The arithmetic is float32 as in the images and points (the pixel a point falls in is rounded
from the same float32 numbers as before), the normal equations are summed in float64.
Intensity is sampled bilinearly with the border replicated, as ``cv2.remap`` samples it.

Compiled on first use and cached on disk by numba (next to this file, or in the user's cache
folder when the package folder is read-only): a few seconds once per machine.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["geometric_rows", "photometric_rows", "warp_accumulate", "weighted_system"]

_NEAR = np.float32(1e-3)  # points nearer to the camera than this (m) are behind it
_ONE = np.float32(1.0)


@njit(cache=True, nogil=True)
def _moved(points, i, R, t):  # pragma: no cover - compiled
    """Point ``i`` moved by ``(R, t)`` (float32)."""
    px, py, pz = points[i, 0], points[i, 1], points[i, 2]
    qx = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
    qy = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
    qz = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
    return qx, qy, qz


@njit(cache=True, nogil=True)
def _store_row(J, k, qx, qy, qz, gx, gy, gz):  # pragma: no cover - compiled
    """Row ``k`` of ``J``: ``[Q x g, g]``, d(g . Q)/d(twist) for the update
    ``T <- exp(twist) T``."""
    J[k, 0] = qy * gz - qz * gy
    J[k, 1] = qz * gx - qx * gz
    J[k, 2] = qx * gy - qy * gx
    J[k, 3] = gx
    J[k, 4] = gy
    J[k, 5] = gz


@njit(cache=True, nogil=True)
def geometric_rows(
    points, R, t, intrinsics, depth, geometry, shape, gate, J, r, z, visible
):  # pragma: no cover - compiled
    """The source ``points`` (N x 3, float32) moved by ``(R, t)`` and associated with the
    target pixel they project to (``intrinsics``: fx, fy, cx, cy as float32; ``shape``:
    height, width) where the target has depth (``depth``: H*W, 0 = none). Each correspondence
    whose point-to-plane residual against the target's vertex and known
    normal (``geometry``: :attr:`~slam.frontend.rgbd_image._TargetLevel.geometry`) is below
    ``gate`` gets row ``k`` of ``J`` (N x 6), its residual ``r[k]`` and its depth ``z[k]``;
    every correspondence within ``gate`` of the target's depth gets its point's index in
    ``visible``. Returns (correspondences, rows, visible points)."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    h, w = shape
    n_assoc = n_geo = n_vis = 0
    for i in range(points.shape[0]):
        qx, qy, qz = _moved(points, i, R, t)
        if not qz > _NEAR:
            continue
        inv_z = _ONE / qz
        u = int(np.rint(fx * qx * inv_z + cx))
        v = int(np.rint(fy * qy * inv_z + cy))
        if u < 0 or u >= w or v < 0 or v >= h:
            continue
        pix = v * w + u
        zt = depth[pix]
        if not zt > 0:
            continue
        n_assoc += 1
        if abs(zt - qz) < gate:
            visible[n_vis] = i
            n_vis += 1
        if geometry[pix, 7] > 0:
            nx, ny, nz = geometry[pix, 4], geometry[pix, 5], geometry[pix, 6]
            res = (qx - geometry[pix, 0]) * nx + (qy - geometry[pix, 1]) * ny
            res += (qz - geometry[pix, 2]) * nz
            if abs(res) < gate:
                _store_row(J, n_geo, qx, qy, qz, nx, ny, nz)
                r[n_geo] = res
                z[n_geo] = qz
                n_geo += 1
    return n_assoc, n_geo, n_vis


@njit(cache=True, nogil=True)
def _bilinear(photo, x, y):  # pragma: no cover - compiled
    """The three channels of ``photo`` (H x W x 3) at (x, y), bilinear, each of the four taps
    clamped into the image (as ``cv2.remap`` with INTER_LINEAR and BORDER_REPLICATE)."""
    h, w = photo.shape[0], photo.shape[1]
    big = np.float32(2.0**30)
    x = min(max(x, -big), big)
    y = min(max(y, -big), big)
    fx, fy = np.floor(x), np.floor(y)
    ax, ay = x - fx, y - fy
    x0, y0 = int(fx), int(fy)
    x1, y1 = min(max(x0 + 1, 0), w - 1), min(max(y0 + 1, 0), h - 1)
    x0, y0 = min(max(x0, 0), w - 1), min(max(y0, 0), h - 1)
    w00, w01 = (_ONE - ay) * (_ONE - ax), (_ONE - ay) * ax
    w10, w11 = ay * (_ONE - ax), ay * ax
    a, b, c, d = photo[y0, x0], photo[y0, x1], photo[y1, x0], photo[y1, x1]
    s0 = a[0] * w00 + b[0] * w01 + c[0] * w10 + d[0] * w11
    s1 = a[1] * w00 + b[1] * w01 + c[1] * w10 + d[1] * w11
    s2 = a[2] * w00 + b[2] * w01 + c[2] * w10 + d[2] * w11
    return s0, s1, s2


@njit(cache=True, nogil=True)
def photometric_rows(
    points, intensity, indices, count, R, t, intrinsics, photo, J, r
):  # pragma: no cover - compiled
    """The first ``count`` of the source ``points`` named by ``indices``, moved by ``(R, t)``
    into the target's colour camera and projected into its ``photo`` (H x W x 3: intensity,
    d/du, d/dv): row ``k`` of ``J`` (d r / d twist) and ``r[k]``, the target's intensity less
    the point's (``intensity``), for each point whose samples are finite (a warped target is
    NaN where unseen). Returns the number of rows."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    m = 0
    for k in range(count):
        i = indices[k]
        qx, qy, qz = _moved(points, i, R, t)
        inv_z = _ONE / qz if qz > _NEAR else _ONE
        u = fx * qx * inv_z + cx
        v = fy * qy * inv_z + cy
        value, du, dv = _bilinear(photo, u, v)
        if not (np.isfinite(value) and np.isfinite(du) and np.isfinite(dv)):
            continue
        gx = du * fx * inv_z
        gy = dv * fy * inv_z
        gz = -(gx * qx + gy * qy) * inv_z
        _store_row(J, m, qx, qy, qz, gx, gy, gz)
        r[m] = value - intensity[i]
        m += 1
    return m


@njit(cache=True, nogil=True)
def weighted_system(J, r, count, offset, scale, delta, weight):  # pragma: no cover - compiled
    """``(J^T W J, J^T W r')`` (float64) of the first ``count`` rows, with ``r' = r - offset``
    and Huber's weights of ``r'`` at ``delta``, times ``weight / scale^2``."""
    # the upper triangle of H (hPQ) and b (bP) as scalars: they stay in registers
    f = weight / (scale * scale)
    off = np.float32(offset)
    h00 = h01 = h02 = h03 = h04 = h05 = h11 = h12 = h13 = h14 = h15 = h22 = h23 = h24 = h25 = (
        h33
    ) = h34 = h35 = h44 = h45 = h55 = 0.0
    b0 = b1 = b2 = b3 = b4 = b5 = 0.0
    for k in range(count):
        res = r[k] - off
        a = abs(res)
        wk = f if a <= delta else f * delta / max(a, 1e-12)
        j0, j1, j2 = float(J[k, 0]), float(J[k, 1]), float(J[k, 2])
        j3, j4, j5 = float(J[k, 3]), float(J[k, 4]), float(J[k, 5])
        w0, w1, w2, w3, w4, w5 = wk * j0, wk * j1, wk * j2, wk * j3, wk * j4, wk * j5
        h00 += w0 * j0
        h01 += w0 * j1
        h02 += w0 * j2
        h03 += w0 * j3
        h04 += w0 * j4
        h05 += w0 * j5
        h11 += w1 * j1
        h12 += w1 * j2
        h13 += w1 * j3
        h14 += w1 * j4
        h15 += w1 * j5
        h22 += w2 * j2
        h23 += w2 * j3
        h24 += w2 * j4
        h25 += w2 * j5
        h33 += w3 * j3
        h34 += w3 * j4
        h35 += w3 * j5
        h44 += w4 * j4
        h45 += w4 * j5
        h55 += w5 * j5
        b0 += w0 * res
        b1 += w1 * res
        b2 += w2 * res
        b3 += w3 * res
        b4 += w4 * res
        b5 += w5 * res
    H = np.array(
        [
            [h00, h01, h02, h03, h04, h05],
            [h01, h11, h12, h13, h14, h15],
            [h02, h12, h22, h23, h24, h25],
            [h03, h13, h23, h33, h34, h35],
            [h04, h14, h24, h34, h44, h45],
            [h05, h15, h25, h35, h45, h55],
        ]
    )
    return H, np.array([b0, b1, b2, b3, b4, b5])


@njit(cache=True, nogil=True)
def warp_accumulate(
    vertices, intrinsics, R, t, intensity, depth, gate, total, count
):  # pragma: no cover - compiled
    """A source view's ``intensity`` seen at destination pixels (:func:`slam.frontend.
    photometric.mean_warped_intensity`): each destination vertex (``vertices``, N x 3, z = 0:
    none) moved into the source camera by ``(R, t)`` and projected (``intrinsics``: fx, fy,
    cx, cy, float32); where it lands inside the source image, in front of it, and within
    ``gate`` of the source's depth at the nearest pixel, its bilinear sample (border
    replicated) is added to ``total`` and 1 to ``count``."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    hs, ws = depth.shape
    for i in range(vertices.shape[0]):
        if not vertices[i, 2] > 0:
            continue
        qx, qy, qz = _moved(vertices, i, R, t)
        if not qz > _NEAR:
            continue
        inv_z = _ONE / qz
        u = fx * qx * inv_z + cx
        v = fy * qy * inv_z + cy
        if not (u >= 0 and u <= ws - 1 and v >= 0 and v <= hs - 1):
            continue
        zs = depth[int(np.rint(v)), int(np.rint(u))]
        if not abs(zs - qz) < gate:
            continue
        x0, y0 = int(np.floor(u)), int(np.floor(v))
        ax, ay = u - np.float32(x0), v - np.float32(y0)
        x1, y1 = min(x0 + 1, ws - 1), min(y0 + 1, hs - 1)
        top = intensity[y0, x0] * (_ONE - ax) + intensity[y0, x1] * ax
        bottom = intensity[y1, x0] * (_ONE - ax) + intensity[y1, x1] * ax
        total[i] += top * (_ONE - ay) + bottom * ay
        count[i] += _ONE
