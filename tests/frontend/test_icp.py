import numpy as np

from slam.frontend.icp import projective_icp, projective_overlap
from slam.geometry import exp_se3, inv_T, rotation_angle_deg, translation_norm
from tests.conftest import look_at, render_depth


def test_icp_recovers_known_motion(room, K_vga):
    T_world_a = look_at([-1.2, -1.0, 1.4], [0.3, 0.4, 0.7])
    motion = exp_se3(np.array([0.01, -0.015, 0.012, 0.02, -0.015, 0.025]))  # ~1.1 deg, 3.5 cm
    T_world_b = T_world_a @ motion
    depth_a = render_depth(room, K_vga, 640, 480, T_world_a)
    depth_b = render_depth(room, K_vga, 640, 480, T_world_b)
    res = projective_icp(depth_b, depth_a, K_vga, np.eye(4), [10, 10, 10], depth_max_m=6.0)
    err = inv_T(motion) @ res.T_target_source
    assert translation_norm(err) < 1e-3, translation_norm(err)
    assert rotation_angle_deg(err) < 0.1, rotation_angle_deg(err)
    assert res.fitness > 0.8
    assert projective_overlap(depth_b, depth_a, K_vga, res.T_target_source, 0.01) > 0.9


def test_overlap_rejects_wrong_pose(room, K_vga):
    T = look_at([-1.2, -1.0, 1.4], [0.3, 0.4, 0.7])
    depth = render_depth(room, K_vga, 160, 120, T)
    K = K_vga.copy()
    K[:2] /= 4
    depth = render_depth(room, K, 160, 120, T)
    assert projective_overlap(depth, depth, K, np.eye(4)) > 0.99
    wrong = exp_se3(np.array([0.0, 0.2, 0.0, 0.3, 0.0, 0.0]))
    assert projective_overlap(depth, depth, K, wrong) < 0.5


def test_icp_singular_system_reports_failure(K_vga):
    empty = np.zeros((120, 160), np.float32)
    K = K_vga.copy()
    K[:2] /= 4
    res = projective_icp(empty, empty, K, np.eye(4), [3, 3, 3])
    assert res.fitness == 0.0
