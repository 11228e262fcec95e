"""Tests of slam.synthetic: determinism, exact geometry, trajectory shape, sensor model, files."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
import yaml

from slam.errors import ConfigError
from slam.geometry import inv_T, rotation_angle_deg, translation_norm
from slam.synthetic import (
    SynthConfig,
    alias_clusters,
    build_scene,
    generate_sequence,
    make_scene,
    make_trajectory,
    render_frame,
)
from slam.synthetic import config as synth_config
from slam.synthetic import writer as synth
from slam.trajectory import read_tum


def small(**kw) -> SynthConfig:
    """160x120 camera with the intrinsics of the default 640x480 one downsampled by 4."""
    base = dict(frames=10, width=160, height=120, fx=525.0 / 4, fy=525.0 / 4, cx=79.5, cy=59.5)
    base.update(kw)
    return SynthConfig(**base)


def backproject(depth: np.ndarray, cfg: SynthConfig, T_world_cam: np.ndarray) -> np.ndarray:
    """World points (M, 3) of the valid depth pixels."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    pc = np.stack([(u - cfg.cx) / cfg.fx * z, (v - cfg.cy) / cfg.fy * z, z], axis=1)
    return pc @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]


def mesh_distance(mesh: o3d.geometry.TriangleMesh, points: np.ndarray) -> np.ndarray:
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return rs.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


@pytest.fixture(scope="module")
def small_scene():
    cfg = small(noise=False)
    return cfg, build_scene(cfg), make_trajectory(dataclasses.replace(cfg, frames=300))


# ----------------------------------------------------------------------------------------------
# trajectory


def _steps(traj):
    rel = [inv_T(a) @ b for a, b in zip(traj.poses[:-1], traj.poses[1:])]
    speed = np.array([np.linalg.norm(r[:3, 3]) for r in rel]) * 30.0
    rot = np.array([rotation_angle_deg(r) for r in rel])
    return speed, rot


def test_loop_trajectory_closes_and_moves_like_a_handheld_camera():
    traj = make_trajectory(SynthConfig(frames=300, loop=True))
    assert len(traj) == 300
    np.testing.assert_allclose(traj.timestamps, np.arange(300) / 30.0)
    speed, rot = _steps(traj)
    assert 0.3 < speed.mean() < 0.5
    assert speed.max() < 0.65
    assert rot.max() < 2.0
    # the last pose is one ordinary step before the first one: the end revisits the start
    close = inv_T(traj.poses[-1]) @ traj.poses[0]
    assert np.linalg.norm(close[:3, 3]) < 0.1
    assert rotation_angle_deg(close) < 3.0
    # smooth: frame-to-frame velocity changes little (no kinks)
    vel = np.diff(traj.positions, axis=0)
    assert np.abs(np.diff(vel, axis=0)).max() < 0.003
    # valid rotations, OpenCV axes: camera y (down) points below the horizon
    R = traj.poses[:, :3, :3]
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    assert np.all(R[:, 2, 1] < 0)
    # inside the room, at a hand-held height
    P = traj.positions
    assert np.all(np.abs(P[:, 0]) < 1.5) and np.all(np.abs(P[:, 1]) < 1.2)
    assert np.all((P[:, 2] > 1.1) & (P[:, 2] < 1.6))


def test_open_trajectory_never_revisits_its_start():
    traj = make_trajectory(SynthConfig(frames=300, loop=False))
    assert traj.path_length() > 2.0
    T0 = traj.poses[0]
    later = traj.poses[100:]
    dist = np.linalg.norm(later[:, :3, 3] - T0[:3, 3], axis=1)
    ang = np.array([rotation_angle_deg(inv_T(T0) @ T) for T in later])
    assert np.all((dist > 0.5) | (ang > 60.0))
    assert dist[-1] > 1.0 and ang[-1] > 150.0
    speed, rot = _steps(traj)
    assert speed.max() < 0.65 and rot.max() < 2.0


def test_trajectory_deterministic_per_seed():
    a = make_trajectory(SynthConfig(frames=50, seed=3))
    b = make_trajectory(SynthConfig(frames=50, seed=3))
    c = make_trajectory(SynthConfig(frames=50, seed=4))
    np.testing.assert_array_equal(a.poses, b.poses)
    assert np.abs(a.positions - c.positions).max() > 0.01


# ----------------------------------------------------------------------------------------------
# rendering


