"""Shared test fixtures: tiny rendered scenes with exact geometry, and the shared datasets path."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

SHARED_DATASETS = Path(__file__).resolve().parents[1].parent / "shared" / "datasets"


def shared_sequence(name: str) -> Path:
    """Path of a sequence in ../shared/datasets, or skip the test with the reason."""
    path = SHARED_DATASETS / name
    if not path.is_dir():
        pytest.skip(
            f"real-data sequence {name} not found at {path} (CI provides ../shared/datasets)"
        )
    return path


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_world_cam`` of an OpenCV camera (z forward, y down) at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


def render_depth(mesh: o3d.geometry.TriangleMesh, K: np.ndarray, w: int, h: int, T_world_cam):
    """Exact z-depth (metres, 0 = miss) of a legacy mesh seen from ``T_world_cam``."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1)
    d_world = d_cam @ T_world_cam[:3, :3].T
    origins = np.broadcast_to(T_world_cam[:3, 3], d_world.shape)
    rays = np.concatenate([origins, d_world], -1).astype(np.float32)
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    depth = np.where(np.isfinite(t_hit), t_hit, 0.0)  # ray direction has z = 1: t is z-depth
    return depth.astype(np.float32)


def room_scene() -> o3d.geometry.TriangleMesh:
    """A small room (inside of a box) with a few boxes and a sphere: well-constrained for ICP."""
    room = o3d.geometry.TriangleMesh.create_box(4.0, 4.0, 3.0).translate((-2.0, -2.0, 0.0))
    room.triangles = o3d.utility.Vector3iVector(np.asarray(room.triangles)[:, ::-1])
    parts = [room]
    for size, pos in [
        ((0.6, 0.4, 0.8), (-0.5, 0.6, 0.0)),
        ((0.3, 0.8, 0.5), (0.7, -0.4, 0.0)),
        ((0.5, 0.5, 1.2), (1.2, 1.0, 0.0)),
    ]:
        parts.append(o3d.geometry.TriangleMesh.create_box(*size).translate(pos))
    parts.append(o3d.geometry.TriangleMesh.create_sphere(0.3).translate((0.0, -0.8, 0.9)))
    mesh = parts[0]
    for p in parts[1:]:
        mesh += p
    return mesh


@pytest.fixture(scope="session")
def room() -> o3d.geometry.TriangleMesh:
    return room_scene()


@pytest.fixture(scope="session")
def K_vga() -> np.ndarray:
    return np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="session")
def synth_loop_320(tmp_path_factory) -> Path:
    """A 320x240 synthetic loop sequence (300 frames, exact ground truth), generated once."""
    from slam.synthetic import SynthConfig, generate_sequence

    out = tmp_path_factory.mktemp("synth") / "loop320"
    cfg = SynthConfig.half_resolution(frames=300, loop=True, seed=1)
    return generate_sequence(out, cfg)


@pytest.fixture(scope="session")
def recorded_run(tmp_path_factory) -> tuple[Path, Path]:
    """A short SLAM run (30 frames of a 320x240 synthetic loop) written to a run folder and
    recorded for rerun with ``slam.api.run_sequence(rerun=...)``: (run folder, .rrd file)."""
    pytest.importorskip("rerun", reason="rerun-sdk (the viz extra) is not installed")
    from slam.api import run_sequence
    from slam.config import config_from_dict
    from slam.synthetic import SynthConfig, generate_sequence

    root = tmp_path_factory.mktemp("recorded")
    seq = generate_sequence(
        root / "seq", SynthConfig.half_resolution(frames=300, render_frames=30, loop=True, seed=2)
    )
    rrd = root / "live.rrd"
    _, run_dir = run_sequence(
        seq, root / "run", config=config_from_dict({"tracking": {"downsample": 1}}), rerun=rrd
    )
    return run_dir, rrd
