"""Writing a synthetic sequence to disk in TUM RGB-D layout (colour and depth PNGs, lists,
ground truth, calibration, the scene mesh), atomically marked complete."""

from __future__ import annotations

import json
import logging
import os
import re
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from slam.errors import DatasetError
from slam.geometry import exp_se3, inv_T, log_se3
from slam.synthetic.config import SynthConfig
from slam.synthetic.kinect import SensorMotion, exposure_gains
from slam.synthetic.render import SynthScene, build_scene, render_frame
from slam.synthetic.trajectory import make_trajectory
from slam.trajectory import Trajectory, atomic_write_text, write_tum

log = logging.getLogger(__name__)

# ------------------------------------------------------------------------------------------------
# sequence writer


def _calibration_yaml(cfg: SynthConfig) -> str:
    return (
        "# pinhole intrinsics of the depth camera, pixels; depth PNG value / depth_scale = metres;"
        " 0 = no depth\n"
        f"width: {int(cfg.width)}\n"
        f"height: {int(cfg.height)}\n"
        f"fx: {float(cfg.fx)!r}\n"
        f"fy: {float(cfg.fy)!r}\n"
        f"cx: {float(cfg.cx)!r}\n"
        f"cy: {float(cfg.cy)!r}\n"
        f"depth_scale: {float(cfg.depth_scale)!r}\n"
    )


