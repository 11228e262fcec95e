"""What a real hand-held Kinect v1 adds to a rendered frame (``SynthConfig.kinect``).

The base sensor model (:func:`slam.synthetic.render._noisy_depth`) gives the depth of a still
camera: axial noise, disparity quantisation, dropouts at edges and grazing angles. A camera in
a hand also shows:

- **rolling shutter**: each colour row is read :data:`READOUT_S` / height after the one above
  it (the Kinect's colour sensor; Kerl, Stueckler, Cremers, ICCV 2015 model Kinect-class
  cameras so), so a turning camera's colour image is sheared; the frame's pose is its middle
  row's. Depth is taken at one instant: deskewing ``tum-fr1-rpy-500``'s depth rows by the
  true motion did not bring frame-to-frame ICP nearer the ground truth (median error 2.59,
  2.36, 2.77, 3.24 mm and 0.39, 0.40, 0.42, 0.45 deg for a readout of 0, 15, 30, 45 ms);
- **motion blur**: colour integrates over :data:`COLOUR_EXPOSURE_S`, smeared along each pixel's
  image motion (depth does not lose pixels to motion: on ``tum-fr1-rpy-500`` 77-78% of the
  pixels have depth at every angular speed, 0-10 deg/s as 90-200 deg/s);
- **auto exposure**: the colour gain drifts by :data:`GAIN_SIGMA` (log) over about a second,
  so one surface's brightness changes between frames;
- **Kinect v1 depth structure**: the projector sits :data:`PROJECTOR_BASELINE_M` beside the
  infrared camera, so surfaces it cannot light behind a foreground edge have no depth (its
  shadow); the correlation window makes edges ragged (foreground bleeding over background or
  no depth, a few pixels wide, in blocks); part of the disparity noise is correlated over
  several pixels, part a fixed pattern of the device (Smisek et al. 2011, Herrera et al.
  2012); dark surfaces return too little infrared for a match.

:class:`SensorMotion` carries what the renderer needs to know of the motion at a frame: the
camera's twist (per second, in its own frame) and the exposure gain. The writer derives them
from the trajectory (:func:`slam.synthetic.writer.generate_sequence`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np

from slam.geometry import exp_se3

#: Rolling-shutter readout of the colour sensor, first row to last (seconds; a Kinect-class
#: sensor's at 30 Hz, not measured on the shared recordings).
READOUT_S = 0.025
#: Colour exposure (seconds; indoor auto exposure). Checked against the real sensor: fine
#: texture's gradient energy falls with the angular speed to 0.71 / 0.40 / 0.34 of a still
#: camera's at 15-30 / 30-50 / 50-80 deg/s on tum-fr1-rpy-500 (0.71 / 0.54 at 15-30 / 30-50 on
#: tum-fr1-xyz); the model's on one synthetic view, 0.69 / 0.52 / 0.40 at 22 / 40 / 65 deg/s.
COLOUR_EXPOSURE_S = 0.015
#: Standard deviation of the log colour gain (auto exposure), and its time scale (seconds).
GAIN_SIGMA = 0.12
GAIN_TIME_S = 0.8
#: Infrared projector's offset from the infrared camera along its x axis (metres).
PROJECTOR_BASELINE_M = 0.075
#: Ragged edges: the band beside a depth edge where depth bleeds or drops, per 8x8 block (px).
EDGE_BAND_PX = (0, 1, 2, 3)
EDGE_BLOCK_PX = 8
#: Share of the disparity noise's variance that is correlated over CORRELATION_PX pixels, and
#: the device's fixed pattern (disparity pixels, standard deviation; 1 mm at 1 m, 4.6 at 2 m).
CORRELATED_SHARE = 0.5
CORRELATION_PX = 4.0
FIXED_PATTERN_PX = 0.05
#: Grey level (0-255) below which a surface starts to return too little infrared, and the
#: dropout probability of a black one.
DARK_GREY = 40.0
DARK_DROPOUT = 0.5


@dataclass(frozen=True)
class SensorMotion:
    """The camera's motion at a frame: ``twist`` ``[wx, wy, wz, vx, vy, vz]`` per second in
    the camera frame (rotation first, as :func:`slam.geometry.exp_se3`) and the colour gain."""

    twist: np.ndarray = field(default_factory=lambda: np.zeros(6))
    gain: float = 1.0


def row_poses(T_world_cam: np.ndarray, twist: np.ndarray, height: int) -> np.ndarray:
    """(height, 4, 4) pose of each row at its readout instant, the middle row at the frame's."""
    tau = (np.arange(height) - 0.5 * (height - 1)) / max(height - 1, 1) * READOUT_S
    if not np.any(twist):
        return np.broadcast_to(T_world_cam, (height, 4, 4)).copy()
    return np.stack([T_world_cam @ exp_se3(t * np.asarray(twist)) for t in tau])


