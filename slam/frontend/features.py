"""ORB features lifted to 3D by depth, and descriptor matching.

Shared by tracking (RANSAC seed/rescue), revisit detection and relocalisation.
"""

from __future__ import annotations

import cv2
import numpy as np

from slam.keyframe import SCALE_FACTOR, FeatureSet


class OrbExtractor:
    """ORB detection on the grey image; keypoints kept only where depth is valid."""

    def __init__(self, n_features: int = 1000, depth_min_m: float = 0.2, depth_max_m: float = 4.0):
        self.orb = cv2.ORB_create(nfeatures=n_features, scaleFactor=SCALE_FACTOR, fastThreshold=10)
        self.depth_min_m = depth_min_m
        self.depth_max_m = depth_max_m

    def extract(self, color: np.ndarray, depth_m: np.ndarray, K: np.ndarray) -> FeatureSet:
        grey = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY) if color.ndim == 3 else color
        keypoints, desc = self.orb.detectAndCompute(grey, None)
        if desc is None or not keypoints:
            return FeatureSet.empty()
        octave = np.array([kp.octave for kp in keypoints], dtype=np.int64)
        px = keypoint_pixels(np.array([kp.pt for kp in keypoints]), octave, grey.shape)
        # depth at the keypoint: nearest pixel of the depth image (which may differ in size)
        sy = depth_m.shape[0] / grey.shape[0]
        sx = depth_m.shape[1] / grey.shape[1]
        ui = np.clip(np.round((px[:, 0] + 0.5) * sx - 0.5).astype(int), 0, depth_m.shape[1] - 1)
        vi = np.clip(np.round((px[:, 1] + 0.5) * sy - 0.5).astype(int), 0, depth_m.shape[0] - 1)
        z = depth_m[vi, ui].astype(np.float64)
        ok = (z > self.depth_min_m) & (z < self.depth_max_m)
        pts = _lift(ui[ok], vi[ok], z[ok], K)
        return FeatureSet(px[ok], desc[ok], pts, octave[ok])

    def in_depth_camera(
        self, feats: FeatureSet, depth_m: np.ndarray, K: np.ndarray, T_depth_colour: np.ndarray
    ) -> FeatureSet:
        """Features :meth:`extract` found on a colour image taken from ``T_depth_colour`` (in
        the depth camera's frame: the two images taken at different instants by a moving
        camera), as the depth camera saw them: each keypoint's point moved into the depth
        camera (:meth:`FeatureSet.in_camera`), and lifted again by the depth where the depth
        camera sees it (the depth at the colour pixel belongs to another ray: at a depth
        edge, another surface). A keypoint whose depth pixel has no depth in range keeps the
        moved point."""
        moved = feats.in_camera(T_depth_colour, K)
        if len(moved) == 0:
            return moved
        ui = np.round(moved.pixels[:, 0]).astype(int)  # (a frame's colour has its depth's size)
        vi = np.round(moved.pixels[:, 1]).astype(int)
        inside = (ui >= 0) & (ui < depth_m.shape[1]) & (vi >= 0) & (vi < depth_m.shape[0])
        z = np.zeros(len(moved))
        z[inside] = depth_m[vi[inside], ui[inside]]
        ok = (z > self.depth_min_m) & (z < self.depth_max_m)
        pts = moved.points_cam.copy()
        pts[ok] = _lift(ui[ok], vi[ok], z[ok], K)
        return FeatureSet(moved.pixels, moved.descriptors, pts, moved.octave)


def keypoint_pixels(pt: np.ndarray, octave: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Full-resolution pixel coordinates (N, 2) of ORB keypoints found at pyramid levels
    ``octave``, from OpenCV's ``KeyPoint.pt``. OpenCV scales a level's pixel by the level's
    scale alone (``pt = x_level * s``), but its pyramid is resized with the pixel-centre
    convention, under which that pixel lies at ``(x_level + 0.5) * W / W_level - 0.5``: its
    keypoints sit ``(s - 1) / 2`` pixels too far up and left, 0.1 px at level 1 and 1.3 px at
    level 7, the same way in every image. (An image and its mirror image find the same
    keypoints only with the centre convention; tests/frontend/test_features.py.)"""
    h, w = shape[:2]
    s = SCALE_FACTOR ** octave.astype(np.float64)
    w_level, h_level = np.round(w / s), np.round(h / s)  # OpenCV's level sizes (cvRound)
    x = (pt[:, 0] / s + 0.5) * (w / w_level) - 0.5
    y = (pt[:, 1] / s + 0.5) * (h / h_level) - 0.5
    return np.stack([x, y], axis=-1)


def _lift(ui: np.ndarray, vi: np.ndarray, z: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3) of depth pixels (integer ``ui``, ``vi``) at depths ``z``."""
    u, v = ui.astype(float), vi.astype(float)
    return np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=-1)


def match_descriptors(a: np.ndarray, b: np.ndarray, ratio: float = 0.8) -> np.ndarray:
    """Hamming matches ``a -> b`` passing Lowe's ratio test and mutual consistency.

    Returns (M, 2) index pairs ``(i_a, i_b)``.
    """
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), dtype=int)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    knn = bf.knnMatch(a, b, k=2)
    pairs = [
        (m[0].queryIdx, m[0].trainIdx)
        for m in knn
        if len(m) == 2 and m[0].distance < ratio * m[1].distance
    ]
    if not pairs:
        return np.zeros((0, 2), dtype=int)
    pairs_arr = np.array(pairs, dtype=int)
    # keep each b index once (the first, i.e. unique best), a cheap mutual filter
    _, first = np.unique(pairs_arr[:, 1], return_index=True)
    return pairs_arr[np.sort(first)]
