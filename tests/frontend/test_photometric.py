import numpy as np

from slam.frontend.photometric import (
    colour_pose,
    joint_align,
    mean_warped_intensity,
    photometric_costs,
    warp_intensity,
)
from slam.frontend.rgbd_image import RgbdImage, grey
from slam.geometry import exp_se3, inv_T, rotation_angle_deg, translation_norm
from tests.conftest import look_at


def _textured_wall(K, w, h, T_world_cam):
    """Depth and colour of the wall z = 2 (world), textured by two crossed sinusoids."""
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1)
    d = rays @ T_world_cam[:3, :3].T
    t = (2.0 - T_world_cam[2, 3]) / d[..., 2]
    x, y = T_world_cam[0, 3] + t * d[..., 0], T_world_cam[1, 3] + t * d[..., 1]
    g = 0.5 + 0.2 * np.sin(2 * np.pi * x / 0.23) + 0.2 * np.sin(2 * np.pi * (0.6 * x + y) / 0.17)
    color = np.repeat((g * 255).round().astype(np.uint8)[..., None], 3, -1)
    return t.astype(np.float32), color  # rays have z = 1: t is the z-depth


def wall_views(motion: np.ndarray) -> tuple[np.ndarray, RgbdImage, RgbdImage]:
    """``(K, source, target)``: a camera 2 m in front of the textured wall (target) and the
    same camera moved by ``motion`` (source), 320 x 240, three pyramid levels."""
    K = np.array([[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1]])
    T_a = look_at([0.0, 0.0, 0.0], [0.0, 0.0, 2.0], up=(0, -1, 0))
    da, ca = _textured_wall(K, 320, 240, T_a)
    db, cb = _textured_wall(K, 320, 240, T_a @ motion)
    return K, RgbdImage(db, grey(cb), K, 3), RgbdImage(da, grey(ca), K, 3)


def test_colour_resolves_sliding_along_a_flat_wall():
    """A flat wall leaves point-to-plane ICP blind to sliding along it (and to the turn about
    its normal); the photometric term of the joint alignment recovers the motion (measured:
    22 mm / 1 deg off without it, 0.003 mm / 0.0001 deg with it)."""
    K = np.array([[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1]])
    T_a = look_at([0.0, 0.0, 0.0], [0.0, 0.0, 2.0], up=(0, -1, 0))
    motion = exp_se3(np.array([0.0, 0.0, np.radians(1.0), 0.02, -0.01, 0.0]))
    da, ca = _textured_wall(K, 320, 240, T_a)
    db, cb = _textured_wall(K, 320, 240, T_a @ motion)
    target = RgbdImage(da, grey(ca), K, 3)
    source = RgbdImage(db, grey(cb), K, 3)
    geo = joint_align(source, target, np.eye(4), [6, 4, 2], photometric_weight=0.0)
    joint = joint_align(source, target, np.eye(4), [6, 4, 2], photometric_weight=1.0)
    err_geo = inv_T(motion) @ geo.T_target_source
    err = inv_T(motion) @ joint.T_target_source
    assert translation_norm(err_geo) > 0.01  # geometry alone cannot see the sliding
    assert translation_norm(err) < 1e-3, translation_norm(err)
    assert rotation_angle_deg(err) < 0.05
    assert joint.fitness > 0.8


def test_where_depth_is_blind_colour_decides_alone():
    """Exact depth of a textured wall whose target carries an artefact (a ramp 8 px wide and
    2 cm high, as a model's smeared edge): the ramp's residuals are few, but exact depth weighs
    them ~100x over colour, and they drag the pose along the wall (measured: 32 mm off). With
    the geometric term left out of the directions it constrains 40x worse than its best,
    colour holds the slide (measured: 1.2 mm, the ramp's pull on the strong directions)."""
    K = np.array([[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1]])
    T_a = look_at([0.0, 0.0, 0.0], [0.0, 0.0, 2.0], up=(0, -1, 0))
    motion = exp_se3(np.array([0.0, 0.0, np.radians(1.0), 0.02, -0.01, 0.0]))
    da, ca = _textured_wall(K, 320, 240, T_a)
    db, cb = _textured_wall(K, 320, 240, T_a @ motion)
    da[:, 200:208] -= np.linspace(0.0, 0.02, 8, dtype=np.float32)[None, :]
    target = RgbdImage(da, grey(ca), K, 3)
    source = RgbdImage(db, grey(cb), K, 3)
    errors = {}
    for ratio in (0.0, 40.0):
        res = joint_align(source, target, np.eye(4), [6, 4, 2], degenerate_ratio=ratio)
        errors[ratio] = translation_norm(inv_T(motion) @ res.T_target_source)
    assert errors[0.0] > 0.01, errors  # every direction to both terms: the ramp drags it
    assert errors[40.0] < 0.002, errors


