"""ORB keypoints: where on the full-resolution image they are, and their depth."""

from __future__ import annotations

import cv2
import numpy as np

from slam.frontend.features import OrbExtractor, keypoint_pixels
from slam.keyframe import SCALE_FACTOR


def _texture(h: int = 480, w: int = 640) -> np.ndarray:
    rng = np.random.default_rng(3)
    noise = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 2.0)
    grey = cv2.normalize(noise, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=2)


def _mirror_offsets(pixels_of) -> dict[int, float]:
    """Per ORB level: the mean offset (px) between the keypoints of an image and those of its
    mirror image (rotated by 180 degrees) mapped back. FAST and ORB's pyramid are symmetric, so
    unbiased pixel coordinates give the same points; a bias b in both images shows as 2 b."""
    image = _texture()
    h, w = image.shape[:2]
    a_px, a_oct = pixels_of(image)
    b_px, b_oct = pixels_of(np.ascontiguousarray(image[::-1, ::-1]))
    b_px = np.array([w - 1, h - 1]) - b_px
    out = {}
    for level in range(1, 6):
        a, b = a_px[a_oct == level], b_px[b_oct == level]
        if len(a) < 10 or len(b) < 10:
            continue
        d = b[None, :, :] - a[:, None, :]
        nearest = d[np.arange(len(a)), np.argmin((d**2).sum(-1), axis=1)]
        close = (nearest**2).sum(-1) < (2 * SCALE_FACTOR**level) ** 2
        out[level] = float(np.abs(nearest[close].mean(axis=0)).max())
    return out


def test_keypoints_of_coarse_levels_sit_where_the_level_s_pixel_is():
    orb = cv2.ORB_create(nfeatures=2000, scaleFactor=SCALE_FACTOR, fastThreshold=10)

    def opencv(image):
        kps = orb.detect(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), None)
        return np.array([k.pt for k in kps]), np.array([k.octave for k in kps])

    def ours(image):
        pt, octave = opencv(image)
        return keypoint_pixels(pt, octave, image.shape), octave

    raw, corrected = _mirror_offsets(opencv), _mirror_offsets(ours)
    assert len(corrected) >= 4
    # OpenCV's own coordinates: (s - 1) / 2 up and left in each image, 2x that between the two
    assert max(raw.values()) > 0.5
    assert max(corrected.values()) < 0.05


def test_a_keypoint_s_depth_is_read_at_its_pixel():
    # a depth ramp along x: the lifted point's depth is the depth of the keypoint's pixel,
    # also when the depth image has half the colour's resolution
    image = _texture()
    K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
    ramp = 1.0 + np.arange(640, dtype=np.float32)[None, :].repeat(480, 0) * 1e-3
    feats = OrbExtractor(2000).extract(image, ramp, K)
    assert len(feats.pixels) > 100
    nearest = 1.0 + np.round(feats.pixels[:, 0]) * 1e-3
    assert np.allclose(feats.points_cam[:, 2], nearest, atol=1e-6)
    half = cv2.resize(ramp, (320, 240), interpolation=cv2.INTER_LINEAR)  # centre convention
    K_half = K.copy()
    K_half[:2] /= 2
    K_half[:2, 2] = (K[:2, 2] + 0.5) / 2 - 0.5
    feats = OrbExtractor(2000).extract(image, half, K_half)
    assert np.abs(feats.points_cam[:, 2] - (1.0 + feats.pixels[:, 0] * 1e-3)).max() <= 1.01e-3
