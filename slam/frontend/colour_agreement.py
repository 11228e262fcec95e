"""How much colour weighs against depth on this recording, measured while tracking:
:class:`ColourAgreement`.

Colour is registered to depth on every synthetic sequence and nearly so on a real Kinect, but
only nearly: on ``tum-fr1-xyz`` a frame's colour puts it 1-3 mm from where depth puts it even
along the directions depth constrains best, against 0.02-0.5 mm on the synthetic rows
(docs/benchmarks.md, session 27). And both terms' information matrices (their robust scales
assume independent pixels) claim far more precision than either has. So colour's weight is
measured, per recording, where depth is surest (its information's strongest directions): each
frame gives two disagreements with the frame-to-model depth estimate there,

- colour's: where colour alone moves the frame against the previous one;
- depth's own: where frame-to-frame ICP puts it;

and each term's claimed variance along those directions. A term's variance factor ``kappa`` is
its measured squared disagreement over its claimed variance (the median over the recent
frames); colour's weight against depth is ``kappa_depth / kappa_colour``: each term's
information scaled to what its disagreements show. The two noise levels are measured, not fitted
to a scene; the information matrices keep their shapes (depth weak along a wall, colour weak
where there is no texture).
"""

from __future__ import annotations

import numpy as np

from slam.frontend.weighted_icp import metric_eigen
from slam.geometry import inv_T, log_se3

__all__ = ["ColourAgreement"]

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