def test_a_warped_view_has_the_colour_of_the_view_it_came_from():
    """A view's intensity warped to the pixels of another view through that view's depth:
    where the source saw the surface, the other view's own intensity; NaN outside the source's
    image and where the source's depth disagrees (occluded)."""
    K = np.array([[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1]])
    T_a = look_at([0.0, 0.0, 0.0], [0.0, 0.0, 2.0], up=(0, -1, 0))
    T_a_b = exp_se3(np.array([0.0, 0.0, np.radians(1.0), 0.2, -0.01, 0.0]))  # 20 cm aside
    da, ca = _textured_wall(K, 320, 240, T_a)
    db, cb = _textured_wall(K, 320, 240, T_a @ T_a_b)
    warped = warp_intensity(db, K, T_a_b, grey(ca), da, 0.05)
    seen = np.isfinite(warped)
    assert 0.7 < seen.mean() < 0.95  # b sees a strip of the wall a does not
    assert np.abs(warped[seen] - grey(cb)[seen]).mean() < 0.005
    assert not seen[:, -5:].any()  # b's right edge is beyond a's image
    occluded = da.copy()
    occluded[:, :160] -= 0.5  # something 0.5 m in front of the wall in a's left half
    assert np.isfinite(warp_intensity(db, K, T_a_b, grey(ca), occluded, 0.05)).mean() < 0.5


def test_warped_views_average_where_they_see_the_surface():
    """Several views warped to one: each pixel is the mean of the views that see it (two
    views of the same wall agree with the destination's own intensity; one darkened by 0.1
    pulls the mean by 0.05 where both see, by 0.1 where only it does); NaN where none does,
    and a view that sees nothing of it adds nothing."""
    K = np.array([[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1]])
    T_dst = look_at([0.0, 0.0, 0.0], [0.0, 0.0, 2.0], up=(0, -1, 0))
    T_left = T_dst @ exp_se3(np.array([0.0, 0.0, 0.0, -0.4, 0.0, 0.0]))
    T_right = T_dst @ exp_se3(np.array([0.0, 0.0, 0.0, 0.4, 0.0, 0.0]))
    T_away = look_at([0.0, 0.0, 0.0], [0.0, 0.0, -2.0], up=(0, -1, 0))  # faces away
    d_dst, c_dst = _textured_wall(K, 320, 240, T_dst)
    views = []
    for T, offset in ((T_left, 0.0), (T_right, -0.1), (T_away, 0.0)):
        d, c = _textured_wall(K, 320, 240, T_left if T is T_away else T)
        views.append((RgbdImage(d, grey(c) + np.float32(offset), K, 1), T))
    one = [
        warp_intensity(d_dst, K, inv_T(T) @ T_dst, im.intensity[0], im.depth[0], 0.05)
        for im, T in views[:2]
    ]
    mean = mean_warped_intensity(d_dst, K, T_dst, views, 0.05)
    both = np.isfinite(one[0]) & np.isfinite(one[1])
    only_right = ~np.isfinite(one[0]) & np.isfinite(one[1])
    assert both.mean() > 0.3 and only_right.mean() > 0.05
    assert np.abs(mean[both] - (grey(c_dst)[both] - 0.05)).mean() < 0.005
    assert np.abs(mean[only_right] - (grey(c_dst)[only_right] - 0.1)).mean() < 0.005
    assert np.array_equal(np.isfinite(mean), np.isfinite(one[0]) | np.isfinite(one[1]))
    assert np.isnan(mean_warped_intensity(d_dst, K, T_dst, views[2:], 0.05)).all()


