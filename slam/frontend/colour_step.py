"""The frame-to-frame colour step of tracking (``tracking.colour.colour_step_weight``, opt-in) and the
weight it gives colour, measured on the recording.

:func:`colour_refine` moves a frame's depth estimate (frame-to-model ICP) by Gauss-Newton on
depth's estimate as a Gaussian prior (with its point-to-plane information there) plus colour's
photometric cost against the previous frame (:func:`colour_equations`, the terms of
:func:`slam.frontend.photometric.joint_align`). Where depth is weak (along a wall filling the
view, a corridor) colour moves the frame; where depth is sure its information holds it.
What it costs is set by where the two terms are evaluated: colour on the most textured pixels
(its Jacobian is the image gradient; elsewhere it adds little information), depth's
information on every second row and column (its shape is the scene's; a coarser pyramid
level would average across depth edges).

How much colour weighs: :class:`ColourAgreement`. Colour is registered to depth on every
synthetic sequence and nearly so on a real Kinect, but only nearly: on ``tum-fr1-xyz`` a frame's
colour puts it 1-3 mm from where depth puts it even along the directions depth constrains best,
against 0.02-0.5 mm on the synthetic rows (docs/archive/journal.md). And both terms'
information matrices (their robust scales assume independent pixels) claim far more precision
than either has. So colour's weight is measured, per recording, where depth is surest (its
information's strongest directions): each frame gives two disagreements with the frame-to-model
depth estimate there,

- colour's: where colour alone moves the frame against the previous one;
- depth's own: where frame-to-frame ICP puts it;

and each term's claimed variance along those directions. A term's variance factor ``kappa`` is
its measured squared disagreement over its claimed variance (the mean over the recent frames: a
variance, so a depth estimate that slid counts in full); colour's weight against depth is
``kappa_depth / kappa_colour``: each term's information scaled to what its disagreements show.
The two noise levels are measured, not fitted to a scene; the information matrices keep their
shapes (depth weak along a wall, colour weak where there is no texture).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from slam.frontend.photometric import (
    _MIN_GEO_SCALE_M,
    _MIN_PHO_SCALE,
    _term_equations,
    _Terms,
    colour_pose,
)
from slam.frontend.rgbd_image import RgbdImage
from slam.frontend.robust import median
from slam.frontend.weighted_icp import metric_eigen
from slam.geometry import exp_se3, inv_T, log_se3

__all__ = [
    "ColourAgreement",
    "ColourEquations",
    "StepSettings",
    "colour_equations",
    "colour_refine",
    "step_with_colour",
]

#: a Gauss-Newton step moving the scene by less than this has converged (metres)
CONVERGED_M = 1e-6
#: frames the variance factors are taken over (a second of video at 30 Hz)
WINDOW = 30
#: depth's strongest directions the disagreements are measured along (of six)
STRONG_DIRECTIONS = 3


class ColourAgreement:
    """The last :data:`WINDOW` frames' variance factors (measured squared disagreement over
    claimed variance, along depth's strongest directions) of colour and of depth."""

    def __init__(self, factors: list[tuple[float, float]] | None = None) -> None:
        self.factors: list[tuple[float, float]] = list(factors or [])

    def add(
        self,
        H_geo: np.ndarray,
        H_pho: np.ndarray,
        depth_m: float,
        steps: tuple[np.ndarray, np.ndarray, np.ndarray],
    ) -> None:
        """One frame: depth's and colour's information at its estimate (``H_geo``, ``H_pho``:
        twists ``exp(x) @ T_prev_cur``, rotation first; rotations count as the motion they
        give at ``depth_m``) and ``steps``, the frame's ``T_prev_cur`` by colour alone, by
        depth against the model (this frame's estimate relative to the previous frame's) and
        by frame-to-frame ICP."""
        colour_step, depth_step, f2f_step = steps
        s, vals, vecs = metric_eigen(H_geo, depth_m)
        strong = vecs[:, -STRONG_DIRECTIONS:]
        back = inv_T(depth_step)

        def squared(step: np.ndarray) -> float:
            return float(np.sum((strong.T @ (log_se3(step @ back) / s)) ** 2))

        H_pho_metric = H_pho * s[:, None] * s[None, :]
        claimed_depth = float(np.sum(1.0 / np.maximum(vals[-STRONG_DIRECTIONS:], 1e-30)))
        colour_info = np.einsum("ij,ik,kj->j", strong, H_pho_metric, strong)
        claimed_colour = float(np.sum(1.0 / np.maximum(colour_info, 1e-30)))
        self.factors = (
            self.factors
            + [(squared(colour_step) / claimed_colour, squared(f2f_step) / claimed_depth)]
        )[-WINDOW:]

    def weight(self) -> float:
        """Colour's photometric weight against depth's point-to-plane term, ``kappa_depth /
        kappa_colour`` over the recent frames (0 before any frame was measured)."""
        if not self.factors:
            return 0.0
        colour, depth = np.mean(np.asarray(self.factors), axis=0)
        return float(depth / max(colour, 1e-30))


