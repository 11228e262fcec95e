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


def test_a_target_for_colour_alone_has_no_geometry_until_asked():
    image = _half_textured_view()
    light = image.target(0, geometry=False)
    assert light.normal.shape == (0, 3) and light.photo is not None
    full = image.target(0)
    assert full.normal.shape == (240 * 320, 3) and full.has_normal.any()
    assert image.target(0, geometry=False) is full  # once built, the full level serves both
    np.testing.assert_array_equal(light.photo, full.photo)
