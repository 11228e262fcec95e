"""Synthetic rows that move and look like a hand-held Kinect v1: the recorded hand's motion
(slam.synthetic.handheld) and the sensor's effects (slam.synthetic.kinect)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slam.errors import ConfigError
from slam.geometry import exp_se3, inv_T
from slam.synthetic import (
    SynthConfig,
    build_scene,
    generate_sequence,
    make_trajectory,
    render_frame,
)
from slam.synthetic.handheld import RECORDINGS, hand_motion, recording
from slam.synthetic.kinect import SensorMotion, image_speed, row_poses


def _departures_mm(P: np.ndarray) -> np.ndarray:
    """Each position's distance from the constant-velocity prediction of the two before it."""
    p = P[:, :3, 3]
    return 1e3 * np.linalg.norm(p[2:] - 2 * p[1:-1] + p[:-2], axis=1)


def test_recordings_are_real_handheld_paths_at_30_hz():
    assert {"fr1_desk2", "fr1_room", "fr1_360", "fr1_plant", "fr1_teddy"} <= set(RECORDINGS)
    for name in RECORDINGS:
        t, P = recording(name)
        assert len(t) >= 600 and np.allclose(np.diff(t), 1 / 30, atol=1e-3)
        np.testing.assert_allclose(P[:, :3, :3] @ P[:, :3, :3].transpose(0, 2, 1),
                                   np.broadcast_to(np.eye(3), (len(P), 3, 3)), atol=1e-6)  # fmt: skip
        # a hand, not a rig: departures from constant velocity of a millimetre, up to several
        d = _departures_mm(P)
        assert 0.5 < np.median(d) < 2.0 and np.percentile(d, 99) > 1.5


@pytest.mark.parametrize("name", ["fr1_desk2", "fr1_360", "fr1_teddy"])
def test_the_synthetic_camera_departs_from_constant_velocity_as_the_recording(name):
    t, P = recording(name)
    cfg = SynthConfig(frames=240, scene="desk", handheld=name)
    synthetic = make_trajectory(cfg).poses
    rec, syn = _departures_mm(P[:240]), _departures_mm(synthetic)
    assert np.median(syn) == pytest.approx(np.median(rec), rel=0.12)
    assert np.percentile(syn, 99) == pytest.approx(np.percentile(rec, 99), rel=0.12)
    # and the kind's own path is still the one it follows (the hand strays centimetres)
    plain = make_trajectory(SynthConfig(frames=240, scene="desk")).poses
    assert np.max(np.linalg.norm(synthetic[:, :3, 3] - plain[:, :3, 3], axis=1)) < 0.25


def test_hand_motion_turns_round_at_the_recording_end_and_unknown_names_are_refused():
    t, _ = recording("fr1_360")
    n = len(t)
    hand = hand_motion("fr1_360", np.arange(n + 5) / 30.0)
    np.testing.assert_allclose(hand[n], hand[n - 2])  # played backwards from the end
    with pytest.raises(ConfigError, match="handheld must be one of"):
        SynthConfig(handheld="fr9_nowhere").validate()


def test_rolling_shutter_rows_follow_the_twist():
    T = exp_se3(np.array([0.1, 0.2, 0.0, 0.5, 0.0, 1.0]))
    twist = np.array([0.0, 2.0, 0.0, 0.3, 0.0, 0.0])  # 115 deg/s about y, 0.3 m/s along x
    rows = row_poses(T, twist, 240)
    np.testing.assert_allclose(0.5 * (rows[119] + rows[120]), T, atol=1e-4)  # middle row
    first_to_last = inv_T(rows[0]) @ rows[-1]
    np.testing.assert_allclose(first_to_last, exp_se3(0.025 * twist), atol=1e-9)


def test_image_speed_of_a_pan_and_of_a_forward_move():
    xn = np.array([0.0, 0.5], np.float32)
    yn = np.zeros(2, np.float32)
    z = np.array([2.0, 2.0], np.float32)
    # turning right about the camera's y axis moves the image left by f * w at the centre
    fu, fv = image_speed(xn, yn, z, np.array([0.0, 1.0, 0, 0, 0, 0]), 500.0, 500.0)
    assert fu[0] == pytest.approx(-500.0) and fv[0] == pytest.approx(0.0)
    # moving forward: the centre stays, a point to the right moves right by f x v / z
    fu, _ = image_speed(xn, yn, z, np.array([0, 0, 0, 0, 0, 1.0]), 500.0, 500.0)
    assert fu[0] == pytest.approx(0.0) and fu[1] == pytest.approx(500 * 0.5 * 1.0 / 2.0)


def test_kinect_frames_shear_blur_and_lose_depth_as_a_handheld_kinect():
    cfg = SynthConfig.half_resolution(frames=30, scene="desk", seed=0, kinect=True)
    still = SynthConfig.half_resolution(frames=30, scene="desk", seed=0)
    scene = build_scene(cfg)
    T = make_trajectory(cfg).poses[10]
    fast = SensorMotion(np.array([0.0, 1.5, 0.0, 0.0, 0.0, 0.0]))  # 86 deg/s pan
    c_k, d_k = render_frame(scene, T, cfg, np.random.default_rng(0), fast)
    c_s, d_s = render_frame(scene, T, still, np.random.default_rng(0))
    valid_k, valid_s = (d_k > 0).mean(), (d_s > 0).mean()
    # shadows, ragged edges and dark surfaces cost depth, but most pixels keep it (a real
    # Kinect v1 keeps 77% on tum-fr1-rpy-500's desk)
    assert 0.5 < valid_k < valid_s
    # the blur along a horizontal pan smooths the rows, not the columns
    gx_k = np.abs(np.diff(c_k.astype(float).mean(2), axis=1)).mean()
    gx_s = np.abs(np.diff(c_s.astype(float).mean(2), axis=1)).mean()
    gy_k = np.abs(np.diff(c_k.astype(float).mean(2), axis=0)).mean()
    gy_s = np.abs(np.diff(c_s.astype(float).mean(2), axis=0)).mean()
    assert gx_k / gx_s < 0.9 * gy_k / gy_s
    # the depth that is left lies near the true surface (noise, not a different scene)
    exact = SynthConfig.half_resolution(frames=30, scene="desk", seed=0, noise=False)
    _, d_true = render_frame(scene, T, exact)
    both = (d_k > 0) & (d_true > 0)
    assert np.median(np.abs(d_k[both] - d_true[both])) < 0.02


def test_a_kinect_sequence_has_a_gain_that_drifts(tmp_path: Path):
    cfg = SynthConfig.half_resolution(
        frames=40, scene="wall", seed=1, handheld="fr1_room", kinect=True, color_offset_ms=10.0
    )
    out = generate_sequence(tmp_path / "seq", cfg)
    import cv2

    means = [cv2.imread(str(out / "rgb" / f"{i:06d}.png")).mean() for i in (0, 20, 39)]
    assert max(means) / min(means) > 1.02  # the auto exposure moved
    assert (out / ".complete").is_file()
