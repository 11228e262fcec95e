"""Pose graph: loop edges correct drift, the robust kernel survives a wrong loop, g2o export."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.backend.pose_graph import Edge, PoseGraph
from slam.config import BackendConfig
from slam.errors import ConfigError
from slam.geometry import exp_se3, inv_T, make_T

N = 40
SIGMA_ODO = 0.01  # matches the drift injected below (a calibrated odometry model)


def circle(n: int = N, radius: float = 1.0) -> np.ndarray:
    """Poses on a circle, looking outwards, closing after the last one."""
    poses = []
    for k in range(n):
        a = 2 * np.pi * k / n
        R = Rotation.from_euler("z", a).as_matrix()
        poses.append(make_T(R, [radius * np.cos(a), radius * np.sin(a), 0.0]))
    return np.stack(poses)


def drifted_odometry(gt: np.ndarray, seed: int = 0) -> list[np.ndarray]:
    """Relative motions with a slow heading bias plus noise."""
    rng = np.random.default_rng(seed)
    rel = []
    for k in range(len(gt) - 1):
        T = inv_T(gt[k]) @ gt[k + 1]
        noise = np.concatenate([[0, 0, 0.006], [0.0, 0.0, 0.0]]) + rng.normal(0, 0.002, 6)
        rel.append(T @ exp_se3(noise))
    return rel


def build(gt, rel, loops=()) -> PoseGraph:
    g = PoseGraph(BackendConfig())
    T = gt[0].copy()
    g.add_node(0, T)
    for k, T_rel in enumerate(rel):
        T = T @ T_rel
        g.add_node(k + 1, T)
        g.add_edge(Edge(k, k + 1, T_rel, np.eye(6) / SIGMA_ODO**2, "odometry"))
    for i, j, T_ij in loops:
        g.add_edge(Edge(i, j, T_ij, np.eye(6) / 0.02**2, "loop"))
    return g


def ate(g: PoseGraph, gt: np.ndarray) -> float:
    est = np.stack([g.nodes[k][:3, 3] for k in range(len(gt))])
    return float(np.sqrt(np.mean(np.sum((est - gt[:, :3, 3]) ** 2, axis=1))))


def test_loop_edge_corrects_drift():
    gt = circle()
    rel = drifted_odometry(gt)
    g_odo = build(gt, rel)
    loop = (0, N - 1, inv_T(gt[0]) @ gt[N - 1])
    g = build(gt, rel, [loop])
    before = ate(g_odo, gt)
    g.optimize()
    after = ate(g, gt)
    assert before > 0.1, before  # the heading bias makes the loop miss by a lot
    assert after < 0.3 * before, (before, after)
    np.testing.assert_allclose(g.nodes[0], gt[0], atol=1e-6)  # the prior holds the first pose


def test_robust_kernel_survives_a_wrong_loop():
    # Cauchy is the default because its influence falls off for large residuals; Huber's stays
    # constant and lets this loop bend the chain (measured: ATE +26%).
    gt = circle()
    rel = drifted_odometry(gt, seed=1)
    g_odo = build(gt, rel)
    g_odo.optimize()
    base = ate(g_odo, gt)
    # a false loop: keyframe 10 "seen" from keyframe 30 with an aliasing offset (1.5 m, 60 deg)
    wrong = (
        inv_T(gt[10])
        @ gt[30]
        @ make_T(Rotation.from_euler("y", 60, degrees=True).as_matrix(), [1.5, 0.0, 0.0])
    )
    g = build(gt, rel, [(10, 30, wrong)])
    g.optimize()
    assert ate(g, gt) <= 1.10 * base, (base, ate(g, gt))
    # the same loop without a robust kernel bends the graph badly
    g_plain = build(gt, rel, [(10, 30, wrong)])
    g_plain.cfg = BackendConfig(loop_kernel="none")
    g_plain.optimize()
    assert ate(g_plain, gt) > 1.5 * base


def test_unknown_kernel_is_a_config_error():
    with pytest.raises(ConfigError, match="loop_kernel"):
        PoseGraph(BackendConfig(loop_kernel="tukey-ish"))


def test_g2o_export_and_state_round_trip():
    gt = circle(6)
    rel = drifted_odometry(gt)
    g = build(gt, rel, [(0, 5, inv_T(gt[0]) @ gt[5])])
    text = g.to_g2o()
    lines = text.strip().splitlines()
    assert sum(line.startswith("VERTEX_SE3:QUAT") for line in lines) == 6
    edges = [line.split() for line in lines if line.startswith("EDGE_SE3:QUAT")]
    assert len(edges) == 6
    assert all(len(e) == 3 + 7 + 21 for e in edges)
    assert float(edges[0][10]) == pytest.approx(1 / SIGMA_ODO**2)  # info(0,0), translation x
    g2 = PoseGraph.from_state_dict(BackendConfig(), g.state_dict())
    assert g2.to_g2o() == text
