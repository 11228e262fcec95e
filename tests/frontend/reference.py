"""numpy versions of compiled passes, kept as the references the tests check them against
(and ``benchmarks/kernels.py`` times them against)."""

import numpy as np

MAX_INCIDENCE_DEG = 75.0


def normal_map(
    vertex: np.ndarray, max_depth_jump_m: float = 0.05, f_px: float | None = None
) -> np.ndarray:
    """Normals from central differences of the vertex map, oriented towards the camera.

    Zero where a neighbour has no depth or lies across a depth discontinuity: a depth step
    over ``max_depth_jump_m``, or, with the focal length ``f_px`` of the vertex map, over what
    a surface at ``MAX_INCIDENCE_DEG`` produces across one pixel (``z tan(75 deg) / f_px``:
    at coarse pyramid levels and far away, e.g. a floor 3.5 m ahead at 1/8 resolution, the
    fixed step alone removes every normal). Computed by component (x, y, z planes), ~4x faster
    than on (H, W, 3) arrays.
    """
    x, y, z = (np.asarray(vertex[..., k], np.float32) for k in range(3))
    h, w = z.shape
    n = np.zeros((h, w, 3), np.float32)
    _central_normals((x, y, z), slice(1, -1), 1, max_depth_jump_m, f_px, out=n[1:-1, 1:-1])
    return n


def _central_normals(
    xyz: tuple[np.ndarray, np.ndarray, np.ndarray],
    centres: slice | tuple[slice, slice],
    step: int,
    max_depth_jump_m: float,
    f_px: float | None,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Normals (n, m, 3) at the ``centres`` (row and column slices of step ``step``, each
    pixel with all four neighbours) from central differences over one pixel each side, into
    ``out`` when given."""
    rows, cols = centres if isinstance(centres, tuple) else (centres, centres)

    def shifted(s: slice, d: int) -> slice:  # the centres' slice moved by d pixels
        stop = s.stop + d  # (a stop of 0 after a negative stop means "to the end")
        return slice(s.start + d, None if stop == 0 else stop, step)

    def at(c: np.ndarray, dr: int, dc: int) -> np.ndarray:
        return c[shifted(rows, dr), shifted(cols, dc)]

    x, y, z = xyz
    dxx, dxy, dxz = (at(c, 0, 1) - at(c, 0, -1) for c in (x, y, z))
    dyx, dyy, dyz = (at(c, 1, 0) - at(c, -1, 0) for c in (x, y, z))
    cx = dxy * dyz - dxz * dyy
    cy = dxz * dyx - dxx * dyz
    cz = dxx * dyy - dxy * dyx
    norm = np.sqrt(cx * cx + cy * cy + cz * cz)
    zc = at(z, 0, 0)
    jump = np.float32(2 * max_depth_jump_m)
    if f_px is not None:
        slope = np.float32(2 * np.tan(np.radians(MAX_INCIDENCE_DEG)) / f_px)
        jump = np.maximum(jump, slope * zc)
    valid = (
        (zc > 0)
        & (norm > 1e-12)
        & (at(z, 0, 1) > 0)
        & (at(z, 0, -1) > 0)
        & (at(z, 1, 0) > 0)
        & (at(z, -1, 0) > 0)
        & (np.abs(dxz) < jump)
        & (np.abs(dyz) < jump)
    )
    # orient towards the camera (the viewing ray is +vertex): flip where n . vertex > 0
    facing = cx * at(x, 0, 0) + cy * at(y, 0, 0) + cz * zc
    inv = np.where(valid, np.where(facing > 0, -1.0, 1.0) / np.maximum(norm, 1e-12), 0.0)
    n = np.empty((*zc.shape, 3), np.float32) if out is None else out
    n[..., 0] = cx * inv
    n[..., 1] = cy * inv
    n[..., 2] = cz * inv
    return n


def geometry_reference(vertex: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Geometry rows of (N, 3) vertices and normals: vertex, 0, normal, 1 where known."""
    out = np.zeros((len(vertex), 8), np.float32)
    out[:, :3] = vertex
    out[:, 4:7] = normal
    out[:, 7] = np.any(normal != 0, axis=1)
    return out


def wavy_depth(rng: np.random.Generator, h: int = 48, w: int = 64, far_from: int | None = None):
    """``(depth, K)``: a wavy surface about 1 m away with a tenth of its pixels missing (3 m
    farther from column ``far_from`` on when given), and intrinsics of a 64 x 48 view scaled
    to ``w`` x ``h``."""
    K = np.array([[60.0 * w / 64, 0.0, 31.5 * w / 64], [0.0, 60.0 * h / 48, 23.5 * h / 48],
                  [0.0, 0.0, 1.0]])  # fmt: skip
    v, u = np.mgrid[0:h, 0:w]
    depth = 1.0 + 0.3 * np.sin(u / 6.0) * np.cos(v / 5.0)
    if far_from is not None:
        depth += 3.0 * (u >= far_from)
    depth = depth.astype(np.float32)
    depth[rng.random((h, w)) < 0.1] = 0.0
    return depth, K
