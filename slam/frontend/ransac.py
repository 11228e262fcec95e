"""Closed-form rigid alignment (Kabsch/Umeyama) and RANSAC over 3D-3D correspondences.

One implementation serves tracking (seed and rescue ICP), loop verification and relocalisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Rigid ``T`` (4x4) minimising ``sum w |T src_i - dst_i|^2`` (centroids + SVD).

    ``src``, ``dst``: (N, 3), N >= 3, not all collinear.
    """
    T = kabsch_batch(src[None], dst[None], None if weights is None else weights[None])
    return T[0]


def kabsch_batch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Batched Kabsch: ``src``, ``dst`` (B, N, 3) -> (B, 4, 4)."""
    if weights is None:
        weights = np.ones(src.shape[:2])
    w = weights / np.maximum(weights.sum(axis=1, keepdims=True), 1e-12)
    # batched matrix products (BLAS), not einsum: einsum's generic loops were most of
    # RANSAC's time
    mu_s = (w[:, None, :] @ src)[:, 0]
    mu_d = (w[:, None, :] @ dst)[:, 0]
    S = np.swapaxes(w[..., None] * (src - mu_s[:, None]), 1, 2) @ (dst - mu_d[:, None])
    U, _, Vt = np.linalg.svd(S)
    V = np.swapaxes(Vt, 1, 2).copy()
    V[:, :, 2] *= np.sign(np.linalg.det(U @ Vt))[:, None]  # a rotation, not a reflection
    R = V @ np.swapaxes(U, 1, 2)
    T = np.tile(np.eye(4), (len(src), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = mu_d - (R @ mu_s[..., None])[..., 0]
    return T


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, float]:
    """Similarity alignment: returns (T with rotation+translation, scale s) with dst ~ s R src + t."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    S = xd.T @ xs / len(src)
    U, sig, Vt = np.linalg.svd(S)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    var_s = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(sig) @ D) / var_s)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mu_d - s * R @ mu_s
    return T, s


@dataclass
class RansacResult:
    """``T_dst_src`` maps source points onto destination points; ``inliers`` is a mask over pairs."""

    T: np.ndarray
    inliers: np.ndarray
    n_inliers: int
    inlier_rmse: float
    success: bool

    @property
    def inlier_ratio(self) -> float:
        return self.n_inliers / max(len(self.inliers), 1)


def ransac_rigid(
    src: np.ndarray,
    dst: np.ndarray,
    iterations: int = 500,
    threshold: float = 0.03,
    min_inliers: int = 10,
    sample_size: int = 3,
    rng: np.random.Generator | None = None,
) -> RansacResult:
    """RANSAC for a rigid transform between matched 3D points ``src[i] <-> dst[i]``.

    Minimal sets of ``sample_size`` (3 or 4) pairs are solved in closed form (all hypotheses at
    once, batched SVD), scored by inlier count within ``threshold`` metres, and the best is refit
    on its inliers (twice, re-selecting inliers). Degenerate (near-collinear) samples are skipped.
    """
    n = len(src)
    fail = RansacResult(np.eye(4), np.zeros(n, bool), 0, float("inf"), False)
    if n < max(sample_size, 3) or n < min_inliers:
        return fail
    rng = rng if rng is not None else np.random.default_rng(0)
    idx = (
        np.argsort(rng.random((iterations, n)), axis=1)[:, :sample_size]
        if n <= 64
        else (_sample_without_replacement(rng, n, iterations, sample_size))
    )
    S, D = src[idx], dst[idx]
    # reject degenerate samples: small triangle area in either set, or inconsistent side lengths
    area_s = np.linalg.norm(np.cross(S[:, 1] - S[:, 0], S[:, 2] - S[:, 0]), axis=1)
    area_d = np.linalg.norm(np.cross(D[:, 1] - D[:, 0], D[:, 2] - D[:, 0]), axis=1)
    len_s = np.linalg.norm(S - np.roll(S, 1, axis=1), axis=2)
    len_d = np.linalg.norm(D - np.roll(D, 1, axis=1), axis=2)
    ok = (area_s > 1e-4) & (area_d > 1e-4) & np.all(np.abs(len_s - len_d) < 2 * threshold, axis=1)
    if not ok.any():
        return fail
    Ts = kabsch_batch(S[ok], D[ok])
    pred = src @ np.swapaxes(Ts[:, :3, :3], 1, 2) + Ts[:, None, :3, 3]
    err2 = ((pred - dst[None]) ** 2).sum(-1)
    counts = (err2 < threshold**2).sum(1)
    best = int(np.argmax(counts))
    inliers = err2[best] < threshold**2
    T = Ts[best]
    for _ in range(2):
        if inliers.sum() < 3:
            break
        T = kabsch(src[inliers], dst[inliers])
        err2_ref = (((src @ T[:3, :3].T + T[:3, 3]) - dst) ** 2).sum(-1)
        inliers = err2_ref < threshold**2
    n_in = int(inliers.sum())
    if n_in < 3:
        return fail
    resid = (src[inliers] @ T[:3, :3].T + T[:3, 3]) - dst[inliers]
    rmse = float(np.sqrt((resid**2).sum(-1).mean()))
    return RansacResult(T, inliers, n_in, rmse, n_in >= min_inliers)


def _sample_without_replacement(
    rng: np.random.Generator, n: int, iterations: int, k: int
) -> np.ndarray:
    """``iterations`` rows of ``k`` distinct indices in [0, n)."""
    idx = rng.integers(0, n, size=(iterations, k))
    for _ in range(10):  # redraw rows with repeated indices
        s = np.sort(idx, axis=1)
        bad = np.any(s[:, 1:] == s[:, :-1], axis=1)
        if not bad.any():
            break
        idx[bad] = rng.integers(0, n, size=(int(bad.sum()), k))
    return idx
