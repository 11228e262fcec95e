import numpy as np

from slam.frontend.rgbd_image import RgbdImage


def _half_textured_view() -> RgbdImage:
    """A fronto-parallel plane 1.5 m away, 320 x 240: its left half is flat grey, its right
    half a checkerboard of 4-pixel squares; the top 20 rows have no depth."""
    K = np.array([[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1]])
    depth = np.full((240, 320), 1.5, np.float32)
    depth[:20] = 0.0
    u, v = np.meshgrid(np.arange(320), np.arange(240))
    intensity = np.where(((u // 4 + v // 4) % 2 == 0) & (u >= 160), 0.8, 0.3).astype(np.float32)
    return RgbdImage(depth, intensity, K, 3)


def test_textured_pixels_are_the_strongest_gradients_with_depth():
    image = _half_textured_view()
    src = image.textured(0, 0.125)
    n_valid = 220 * 320
    assert len(src.points) == int(np.ceil(0.125 * n_valid))
    u = src.points[:, 0] / src.points[:, 2] * 262.5 + 159.5
    v = src.points[:, 1] / src.points[:, 2] * 262.5 + 119.5
    assert u.min() > 155.0  # all on the checkerboard (its left edge included)
    assert v.min() > 19.5  # none where there is no depth
    np.testing.assert_allclose(src.points[:, 2], 1.5)
    assert np.all(np.isclose(src.intensity, 0.3) | np.isclose(src.intensity, 0.8))
    # every pixel: the same points as the plain source level
    assert len(image.textured(0, 1.0).points) == len(image.source(0).points) == n_valid


def test_a_target_for_colour_alone_has_no_geometry_until_asked():
    image = _half_textured_view()
    light = image.target(0, geometry=False)
    assert light.normal.shape == (0, 3) and light.photo is not None
    full = image.target(0)
    assert full.normal.shape == (240 * 320, 3) and full.has_normal.any()
    assert image.target(0, geometry=False) is full  # once built, the full level serves both
    np.testing.assert_array_equal(light.photo, full.photo)


def test_odd_target_is_the_finest_levels_odd_pixels_with_their_own_depth():
    """Every second row and column (odd indices) of the finest level, each pixel with its own
    depth (not a pyramid's average) and the full-resolution normal; its intrinsics project
    each vertex onto its grid cell."""
    image = _half_textured_view()
    odd, K_odd = image.odd_target()
    full = image.target(0)
    h, w = odd.shape
    assert (h, w) == (119, 159)
    rows, cols = np.meshgrid(np.arange(1, 2 * h, 2), np.arange(1, 2 * w, 2), indexing="ij")
    at = (rows * 320 + cols).reshape(-1)
    np.testing.assert_array_equal(odd.depth, full.depth[at])
    np.testing.assert_array_equal(odd.normal, full.normal[at])
    v = odd.vertex[odd.depth > 0]
    u_px = K_odd[0, 0] * v[:, 0] / v[:, 2] + K_odd[0, 2]
    v_px = K_odd[1, 1] * v[:, 1] / v[:, 2] + K_odd[1, 2]
    grid_v, grid_u = np.divmod(np.flatnonzero(odd.depth > 0), w)
    np.testing.assert_allclose(u_px, grid_u, atol=1e-3)
    np.testing.assert_allclose(v_px, grid_v, atol=1e-3)