@dataclass
class ColourEquations:
    """The two terms of :func:`~slam.frontend.photometric.joint_align` at one pose of a frame
    against the previous one, for :func:`colour_refine`: depth's information ``H_geo``
    (point-to-plane, at its robust scale), colour's normal equations ``(H_pho, b_pho)`` at
    photometric weight 1, and the median depth of the correspondences (to compare rotations
    with translations)."""

    T_target_source: np.ndarray
    H_geo: np.ndarray
    H_pho: np.ndarray
    b_pho: np.ndarray
    depth_m: float

    def colour_alone(self) -> np.ndarray:
        """The twist of colour's own Gauss-Newton step from this pose (update
        ``exp(twist) @ T_target_source``): where colour alone would put the frame."""
        H = self.H_pho.copy()
        H[np.diag_indices(6)] += 1e-9 * np.trace(H) + 1e-12
        return -np.linalg.solve(H, self.b_pho)


@dataclass(frozen=True)
class StepSettings:
    """How the colour step evaluates its two terms (``tracking.colour_step_*``, the ICP's
    gates): the geometric correspondences' gate and Huber delta (m); colour's term on the
    ``textured`` fraction of the source pixels (finest level) whose intensity changes fastest
    (:meth:`~slam.frontend.rgbd_image.RgbdImage.textured`; 1: all); depth's on every pixel
    (``geometry_stride`` 1) or, from the source, on every ``geometry_stride``-th row and
    column of the finest level against the target's pixels of odd row and column
    (:meth:`~slam.frontend.rgbd_image.RgbdImage.odd_target`)."""

    max_correspondence_m: float = 0.07
    huber_delta_m: float = 0.05
    textured: float = 1.0
    geometry_stride: int = 1


def colour_equations(
    source: RgbdImage,
    target: RgbdImage,
    T_target_source: np.ndarray,
    settings: StepSettings = StepSettings(),
    colour_poses: tuple[np.ndarray | None, np.ndarray | None] = (None, None),
    depth_information: tuple[np.ndarray, float] | None = None,
) -> ColourEquations | None:
    """:class:`ColourEquations` of ``source`` against ``target`` at ``T_target_source``, the
    terms evaluated as ``settings`` say; None when either has no intensity or the views do not
    correspond (fewer than 6 points). ``colour_poses``: as in :func:`joint_align`.
    ``depth_information``: depth's information and median depth, when known (the Gauss-Newton
    steps after the first): depth's term is then not evaluated."""
    if source.intensity is None or target.intensity is None:
        return None
    T = np.asarray(T_target_source, float)
    T_colour = colour_pose(T, *colour_poses)
    terms = _Terms(
        np.float32(settings.max_correspondence_m),
        settings.huber_delta_m,
        _MIN_GEO_SCALE_M,
        1.0,
        _MIN_PHO_SCALE,
        0.0,
    )
    textured, stride = settings.textured, settings.geometry_stride
    both = textured >= 1.0 and stride == 1 and depth_information is None
    src = source.source(0) if textured >= 1.0 else source.textured(0, textured)
    parts = _term_equations(
        src, target.target(0, geometry=both), target.K[0], T, terms, T_colour,
        geometric_term=both,
    )  # fmt: skip
    if parts is None or parts[1] is None:
        return None
    H_pho, b_pho = parts[1]
    if depth_information is not None:
        return ColourEquations(T, depth_information[0], H_pho, b_pho, depth_information[1])
    if both:  # one pass over the pixels gives both terms
        assert parts[0] is not None and parts[3] is not None
        return ColourEquations(T, parts[0][0], H_pho, b_pho, median(parts[3]))
    depth_terms = dataclasses.replace(terms, photometric_weight=0.0)
    src = source.source(0, stride)
    tgt, K = (target.target(0), target.K[0]) if stride == 1 else target.odd_target()
    geo = _term_equations(src, tgt, K, T, depth_terms)
    if geo is None or geo[0] is None:
        return None
    return ColourEquations(T, geo[0][0], H_pho, b_pho, median(src.points[:, 2]))


