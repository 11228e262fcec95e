"""Bundle adjustment of keyframe poses and ORB landmark positions on GTSAM.

The factor graph: a ``Pose3`` per keyframe, a ``Point3`` per landmark (a track of
:class:`~slam.backend.landmarks.LandmarkMap` seen by two keyframes or more) and, per
observation, one ``GenericStereoFactor3D``: ORB-SLAM2's RGB-D trick, the depth ``z`` measured at
the keypoint turned into the right pixel of a virtual stereo pair, ``u_R = u - fx * b / z``.

Why the stereo factor rather than a projection factor plus a range factor: one C++ factor (and
one 3-vector residual, robustified as a whole) per observation instead of two, which halves the
graph built from Python; and its third coordinate is a *disparity*, in which structured-light
depth noise is constant (Kinect depth noise grows as z^2: sigma_z = ``depth_sigma_m`` * z^2 at
z metres is a constant disparity noise ``fx * b * depth_sigma_m``), so one noise model fits near
and far points alike. The pixel and the depth are measured independently, but ``u_R`` contains
``u``; the noise model is therefore the full covariance of (u_L, u_R, v) (``Cov(u_L, u_R) =
sigma_px^2``), which makes the factor exactly a projection term (``pixel_sigma_px``) plus an
independent depth term, whatever the virtual baseline. The pixel noise is that of the
keypoint's ORB pyramid level, ``pixel_sigma_px * 1.2**level`` (ORB-SLAM's weighting; the
keypoint error grows so with the level); with one noise for all, coarse-level keypoints of fast
pans pulled keyframes off (synthetic ``fastrot-fr1``: final ATE 0.0035 m against its pose
graph's 0.0017 m; weighted 0.0016 m). The depth noise is per observation too
(:func:`depth_sigmas`): the sensor's, plus what a pixel's error reads on the slope of the depth
around the keypoint (a keypoint on a corner or a depth edge reads a neighbouring ray's depth; on
a flat poster its depth is as good as the sensor's). Robust: Huber on the whitened residual at
``huber_px`` pixels (of level 0). The gauge is fixed by a prior on the first keyframe of each connected
part (or on the keyframes the caller fixes). Levenberg-Marquardt; then observations whose
residual stays above ``outlier_chi2`` are removed and the problem is optimised again.

The pose graph's own edges (depth registration: odometry and loops) stay in the problem with
their information scaled by a weight (``ba.pose_graph_weight``): BA refines the pose graph's
solution rather than replacing it. Where tracks are long (a desk seen over and over) the
landmarks dominate; where they are short (each landmark seen by 2-3 keyframes) sparse features
alone would drift more than dense ICP odometry does, and the edges hold the keyframes; a
keyframe no landmark constrains moves with its neighbours instead of staying behind. How much
the edges should weigh differs by orders of magnitude between sequences (exact synthetic depth
against a real Kinect); the weight is fixed (``ba.pose_graph_weight``).

What BA does on the sequences that cannot feed it (:class:`BundleAdjuster`):

- depth-only sequences (no colour, hence no ORB features): nothing: no landmarks exist, the
  result says why (``skipped``) and the pose-graph poses stand. The same holds when too few
  landmarks are observed per keyframe (``ba.min_observations_per_keyframe``).
- colour not registered to depth (``color_registered=False``; e.g. 7-Scenes, whose colour and
  depth come from two cameras with an unknown offset and ~10% different focal lengths): BA
  runs, but with the depth term weakened to ``ba.unregistered_depth_sigma_m``. The keypoint's
  pixel is still a sharp measurement of the colour camera (modelled with the depth camera's
  intrinsics: a smooth systematic error, largely absorbed by the landmark positions), but the
  depth read at that pixel belongs to a neighbouring ray, and keypoints sit on corners, often
  on depth edges, where the neighbouring ray hits another surface. Measured on 7scenes-1000
  (keyframe ATE, pose graph 49.6 mm, edges at weight 1): 44.7 mm with a depth noise of 4 mm
  at 1 m, 32.9 mm at 6 cm; inflating the pixel noise instead made it worse (48.4 mm at 2 px).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Mapping, Sequence

import gtsam
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from slam.backend.ba_problem import BAProblem, BAResult, BundleAdjustmentError
from slam.backend.pose_graph import Edge
from slam.config import BAConfig
from slam.geometry import inv_T, rotation_angle_deg, translation_norm
from slam.keyframe import SCALE_FACTOR

log = logging.getLogger(__name__)

#: virtual stereo baseline (metres); any value gives the same solution (see the docstring)
VIRTUAL_BASELINE_M = 0.08
#: chi^2 95% quantiles: 3 dof (pixel + depth), 2 dof (pixel only)
CHI2_3DOF = 7.815
CHI2_2DOF = 5.991


def _x(k: int) -> int:
    return gtsam.symbol("x", int(k))


def _l(i: int) -> int:
    return gtsam.symbol("l", int(i))


def initial_points(problem: BAProblem, poses: Mapping[int, np.ndarray]) -> np.ndarray:
    """Landmark positions (L, 3, world) from depth: the mean of the observations' pixels lifted
    by their depth under ``poses`` (observations without depth do not contribute; a landmark
    with none gets its first observation at 1 m)."""
    K = problem.K
    z = np.where(problem.depth > 0, problem.depth, 1.0)
    x = (problem.uv[:, 0] - K[0, 2]) / K[0, 0] * z
    y = (problem.uv[:, 1] - K[1, 2]) / K[1, 1] * z
    Ts = np.stack([poses[int(k)] for k in problem.kf]) if len(problem) else np.zeros((0, 4, 4))
    pc = np.stack([x, y, z], axis=1)
    pw = np.einsum("mij,mj->mi", Ts[:, :3, :3], pc) + Ts[:, :3, 3]
    w = (problem.depth > 0).astype(float)
    L = problem.n_landmarks
    sums = np.zeros((L, 3))
    np.add.at(sums, problem.landmark, pw * w[:, None])
    counts = np.bincount(problem.landmark, weights=w, minlength=L)
    first = np.full(L, -1)
    first[problem.landmark[::-1]] = np.arange(len(problem))[::-1]
    out = pw[first].copy()
    has = counts > 0
    out[has] = sums[has] / counts[has, None]
    return out


def _noise_cov(fx: float, pixel_sigma: float, depth_sigma: float) -> np.ndarray:
    """Covariance of (u_L, u_R, v) for a pixel noise and a depth noise at 1 m (see module)."""
    s2 = pixel_sigma**2
    sd = fx * VIRTUAL_BASELINE_M * depth_sigma  # disparity noise in pixels, the same at all z
    return np.array([[s2, s2, 0.0], [s2, s2 + sd**2, 0.0], [0.0, 0.0, s2]])


#: per-observation depth noises are rounded to powers of this ratio (one GTSAM noise model
#: per level and step instead of one per observation)
_DEPTH_SIGMA_STEP = 1.25


def depth_sigmas(problem: BAProblem, cfg: BAConfig) -> np.ndarray:
    """Per observation, its depth noise at 1 m (the factor scales it by z^2): the sensor's
    ``depth_sigma_m``, and the depth the keypoint's pixel error reaches on the surface around
    it, ``slope * depth_misregistration_px * 1.2**level`` (a keypoint on a depth edge reads a
    neighbouring ray's depth; on a flat poster its depth is as good as the sensor's), added in
    quadrature; rounded to steps of ``_DEPTH_SIGMA_STEP``."""
    s0 = float(cfg.depth_sigma_m)
    if problem.depth_slope is None or cfg.depth_misregistration_px <= 0:
        return np.full(len(problem), s0)
    z = np.where(problem.depth > 0, problem.depth, 1.0)
    edge = problem.depth_slope * cfg.depth_misregistration_px * problem.pixel_scale() / z**2
    sigma = np.sqrt(s0**2 + edge**2)
    steps = np.round(np.log(sigma / s0) / np.log(_DEPTH_SIGMA_STEP))
    return s0 * _DEPTH_SIGMA_STEP**steps


def residuals(
    problem: BAProblem,
    poses: Mapping[int, np.ndarray],
    points: np.ndarray,
    pixel_sigma: float,
    depth_sigma: float | np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Per observation: the reprojection error (pixels, 2D norm) and the whitened chi^2 of the
    factor's residual (3 dof with depth, 2 without). Points behind the camera: inf.
    ``depth_sigma``: the depth noise at 1 m, one for all or one per observation."""
    K = problem.K
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    Ts = np.stack([poses[int(k)] for k in problem.kf])
    R, t = Ts[:, :3, :3], Ts[:, :3, 3]
    pc = np.einsum("mji,mj->mi", R, points[problem.landmark] - t)
    z = pc[:, 2]
    front = z > 1e-6
    zs = np.where(front, z, 1.0)
    du = fx * pc[:, 0] / zs + cx - problem.uv[:, 0]
    dv = fy * pc[:, 1] / zs + cy - problem.uv[:, 1]
    bf = fx * VIRTUAL_BASELINE_M
    has_d = problem.depth > 0
    dd = np.where(has_d, bf / np.where(has_d, problem.depth, 1.0) - bf / zs, 0.0)  # u_R error
    reproj = np.sqrt(du**2 + dv**2)
    sigma = pixel_sigma * problem.pixel_scale()
    # the inverse of _noise_cov per observation, in closed form: (u_L, u_R, v) with
    # Cov = [[s2, s2, 0], [s2, s2 + sd2, 0], [0, 0, s2]]
    s2 = sigma**2
    sd2 = (fx * VIRTUAL_BASELINE_M * depth_sigma) ** 2
    chi2_d = (du**2 * (s2 + sd2) - 2 * du * (du + dd) * s2 + (du + dd) ** 2 * s2) / (s2 * sd2)
    chi2 = np.where(has_d, chi2_d + dv**2 / s2, (du**2 + dv**2) / s2)
    reproj = np.where(front, reproj, np.inf)
    chi2 = np.where(front, chi2, np.inf)
    return reproj, chi2