def test_render_is_deterministic_for_a_seed():
    cfg = small(noise=True, seed=5)
    traj = make_trajectory(cfg)
    outs = []
    for _ in range(2):
        scene = build_scene(cfg)
        rng = np.random.default_rng(cfg.seed)
        outs.append([render_frame(scene, traj.poses[i], cfg, rng) for i in (0, 3, 7)])
    for (c1, d1), (c2, d2) in zip(*outs):
        assert d1.dtype == np.float32 and d1.shape == (120, 160)
        assert c1.dtype == np.uint8 and c1.shape == (120, 160, 3)
        np.testing.assert_array_equal(d1, d2)
        np.testing.assert_array_equal(c1, c2)
    other = render_frame(build_scene(cfg), traj.poses[0], cfg, np.random.default_rng(99))[1]
    assert not np.array_equal(other, outs[0][0][1])  # the noise does come from rng


def test_noiseless_depth_lies_on_the_true_surface(small_scene):
    cfg, scene, traj = small_scene
    mesh = make_scene(cfg)
    for i in (0, 60, 130, 200, 270):
        _, depth = render_frame(scene, traj.poses[i], cfg, None)
        assert (depth > 0).mean() > 0.9
        dist = mesh_distance(mesh, backproject(depth, cfg, traj.poses[i]))
        assert dist.max() < 1e-3, (i, dist.max())
        assert np.median(dist) < 1e-5
        # and quantised to the 16-bit PNG grid it is still within 0.1 mm + grazing slack
        q = np.round(depth * cfg.depth_scale) / cfg.depth_scale
        assert np.median(mesh_distance(mesh, backproject(q, cfg, traj.poses[i]))) < 1e-4


def test_views_are_at_indoor_range_and_not_a_single_plane(small_scene):
    cfg, scene, traj = small_scene
    for i in range(0, 300, 25):
        _, depth = render_frame(scene, traj.poses[i], cfg, None)
        d = depth[depth > 0]
        assert 0.8 < np.median(d) < 2.5, (i, np.median(d))
        pts = backproject(depth, cfg, traj.poses[i])
        c = pts - pts.mean(0)
        normal = np.linalg.svd(c, full_matrices=False)[2][-1]
        off_plane = np.abs(c @ normal) > 0.05
        assert off_plane.mean() > 0.15, (i, off_plane.mean())


def test_noise_model():
    cfg_n = small(noise=True, seed=2)
    cfg_c = small(noise=False, seed=2)
    scene = build_scene(cfg_n)
    traj = make_trajectory(dataclasses.replace(cfg_n, frames=300))
    rng = np.random.default_rng(0)
    for i in (10, 110, 210):
        color_n, dn = render_frame(scene, traj.poses[i], cfg_n, rng)
        color_c, dc = render_frame(scene, traj.poses[i], cfg_c, rng)
        valid = dn > 0
        assert valid.mean() > 0.5
        dropped = ((dc > 0) & ~valid).mean()
        assert 0.01 < dropped < 0.35
        assert (
            dn[valid].min() >= synth_config.MIN_DEPTH and dn[valid].max() <= synth_config.MAX_DEPTH
        )
        both = valid & (dc > 0)
        err = dn[both] - dc[both]
        # axial sigma at ~1.5 m is ~3.5 mm (plus quantisation): errors of that order, unbiased
        assert 0.001 < np.std(err) < 0.012
        assert abs(np.median(err)) < 0.002
        assert np.all(np.abs(err) < 0.1)
        # depth lands on the 1/depth_scale grid
        scaled = dn[valid] * cfg_n.depth_scale
        assert np.abs(scaled - np.round(scaled)).max() < 0.01
        # colour noise is small
        diff = color_n.astype(float) - color_c
        assert 0.5 < diff.std() < 4.0


def test_orb_features_everywhere():
    cfg = SynthConfig(noise=True, frames=300)
    scene = build_scene(cfg)
    traj = make_trajectory(cfg)
    orb = cv2.ORB_create(1000)
    rng = np.random.default_rng(0)
    for i in (0, 75, 150, 225):
        color, depth = render_frame(scene, traj.poses[i], cfg, rng)
        assert color.shape == (480, 640, 3) and depth.shape == (480, 640)
        assert (depth > 0).mean() > 0.5
        kps = orb.detect(cv2.cvtColor(color, cv2.COLOR_RGB2GRAY), None)
        assert len(kps) > 300, (i, len(kps))


def test_render_accepts_the_make_scene_mesh(small_scene):
    cfg, scene, traj = small_scene
    mesh = make_scene(cfg)
    c1, d1 = render_frame(mesh, traj.poses[40], cfg, None)
    c2, d2 = render_frame(scene, traj.poses[40], cfg, None)
    np.testing.assert_array_equal(d1, d2)
    np.testing.assert_array_equal(c1, c2)
    with pytest.raises(TypeError):
        render_frame("not a scene", traj.poses[0], cfg, None)


