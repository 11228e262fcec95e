"""Render a coloured PLY mesh to a PNG (headless: Open3D ray casting, no OpenGL).

    python scripts/render_mesh.py runs/demo/mesh.ply docs/mesh.png [--trajectory runs/demo/trajectory.txt]

The camera looks at the mesh from above and behind its centre (or from the first pose of a
trajectory file when given, pulled back). Vertex colours are interpolated and lit by the normal.
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np
import open3d as o3d


def look_at(eye: np.ndarray, target: np.ndarray, up: tuple = (0.0, 0.0, 1.0)) -> np.ndarray:
    up = np.asarray(up, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = eye
    return T


def render(mesh: o3d.geometry.TriangleMesh, T_world_cam: np.ndarray, w=960, h=720, f=700.0):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    d = (
        np.stack([(u - w / 2) / f, (v - h / 2) / f, np.ones_like(u, float)], -1)
        @ T_world_cam[:3, :3].T
    )
    rays = np.concatenate([np.broadcast_to(T_world_cam[:3, 3], d.shape), d], -1).astype(np.float32)
    out = scene.cast_rays(o3d.core.Tensor(rays))
    hit = np.isfinite(out["t_hit"].numpy())
    tri = out["primitive_ids"].numpy().astype(np.int64)
    bary = out["primitive_uvs"].numpy()
    normals = out["primitive_normals"].numpy()
    img = np.full((h, w, 3), 255, np.float32)
    colors = np.asarray(mesh.vertex_colors)
    if len(colors):
        tris = np.asarray(mesh.triangles)[tri[hit]]
        b = bary[hit]
        c = (
            colors[tris[:, 0]] * (1 - b[:, :1] - b[:, 1:2])
            + colors[tris[:, 1]] * b[:, :1]
            + colors[tris[:, 2]] * b[:, 1:2]
        )
    else:
        c = np.full((int(hit.sum()), 3), 0.8)
    shade = 0.55 + 0.45 * np.abs(
        (normals[hit] * d[hit] / np.linalg.norm(d[hit], axis=1, keepdims=True)).sum(1)
    )
    img[hit] = 255 * np.clip(c * shade[:, None], 0, 1)
    return cv2.cvtColor(img.astype(np.uint8), cv2.COLOR_RGB2BGR)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("mesh")
    p.add_argument("png")
    p.add_argument("--eye", type=float, nargs=3, default=None, help="camera position (world)")
    args = p.parse_args()
    mesh = o3d.io.read_triangle_mesh(args.mesh)
    bb = mesh.get_axis_aligned_bounding_box()
    center = bb.get_center()
    extent = bb.get_extent()
    eye = np.array(args.eye) if args.eye else center + np.array([0.0, -0.55, -0.75]) * extent.max()
    T = look_at(eye, center, up=np.array([0.0, -1.0, 0.0]))
    cv2.imwrite(args.png, render(mesh, T))


if __name__ == "__main__":
    main()