def _rmse(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if len(x) else 0.0


def _components(problem: BAProblem, kf_ids: list[int], edges: Sequence[Edge]) -> list[list[int]]:
    """Keyframes grouped by connection (shared landmarks or edges)."""
    index = {k: i for i, k in enumerate(kf_ids)}
    n = len(kf_ids)
    rows = [np.array([index[int(k)] for k in problem.kf], dtype=np.int64)]
    cols = [n + problem.landmark]
    for e in edges:
        rows.append(np.array([index[e.i]]))
        cols.append(np.array([index[e.j]]))
    r, c = np.concatenate(rows), np.concatenate(cols)
    size = n + problem.n_landmarks
    A = coo_matrix((np.ones(len(r)), (r, c)), shape=(size, size))
    _, labels = connected_components(A, directed=False)
    groups: dict[int, list[int]] = {}
    for k, lab in zip(kf_ids, labels[:n]):
        groups.setdefault(int(lab), []).append(k)
    return list(groups.values())


class _Solver:
    """The factor graph of a bundle-adjustment problem and its Levenberg-Marquardt solve: one
    stereo factor per observation with depth (a projection factor without), noise by ORB
    pyramid level under a Huber kernel, the pose graph's ``edges`` (loops under a Cauchy
    kernel) at ``edge_weight``, and a prior on the ``fixed`` keyframes (at least one per
    connected part: the gauge)."""

    def __init__(
        self,
        problem: BAProblem,
        cfg: BAConfig,
        fixed: set[int],
        edges: list[Edge],
        edge_weight: float,
        loop_kernel_width: float,
    ) -> None:
        self.cfg, self.fixed, self.edges = cfg, fixed, edges
        self.edge_weight, self.loop_kernel_width = edge_weight, loop_kernel_width
        sigma = float(cfg.pixel_sigma_px)
        K = self.K = problem.K
        self.calib = gtsam.Cal3_S2Stereo(
            K[0, 0], K[1, 1], 0.0, K[0, 2], K[1, 2], VIRTUAL_BASELINE_M
        )
        self.calib_mono = gtsam.Cal3_S2(K[0, 0], K[1, 1], 0.0, K[0, 2], K[1, 2])
        huber = gtsam.noiseModel.mEstimator.Huber.Create(cfg.huber_px / sigma)
        # one noise model per ORB pyramid level (a keypoint's pixel noise grows with its level)
        # and depth noise (:func:`depth_sigmas`), made when first needed
        levels = np.unique(problem.level) if problem.level is not None else np.zeros(1, np.int64)
        self.huber = huber
        self.stereo_noise: dict[tuple[int, float], gtsam.noiseModel.Base] = {}
        self.mono_noise = {
            int(lv): gtsam.noiseModel.Robust.Create(
                huber, gtsam.noiseModel.Isotropic.Sigma(2, sigma * SCALE_FACTOR ** int(lv))
            )
            for lv in levels
        }
        self.prior_noise = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)

    def _stereo_noise(self, level: int, depth_sigma: float) -> gtsam.noiseModel.Base:
        key = (level, depth_sigma)
        if key not in self.stereo_noise:
            pixel = float(self.cfg.pixel_sigma_px) * SCALE_FACTOR**level
            cov = _noise_cov(self.K[0, 0], pixel, depth_sigma)
            self.stereo_noise[key] = gtsam.noiseModel.Robust.Create(
                self.huber, gtsam.noiseModel.Gaussian.Covariance(cov)
            )
        return self.stereo_noise[key]

    def variables(self, prob: BAProblem) -> tuple[list[int], set[int]]:
        """The keyframes to optimise and those held by a prior (at least one per part)."""
        edges = self.edges
        kf_ids = sorted(
            {int(k) for k in np.unique(prob.kf)} | {e.i for e in edges} | {e.j for e in edges}
        )
        held = self.fixed.intersection(kf_ids)
        for group in _components(prob, kf_ids, edges):
            if not held.intersection(group):
                held.add(min(group))
        return kf_ids, held

    def build(self, prob: BAProblem, pts: np.ndarray, start: Mapping[int, np.ndarray]):
        kf_ids, held = self.variables(prob)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        for k in kf_ids:
            values.insert(_x(k), gtsam.Pose3(start[k]))
        for i in range(prob.n_landmarks):
            values.insert(_l(i), gtsam.Point3(*pts[i]))
        for k in sorted(held):
            graph.add(gtsam.PriorFactorPose3(_x(k), gtsam.Pose3(start[k]), self.prior_noise))
        bf = self.K[0, 0] * VIRTUAL_BASELINE_M
        obs_level = prob.level.tolist() if prob.level is not None else [0] * len(prob)
        obs_depth_sigma = depth_sigmas(prob, self.cfg).tolist()
        for k, lm, (u, v), z, lv, sd in zip(
            prob.kf.tolist(), prob.landmark.tolist(), prob.uv, prob.depth, obs_level,
            obs_depth_sigma,
        ):  # fmt: skip
            if z > 0:
                m = gtsam.StereoPoint2(u, u - bf / z, v)
                noise = self._stereo_noise(lv, sd)
                graph.add(gtsam.GenericStereoFactor3D(m, noise, _x(k), _l(lm), self.calib))
            else:
                graph.add(
                    gtsam.GenericProjectionFactorCal3_S2(
                        gtsam.Point2(u, v), self.mono_noise[lv], _x(k), _l(lm), self.calib_mono
                    )
                )
        for e in self.edges:
            gauss = gtsam.noiseModel.Gaussian.Information(e.information * self.edge_weight)
            noise = (
                gtsam.noiseModel.Robust.Create(
                    gtsam.noiseModel.mEstimator.Cauchy.Create(self.loop_kernel_width), gauss
                )
                if e.kind == "loop"
                else gauss
            )
            graph.add(gtsam.BetweenFactorPose3(_x(e.i), _x(e.j), gtsam.Pose3(e.T_i_j), noise))
        return graph, values, kf_ids

    def optimise(self, prob: BAProblem, pts: np.ndarray, start: Mapping[int, np.ndarray]):
        """(poses by keyframe id, landmark points, iterations, error before, error after)."""
        graph, values, kf_ids = self.build(prob, pts, start)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.cfg.max_iterations)
        params.setRelativeErrorTol(1e-5)
        params.setAbsoluteErrorTol(1e-6)
        params.setLinearSolverType("SEQUENTIAL_CHOLESKY")  # ~25% faster than multifrontal here
        # eliminate the landmarks first (the Schur complement onto the poses), the poses in
        # COLAMD's order: a few times faster than COLAMD's ordering of everything
        params.setOrdering(
            gtsam.Ordering.ColamdConstrainedLastNonlinearFactorGraph(
                graph, gtsam.KeyVector([_x(k) for k in kf_ids])
            )
        )
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        e0 = graph.error(values)
        res = opt.optimize()
        out_poses = {k: res.atPose3(_x(k)).matrix() for k in kf_ids}
        for k in start:  # keyframes no longer in the problem keep their pose
            out_poses.setdefault(k, np.asarray(start[k]))
        out_pts = np.array([res.atPoint3(_l(i)) for i in range(prob.n_landmarks)]).reshape(-1, 3)
        return out_poses, out_pts, opt.iterations(), e0, graph.error(res)


