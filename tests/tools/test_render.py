"""Still images of a run (Open3D ray casting on the CPU) and scripts/render_mesh.py."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

from slam.tools.render import FINAL_BGR, KEYFRAME_BGR, render_run

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "render_mesh.py"


def share_of(img: np.ndarray, bgr: tuple[int, int, int], tol: int = 40) -> float:
    return float(np.mean(np.all(np.abs(img.astype(int) - bgr) < tol, axis=2)))


def test_render_run_draws_mesh_trajectory_and_keyframes(recorded_run, tmp_path):
    run_dir, _ = recorded_run
    png = render_run(run_dir, tmp_path / "run.png", width=640, height=400)
    img = cv2.imread(str(png))
    assert img.shape == (400, 640, 3)
    assert np.mean(np.any(img < 230, axis=2)) > 0.2  # the mesh fills a good part of the view
    assert share_of(img, FINAL_BGR) > 0.0005  # the trajectory is in view
    assert share_of(img, KEYFRAME_BGR) > 0.0001


def test_render_mesh_script_accepts_a_trajectory(recorded_run, tmp_path):
    run_dir, _ = recorded_run
    out = tmp_path / "mesh.png"
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), str(run_dir / "mesh.ply"), str(out), "--size", "320x200",
         "--trajectory", str(run_dir / "trajectory.txt")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    img = cv2.imread(str(out))
    assert img.shape == (200, 320, 3) and share_of(img, FINAL_BGR) > 0.0005
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), str(run_dir), str(out), "--size", "320x200",
         "--eye", "0", "-1", "-1.5"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert cv2.imread(str(out)).shape == (200, 320, 3)
