"""Still images of a run without a display or GPU: the mesh ray-cast with Open3D's
``RaycastingScene`` (CPU), with the trajectories, keyframes and loop edges drawn over it.

This is what the README's picture of a run is made with (``scripts/render_mesh.py``); rerun's
viewer (``slam view``) shows the same data interactively but needs a display to render.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from slam.errors import SlamError
from slam.run_folder import MESH_FILE, RunFolder
from slam.trajectory import Trajectory

if TYPE_CHECKING:
    import open3d as o3d

log = logging.getLogger(__name__)

__all__ = ["Overlay", "default_view", "look_at", "render_mesh", "render_run"]

# BGR (OpenCV)
ODOMETRY_BGR = (244, 133, 66)
FINAL_BGR = (0, 140, 255)
KEYFRAME_BGR = (83, 168, 52)
LOOP_BGR = (40, 40, 220)


@dataclass
class Overlay:
    """3D things drawn over the rendered mesh: polylines ``(points (N, 3), BGR, width px)``,
    points ``(points (N, 3), BGR, radius px)`` and segments ``(a (3,), b (3,))`` in one colour.
    Parts hidden behind the surface are drawn faded."""

    lines: list[tuple[np.ndarray, tuple[int, int, int], int]] = field(default_factory=list)
    points: list[tuple[np.ndarray, tuple[int, int, int], int]] = field(default_factory=list)
    segments: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    segment_bgr: tuple[int, int, int] = LOOP_BGR


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``T_world_cam`` of a camera (x right, y down, z forward) at ``eye`` looking at
    ``target`` with ``up`` pointing up in the image."""
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = eye
    return T


def default_view(
    mesh: o3d.geometry.TriangleMesh, trajectory: Trajectory | None = None
) -> np.ndarray:
    """A readable overview: from behind the cameras and above them, looking at the middle of
    the mesh. "Up" is the cameras' mean up direction (-y of the camera; the world of a run is
    its first camera, y down), "behind" is against their mean viewing direction. Without a
    trajectory the first camera is taken to be the world frame."""
    verts = np.asarray(mesh.vertices)
    if len(verts) == 0:
        raise SlamError("the mesh is empty: nothing to render")
    lo, hi = np.percentile(verts, 5, axis=0), np.percentile(verts, 95, axis=0)
    center = (lo + hi) / 2
    size = float(np.linalg.norm(hi - lo))
    if trajectory is not None and len(trajectory):
        R = trajectory.poses[:, :3, :3]
        up = -R[:, :, 1].mean(0)
        forward = R[:, :, 2].mean(0)
        cam_center = trajectory.positions.mean(0)
    else:
        up, forward = np.array([0.0, -1.0, 0.0]), np.array([0.0, 0.0, 1.0])
        cam_center = center - 0.5 * size * forward
    up /= np.linalg.norm(up)
    forward = forward - up * (forward @ up)
    forward /= max(np.linalg.norm(forward), 1e-9)
    right = np.cross(forward, up)
    # a three-quarter view from behind, above and to the side of the cameras
    target = 0.4 * center + 0.6 * cam_center
    eye = target - 0.55 * size * forward + 0.4 * size * up + 0.2 * size * right
    return look_at(eye, target, up)


def _raycast(mesh: o3d.geometry.TriangleMesh, T: np.ndarray, w: int, h: int, f: float):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    d_cam = np.stack([(u - w / 2) / f, (v - h / 2) / f, np.ones_like(u)], -1)
    d = d_cam @ T[:3, :3].T
    rays = np.concatenate([np.broadcast_to(T[:3, 3], d.shape), d], -1).astype(np.float32)
    out = scene.cast_rays(o3d.core.Tensor(rays))
    return {
        k: out[k].numpy() for k in ("t_hit", "primitive_ids", "primitive_uvs", "primitive_normals")
    }, d


def render_mesh(
    mesh: o3d.geometry.TriangleMesh,
    T_world_cam: np.ndarray,
    width: int = 1280,
    height: int = 800,
    focal: float | None = None,
    overlay: Overlay | None = None,
) -> np.ndarray:
    """BGR image (uint8) of the mesh seen from ``T_world_cam``: vertex colours interpolated,
    lit by the normal, white background; then ``overlay`` drawn on top."""
    import cv2

    f = focal or 0.75 * width
    out, d = _raycast(mesh, T_world_cam, width, height, f)
    hit = np.isfinite(out["t_hit"])
    img = np.full((height, width, 3), 255.0, np.float32)
    colors = np.asarray(mesh.vertex_colors)
    tri = out["primitive_ids"].astype(np.int64)[hit]
    if len(colors):
        tris = np.asarray(mesh.triangles)[tri]
        b = out["primitive_uvs"][hit]
        c = (
            colors[tris[:, 0]] * (1 - b[:, :1] - b[:, 1:2])
            + colors[tris[:, 1]] * b[:, :1]
            + colors[tris[:, 2]] * b[:, 1:2]
        )
    else:
        c = np.full((int(hit.sum()), 3), 0.8)
    dn = d[hit] / np.linalg.norm(d[hit], axis=1, keepdims=True)
    shade = 0.55 + 0.45 * np.abs((out["primitive_normals"][hit] * dn).sum(1))
    img[hit] = 255 * np.clip(c * shade[:, None], 0, 1)
    bgr = cv2.cvtColor(img.astype(np.uint8), cv2.COLOR_RGB2BGR)
    if overlay is not None:
        z = np.where(hit, out["t_hit"], np.inf)  # ray t = z-depth (unit z direction)
        _draw_overlay(bgr, overlay, T_world_cam, f, z)
    return bgr


