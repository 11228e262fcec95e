"""How much the pose graph's edges should weigh against the landmarks in bundle adjustment,
estimated from the adjustment's own residuals (variance component estimation).

Bundle adjustment joins two kinds of measurement: ORB observations of landmarks (noise: the
keypoint's pixel and the sensor's depth) and the pose graph's edges (depth registration:
odometry and loops), whose information has a measured shape but a magnitude set by a model of
odometry drift. How accurate each kind really is differs from sequence to sequence by orders of
magnitude: on exact synthetic depth the edges at the true poses sit at 0.005 of their assumed
variance (at ``ba.pose_graph_weight`` 100), on ``tum-fr1-xyz`` at 46 times it, while the
landmarks sit at 0.05-1.4 of theirs. A fixed weight therefore lets features bend an accurate
odometry (a loop-free exact corridor: keyframe ATE 0.9 -> 2.2 mm) or lets a drifting odometry
hold features back (fr1: 9.1 mm at weight 10, 9.5 at 100).

Helmert's variance component estimation (Förstner 1979; Koch, "Parameter estimation and
hypothesis testing in linear models") measures the two from the adjustment: each group ``g``
of observations gets ``s_g^2 = v_g^T P_g v_g / r_g``, its weighted squared residuals over its
redundancy ``r_g = n_g - tr(A_g N^-1 A_g^T P_g)`` (its observations less the parameters it
determines; ``N`` the normal matrix of the whole problem). At the right relative weight both
factors are equal; :func:`estimate` returns them, and :func:`bundle_adjust
<slam.backend.bundle_adjustment.bundle_adjust>` rescales the edges by ``s_L^2 / s_E^2`` and
solves again until the weight settles. The edges touch poses only, so their trace needs just
the poses' joint marginal covariance (the inverse of the reduced camera system, from GTSAM);
the landmarks' redundancy follows as ``n_L - (parameters - t_E - t_prior)``. Robust kernels
enter through the linearisation (whitened, robust-weighted residuals and Jacobians).

The estimate has a known bias. Landmark errors shared along a track (a corner seen alike from
similar views, a far depth quantised alike) do not show in the landmarks' own redundancy, so
the estimate lays them on the edges and lowers the edges' weight. Where the edges form cycles
(loops), their disagreement among themselves measures them and the estimate stands either way;
along a loop-free chain the edges are checked against the landmarks only, and only a rise of
their weight, found despite that bias, is taken (:func:`next_weight`). Measured at the true
poses of two loop-free rows, ``hall-x1-s0`` and ``wall-x1-s1``: their edges sit at 0.15 and
0.005 of the variance assumed at weight 100, yet the estimate lowered the weight to 16 and 55,
keyframe ATE 8.3 -> 10.3 and 3.9 -> 4.6 mm (``benchmarks/edge_weight.py``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

log = logging.getLogger(__name__)

#: the edges must over-determine at least one pose's worth of dof for their variance to be told
#: apart from the landmarks' (a chain of edges that nothing else constrains has no redundancy)
MIN_REDUNDANCY = 6.0


@dataclass(frozen=True)
class VarianceComponents:
    """Each group's weighted squared residuals and redundancy at an adjustment's solution:
    landmark observations (``landmark_*``) and pose-graph edges (``edge_*``)."""

    landmark_chi2: float
    landmark_redundancy: float
    edge_chi2: float
    edge_redundancy: float

    @property
    def landmark_factor(self) -> float:
        """The landmarks' variance over their assumed one (1: as assumed)."""
        return self.landmark_chi2 / self.landmark_redundancy

    @property
    def edge_factor(self) -> float:
        """The edges' variance over their assumed one, at the weight they were given."""
        return self.edge_chi2 / self.edge_redundancy

    @property
    def edge_weight_scale(self) -> float:
        """What the edges' weight should be multiplied by for both groups to agree with their
        noise in the same proportion."""
        return self.landmark_factor / max(self.edge_factor, 1e-300)


def edge_cycles(edges: list[tuple[int, int]]) -> int:
    """The number of independent cycles of a graph given by its edges (node pairs): edges less
    nodes plus connected parts. 0: a chain or a tree, where no edge is checked by another."""
    nodes = {n for e in edges for n in e}
    if not nodes:
        return 0
    index = {n: i for i, n in enumerate(sorted(nodes))}
    rows = [index[i] for i, _ in edges]
    cols = [index[j] for _, j in edges]
    graph = coo_matrix((np.ones(len(edges)), (rows, cols)), shape=(len(index), len(index)))
    parts, _ = connected_components(graph, directed=False)
    return len(edges) - len(nodes) + parts


def next_weight(weight: float, start: float, vc: VarianceComponents, cycles: int) -> float:
    """The edges' weight after an estimate ``vc`` made at ``weight``: rescaled so both groups
    meet their noise in the same proportion; with no cycle among the edges (``cycles`` 0), not
    below the ``start`` weight (see the module docstring)."""
    new = weight * vc.edge_weight_scale
    return new if cycles > 0 else max(new, start)


def _is_pose(key: int, pose_chr: int) -> bool:
    return gtsam.Symbol(key).chr() == pose_chr


def estimate(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, pose_keys: list[int]
) -> VarianceComponents | None:
    """The variance components of a solved bundle-adjustment ``graph`` at ``values``: factors
    between two poses are edges, single-pose factors are priors (the gauge), every other factor
    observes a landmark. None when a group has too little redundancy to be estimated, or the
    problem's covariance cannot be computed."""
    if not pose_keys:
        return None
    pose_chr = gtsam.Symbol(pose_keys[0]).chr()
    linear = graph.linearize(values)
    landmark_chi2 = edge_chi2 = 0.0
    n_landmark = n_edge = n_prior = 0
    edges: list[tuple[list[int], np.ndarray]] = []
    for i in range(graph.size()):
        keys = list(graph.at(i).keys())
        A, b = linear.at(i).jacobian()
        if all(_is_pose(k, pose_chr) for k in keys):
            if len(keys) == 1:
                n_prior += len(b)
                continue
            edge_chi2 += float(b @ b)
            n_edge += len(b)
            edges.append((keys, A))
        else:
            landmark_chi2 += float(b @ b)
            n_landmark += len(b)
    if not edges or n_landmark == 0:
        return None
    n_params = sum(6 if _is_pose(k, pose_chr) else 3 for k in values.keys())
    try:
        joint = gtsam.Marginals(graph, values).jointMarginalCovariance(gtsam.KeyVector(pose_keys))
    except RuntimeError as exc:  # an indeterminate system: no covariance to read
        log.info("variance components not estimated: %s", exc)
        return None
    cov = joint.fullMatrix()
    col = {int(k): 6 * n for n, k in enumerate(pose_keys)}
    edge_trace = 0.0
    for keys, A in edges:
        idx = np.concatenate([np.arange(col[int(k)], col[int(k)] + 6) for k in keys])
        edge_trace += float(np.einsum("ij,jk,ik->", A, cov[np.ix_(idx, idx)], A))
    edge_r = n_edge - edge_trace
    landmark_r = n_landmark - (n_params - edge_trace - n_prior)
    if edge_r < MIN_REDUNDANCY or landmark_r < MIN_REDUNDANCY:
        return None
    return VarianceComponents(landmark_chi2, landmark_r, edge_chi2, edge_r)
