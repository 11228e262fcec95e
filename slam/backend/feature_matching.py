"""Guided matching of ORB features between two keyframes: each feature of one keyframe, lifted
by its depth and moved by the known relative pose, is matched to the other keyframe's features
near where it projects (by Hamming distance, with a ratio test among those candidates). Used
to build landmark tracks (:mod:`slam.backend.landmarks`)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from slam.camera import project
from slam.config import BAConfig
from slam.geometry import transform_points
from slam.keyframe import Keyframe

#: bits set in each byte value (Hamming distance of ORB descriptors by table look-up)
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint16)
#: candidates within the matching radius considered per projected feature
_K_NEAREST = 4
_NO_MATCH = 1 << 12
#: keypoints of one keyframe closer than this (pixels) are one corner found at several levels
DUPLICATE_PX = 2.0


def colour_intrinsics(K_tracking: np.ndarray, downsample: int) -> np.ndarray:
    """The intrinsics ORB pixels refer to (the full-resolution image) from a keyframe's
    tracking-resolution ``K`` (inverse of :func:`slam.camera.scale_intrinsics`)."""
    K = np.asarray(K_tracking, float).copy()
    if downsample == 1:
        return K
    K[0, 0] *= downsample
    K[1, 1] *= downsample
    K[0, 2] = (K[0, 2] + 0.5) * downsample - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * downsample - 0.5
    return K


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances between ORB descriptors ``a`` (..., 32) and ``b`` (..., 32) uint8."""
    return _POPCOUNT[np.bitwise_xor(a, b)].sum(axis=-1)


@dataclass
class Matches:
    """Feature pairs between keyframe ``a`` (rows ``ia``) and keyframe ``b`` (rows ``ib``)."""

    ia: np.ndarray
    ib: np.ndarray
    distance: np.ndarray

    def __len__(self) -> int:
        return len(self.ia)


def distinct_features(pixels: np.ndarray, radius_px: float = DUPLICATE_PX) -> np.ndarray:
    """Mask of the keypoints that are not near-duplicates of an earlier one: ORB detects a
    corner at several pyramid levels, leaving clusters of keypoints within a pixel or two of
    each other (typically as many such pairs as keypoints) that would make one physical point
    two features of one keyframe. The first of each cluster (the finest level) is kept."""
    keep = np.ones(len(pixels), bool)
    if len(pixels) < 2:
        return keep
    pairs = cKDTree(pixels).query_pairs(radius_px, output_type="ndarray")
    if len(pairs):
        keep[pairs.max(axis=1)] = False
    return keep


def guided_match(
    kf_a: Keyframe,
    kf_b: Keyframe,
    T_a_b: np.ndarray,
    K: np.ndarray,
    cfg: BAConfig,
    use_a: np.ndarray | None = None,
    use_b: np.ndarray | None = None,
    tree_a: cKDTree | None = None,
) -> Matches:
    """Matches between the features of ``kf_a`` and ``kf_b`` given their relative pose
    ``T_a_b`` (b's camera in a's): b's points projected into a, candidates of a within
    ``match_radius_px`` whose depth agrees (2 cm + ``depth_tolerance`` of the depth), the
    nearest descriptor if within ``max_hamming`` and ``match_ratio`` of the second nearest;
    each feature of a keeps its best match only. ``use_a``/``use_b``: masks of the features
    that may match (default all); ``tree_a``: a k-d tree over a's usable pixels, if built."""
    fa, fb = kf_a.features, kf_b.features
    empty = Matches(np.zeros(0, int), np.zeros(0, int), np.zeros(0, int))
    idx_a = np.flatnonzero(use_a) if use_a is not None else np.arange(len(fa))
    idx_b = np.flatnonzero(use_b) if use_b is not None else np.arange(len(fb))
    if len(idx_a) < 2 or len(idx_b) == 0:
        return empty
    X = transform_points(T_a_b, fb.points_cam[idx_b])
    front = X[:, 2] > 0.05
    if not front.any():
        return empty
    ib_all = idx_b[front]
    uv = project(X[front], K)
    tree = tree_a if tree_a is not None else cKDTree(fa.pixels[idx_a])
    k = min(_K_NEAREST, len(idx_a))
    _, cand = tree.query(uv, k=k, distance_upper_bound=cfg.match_radius_px)
    cand = np.asarray(cand).reshape(len(uv), k)
    valid = cand < len(idx_a)
    cand = idx_a[np.where(valid, cand, 0)]  # rows of a's features
    z_pred = X[front, 2][:, None]
    valid &= np.abs(fa.points_cam[cand, 2] - z_pred) < 0.02 + cfg.depth_tolerance * z_pred
    dist = hamming(fb.descriptors[ib_all][:, None, :], fa.descriptors[cand]).astype(int)
    dist = np.where(valid, dist, _NO_MATCH)
    order = np.argsort(dist, axis=1)
    rows = np.arange(len(uv))
    best = dist[rows, order[:, 0]]
    second = dist[rows, order[:, 1]] if k > 1 else np.full(len(uv), _NO_MATCH)
    ok = (best <= cfg.max_hamming) & (best < cfg.match_ratio * second)
    ia = cand[rows, order[:, 0]][ok]
    ib = ib_all[ok]
    d = best[ok]
    # one match per feature of a: the nearest descriptor
    o = np.lexsort((d, ia))
    ia, ib, d = ia[o], ib[o], d[o]
    first = np.ones(len(ia), bool)
    first[1:] = ia[1:] != ia[:-1]
    return Matches(ia[first], ib[first], d[first])


def match_candidates(
    keyframes: Iterable[Keyframe],
    kf: Keyframe,
    poses: Mapping[int, np.ndarray],
    cfg: BAConfig,
    same_map: Callable[[Keyframe, Keyframe], bool] | None = None,
) -> list[Keyframe]:
    """The keyframes a new keyframe is matched against: the previous ``match_window`` of
    the same map, then up to ``match_nearby`` others whose poses lie within
    ``nearby_distance_m`` / ``nearby_angle_deg``, nearest first."""
    older = [
        o
        for o in keyframes
        if o.id != kf.id and len(o.features) and (same_map is None or same_map(o, kf))
    ]
    older.sort(key=lambda o: o.id)
    window = older[-cfg.match_window :]
    rest = older[: -cfg.match_window] if len(older) > cfg.match_window else []
    if not rest or cfg.match_nearby == 0:
        return window[::-1]
    T = poses[kf.id]
    Ts = np.stack([poses[o.id] for o in rest])
    dist = np.linalg.norm(Ts[:, :3, 3] - T[:3, 3], axis=1)
    # angle between the optical axes
    cosang = np.clip(Ts[:, :3, 2] @ T[:3, 2], -1.0, 1.0)
    ang = np.degrees(np.arccos(cosang))
    near = np.flatnonzero((dist < cfg.nearby_distance_m) & (ang < cfg.nearby_angle_deg))
    near = near[np.argsort(dist[near] / max(cfg.nearby_distance_m, 1e-9) + ang[near] / 90.0)]
    return window[::-1] + [rest[i] for i in near[: cfg.match_nearby]]