def _imwrite(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise DatasetError(f"{path}: cv2.imwrite failed")


#: The jitter of a camera's timestamps (seconds, uniform +-): TUM fr1's colour images are 28-36
#: ms apart at 30 Hz.
COLOR_JITTER_S = 0.002


def _color_offsets(cfg: SynthConfig, n: int) -> np.ndarray:
    """Seconds each colour image is taken after its depth image: a colour camera running at its
    own steady rate, so the offset drifts from ``+cfg.color_offset_ms`` to ``-color_offset_ms``
    over the sequence (TUM fr1_xyz's goes 15 -> -12 ms), with :data:`COLOR_JITTER_S` of
    timestamp jitter, within +-``color_offset_ms``. Consecutive colour images are then about a
    frame interval apart, as a 30 Hz camera's are (offsets drawn independently per frame would
    put two colour images a few milliseconds apart). Drawn from their own generator: the depth
    images do not change with the offset."""
    if cfg.color_offset_ms <= 0:
        return np.zeros(n)
    rng = np.random.default_rng([int(cfg.seed), 1])
    limit = cfg.color_offset_ms * 1e-3
    drift = np.linspace(limit, -limit, n)
    return np.clip(drift + rng.uniform(-COLOR_JITTER_S, COLOR_JITTER_S, n), -limit, limit)


def _pose_at(traj: Trajectory, i: int, dt_s: float) -> np.ndarray:
    """The camera's pose ``dt_s`` seconds after frame ``i`` (within a frame interval): along
    the constant twist to the next frame (from the previous one before it; the first and the
    last frame continue the twist of their one neighbour)."""
    n = len(traj)
    if n == 1 or dt_s == 0:
        return traj.poses[i]
    j = i + 1 if (dt_s > 0 and i + 1 < n) or i == 0 else i - 1
    step = inv_T(traj.poses[i]) @ traj.poses[j]
    fraction = dt_s / (traj.timestamps[j] - traj.timestamps[i])
    return traj.poses[i] @ exp_se3(fraction * log_se3(step))


def generate_sequence(
    out_dir: str | Path,
    cfg: SynthConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Render a synthetic sequence into ``out_dir`` in the TUM RGB-D layout and return its path.
    ``progress(frames done, frames total)`` is called after every rendered frame.

    Writes ``rgb/NNNNNN.png``, ``depth/NNNNNN.png`` (uint16, metres * depth_scale, 0 = none),
    ``rgb.txt``, ``depth.txt``, ``groundtruth.txt`` (camera-to-world), ``calibration.yaml``,
    ``scene.ply`` (true surface) and, last, ``.complete`` (JSON of the config). A folder without
    ``.complete`` is an interrupted generation; an existing marker is removed first.
    """
    cfg = SynthConfig() if cfg is None else cfg
    cfg.validate()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    marker = out / ".complete"
    marker.unlink(missing_ok=True)
    (out / "rgb").mkdir(exist_ok=True)
    (out / "depth").mkdir(exist_ok=True)

    t0 = time.perf_counter()
    scene = build_scene(cfg)
    traj = make_trajectory(cfg)
    if cfg.render_frames is not None:
        n = max(1, min(int(cfg.render_frames), len(traj)))
        traj = Trajectory(traj.timestamps[:n], traj.poses[:n])
    rng = np.random.default_rng(int(cfg.seed))
    log.info(
        "generating synthetic sequence %s: %d frames %dx%d seed=%d loop=%s noise=%s alias=%s",
        out,
        cfg.frames,
        cfg.width,
        cfg.height,
        cfg.seed,
        cfg.loop,
        cfg.noise,
        cfg.alias,
    )
    color_dt_s = _color_offsets(cfg, len(traj))
    names = [f"{i:06d}.png" for i in range(len(traj))]
    t_render = _render_images(out, scene, traj, cfg, rng, color_dt_s, names, progress)
    _write_lists(out, traj, color_dt_s, names)
    write_tum(out / "groundtruth.txt", traj)
    atomic_write_text(out / "calibration.yaml", _calibration_yaml(cfg))
    tmp_ply = out / ".scene.tmp.ply"
    # str path: accepted by every supported Open3D (0.18 takes str only, newer stubs say PathLike)
    if not o3d.io.write_triangle_mesh(str(tmp_ply), scene.mesh, write_ascii=False):  # type: ignore[arg-type]
        raise DatasetError(f"{tmp_ply}: writing the scene mesh failed")
    os.replace(tmp_ply, out / "scene.ply")
    _remove_frames_from(out, len(traj))
    atomic_write_text(marker, json.dumps(asdict(cfg), sort_keys=True) + "\n")
    dt = time.perf_counter() - t0
    log.info(
        "synthetic sequence %s done: %d frames in %.1f s (render %.1f ms/frame)",
        out,
        len(traj),
        dt,
        1000 * t_render / max(len(traj), 1),
    )
    return out


def _render_images(
    out: Path,
    scene: SynthScene,
    traj: Trajectory,
    cfg: SynthConfig,
    rng: np.random.Generator,
    color_dt_s: np.ndarray,
    names: list[str],
    progress: Callable[[int, int], None] | None,
) -> float:
    """Every frame's colour (at its own instant, ``color_dt_s`` off the depth's) and depth
    written as PNGs under ``out/rgb`` and ``out/depth``; returns the seconds spent rendering."""
    color_rng = np.random.default_rng([int(cfg.seed), 2])  # the depth's noise stays the same
    motions = _sensor_motions(traj, cfg)
    t_render = 0.0
    pending: list[Future] = []
    with ThreadPoolExecutor(max_workers=2) as pool:  # PNG encoding overlaps with rendering
        for i, T in enumerate(traj.poses):
            t1 = time.perf_counter()
            color, depth = render_frame(scene, T, cfg, rng, motions[i])
            if color_dt_s[i] != 0.0:  # the colour camera's own instant
                T_colour = _pose_at(traj, i, color_dt_s[i])
                color, _ = render_frame(scene, T_colour, cfg, color_rng, motions[i])
            t_render += time.perf_counter() - t1
            d16 = np.clip(np.round(depth * cfg.depth_scale), 0, 65535).astype(np.uint16)
            pending.append(pool.submit(_imwrite, out / "rgb" / names[i], color[..., ::-1].copy()))
            pending.append(pool.submit(_imwrite, out / "depth" / names[i], d16))
            while len(pending) > 8:
                pending.pop(0).result()
            if (i + 1) % 100 == 0:
                log.debug("rendered %d/%d frames", i + 1, len(traj))
            if progress is not None:
                progress(i + 1, len(traj))
        for fut in pending:
            fut.result()
    return t_render


def _sensor_motions(traj: Trajectory, cfg: SynthConfig) -> list[SensorMotion | None]:
    """Each frame's motion as the Kinect model needs it (``cfg.kinect``; else None): the twist
    per second from the frame before to the frame after (one-sided at the ends) and the
    exposure gain at the frame's time."""
    n = len(traj)
    if not cfg.kinect:
        return [None] * n
    gains = exposure_gains(int(cfg.seed), traj.timestamps)
    out: list[SensorMotion | None] = []
    for i in range(n):
        a, b = max(i - 1, 0), min(i + 1, n - 1)
        twist = np.zeros(6)
        if b > a:
            step = inv_T(traj.poses[a]) @ traj.poses[b]
            twist = log_se3(step) / (traj.timestamps[b] - traj.timestamps[a])
        out.append(SensorMotion(twist, float(gains[i])))
    return out


def _write_lists(out: Path, traj: Trajectory, color_dt_s: np.ndarray, names: list[str]) -> None:
    """``rgb.txt`` (each colour image at its own instant) and ``depth.txt``."""
    stamps = [f"{t:.6f}" for t in traj.timestamps]
    rgb_stamps = [f"{t:.6f}" for t in traj.timestamps + color_dt_s]
    atomic_write_text(
        out / "rgb.txt",
        "# color images (synthetic, slam.synthetic)\n# timestamp filename\n"
        + "".join(f"{s} rgb/{nm}\n" for s, nm in zip(rgb_stamps, names)),
    )
    atomic_write_text(
        out / "depth.txt",
        "# depth maps (synthetic, slam.synthetic)\n# timestamp filename\n"
        + "".join(f"{s} depth/{nm}\n" for s, nm in zip(stamps, names)),
    )


def _remove_frames_from(out: Path, n: int) -> None:
    """Frames numbered ``n`` and above, left over from an earlier, longer generation into the
    same folder."""
    frame_re = re.compile(r"^(\d{6})\.png$")
    for sub in ("rgb", "depth"):
        for p in (out / sub).iterdir():
            m = frame_re.match(p.name)
            if m and int(m.group(1)) >= n:
                p.unlink()


def is_complete(out_dir: str | Path) -> bool:
    """True when ``out_dir`` holds a fully written synthetic sequence (``.complete`` marker)."""
    return (Path(out_dir) / ".complete").is_file()
