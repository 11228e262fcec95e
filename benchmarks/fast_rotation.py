"""A synthetic hand-held sequence with fast pans (60, 120 and 180 deg/s peak), exact ground truth.

    python benchmarks/fast_rotation.py OUT_DIR                 # 300 frames 640x480, ~1 min
    python benchmarks/fast_rotation.py OUT_DIR --blur-ms 16    # colour motion-blurred (16 ms exposure)

The demo's room (``SynthConfig(seed=0)``: same scene, Kinect-like depth noise); the camera stands
near the room centre at ~1.35 m, drifts on a small ellipse (~5 mm a frame, like a hand) with
pitch / roll wobble, and turns: a slow yaw drift (8 deg/s) plus three pans whose angular rate
follows a raised cosine over 1 s, peaking at +60 deg/s (t = 1.5-2.5 s), -120 deg/s (4-5 s) and
+180 deg/s (6.5-7.5 s), i.e. up to 6 deg a frame at 30 Hz, with some pitch during each pan.
That is the motion of TUM fr1 rotation-heavy recordings (fr1_desk/360/room) where the
tracker took rotation for translation. With ``--blur-ms`` the colour image is the mean of 7
renderings spread over the exposure (depth stays instantaneous, mid-exposure). Writes the TUM
layout (rgb.txt, depth.txt, groundtruth.txt, calibration.yaml) that ``slam.open_sequence`` reads.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from slam.data.calibration import TUM_DEFAULTS
from slam.synthetic import COLOR_NOISE_SIGMA, FPS, SynthConfig, build_scene, render_frame
from slam.trajectory import Trajectory, write_tum

#: (start s, duration s, peak yaw rate deg/s, peak pitch rate deg/s) of each pan
PANS = ((1.5, 1.0, 60.0, 10.0), (4.0, 1.0, -120.0, -15.0), (6.5, 1.0, 180.0, 20.0))
SLOW_YAW_DEG_S = 8.0


def _pan_angle(t: np.ndarray, start: float, duration: float, ramp: float | None) -> np.ndarray:
    """Integral over [0, t] of a unit-peak rate profile on [start, start + duration] that rises
    and falls by half-cosine ramps of ``ramp`` seconds (None: duration / 2, a raised cosine)."""
    r = duration / 2 if ramp is None else min(ramp, duration / 2)
    x = np.clip(t - start, 0.0, duration)

    def rise(y):  # integral of 0.5 (1 - cos(pi y / r)) over [0, y], y in [0, r]
        return 0.5 * (y - r / np.pi * np.sin(np.pi * y / r))

    full = duration - r  # area of the whole profile
    return np.where(
        x <= r, rise(x), np.where(x <= duration - r, rise(r) + (x - r), full - rise(duration - x))
    )


def fast_rotation_poses(t: np.ndarray, seed: int = 0, ramp_s: float | None = None) -> np.ndarray:
    """``T_world_cam`` (N, 4, 4) at times ``t`` (seconds): OpenCV camera axes, world z up.
    ``ramp_s``: seconds for a pan's rate to rise to its peak and to fall back (None: raised
    cosine over the whole second; 0.1: abrupt hand-held starts and stops, the peak rate held
    in between)."""
    rng = np.random.default_rng([seed, 0xFA57])
    ph = rng.uniform(0, 2 * np.pi, 6)
    w = 2 * np.pi * t / 10.0
    x = 0.25 * np.cos(w + ph[0]) - 0.25 * np.cos(ph[0])
    y = 0.18 * np.sin(w + ph[1]) - 0.18 * np.sin(ph[1])
    z = 1.35 + 0.03 * np.sin(3 * w + ph[2])
    yaw = np.radians(30.0 + SLOW_YAW_DEG_S * t)
    pitch = np.radians(-18.0 + 4.0 * np.sin(2 * w + ph[3]))
    for start, dur, yaw_rate, pitch_rate in PANS:
        s = _pan_angle(t, start, dur, ramp_s)
        yaw = yaw + np.radians(yaw_rate) * s
        pitch = pitch + np.radians(pitch_rate) * s
    roll = np.radians(2.5 * np.sin(3 * w + ph[4]) + 1.0 * np.sin(7 * w + ph[5]))
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    # camera-to-world: world-from-"body" (yaw about z, pitch about the body's left axis), then
    # body (x forward, y left, z up) to OpenCV camera (x right, y down, z forward), then roll
    R_body = Rotation.from_euler("ZY", np.stack([yaw, -pitch], 1)).as_matrix()
    R_cam_axes = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    R_roll = Rotation.from_euler("z", roll[:, None]).as_matrix()
    poses[:, :3, :3] = R_body @ R_cam_axes @ R_roll
    poses[:, :3, 3] = np.stack([x, y, z], 1)
    return poses


def _render(scene, cfg: SynthConfig, pose_at, t: float, readout_s: float, rng, bands: int = 30):
    """Render at time ``t``; with ``readout_s`` > 0 as a rolling shutter: rows are exposed top to
    bottom over ``readout_s`` (mid-image row at ``t``), rendered in ``bands`` horizontal bands
    each from its own pose."""
    if readout_s <= 0:
        return render_frame(scene, pose_at(t), cfg, rng)
    H = int(cfg.height)
    edges = np.linspace(0, H, bands + 1).round().astype(int)
    colors, depths = [], []
    for r0, r1 in zip(edges[:-1], edges[1:]):
        band = dataclasses.replace(cfg, height=int(r1 - r0), cy=cfg.cy - r0)
        tb = t + ((r0 + r1) / 2 / H - 0.5) * readout_s
        c, d = render_frame(scene, pose_at(tb), band, rng)
        colors.append(c)
        depths.append(d)
    return np.concatenate(colors), np.concatenate(depths)


def generate(
    out_dir: str | Path,
    frames: int = 300,
    blur_ms: float = 0.0,
    half: bool = False,
    seed: int = 0,
    ramp_s: float | None = None,
    readout_ms: float = 0.0,
    color_offset_ms: float = 0.0,
    distortion: tuple[float, ...] | None = None,
    tum_fr1: bool = False,
) -> Path:
    """Render the sequence into ``out_dir`` (TUM layout) and return the path.

    ``readout_ms``: rolling-shutter readout time of both cameras (0: global shutter);
    ``color_offset_ms``: the colour image is taken this much after the depth image (its
    timestamp in rgb.txt says so; the loader pairs them as TUM's are paired); ``distortion``:
    OpenCV radial-tangential coefficients (k1, k2, p1, p2, k3) applied to both images, which
    the calibration file does not mention (as TUM fr1/fr2 recordings, whose images are as
    recorded). ``tum_fr1``: TUM freiburg1's camera, i.e. its calibrated intrinsics (written to
    calibration.yaml) and its published distortion (in the images only, as TUM ships fr1).
    Ground truth is written at 4x the frame rate."""
    cfg = SynthConfig.half_resolution(seed=seed) if half else SynthConfig(seed=seed)
    cfg = dataclasses.replace(cfg, frames=frames)
    if tum_fr1:
        fr1 = TUM_DEFAULTS["freiburg1"]
        cfg = dataclasses.replace(cfg, fx=fr1.fx, fy=fr1.fy, cx=fr1.cx, cy=fr1.cy)
        distortion = tuple(fr1.distortion)
    clean = dataclasses.replace(cfg, noise=False)
    out = Path(out_dir)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(exist_ok=True)
    scene = build_scene(cfg)
    t = np.arange(frames) / FPS
    rng = np.random.default_rng(seed)
    readout = readout_ms / 1e3
    dt_color = color_offset_ms / 1e3

    def pose_at(tt: float) -> np.ndarray:
        return fast_rotation_poses(np.array([tt]), seed, ramp_s)[0]

    sub = np.linspace(-0.5, 0.5, 7) * blur_ms / 1e3
    distort = None
    if distortion is not None:  # pixel u_d of the recorded image shows ideal pixel undistort(u_d)
        K = cfg.calibration().K
        W, H = int(cfg.width), int(cfg.height)
        grid = np.stack(np.meshgrid(np.arange(W), np.arange(H)), -1).reshape(-1, 1, 2)
        und = cv2.undistortPoints(grid.astype(np.float64), K, np.array(distortion), P=K)
        maps = und.reshape(H, W, 2).astype(np.float32)
        distort = (maps[..., 0].copy(), maps[..., 1].copy())
    rgb_lines, depth_lines = [], []
    for i in range(frames):
        color, depth = _render(scene, cfg, pose_at, t[i], readout, rng)
        if blur_ms > 0:
            acc = np.zeros(color.shape, np.float32)
            for ds in sub:
                acc += _render(scene, clean, pose_at, t[i] + dt_color + ds, readout, rng)[0]
            acc /= len(sub)
            acc += rng.standard_normal(acc.shape[:2] + (1,), dtype=np.float32) * COLOR_NOISE_SIGMA
            color = np.clip(np.round(acc), 0, 255).astype(np.uint8)
        elif dt_color != 0:
            color = _render(scene, cfg, pose_at, t[i] + dt_color, readout, rng)[0]
        if distort is not None:
            color = cv2.remap(color, *distort, cv2.INTER_LINEAR)
            depth = cv2.remap(depth, *distort, cv2.INTER_NEAREST)
        name = f"{i:06d}.png"
        cv2.imwrite(str(out / "rgb" / name), color[..., ::-1].copy())
        d16 = np.clip(np.round(depth * cfg.depth_scale), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(out / "depth" / name), d16)
        rgb_lines.append(f"{t[i] + dt_color:.6f} rgb/{name}\n")
        depth_lines.append(f"{t[i]:.6f} depth/{name}\n")
    (out / "rgb.txt").write_text("# timestamp filename\n" + "".join(rgb_lines))
    (out / "depth.txt").write_text("# timestamp filename\n" + "".join(depth_lines))
    t_gt = np.arange(-4, 4 * frames + 4) / (4 * FPS)
    write_tum(out / "groundtruth.txt", Trajectory(t_gt, fast_rotation_poses(t_gt, seed, ramp_s)))
    (out / "calibration.yaml").write_text(
        "".join(f"{k}: {getattr(cfg, k)}\n" for k in ("width", "height", "fx", "fy", "cx", "cy"))
        + f"depth_scale: {cfg.depth_scale}\n"
    )
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out_dir")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--blur-ms", type=float, default=0.0, help="colour exposure (motion blur)")
    p.add_argument("--half", action="store_true", help="320x240 instead of 640x480")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--ramp-s", type=float, default=None, help="pan rate ramp (default: smooth)")
    p.add_argument("--readout-ms", type=float, default=0.0, help="rolling-shutter readout")
    p.add_argument("--color-offset-ms", type=float, default=0.0, help="colour after depth by")
    p.add_argument(
        "--distortion", default=None, help='"k1 k2 p1 p2 k3" lens distortion (not in the yaml)'
    )
    p.add_argument("--tum-fr1", action="store_true", help="TUM fr1 intrinsics and distortion")
    a = p.parse_args()
    dist = None if a.distortion is None else tuple(float(x) for x in a.distortion.split())
    out = generate(
        a.out_dir,
        a.frames,
        a.blur_ms,
        a.half,
        a.seed,
        a.ramp_s,
        a.readout_ms,
        a.color_offset_ms,
        dist,
        a.tum_fr1,
    )
    print(out)


if __name__ == "__main__":
    main()