def image_speed(
    xn: np.ndarray, yn: np.ndarray, z: np.ndarray, twist: np.ndarray, fx: float, fy: float
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels per second the image of each scene point moves for a camera moving with
    ``twist`` (per second, its own frame, rotation first): the point at normalised image
    coordinates ``xn, yn`` and depth ``z`` (<= 0: none, moved by the rotation alone, as a
    point at infinity)."""
    w = np.asarray(twist[:3], np.float32)
    v = np.asarray(twist[3:], np.float32)
    inv_z = np.where(z > 0, 1.0 / np.where(z > 0, z, 1.0), 0.0).astype(np.float32)
    # d/dt of the camera-frame point over its depth: -(w x (xn, yn, 1)) - v / z
    dx = -(w[1] - w[2] * yn) - v[0] * inv_z
    dy = -(w[2] * xn - w[0]) - v[1] * inv_z
    dz = -(w[0] * yn - w[1] * xn) - v[2] * inv_z
    return fx * (dx - xn * dz), fy * (dy - yn * dz)


def motion_blur(
    colour: np.ndarray, flow: tuple[np.ndarray, np.ndarray], exposure_s: float, samples: int = 7
) -> np.ndarray:
    """(H, W, 3) float32 colour averaged along each pixel's image motion over the exposure."""
    h, w = colour.shape[:2]
    fu = (flow[0] * exposure_s).reshape(h, w).astype(np.float32)
    fv = (flow[1] * exposure_s).reshape(h, w).astype(np.float32)
    if float(np.max(np.abs(fu)) + np.max(np.abs(fv))) < 0.25:
        return colour
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    out = np.zeros_like(colour)
    for s in np.linspace(-0.5, 0.5, samples, dtype=np.float32):
        out += cv2.remap(colour, u + s * fu, v + s * fv, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
    return out / np.float32(samples)


def exposure_gains(seed: int, t_s: np.ndarray) -> np.ndarray:
    """The colour gain at each time: exp of a smooth Gaussian process (:data:`GAIN_SIGMA`,
    correlated over :data:`GAIN_TIME_S`), from the seed."""
    rng = np.random.default_rng([int(seed), 0x6A1])
    t = np.asarray(t_s, float)
    n = 8
    f = rng.uniform(0.3, 1.5, n) / GAIN_TIME_S  # rad/s
    phase = rng.uniform(0, 2 * np.pi, n)
    amp = rng.standard_normal(n) * GAIN_SIGMA * np.sqrt(2.0 / n)
    return np.exp(np.sum(amp[None] * np.sin(f[None] * t[:, None] + phase[None]), axis=1))


@lru_cache(maxsize=4)
def fixed_pattern(seed: int, height: int, width: int) -> np.ndarray:
    """The device's own disparity error (pixels), smooth over tens of pixels, fixed in the image."""
    rng = np.random.default_rng([int(seed), 0xF1D])
    coarse = rng.standard_normal((max(height // 32, 2), max(width // 32, 2))).astype(np.float32)
    field_ = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    return field_ * np.float32(FIXED_PATTERN_PX / max(float(field_.std()), 1e-6))


def projector_shadow(
    raycaster, T_world_cam: np.ndarray, points: np.ndarray, hit: np.ndarray
) -> np.ndarray:
    """Pixels whose surface point (``points``, world frame) the projector cannot light:
    something lies between it and the point."""
    import open3d as o3d

    proj = T_world_cam[:3, 3] + T_world_cam[:3, 0] * PROJECTOR_BASELINE_M  # along the x axis
    direction = points - proj.astype(np.float32)
    rays = np.concatenate([np.broadcast_to(proj, direction.shape), direction], axis=1)
    rays = np.ascontiguousarray(rays, dtype=np.float32)
    t_hit = raycaster.cast_rays(o3d.core.Tensor.from_numpy(rays))["t_hit"].numpy()
    # t_hit is in units of the whole way to the point: an earlier hit (1 cm before) blocks it
    length = np.linalg.norm(direction, axis=1)
    return hit & (t_hit * length < length - 0.01)


def ragged_edges(
    depth: np.ndarray, edge: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Depth with the foreground bled over the background beside edges, and the pixels left
    without depth there: per 8x8 block a band of 0-3 px, half the blocks bleeding, half empty."""
    h, w = depth.shape
    bh, bw = -(-h // EDGE_BLOCK_PX), -(-w // EDGE_BLOCK_PX)
    band_px = rng.choice(EDGE_BAND_PX, size=(bh, bw))
    bleed = rng.random((bh, bw)) < 0.5
    up = np.ones((EDGE_BLOCK_PX, EDGE_BLOCK_PX), np.uint8)
    band_img = np.kron(band_px, up)[:h, :w]
    bleed_img = np.kron(bleed, up)[:h, :w].astype(bool)
    e8 = edge.astype(np.uint8)
    band = np.zeros((h, w), bool)
    for r in EDGE_BAND_PX[1:]:
        grown = cv2.dilate(e8, np.ones((2 * r + 1, 2 * r + 1), np.uint8)).astype(bool)
        band |= grown & (band_img == r)
    far = np.where(depth > 0, depth, np.float32(1e3))
    nearest = cv2.erode(far, np.ones((7, 7), np.uint8))  # the foreground's depth nearby
    bled = np.where(band & bleed_img & (nearest < 1e3), nearest, depth)
    return bled.astype(np.float32), band & ~bleed_img


def dark_dropout(grey: np.ndarray) -> np.ndarray:
    """Probability that a surface of this grey level (0-255) returns too little infrared."""
    return (DARK_DROPOUT * np.clip((DARK_GREY - grey) / DARK_GREY, 0.0, 1.0)).astype(np.float32)
