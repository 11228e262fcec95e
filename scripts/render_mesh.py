"""Render a run folder, or a coloured PLY mesh, to a PNG (headless: Open3D ray casting on the CPU,
no OpenGL or display needed).

    python scripts/render_mesh.py runs/demo docs/run.png              # mesh + trajectories,
                                                                     # keyframes, loop edges
    python scripts/render_mesh.py runs/demo/mesh.ply mesh.png --trajectory runs/demo/trajectory.txt
    python scripts/render_mesh.py runs/demo/mesh.ply mesh.png --eye 0 -2 -3 --target 0 0 1

The default view looks from behind, above and beside the cameras at the middle of the scene
(slam.tools.render.default_view); ``--eye``/``--target`` choose another one (world coordinates of
the run: the first camera's frame, x right, y down, z forward).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("source", help="a run folder (slam run --out) or a PLY mesh")
    p.add_argument("png", help="image to write")
    p.add_argument("--trajectory", help="TUM trajectory drawn over a mesh (run folders: their own)")
    p.add_argument("--eye", type=float, nargs=3, help="camera position (world)")
    p.add_argument("--target", type=float, nargs=3, help="point looked at (default: scene middle)")
    p.add_argument("--size", default="1280x800", help="image size WxH (default 1280x800)")
    args = p.parse_args(argv)

    import cv2
    import open3d as o3d

    from slam.tools.render import (
        FINAL_BGR,
        Overlay,
        default_view,
        look_at,
        render_mesh,
        render_run,
    )
    from slam.trajectory import read_tum

    w, h = (int(x) for x in args.size.lower().split("x"))
    src = Path(args.source)
    mesh_path = src / "mesh.ply" if src.is_dir() else src
    if not mesh_path.is_file():
        p.error(f"{mesh_path}: mesh not found")
    mesh = o3d.io.read_triangle_mesh(str(mesh_path))
    traj = None
    if args.trajectory:
        traj = read_tum(args.trajectory)
    elif src.is_dir() and (src / "trajectory.txt").is_file():
        traj = read_tum(src / "trajectory.txt")
    T = default_view(mesh, traj)
    if args.eye is not None or args.target is not None:
        eye = np.array(args.eye) if args.eye is not None else T[:3, 3]
        target = (
            np.array(args.target)
            if args.target is not None
            else np.asarray(mesh.get_axis_aligned_bounding_box().get_center())
        )
        T = look_at(eye, target, -T[:3, 1])
    if src.is_dir():
        out = render_run(src, args.png, w, h, T_world_cam=T)
    else:
        overlay = Overlay(lines=[(traj.positions, FINAL_BGR, 2)] if traj is not None else [])
        cv2.imwrite(args.png, render_mesh(mesh, T, w, h, overlay=overlay))
        out = Path(args.png)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
