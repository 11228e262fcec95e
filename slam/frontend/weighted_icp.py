"""What depth's point-to-plane normal equations say about the constraint on a pose.

A structured-light sensor's axial depth noise grows with the square of the depth (Nguyen, Izadi,
Lovell 2012: ``sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2`` metres for a Kinect v1), so a point 4 m
away is ~50 times noisier than one at 1 m: each point's term is weighed by ``1 / sigma(z)^2``.

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
from slam.frontend.depth_kernels import information
from slam.frontend.pointcloud import geometry_rows


def vertex_map(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 camera-frame points of a depth image (0 where no depth)."""
    h, w = depth_m.shape
    xs = ((np.arange(w) - K[0, 2]) / K[0, 0]).astype(np.float32)
    ys = ((np.arange(h) - K[1, 2]) / K[1, 1]).astype(np.float32)
    z = np.asarray(depth_m, np.float32)
    return np.stack([z * xs[None, :], z * ys[:, None], z], axis=-1)


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
    # normals face the camera: z is never 0 where one is known; every other column: the
    # ratio is a shape, not a sum (2x cheaper); one compiled pass (depth_kernels.information)
    geometry = geometry_rows(d, K)
    noise_model = np.array([noise.sigma0_m, noise.quadratic, noise.z0_m])
    H, depths = information(geometry, d.shape[1], noise_model)
    if len(depths) < 6:
        return None
    return H, float(np.partition(depths, len(depths) // 2)[len(depths) // 2])


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