def test_colour_term_only_where_colour_is_registered(tmp_path):
    """7-Scenes (also converted to the TUM layout, its pose/ files kept) keeps the depth-only
    path: its colour camera is not registered to depth."""
    from slam.config import TrackingConfig
    from slam.data import open_sequence
    from slam.frontend.tracker import Tracker
    from tests.data.test_tum import _write_seq

    assert Tracker(TrackingConfig(), color_registered=True).color_registered
    assert not Tracker(TrackingConfig(), color_registered=False).color_registered
    root = _write_seq(tmp_path / "s", [0.0], [0.0])
    assert open_sequence(root).color_registered
    (root / "pose").mkdir()
    (root / "pose" / "frame-000000.pose.txt").write_text(" ".join(["1", "0", "0", "0"] * 4))
    assert not open_sequence(root).color_registered


def test_colour_taken_from_another_pose_is_aligned_from_there():
    """A camera moving while its colour and depth images are taken at instants apart (TUM
    fr1's Kinect: up to 17 ms): the source's colour comes from 4 mm and 0.1 deg further along
    the motion, the target's from 2 mm before. On a wall colour decides the slide, so the
    joint alignment lands where the colours were taken (measured: 6.4 mm off); told each
    colour camera's pose in its depth camera (``colour_poses``) it recovers the depth
    camera's motion (measured: 0.008 mm)."""
    K = np.array([[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1]])
    T_a = look_at([0.0, 0.0, 0.0], [0.0, 0.0, 2.0], up=(0, -1, 0))
    motion = exp_se3(np.array([0.0, 0.0, np.radians(1.0), 0.02, -0.01, 0.0]))
    C_source = exp_se3(np.array([0.0, 0.0, np.radians(0.1), 0.004, 0.0015, 0.0]))
    C_target = exp_se3(np.array([0.0, 0.0, np.radians(-0.05), -0.002, -0.0008, 0.0]))
    da, _ = _textured_wall(K, 320, 240, T_a)
    _, ca = _textured_wall(K, 320, 240, T_a @ C_target)
    db, _ = _textured_wall(K, 320, 240, T_a @ motion)
    _, cb = _textured_wall(K, 320, 240, T_a @ motion @ C_source)
    target = RgbdImage(da, grey(ca), K, 3)
    source = RgbdImage(db, grey(cb), K, 3)
    errors = {}
    for told in (False, True):
        poses = (C_source, C_target) if told else (None, None)
        res = joint_align(
            source, target, np.eye(4), [6, 4, 2], degenerate_ratio=40.0, colour_poses=poses
        )
        errors[told] = translation_norm(inv_T(motion) @ res.T_target_source)
    assert errors[False] > 0.003, errors
    assert errors[True] < 3e-4, errors


def test_the_images_score_the_true_step_below_a_slide_along_the_wall():
    """Two views of the textured wall: the photometric cost at the true step is the smallest,
    a 3 mm slide along the wall (a third of a pixel at level 1, where geometry is blind) costs
    more, and a larger slide more still; scored on the pixels every step sees."""
    motion = exp_se3(np.array([0.0, 0.0, np.radians(0.5), 0.01, -0.005, 0.0]))
    K, source, target = wall_views(motion)
    slide = np.eye(4)
    steps = []
    for d in (0.0, 0.003, 0.01):
        slide[0, 3] = d
        steps.append((motion @ slide, None))
    costs = photometric_costs(
        source.source(1), target.target(1, geometry=False), target.K[1], steps, 0.06
    )
    assert costs[0] < costs[1] < costs[2], costs
    # a step whose points all leave the target's image scores nothing
    away = exp_se3(np.array([0.0, 0.0, 0.0, 5.0, 0.0, 0.0]))
    assert photometric_costs(
        source.source(1), target.target(1, geometry=False), target.K[1], [(away, None)], 0.06
    ) == [float("inf")]


def test_the_colour_cameras_pose_follows_from_the_depth_cameras():
    T = exp_se3(np.array([0.1, 0.0, 0.0, 0.02, 0.0, 0.0]))
    C_s = exp_se3(np.array([0.0, 0.01, 0.0, 0.0, 0.003, 0.0]))
    C_t = exp_se3(np.array([0.0, 0.0, 0.02, 0.004, 0.0, 0.0]))
    assert colour_pose(T, None, None) is None
    np.testing.assert_allclose(colour_pose(T, C_s, None), T @ C_s)
    np.testing.assert_allclose(colour_pose(T, None, C_t), inv_T(C_t) @ T)
    # a point in the source colour camera, through its depth camera and the target's
    p = np.array([0.3, -0.2, 1.5, 1.0])
    np.testing.assert_allclose(colour_pose(T, C_s, C_t) @ p, inv_T(C_t) @ (T @ (C_s @ p)))
