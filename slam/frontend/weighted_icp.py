"""Point-to-plane ICP weighted by the depth sensor's noise, and what its normal equations say
about the constraint.

A structured-light sensor's axial depth noise grows with the square of the depth (Nguyen, Izadi,
Lovell 2012: ``sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2`` metres for a Kinect v1), so a point 4 m
away is ~50 times noisier than one at 1 m. Each point-to-plane residual is weighed by
``1 / sigma(z)^2`` (times a Huber weight of the residual in sigma units) instead of cutting far
depth away: near depth dominates where it constrains the pose, and far depth still constrains
what near depth cannot (sliding along a wall that fills the view), at its true weight.

The weighted normal equations ``H = sum_i w_i J_i^T J_i`` are the information of the pose
(the inverse of its covariance under the noise model). :func:`constraint` reads from them how
well each direction of motion is constrained (Gelfand et al. 2003, "geometrically stable
sampling"; Zhang, Kaess, Singh 2016, "degeneracy factor"): rotations are expressed as the
motion they cause at the scene's depth, so all six directions are compared in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.camera import DepthNoise
from slam.frontend.pointcloud import normal_map
from slam.frontend.robust import median, robust_scale
from slam.geometry import exp_se3


def vertex_map(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 camera-frame points of a depth image (0 where no depth)."""
    h, w = depth_m.shape
    xs = ((np.arange(w) - K[0, 2]) / K[0, 0]).astype(np.float32)
    ys = ((np.arange(h) - K[1, 2]) / K[1, 1]).astype(np.float32)
    z = np.asarray(depth_m, np.float32)
    return np.stack([z * xs[None, :], z * ys[:, None], z], axis=-1)


