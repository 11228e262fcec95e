import numpy as np
import open3d as o3d
import pytest

from slam.config import TrackingConfig
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


def test_a_far_start_on_a_weakly_constrained_scene_needs_more_iterations():
    # a box on a floor (the cabinet's shape): from 8.5 cm and 6 deg away, the slide along the
    # floor converges slowly; tracking.icp.iterations' budget stops about 1 cm short, that of
    # tracking.icp.large_motion_iterations (twice the steps) lands nearer
    floor = o3d.geometry.TriangleMesh.create_box(6.0, 6.0, 0.01).translate((-3.0, -3.0, -0.01))
    box = o3d.geometry.TriangleMesh.create_box(0.8, 0.5, 0.7).translate((-0.4, -0.25, 0.0))
    K = np.array([[262.5, 0.0, 159.5], [0.0, 262.5, 119.5], [0.0, 0.0, 1.0]])
    T_world_a = look_at([-0.9, -1.3, 1.2], [0.0, 0.0, 0.35])
    motion = exp_se3(np.array([0.0782, 0.0568, -0.0422, -0.0759, -0.0374, 0.0025]))
    depth_a = render_depth(floor + box, K, 320, 240, T_world_a)
    depth_b = render_depth(floor + box, K, 320, 240, T_world_a @ motion)
    cfg = TrackingConfig()
    errors = []
    for iterations in (cfg.icp.iterations, cfg.icp.large_motion_iterations):
        res = projective_icp(depth_b, depth_a, K, np.eye(4), iterations, 4.0, 0.03, 0.05, 2.0)
        errors.append(translation_norm(inv_T(motion) @ res.T_target_source))
    assert errors[0] > 0.008, errors  # measured 9.8 mm
    assert errors[1] < 0.7 * errors[0], errors  # measured 6.4 mm


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


def test_fitness_and_overlap_count_only_pixels_in_range(room, K_vga):
    # the same view with most of its pixels pushed beyond the ICP and model range (a hall's far
    # walls): what is in range still aligns perfectly, and both scores say so
    K = K_vga.copy()
    K[:2] /= 2
    T = look_at([-1.2, -1.0, 1.4], [0.3, 0.4, 0.7])
    depth = render_depth(room, K, 320, 240, T)
    far = depth.copy()
    far[:, 100:] = np.where(far[:, 100:] > 0, far[:, 100:] + 6.0, 0.0)
    res = projective_icp(far, depth, K, np.eye(4), [4, 4, 4], depth_max_m=4.0)
    assert res.fitness > 0.9, res.fitness
    model = np.where(far < 4.0, far, 0.0)  # a model fused up to 4 m holds none of the far part
    assert projective_overlap(far, model, K, np.eye(4)) < 0.4
    assert projective_overlap(far, model, K, np.eye(4), source_max_m=4.0) > 0.99


def test_overlap_gate_widens_with_the_depth_noise(K_vga):
    # a wall 6 m away measured 5 cm behind the model: within 3 sigma of a Kinect (6 cm at
    # 6 m), not within the fixed 3 cm gate; at 1 m the same offset stays outside
    from slam.camera import DepthNoise

    K = K_vga.copy()
    K[:2] /= 4
    for z, expected in [(6.0, 1.0), (1.0, 0.0)]:
        model = np.full((120, 160), z, np.float32)
        frame = model + np.float32(0.05)
        assert projective_overlap(frame, model, K, np.eye(4), 0.03) == 0.0
        noisy = projective_overlap(frame, model, K, np.eye(4), 0.03, noise=DepthNoise())
        assert noisy == expected


def test_agreement_rmse_is_the_point_to_plane_residual_in_metres(K_vga):
    # a tilted plane measured 4 mm in front of the model along its normal: RMSE 4 mm (the
    # along-ray difference is larger); Open3D's inlier_rmse is not in metres
    from slam.frontend.icp import projective_agreement

    K = K_vga.copy()
    K[:2] /= 2
    u, v = np.meshgrid(np.arange(320), np.arange(240))
    xn = (u - K[0, 2]) / K[0, 0]
    # the plane 0.8 z - 0.6 x = 1.6 (unit normal (-0.6, 0, 0.8)): z = 2 / (1 - 0.75 xn)
    model = (2.0 / (1 - 0.75 * xn)).astype(np.float32)
    # the same plane 4 mm farther along its normal: 0.8 z - 0.6 x = 1.604
    frame = (2.005 / (1 - 0.75 * xn)).astype(np.float32)
    fraction, rmse = projective_agreement(frame, model, K, np.eye(4))
    assert fraction > 0.95
    assert rmse == pytest.approx(0.004, abs=3e-4)
    assert np.isnan(projective_agreement(frame, np.zeros_like(model), K, np.eye(4))[1])