def bundle_adjust(
    problem: BAProblem,
    poses: Mapping[int, np.ndarray],
    cfg: BAConfig,
    fixed: Iterable[int] | None = None,
    edges: Sequence[Edge] = (),
    edge_weight: float = 1.0,
    loop_kernel_width: float = 2.0,
) -> BAResult:
    """Optimise the poses of the keyframes observed in ``problem`` (plus those joined by
    ``edges``) and the landmark positions, starting from ``poses`` (``T_world_kf`` by id) and
    landmarks initialised from depth (:func:`initial_points`); then remove the observations
    whose whitened residual exceeds ``cfg.outlier_chi2`` and optimise again without them.

    ``fixed``: keyframes held at their starting pose (default: the first keyframe of each
    connected part fixes the gauge). ``edges``: relative-pose edges (the pose graph's
    :class:`~slam.backend.pose_graph.Edge`; loop edges get a Cauchy kernel of width
    ``loop_kernel_width``) with information scaled by ``edge_weight``; only edges between
    keyframes in ``poses`` are used.
    """
    t0 = time.perf_counter()
    sigma = float(cfg.pixel_sigma_px)
    missing = sorted({int(k) for k in np.unique(problem.kf)} - set(poses))
    if missing:
        raise BundleAdjustmentError(f"observations of keyframes {missing[:5]} without a pose")
    if len(problem) == 0:
        return BAResult(skipped="no landmark is observed by two keyframes", ms=_ms(t0))
    edges = [e for e in edges if e.i in poses and e.j in poses and edge_weight > 0]
    solver = _Solver(
        problem, cfg, {int(k) for k in (fixed or ())}, edges, edge_weight, loop_kernel_width
    )
    points0 = initial_points(problem, poses)
    reproj0, _ = residuals(problem, poses, points0, sigma, depth_sigmas(problem, cfg))
    prob = problem
    new_poses, pts, iters, err0, err1 = solver.optimise(prob, points0, poses)
    _, chi2 = residuals(prob, new_poses, pts, sigma, depth_sigmas(prob, cfg))
    thr = np.where(prob.depth > 0, cfg.outlier_chi2, cfg.outlier_chi2 * CHI2_2DOF / CHI2_3DOF)
    outlier = ~(chi2 <= thr)
    inlier_mask = ~outlier
    if outlier.any():
        prob = problem.subset(inlier_mask)
        inlier_mask = np.isin(problem.landmark_ids[problem.landmark], prob.landmark_ids) & ~outlier
        if len(prob) == 0:
            return BAResult(skipped="every observation is an outlier", ms=_ms(t0))
        pts_in = pts[np.searchsorted(problem.landmark_ids, prob.landmark_ids)]
        new_poses, pts, it2, _, err1 = solver.optimise(prob, pts_in, new_poses)
        iters += it2
    reproj1, _ = residuals(prob, new_poses, pts, sigma, depth_sigmas(prob, cfg))
    changes = [inv_T(np.asarray(poses[k])) @ new_poses[k] for k in new_poses]
    result = BAResult(
        poses=new_poses,
        points=pts,
        landmark_ids=prob.landmark_ids,
        reprojection_rmse_px_before=_rmse(reproj0[inlier_mask]),
        reprojection_rmse_px_after=_rmse(reproj1),
        landmarks=prob.n_landmarks,
        observations=len(prob),
        outliers=int(outlier.sum()),
        outlier_kf=problem.kf[outlier],
        outlier_feature=problem.feature[outlier],
        keyframes=len(solver.variables(prob)[0]),
        iterations=int(iters),
        ms=_ms(t0),
        error_before=float(err0),
        error_after=float(err1),
        max_pose_change_m=max(translation_norm(T) for T in changes),
        max_pose_change_deg=max(rotation_angle_deg(T) for T in changes),
        edge_weight=solver.edge_weight if edges else 0.0,
    )
    _log_result(result)
    return result


def _log_result(result: BAResult) -> None:
    log.info(
        "bundle adjustment: %d keyframes, %d landmarks, %d observations (%d outliers removed): "
        "reprojection RMSE %.2f -> %.2f px in %d iterations, %.0f ms; poses moved up to "
        "%.1f mm / %.2f deg",
        result.keyframes,
        result.landmarks,
        result.observations,
        result.outliers,
        result.reprojection_rmse_px_before,
        result.reprojection_rmse_px_after,
        result.iterations,
        result.ms,
        1e3 * result.max_pose_change_m,
        result.max_pose_change_deg,
    )


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3