def _cluster_views(cfg):
    """Poses looking at cluster copy 0 and at the equivalent place of copy 1 (or where it would be)."""
    clusters = alias_clusters(dataclasses.replace(cfg, alias=True))
    f = np.array([-1.0, 0.0, -0.4])
    f /= np.linalg.norm(f)
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    T_local_cam = np.eye(4)
    T_local_cam[:3, :3] = np.stack([right, np.cross(f, right), f], axis=1)
    T_local_cam[:3, 3] = [1.3, 0.0, 1.2]
    return clusters[0] @ T_local_cam, clusters[1] @ T_local_cam


def test_alias_scene_repeats_the_same_structure():
    results = {}
    for alias in (True, False):
        cfg = small(noise=False, alias=alias)
        scene = build_scene(cfg)
        Ta, Tb = _cluster_views(cfg)
        ca, da = render_frame(scene, Ta, cfg, None)
        cb, db = render_frame(scene, Tb, cfg, None)
        assert (da > 0).mean() > 0.9 and (db > 0).mean() > 0.9
        same = (np.abs(da - db) < 1e-3) & (np.abs(ca.astype(int) - cb).max(axis=2) <= 2)
        results[alias] = same.mean()
    assert len(alias_clusters(small(alias=True))) == 2
    assert len(alias_clusters(small(alias=False))) == 1
    assert results[True] > 0.4, results
    assert results[False] < 0.2, results
    # and the aliased scene renders along the normal trajectory too
    cfg = small(noise=True, alias=True)
    scene = build_scene(cfg)
    traj = make_trajectory(dataclasses.replace(cfg, frames=300))
    rng = np.random.default_rng(0)
    for i in (0, 150):
        _, depth = render_frame(scene, traj.poses[i], cfg, rng)
        assert (depth > 0).mean() > 0.5


# ----------------------------------------------------------------------------------------------
# sequence files


