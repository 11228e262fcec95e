"""The noise-weighted point-to-plane ICP and the constraint analysis of its normal equations."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slam.camera import DepthNoise
from slam.frontend.weighted_icp import (
    constraint,
    depth_constraint,
    depth_information,
    metric_eigen,
    without_blind_directions,
)

K = np.array([[262.5, 0.0, 159.75], [0.0, 262.5, 119.75], [0.0, 0.0, 1.0]])
W, H = 320, 240


def _render(planes: list[tuple[np.ndarray, float]], T_world_cam: np.ndarray) -> np.ndarray:
    """Depth (HxW) of the nearest of some planes ``n . x = d`` (world frame) seen from a pose."""
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1)
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    best = np.full((H, W), np.inf)
    for n, d in planes:
        denom = rays @ (R.T @ n)
        lam = (d - n @ t) / np.where(np.abs(denom) > 1e-9, denom, np.nan)
        best = np.where((lam > 0) & (lam < best), lam, best)  # lam is the z-depth (ray z = 1)
    return np.where(np.isfinite(best), best, 0.0).astype(np.float32)


#: the corner of a room: a wall 3 m ahead, one 1 m to the left, the floor 0.8 m below (the
#: OpenCV camera's y points down); each fills a good part of the view
CORNER = [
    (np.array([0.0, 0.0, 1.0]), 3.0),
    (np.array([1.0, 0.0, 0.0]), -1.0),
    (np.array([0.0, 1.0, 0.0]), 0.8),
]


def test_noise_grows_with_the_square_of_depth():
    noise = DepthNoise()
    assert noise.sigma(np.float32(0.4)) == pytest.approx(0.0012)
    s1, s2, s4 = (float(noise.sigma(np.float32(z))) for z in (1.0, 2.0, 4.0))
    assert s1 == pytest.approx(0.0012 + 0.0019 * 0.36, rel=1e-5)
    assert s4 / s1 > 12  # a far point weighs (s4 / s1)^2 > 150 times less


def test_a_single_wall_leaves_three_directions_blind_and_a_corner_none():
    wall = depth_information(_render(CORNER[:1], np.eye(4)), K, 4.0, DepthNoise())
    corner = depth_information(_render(CORNER, np.eye(4)), K, 4.0, DepthNoise())
    assert wall is not None and corner is not None
    c_wall, c_corner = constraint(*wall), constraint(*corner)
    # a plane constrains 3 of 6 directions: the weakest is orders of magnitude weaker
    assert c_wall.ratio > 1e3
    assert c_corner.ratio < 30
    assert c_wall.weakest_std_m > 100 * c_corner.weakest_std_m
    vals = np.linalg.eigvalsh(wall[0])
    assert np.sum(vals < 1e-6 * vals[-1]) == 3


def test_a_depth_image_says_how_blind_its_geometry_is_before_any_alignment():
    # the same analysis from the depth alone (the Jacobian at the solution): a wall filling the
    # view is blind along three directions, a room's corner along none; points beyond the
    # range do not count
    noise = DepthNoise()
    wall = depth_constraint(_render(CORNER[:1], np.eye(4)), K, 4.0, noise)
    corner = depth_constraint(_render(CORNER, np.eye(4)), K, 4.0, noise)
    assert wall.ratio > 1e3 and corner.ratio < 15
    cut = depth_constraint(_render(CORNER, np.eye(4)), K, 0.5, noise)  # nothing within 0.5 m
    assert cut.ratio == float("inf")
    assert depth_information(_render(CORNER, np.eye(4)), K, 0.5, noise) is None


def test_a_wall_s_information_is_strong_across_it_and_nil_along_it():
    # the information behind the ratio, in metric coordinates: a wall facing the camera pins
    # the motion towards it (and the two tilts), and says nothing of the slides along it nor
    # the turn about its normal; its median depth is the wall's distance
    H, median_z = depth_information(_render(CORNER[:1], np.eye(4)), K, 4.0, DepthNoise())
    assert median_z == pytest.approx(3.0, rel=0.05)  # CORNER[0]: the plane z = 3
    s, vals, vecs = metric_eigen(H, median_z)
    assert np.allclose(s, [1 / median_z] * 3 + [1.0] * 3)
    assert vals[-1] / max(vals[2], 1e-30) > 1e6  # three directions nil
    strongest = vecs[:, -3:]  # spans the push towards the wall (t_z) and the tilts (w_x, w_y)
    for axis in (0, 1, 5):
        assert np.linalg.norm(strongest[axis]) > 0.99


@settings(max_examples=30, deadline=None)
@given(
    st.lists(st.floats(-1.0, 1.0), min_size=36, max_size=36),
    st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6),
    st.floats(0.5, 5.0),
)
def test_blind_directions_lose_their_information_and_gradient(a, g, depth_m):
    """The information of a term minus its blind directions: what a strong direction says is
    kept exactly, a blind one says nothing, and the result stays symmetric positive
    semi-definite."""
    rng_basis, _ = np.linalg.qr(np.array(a).reshape(6, 6) + 3 * np.eye(6))
    s = np.array([1.0 / depth_m] * 3 + [1.0] * 3)  # rotations compare as motion at depth_m
    vals = np.array([1e-6, 1e-5, 1.0, 2.0, 5.0, 10.0])  # two directions ~1000x weaker (std)
    Hs = (rng_basis * vals) @ rng_basis.T
    H = Hs / s[:, None] / s[None, :]
    b = np.array(g)
    H2, b2 = without_blind_directions(H, b, depth_m, 40.0)
    strong, blind = rng_basis[:, 2:], rng_basis[:, :2]
    Hs2 = H2 * s[:, None] * s[None, :]
    np.testing.assert_allclose(strong.T @ Hs2 @ strong, strong.T @ Hs @ strong, atol=1e-9)
    np.testing.assert_allclose(blind.T @ Hs2, 0.0, atol=1e-9)
    np.testing.assert_allclose(blind.T @ (b2 * s), 0.0, atol=1e-9)
    np.testing.assert_allclose(strong.T @ (b2 * s), strong.T @ (b * s), atol=1e-9)
    np.testing.assert_allclose(H2, H2.T, atol=1e-9)
    assert np.linalg.eigvalsh(Hs2).min() > -1e-9
    # nothing is blind at a looser ratio: the equations come back as they were
    H3, b3 = without_blind_directions(H, b, depth_m, 1e4)
    assert H3 is H and b3 is b
