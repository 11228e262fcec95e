"""The edges' weight in bundle adjustment, estimated from its residuals (variance component
estimation): on synthetic problems whose landmark and edge noise differ from what is assumed
by known factors, the estimate finds their ratio, and the poses it gives are nearer the truth
than those of a wrong fixed weight; along a loop-free chain of edges it only ever raises it."""

from __future__ import annotations

import numpy as np
import pytest

from slam.backend.bundle_adjustment import bundle_adjust
from slam.backend.pose_graph import Edge
from slam.backend.variance_components import edge_cycles
from slam.config import BAConfig
from slam.geometry import exp_se3, inv_T
from slam.synthetic.ba_problem import make_problem, pose_errors

#: 20 keyframes over half a circle, pixel noise 0.5 px, depth noise 2 mm at 1 m (as z^2)
PROBLEM = dict(n_keyframes=20, n_points=6000, laps=0.5, max_observations=300, depth_sigma=0.002)
#: odometry edges between consecutive keyframes: true noise per axis
EDGE_SIGMA_M, EDGE_SIGMA_RAD = 0.002, np.radians(0.1)


def odometry_edges(
    poses_true: dict[int, np.ndarray], assumed: float, seed: int, loops: bool = True
) -> list[Edge]:
    """Consecutive keyframes' relative poses, each moved by noise of ``EDGE_SIGMA_*``, with
    the information of ``assumed`` times that noise (1: the truth); with ``loops``, also every
    keyframe to the one five ahead (cycles: the edges check each other; Gaussian, like
    odometry edges: a loop edge's Cauchy kernel would shrink its residuals)."""
    rng = np.random.default_rng(seed + 100)
    sigma = np.array([EDGE_SIGMA_RAD] * 3 + [EDGE_SIGMA_M] * 3)
    info = np.diag(1.0 / (assumed * sigma) ** 2)
    edges = []
    for gap in [1, 5] if loops else [1]:
        for k in range(len(poses_true) - gap):
            T = inv_T(poses_true[k]) @ poses_true[k + gap] @ exp_se3(rng.normal(size=6) * sigma)
            edges.append(Edge(k, k + gap, T, info, "odometry"))
    return edges


def settled_weight(landmark_assumed: float, edge_assumed: float, start: float, seed: int):
    s = make_problem(**PROBLEM, pixel_sigma=0.5, seed=seed)
    cfg = BAConfig(pixel_sigma_px=0.5 * landmark_assumed, depth_sigma_m=0.002 * landmark_assumed)
    edges = odometry_edges(s.poses_true, edge_assumed, seed)
    res = bundle_adjust(
        s.problem, s.poses_init, cfg, edges=edges, edge_weight=start, edge_weight_rounds=6
    )
    return res, s


@pytest.mark.parametrize("seed", [0, 1])
def test_the_weight_settles_where_both_groups_meet_their_noise(seed):
    """Landmark noise assumed 2x too large (variance factor 0.25), edge noise 2x too small
    (factor 4): the edges' weight should be 0.25 / 4 = 1/16 of what they were given; with both
    noises right, 1. Either way from a start 100x off."""
    res, _ = settled_weight(2.0, 0.5, start=1.0, seed=seed)
    assert 1 / 16 / 1.6 < res.edge_weight < 1 / 16 * 1.6, res.edge_weight
    res, _ = settled_weight(1.0, 1.0, start=100.0, seed=seed)
    assert 1 / 1.6 < res.edge_weight < 1.6, res.edge_weight


def test_the_estimated_weight_beats_a_wrong_fixed_one():
    """Edges given 1000x their information (a drifting odometry trusted as exact): keyframes
    follow the edges' noise; with the weight estimated they are nearer the truth."""
    s = make_problem(**PROBLEM, pixel_sigma=0.5, seed=2)
    cfg = BAConfig(pixel_sigma_px=0.5, depth_sigma_m=0.002)
    edges = odometry_edges(s.poses_true, 1.0, 2)
    fixed = bundle_adjust(s.problem, s.poses_init, cfg, edges=edges, edge_weight=1000.0)
    settled = bundle_adjust(
        s.problem, s.poses_init, cfg, edges=edges, edge_weight=1000.0, edge_weight_rounds=6
    )
    err_fixed = pose_errors(fixed.poses, s.poses_true)[0]
    err_settled = pose_errors(settled.poses, s.poses_true)[0]
    assert np.sqrt(np.mean(err_settled**2)) < 0.7 * np.sqrt(np.mean(err_fixed**2))
    assert fixed.edge_weight == 1000.0  # without rounds the weight is the one given


def test_a_loop_free_chain_only_raises_the_weight():
    """Without a cycle the edges are checked against the landmarks only, whose shared errors
    the estimate would lay on the edges: a lower estimate is not taken, a higher one is."""
    s = make_problem(**PROBLEM, pixel_sigma=0.5, seed=0)
    cfg = BAConfig(pixel_sigma_px=1.0, depth_sigma_m=0.004)  # landmarks: variance factor 0.25
    for assumed, start in [(0.5, 1.0), (1.0, 1.0 / 64)]:
        edges = odometry_edges(s.poses_true, assumed, 0, loops=False)
        res = bundle_adjust(
            s.problem, s.poses_init, cfg, edges=edges, edge_weight=start, edge_weight_rounds=6
        )
        if assumed == 0.5:  # edges noisier than given: the estimate would lower the weight
            assert res.edge_weight == start
        else:  # edges as given, landmarks better: 0.25 of what was given, a rise
            assert 0.25 / 1.6 < res.edge_weight < 0.25 * 1.6, res.edge_weight


def test_cycles_of_an_edge_graph():
    assert edge_cycles([]) == 0
    assert edge_cycles([(0, 1), (1, 2), (2, 3)]) == 0  # a chain
    assert edge_cycles([(0, 1), (1, 2), (2, 0)]) == 1
    assert edge_cycles([(0, 1), (0, 1), (5, 6)]) == 1  # two edges between one pair, two parts


def test_without_edges_nothing_is_estimated():
    s = make_problem(**PROBLEM, pixel_sigma=0.5, seed=0)
    res = bundle_adjust(s.problem, s.poses_init, BAConfig(), edge_weight_rounds=3)
    assert res.edge_weight == 0.0 and res.skipped is None