def test_generate_sequence_writes_a_tum_folder(tmp_path: Path):
    cfg = small(frames=6, seed=1)
    out = generate_sequence(tmp_path / "seq", cfg)
    assert out == tmp_path / "seq"
    assert (out / ".complete").is_file()
    assert json.loads((out / ".complete").read_text())["seed"] == 1
    assert sorted(p.name for p in (out / "rgb").iterdir()) == [f"{i:06d}.png" for i in range(6)]
    assert sorted(p.name for p in (out / "depth").iterdir()) == [f"{i:06d}.png" for i in range(6)]

    for name, folder in (("rgb.txt", "rgb"), ("depth.txt", "depth")):
        lines = (out / name).read_text().splitlines()
        assert lines[0].startswith("#")
        entries = [ln.split() for ln in lines if not ln.startswith("#")]
        assert len(entries) == 6
        assert [e[0] for e in entries] == [f"{i / 30:.6f}" for i in range(6)]
        assert [e[1] for e in entries] == [f"{folder}/{i:06d}.png" for i in range(6)]

    calib = yaml.safe_load((out / "calibration.yaml").read_text())
    assert list(calib) == ["width", "height", "fx", "fy", "cx", "cy", "depth_scale"]
    assert calib == {
        "width": 160,
        "height": 120,
        "fx": 131.25,
        "fy": 131.25,
        "cx": 79.5,
        "cy": 59.5,
        "depth_scale": 5000.0,
    }

    gt = read_tum(out / "groundtruth.txt")
    ref = make_trajectory(cfg)
    np.testing.assert_allclose(gt.timestamps, ref.timestamps, atol=1e-6)
    np.testing.assert_allclose(gt.poses, ref.poses, atol=1e-6)

    # images: frame 0 equals a fresh render with the sequence's rng; RGB order, 16-bit depth
    color, depth = render_frame(build_scene(cfg), ref.poses[0], cfg, np.random.default_rng(1))
    rgb = cv2.imread(str(out / "rgb" / "000000.png"), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(rgb[..., ::-1], color)
    d16 = cv2.imread(str(out / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert d16.dtype == np.uint16 and d16.shape == (120, 160)
    np.testing.assert_array_equal(d16, np.round(depth * 5000.0).astype(np.uint16))

    mesh = o3d.io.read_triangle_mesh(str(out / "scene.ply"))
    assert len(mesh.triangles) == len(make_scene(cfg).triangles)

    # the project's TUM loader reads it back
    from slam.data.tum import TumSequence

    seq = TumSequence(out)
    assert len(seq) == 6
    assert seq.calibration.fx == pytest.approx(131.25)
    frame = seq[0]
    np.testing.assert_allclose(frame.depth_m, d16 / 5000.0, atol=1e-6)

    # regenerating with fewer frames into the same folder leaves no stale frames
    generate_sequence(out, dataclasses.replace(cfg, frames=3))
    assert len(list((out / "rgb").iterdir())) == 3
    assert len(list((out / "depth").iterdir())) == 3


def test_colour_taken_off_the_depths_instant(tmp_path: Path):
    """``color_offset_ms``: each colour image is rendered from the camera's pose at its own
    time, which ``rgb.txt`` gives (within the offset of the depth's); the depth images and the
    ground truth are those of the synchronised sequence."""
    cfg = small(frames=5, seed=2)
    sync = generate_sequence(tmp_path / "sync", cfg)
    out = generate_sequence(tmp_path / "off", dataclasses.replace(cfg, color_offset_ms=15.0))
    from slam.data.tum import TumSequence

    a, b = TumSequence(sync), TumSequence(out)
    offsets = np.array([b[i].color_dt_s for i in range(5)])
    assert np.all(np.abs(offsets) <= 0.015 + 1e-6) and np.all(offsets != 0)
    # a colour camera at its own steady rate: the offset drifts from +15 to -15 ms, and
    # consecutive colour images are a frame interval apart, up to the drift and the jitter
    assert offsets[0] > 0.011 and offsets[-1] < -0.011
    assert np.all(np.abs(np.diff(offsets) + 0.0075) <= 2 * synth.COLOR_JITTER_S + 1e-5)
    np.testing.assert_allclose(b.timestamps(), a.timestamps())
    for i in range(5):
        np.testing.assert_array_equal(b[i].depth_m, a[i].depth_m)
    # the colour is the render at the pose interpolated to its time, up to its own pixel noise
    # (measured: 2.3 grey levels apart on average; from the depth's pose 40)
    i = int(np.argmax(np.abs(offsets)))
    T = synth._pose_at(make_trajectory(cfg), i, offsets[i])
    color, _ = render_frame(build_scene(cfg), T, cfg, np.random.default_rng(7))
    rgb, rgb_sync = b[i].color.astype(int), a[i].color.astype(int)
    off_own, off_sync = np.mean(np.abs(rgb - color)), np.mean(np.abs(rgb - rgb_sync))
    assert off_own < 0.5 * off_sync, (off_own, off_sync)
    # the first and the last frame continue their one neighbour's motion (they are not
    # left at their depth's pose)
    traj = make_trajectory(cfg)
    inner = translation_norm(inv_T(traj.poses[2]) @ synth._pose_at(traj, 2, 0.01))
    for end, dt in ((0, -0.01), (4, 0.01)):
        moved = translation_norm(inv_T(traj.poses[end]) @ synth._pose_at(traj, end, dt))
        assert 0.5 * inner < moved < 2 * inner, (moved, inner)
    with pytest.raises(ConfigError, match="color_offset_ms"):
        SynthConfig(color_offset_ms=20.0).validate()


def test_interrupted_generation_has_no_complete_marker(tmp_path: Path, monkeypatch):
    cfg = small(frames=4)
    out = generate_sequence(tmp_path / "seq", cfg)
    assert synth.is_complete(out)
    calls = {"n": 0}
    real = synth.render_frame

    def failing(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] > 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(synth, "render_frame", failing)
    with pytest.raises(KeyboardInterrupt):
        generate_sequence(out, cfg)
    assert not (out / ".complete").exists()
    assert not synth.is_complete(out)


def test_config_validation(tmp_path: Path):
    from slam.errors import CalibrationError

    with pytest.raises(ConfigError):
        make_trajectory(SynthConfig(frames=0))
    with pytest.raises(CalibrationError):
        generate_sequence(tmp_path / "x", SynthConfig(frames=2, fx=-1.0))


def test_drift_bias_is_a_radial_depth_distortion(small_scene):
    """drift_bias scales depth by 1 + b * r^2 (r: normalised image radius); colour and ground
    truth are untouched."""
    cfg, scene, traj = small_scene
    b = 0.05
    biased = dataclasses.replace(cfg, drift_bias=b)
    color0, depth0 = render_frame(scene, traj.poses[0], cfg, None)
    color1, depth1 = render_frame(scene, traj.poses[0], biased, None)
    np.testing.assert_array_equal(color0, color1)
    v, u = np.nonzero((depth0 > 0) & (depth1 > 0))
    r2 = ((u - cfg.cx) / cfg.fx) ** 2 + ((v - cfg.cy) / cfg.fy) ** 2
    np.testing.assert_allclose(depth1[v, u], depth0[v, u] * (1 + b * r2), rtol=1e-5)
    assert (depth1[v, u] / depth0[v, u]).max() > 1 + 0.5 * b * r2.max()