@dataclass
class SourcePoints:
    """A depth image's valid pixels as camera-frame points with their depth noise."""

    points: np.ndarray  # (N, 3) float32
    sigma: np.ndarray  # (N,) float32, metres
    normals: np.ndarray | None = None  # (N, 3) float32, 0 where unknown

    def normal_columns(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Normal x, y, z as contiguous arrays (built once)."""
        if not hasattr(self, "_ncolumns"):
            assert self.normals is not None
            self._ncolumns = tuple(np.ascontiguousarray(self.normals[:, k]) for k in range(3))
        return self._ncolumns  # type: ignore[return-value]

    def columns(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, y, z as contiguous arrays (built once)."""
        if not hasattr(self, "_columns"):
            self._columns = tuple(np.ascontiguousarray(self.points[:, k]) for k in range(3))
        return self._columns  # type: ignore[return-value]

    @staticmethod
    def from_depth(depth_m: np.ndarray, K: np.ndarray, noise: DepthNoise) -> SourcePoints:
        """Points with a known normal (from the depth's vertex map)."""
        vertex = vertex_map(depth_m, K)
        normal = normal_map(vertex, f_px=float(K[0, 0]))
        v, u = np.nonzero(normal[..., 2] != 0)
        pts = vertex[v, u]
        return SourcePoints(pts, noise.sigma(pts[:, 2]), normal[v, u])


Columns = tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass
class _Target:
    """A target vertex and normal map as flat x, y, z columns, and its camera."""

    vertex: Columns
    normal: Columns
    K: np.ndarray
    size: tuple[int, int]  # (h, w)

    @staticmethod
    def of(tgt_vertex: np.ndarray, tgt_normal: np.ndarray, K: np.ndarray) -> _Target:
        def columns(a: np.ndarray) -> Columns:
            return tuple(np.ascontiguousarray(a[..., k]).reshape(-1) for k in range(3))  # type: ignore[return-value]

        return _Target(columns(tgt_vertex), columns(tgt_normal), K, tgt_vertex.shape[:2])

    def associate(
        self, src: SourcePoints, T: np.ndarray, gate_m: float, min_normal_cos: float
    ) -> tuple[Columns, Columns, np.ndarray, np.ndarray] | None:
        """Projective correspondences of the source points moved by ``T``: the moved points,
        the target normals, the point-to-plane residuals and the points' depth noise, of the
        pairs within ``gate_m`` plus 3 sigma whose normals agree (cosine >= ``min_normal_cos``;
        unknown target normals are 0 and fail). None when fewer than 6 remain."""
        h, w = self.size
        vx, vy, vz = self.vertex
        nx, ny, nz = self.normal
        px, py, pz = src.columns()
        sx, sy, sz = src.normal_columns()
        f32 = np.float32
        K = self.K
        fx, fy, cx, cy = (f32(k) for k in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        R, t = T[:3, :3].astype(f32), T[:3, 3].astype(f32)
        qx = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
        qy = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
        qz = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
        front = qz > f32(1e-3)
        inv_z = f32(1.0) / np.where(front, qz, f32(1.0))
        ui = (fx * qx * inv_z + cx + f32(0.5)).astype(np.int32)
        vi = (fy * qy * inv_z + cy + f32(0.5)).astype(np.int32)
        idx = np.flatnonzero(front & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h))
        pix = vi[idx] * w + ui[idx]
        ax, ay, az = qx[idx], qy[idx], qz[idx]
        mx, my, mz = nx[pix], ny[pix], nz[pix]
        res = (ax - vx[pix]) * mx + (ay - vy[pix]) * my + (az - vz[pix]) * mz
        sig = src.sigma[idx]
        # the source normal, rotated into the target camera, against the target's
        cos = (
            (R[0, 0] * sx[idx] + R[0, 1] * sy[idx] + R[0, 2] * sz[idx]) * mx
            + (R[1, 0] * sx[idx] + R[1, 1] * sy[idx] + R[1, 2] * sz[idx]) * my
            + (R[2, 0] * sx[idx] + R[2, 1] * sy[idx] + R[2, 2] * sz[idx]) * mz
        )
        keep = np.flatnonzero((np.abs(res) < f32(gate_m) + 3 * sig) & (cos >= min_normal_cos))
        if len(keep) < 6:
            return None
        moved = (ax[keep], ay[keep], az[keep])
        return moved, (mx[keep], my[keep], mz[keep]), res[keep], sig[keep]


@dataclass
class WeightedIcp:
    """The outcome of :func:`weighted_point_to_plane`: ``T_target_source``, its information
    ``H`` (6x6, twist order rotation then translation, 1/m^2 and 1/rad^2 units), the fraction of
    source points with a correspondence, the residual RMSE in metres and the median depth of
    the correspondences (the lever arm of rotations)."""

    T_target_source: np.ndarray
    H: np.ndarray
    fitness: float
    rmse_m: float
    depth_m: float


def weighted_point_to_plane(
    src: SourcePoints,
    tgt_vertex: np.ndarray,
    tgt_normal: np.ndarray,
    K: np.ndarray,
    T_init: np.ndarray,
    iterations: int,
    gate_m: float,
    huber_k: float = 2.0,
    min_normal_cos: float = 0.9,
) -> WeightedIcp | None:
    """Gauss-Newton point-to-plane ICP with projective association against a target vertex
    and normal map (HxWx3, target camera frame, zero normal where unknown). A correspondence is
    kept when its residual is within ``gate_m`` plus 3 sigma of its depth noise and the
    source normal (rotated) agrees with the target's (cosine >= ``min_normal_cos``); weights are
    ``huber(e / s) / (s sigma)^2`` with ``e = r / sigma`` and ``s`` the robust scale of ``e``
    (measured on the first iteration: the noise model gives the shape, the data the level).
    None when fewer than 6 points correspond. Arrays are handled by component (x, y, z
    columns): ~4x faster than (N, 3) rows in numpy."""
    target = _Target.of(tgt_vertex, tgt_normal, K)
    T = np.asarray(T_init, float).copy()
    scale = None
    H = np.zeros((6, 6))
    r = np.zeros(0, np.float32)
    qz_kept = np.zeros(0, np.float32)
    f32 = np.float32
    for _ in range(max(int(iterations), 1)):
        kept = target.associate(src, T, gate_m, min_normal_cos)
        if kept is None:
            return None
        (ax, ay, az), (mx, my, mz), r, sig = kept
        e = r / sig
        if scale is None:
            scale = robust_scale(e, 1e-3)
        a = np.abs(e) * f32(1.0 / scale)
        wt = np.where(a <= huber_k, f32(1.0), f32(huber_k) / np.maximum(a, f32(1e-12)))
        wt /= (f32(scale) * sig) ** 2
        J = np.empty((6, len(r)), np.float32)
        np.subtract(ay * mz, az * my, out=J[0])
        np.subtract(az * mx, ax * mz, out=J[1])
        np.subtract(ax * my, ay * mx, out=J[2])
        J[3], J[4], J[5] = mx, my, mz
        Jw = J * wt
        H = (Jw @ J.T).astype(np.float64)
        b = (Jw @ r).astype(np.float64)
        damped = H + np.eye(6) * (1e-9 * np.trace(H) + 1e-12)
        T = exp_se3(-np.linalg.solve(damped, b)) @ T
        qz_kept = az
    return WeightedIcp(
        T,
        H,
        len(r) / max(len(src.points), 1),
        float(np.sqrt(np.mean(np.square(r, dtype=np.float64)))),
        median(qz_kept),
    )


@dataclass
class Constraint:
    """How well an alignment's geometry constrains the pose: the standard deviation (metres,
    rotations as motion at the scene's depth) along the weakest and the strongest direction of
    the 6-D motion, the weakest direction itself (unit twist, rotation then translation, in the
    scaled coordinates) and its share of translation (1: a pure slide, 0: a pure rotation)."""

    weakest_std_m: float
    strongest_std_m: float
    direction: np.ndarray
    translation_share: float

    @property
    def ratio(self) -> float:
        """Weakest over strongest standard deviation (>= 1; large: degenerate)."""
        return self.weakest_std_m / max(self.strongest_std_m, 1e-30)


def metric_eigen(H: np.ndarray, depth_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(s, vals, vecs)``: the eigen-decomposition (ascending) of the information ``H`` in
    scaled coordinates ``x / s`` where a rotation of 1 rad counts as the ``depth_m`` metres it
    moves the scene (``s = [1/L]*3 + [1]*3``), so the six directions compare in metres."""
    L = max(float(depth_m), 0.1)
    s = np.array([1.0 / L] * 3 + [1.0] * 3)
    Hs = H * s[:, None] * s[None, :]
    vals, vecs = np.linalg.eigh(0.5 * (Hs + Hs.T))
    return s, vals, vecs


def constraint(H: np.ndarray, depth_m: float) -> Constraint:
    """Eigen-analysis of the information ``H`` with rotations scaled by ``depth_m`` (a rotation
    of 1 rad moves the scene by ``depth_m`` metres), so the six directions compare in metres."""
    _, vals, vecs = metric_eigen(H, depth_m)
    vals = np.maximum(vals, 1e-30)
    d = vecs[:, 0]
    return Constraint(
        float(1.0 / np.sqrt(vals[0])),
        float(1.0 / np.sqrt(vals[-1])),
        d,
        float(np.linalg.norm(d[3:]) ** 2),
    )


def without_blind_directions(
    H: np.ndarray, b: np.ndarray, depth_m: float, ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """The normal equations ``(H, b)`` of an alignment term without the directions it
    constrains more than ``ratio`` times worse than its best (standard deviations, compared as
    :func:`constraint` does, rotations as motion at ``depth_m``): there its information and its
    gradient are set to zero, so another term decides alone. Depth is blind along a corridor
    or a wall filling the view, and what little it says there comes from a few pixels at depth
    edges and the model's bias (a sub-millimetre bias moves the estimate by about the bias
    times the ratio), not from the noise its weights assume."""
    s, vals, vecs = metric_eigen(H, depth_m)
    strong = vals >= vals[-1] / ratio**2
    if strong.all():
        return H, b
    V = vecs[:, strong]
    Hs = (V * vals[strong]) @ V.T
    bs = V @ (V.T @ (b * s))
    return Hs / s[:, None] / s[None, :], bs / s


def depth_information(
    depth_m: np.ndarray, K: np.ndarray, depth_max_m: float, noise: DepthNoise
) -> tuple[np.ndarray, float] | None:
    """``(H, median depth m)``: the point-to-plane information ``sum w J^T J`` of a depth
    image's points nearer than ``depth_max_m`` (with their normals; ``J = [p x n, n]``, twist
    rotation first, ``w = 1 / sigma(z)^2``) and the points' median depth; None with fewer than 6
    points. At the correct pose an alignment's residuals have this Jacobian."""
    d = np.where((depth_m > 0) & (depth_m < depth_max_m), depth_m, np.float32(0.0))
    vertex = vertex_map(np.asarray(d, np.float32), K)
    normal = normal_map(vertex, f_px=float(K[0, 0]))
    ok = normal[..., 2] != 0  # normals face the camera: z is never 0 where one is known
    ok[:, 1::2] = False  # every other column: the ratio is a shape, not a sum (2x cheaper)
    p, n = vertex[ok].astype(np.float64), normal[ok].astype(np.float64)
    if len(p) < 6:
        return None
    J = np.concatenate([np.cross(p, n), n], axis=1)
    w = 1.0 / noise.sigma(p[:, 2]).astype(np.float64) ** 2
    return (J * w[:, None]).T @ J, float(np.partition(p[:, 2], len(p) // 2)[len(p) // 2])


def depth_constraint(
    depth_m: np.ndarray, K: np.ndarray, depth_max_m: float, noise: DepthNoise
) -> Constraint:
    """How well a depth image's own geometry constrains a point-to-plane alignment, before any
    alignment: :func:`depth_information` as :func:`constraint` sees it (rotations scaled by the
    points' median depth). At the correct pose the residuals' Jacobian is this one, so a large
    ratio says which motion depth cannot see: a wall filling the view, a corridor."""
    info = depth_information(depth_m, K, depth_max_m, noise)
    if info is None:
        return Constraint(float("inf"), 0.0, np.zeros(6), 0.0)
    return constraint(*info)