def colour_refine(
    source: RgbdImage,
    target: RgbdImage,
    first: ColourEquations,
    photometric_weight: float,
    iterations: int,
    settings: StepSettings = StepSettings(),
    colour_poses: tuple[np.ndarray | None, np.ndarray | None] = (None, None),
) -> np.ndarray:
    """``T_target_source`` refined from ``first.T_target_source``, a pose whose depth alignment
    is trusted (depth's optimum against the model), by Gauss-Newton on
    ``1/2 x^T H_geo x + photometric_weight * E_pho``: depth as a Gaussian prior at its optimum,
    with the information its point-to-plane term has there, and colour's cost. Where depth
    constrains the pose its information holds the frame; where depth is weak (along a wall
    filling the view, a corridor) colour moves it."""
    T = first.T_target_source
    eq: ColourEquations | None = first
    moved = np.zeros(6)  # the twist from the depth optimum, summed over the steps
    for k in range(iterations if photometric_weight > 0 else 0):
        if k > 0:
            prior = (first.H_geo, first.depth_m)  # depth's information: not evaluated again
            eq = colour_equations(source, target, T, settings, colour_poses, prior)
            if eq is None:
                break
        H = first.H_geo + photometric_weight * eq.H_pho
        H[np.diag_indices(6)] += 1e-9 * np.trace(H) + 1e-12
        dx = -np.linalg.solve(H, first.H_geo @ moved + photometric_weight * eq.b_pho)
        moved += dx
        T = exp_se3(dx) @ T
        if np.linalg.norm(dx[3:]) + first.depth_m * np.linalg.norm(dx[:3]) < CONVERGED_M:
            break  # converged: another step would move the frame by less than a micrometre
    return T


def step_with_colour(
    source: RgbdImage,
    target: RgbdImage,
    T_prev_cur: np.ndarray,
    agreement: ColourAgreement,
    measured: tuple[np.ndarray | None, np.ndarray | None],
    weight: float,
    iterations: int,
    settings: StepSettings = StepSettings(),
    colour_poses: tuple[np.ndarray | None, np.ndarray | None] = (None, None),
) -> np.ndarray:
    """A frame's depth estimate ``T_prev_cur`` against the previous frame (``source`` against
    ``target``) refined by :func:`colour_refine` at ``weight`` times the weight colour has
    earned (``agreement``, first updated with this frame when ``measured`` holds its
    frame-to-model depth step, relative to the previous frame's depth estimate, and its
    frame-to-frame ICP step). Unchanged when the views do not correspond."""
    first = colour_equations(source, target, T_prev_cur, settings, colour_poses)
    if first is None:
        return T_prev_cur
    depth_step, f2f_step = measured
    if depth_step is not None and f2f_step is not None:
        colour_alone = exp_se3(first.colour_alone()) @ first.T_target_source
        agreement.add(first.H_geo, first.H_pho, first.depth_m, (colour_alone, depth_step, f2f_step))
    weight = weight * agreement.weight()
    return colour_refine(source, target, first, weight, iterations, settings, colour_poses)