def _project(points: np.ndarray, T: np.ndarray, f: float, w: int, h: int):
    Tinv = np.linalg.inv(T)
    pc = points @ Tinv[:3, :3].T + Tinv[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = pc[:, :2] / z[:, None] * f + np.array([w / 2, h / 2])
    return uv, z


def _visible(uv: np.ndarray, z: np.ndarray, zbuf: np.ndarray, tol: float = 0.03) -> np.ndarray:
    h, w = zbuf.shape
    ui = np.clip(np.floor(uv[:, 0]).astype(int), 0, w - 1)
    vi = np.clip(np.floor(uv[:, 1]).astype(int), 0, h - 1)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    return ~inside | (z <= zbuf[vi, ui] + tol)


def _densify(points: np.ndarray, step: float = 0.01) -> np.ndarray:
    out = [points[:1]]
    for a, b in zip(points[:-1], points[1:]):
        n = max(int(np.linalg.norm(b - a) / step), 1)
        out.append(a + (b - a) * (np.arange(1, n + 1)[:, None] / n))
    return np.concatenate(out)


def _draw_polyline(img, layer, pts, bgr, width, T, f, zbuf) -> None:
    import cv2

    h, w = zbuf.shape
    dense = _densify(pts)
    uv, z = _project(dense, T, f, w, h)
    vis = _visible(uv, z, zbuf)
    for k in range(len(dense) - 1):
        if z[k] <= 0.05 or z[k + 1] <= 0.05:
            continue
        a = tuple(int(round(x)) for x in uv[k])
        b = tuple(int(round(x)) for x in uv[k + 1])
        target = img if vis[k] and vis[k + 1] else layer
        cv2.line(target, a, b, bgr, width, cv2.LINE_AA)


def _draw_overlay(img: np.ndarray, ov: Overlay, T: np.ndarray, f: float, zbuf: np.ndarray) -> None:
    import cv2

    h, w = zbuf.shape
    hidden = img.copy()  # occluded parts are drawn here and blended in faintly
    base = img.copy()
    for a, b in ov.segments:
        _draw_polyline(img, hidden, np.array([a, b]), ov.segment_bgr, 1, T, f, zbuf)
    for pts, bgr, width in ov.lines:
        if len(pts) >= 2:
            _draw_polyline(img, hidden, np.asarray(pts, float), bgr, width, T, f, zbuf)
    for pts, bgr, radius in ov.points:
        uv, z = _project(np.asarray(pts, float).reshape(-1, 3), T, f, w, h)
        vis = _visible(uv, z, zbuf)
        for (u, v), zz, ok in zip(uv, z, vis):
            if zz > 0.05:
                c = (int(round(u)), int(round(v)))
                cv2.circle(img if ok else hidden, c, radius, bgr, -1, cv2.LINE_AA)
    changed = np.any(hidden != base, axis=2)
    img[changed] = (0.65 * base[changed] + 0.35 * hidden[changed]).astype(np.uint8)


def _legend(img: np.ndarray, items: list[tuple[str, tuple[int, int, int]]]) -> None:
    import cv2

    y = 28
    for text, bgr in items:
        cv2.line(img, (16, y - 6), (46, y - 6), bgr, 3, cv2.LINE_AA)
        cv2.putText(img, text, (54, y), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (30, 30, 30), 1, cv2.LINE_AA)
        y += 26


def _run_overlay(
    run: RunFolder, traj: Trajectory, odometry: bool
) -> tuple[Overlay, list[tuple[str, tuple[int, int, int]]]]:
    """The overlay of a run (trajectories, keyframes, accepted loop edges) and its legend."""
    from slam.tools.report import loop_edges

    ov = Overlay()
    legend = []
    odo = run.odometry() if odometry else None
    if odo is not None:
        same = len(odo) == len(traj) and np.allclose(odo.poses, traj.poses)
        if not same:
            ov.lines.append((odo.positions, ODOMETRY_BGR, 2))
            legend.append(("odometry (before loop closure)", ODOMETRY_BGR))
    ov.lines.append((traj.positions, FINAL_BGR, 2))
    legend.append(("final trajectory", FINAL_BGR))
    statuses = run.tracking()
    if statuses is not None:
        kf_t = {round(s.timestamp, 6) for s in statuses if s.keyframe and s.ok}
        kf = [p for t, p in zip(traj.timestamps, traj.positions) if round(float(t), 6) in kf_t]
        if kf:
            ov.points.append((np.array(kf), KEYFRAME_BGR, 4))
            legend.append((f"keyframes ({len(kf)})", KEYFRAME_BGR))
    edges = loop_edges(traj, run.accepted_loops())
    if edges:
        ov.segments = edges
        legend.append((f"accepted loop edges ({len(edges)})", LOOP_BGR))
    return ov, legend


def render_run(
    run_dir: str | Path,
    png: str | Path,
    width: int = 1280,
    height: int = 800,
    T_world_cam: np.ndarray | None = None,
    odometry: bool = True,
) -> Path:
    """Render a run folder's ``mesh.ply`` with its final trajectory (orange), odometry (blue,
    when loop closure changed it), keyframes of the final trajectory (green) and accepted loop
    edges (red) into ``png``; view :func:`default_view` unless ``T_world_cam`` is given."""
    import cv2

    run = RunFolder(run_dir)
    mesh = run.mesh()
    if mesh is None:
        raise SlamError(f"{run.path}: no {MESH_FILE} to render (was output.save_mesh off?)")
    traj = run.trajectory()
    ov, legend = _run_overlay(run, traj, odometry)
    T = T_world_cam if T_world_cam is not None else default_view(mesh, traj)
    img = render_mesh(mesh, T, width, height, overlay=ov)
    _legend(img, legend)
    png = Path(png)
    png.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(png), img):
        raise SlamError(f"{png}: cannot write the image")
    log.info("rendered %s into %s", run.path, png)
    return png
