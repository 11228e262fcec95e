"""Parameters and constants of the synthetic sequences: room, sensor model, texture atlas
(:class:`SynthConfig`). See :mod:`slam.synthetic` for the whole generator."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from slam.data.base import Calibration
from slam.errors import ConfigError

log = logging.getLogger(__name__)

# ------------------------------------------------------------------------------------------------
# constants

#: Room extent in metres (world frame): x in [-2.5, 2.5], y in [-2, 2], z in [0, 2.6].
ROOM_MIN = np.array([-2.5, -2.0, 0.0])
ROOM_MAX = np.array([2.5, 2.0, 2.6])

FPS = 30.0

#: Scene kinds: the furnished room of the demo, and the kinds of :mod:`slam.synthetic.kinds`.
SCENES = ("room", "wall", "corridor", "hall", "desk")

#: Depth sensor working range (metres); outside it the sensor returns no depth (always applied).
MIN_DEPTH = 0.3
MAX_DEPTH = 4.0

#: Kinect-v1-like disparity quantisation: baseline 7.5 cm, IR focal length 580 px, 1/8 sub-pixel
#: disparity steps (depth step ~3 mm at 1 m, ~12 mm at 2 m, ~46 mm at 4 m), independent of the
#: rendered image size (it models the native sensor).
KINECT_BASELINE = 0.075
KINECT_FOCAL = 580.0
DISPARITY_SUBPIXEL = 8.0

#: Dropout model (noise=True).
GRAZING_COS = 0.2  # no depth where |cos(angle between ray and surface normal)| < this
EDGE_JUMP = 0.05  # metres; neighbouring depth discontinuity counted as an edge
RANDOM_DROPOUT = 0.01
COLOR_NOISE_SIGMA = 2.0  # grey levels

#: Texture atlas: TEX_SIZE x TEX_SIZE texels, TEX_RES metres per texel (period 6.1 m).
TEX_SIZE = 2048
TEX_RES = 0.003

#: Fixed directional lights (applied to object-local normals, so cloned objects shade alike).
_LIGHTS = (
    (np.array([0.3, 0.5, 1.0]) / np.linalg.norm([0.3, 0.5, 1.0]), 0.45),
    (np.array([-0.6, -0.2, 0.4]) / np.linalg.norm([-0.6, -0.2, 0.4]), 0.25),
)
_AMBIENT = 0.35


@dataclass
class SynthConfig:
    """Parameters of a synthetic sequence. Everything is deterministic for a given ``seed``.

    ``loop``: the camera path is a closed loop (the last frames revisit the first pose) when true,
    an open sweep that never comes back to its start otherwise. ``noise``: Kinect-like depth noise,
    quantisation and dropouts plus colour pixel noise; with ``noise=False`` depth is exact (still
    limited to the sensor range 0.3-4.0 m). ``alias``: the scene contains the same textured
    furniture cluster twice (on opposite walls) to fool place recognition. ``drift_bias``: a
    systematic depth distortion for loop-closure experiments, as uncalibrated Kinects have
    (Herrera et al. 2012, Teichman et al. 2013): depth grows by the factor
    ``1 + drift_bias * r^2`` with ``r^2 = x_n^2 + y_n^2`` the squared normalised image radius
    (0 at the centre, ~0.6 at the corners of a 525 px focal length VGA image). Every frame
    then disagrees slightly with the model built from other viewpoints, so odometry drifts
    steadily; ground truth stays exact. Motion speeds are tuned for ``frames`` around 300 (the path
    is parameterised over the sequence, so fewer frames means faster motion).

    ``scene``: one of :data:`SCENES`; kinds other than ``room`` (the furnished room) stress
    tracking (:mod:`slam.synthetic.kinds`: a bare textured wall, a corridor, a far hall, a desk)
    and ignore ``loop`` and ``alias``; their paths are defined by rates (seconds, not frames).
    ``speed``: multiplies the camera's motion (the room: turns over the sequence; the other
    kinds: every rate). ``color_offset_ms``: the colour camera is not synchronised with the
    depth camera: each colour image is taken off its depth image's instant by an offset that
    drifts from this many milliseconds after it to as many before over the sequence (a colour
    camera at its own steady rate, with 2 ms of jitter: TUM fr1 / fr2's Kinect, up to 17 ms
    apart), from the camera's pose at that time, and ``rgb.txt`` says when; 0: the two at the
    same instant.

    ``handheld``: a recorded hand-held camera's motion (one of
    :data:`slam.synthetic.handheld.RECORDINGS`, from ``seed * 7`` seconds into it) is added to
    the path, its jerks and fast turns as recorded; "" for the path alone. ``kinect``: the
    images are taken as a hand-held Kinect v1 takes them (:mod:`slam.synthetic.kinect`:
    rolling shutter, motion blur, auto exposure, projector shadows, ragged edges, correlated
    depth noise, dropouts on fast motion and dark surfaces).
    """

    frames: int = 300
    loop: bool = True
    seed: int = 0
    width: int = 640
    height: int = 480
    fx: float = 525.0
    fy: float = 525.0
    cx: float = 319.5
    cy: float = 239.5
    depth_scale: float = 5000.0
    noise: bool = True
    alias: bool = False
    drift_bias: float = 0.0
    render_frames: int | None = None  # render only the first N frames of the trajectory
    scene: str = "room"
    speed: float = 1.0
    color_offset_ms: float = 0.0
    handheld: str = ""
    kinect: bool = False

    @classmethod
    def half_resolution(cls, **overrides) -> SynthConfig:
        """The default camera at 320x240 (focal lengths halved, principal point on the pixel-
        centre convention): a quarter of the pixels, for quick tests and sweeps."""
        d = cls()
        cam = dict(
            width=d.width // 2,
            height=d.height // 2,
            fx=d.fx / 2,
            fy=d.fy / 2,
            cx=(d.cx + 0.5) / 2 - 0.5,
            cy=(d.cy + 0.5) / 2 - 0.5,
        )
        return cls(**{**cam, **overrides})

    def calibration(self) -> Calibration:
        """The :class:`Calibration` of the rendered images (validates the intrinsics)."""
        return Calibration(
            self.width, self.height, self.fx, self.fy, self.cx, self.cy, self.depth_scale
        )

    def validate(self) -> None:
        """Raise :class:`ConfigError` / :class:`CalibrationError` on unusable values."""
        if int(self.frames) < 1:
            raise ConfigError(f"SynthConfig.frames must be >= 1, got {self.frames}")
        if self.scene not in SCENES:
            raise ConfigError(f"SynthConfig.scene must be one of {SCENES}, got {self.scene!r}")
        if not (np.isfinite(self.speed) and self.speed > 0):
            raise ConfigError(f"SynthConfig.speed must be a positive number, got {self.speed}")
        if not (np.isfinite(self.color_offset_ms) and 0 <= self.color_offset_ms < 500 / FPS):
            raise ConfigError(
                "SynthConfig.color_offset_ms must be >= 0 and under half a frame interval "
                f"({500 / FPS:.1f} ms: each colour image pairs with its own depth image), got "
                f"{self.color_offset_ms}"
            )
        if self.handheld:
            from slam.synthetic.handheld import recording

            recording(self.handheld)  # raises ConfigError naming the recordings
        self.calibration()
