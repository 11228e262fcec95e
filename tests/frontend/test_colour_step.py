import numpy as np
import pytest

from slam.frontend.colour_step import (
    WINDOW,
    ColourAgreement,
    StepSettings,
    colour_equations,
    colour_refine,
)
from slam.geometry import exp_se3, inv_T
from tests.frontend.test_photometric import wall_views


def _agreement(
    sigma_colour_m: float,
    sigma_f2f_m: float,
    seed: int = 0,
    agreement: ColourAgreement | None = None,
) -> ColourAgreement:
    """Frames whose colour and frame-to-frame depth estimates scatter around the model
    estimate (the identity) by the given standard deviations in every direction; depth's
    information is 100x stronger along the translations than along the rotations, colour's
    the same in all directions (at 1 m depth rotations and translations compare 1:1)."""
    rng = np.random.default_rng(seed)
    H_geo = np.diag([1.0, 1.0, 1.0, 100.0, 100.0, 100.0]) * 1e6
    H_pho = np.eye(6) * 4e6
    agreement = agreement or ColourAgreement()
    for _ in range(WINDOW):
        colour = exp_se3(rng.normal(0.0, sigma_colour_m, 6))
        f2f = exp_se3(rng.normal(0.0, sigma_f2f_m, 6))
        agreement.add(H_geo, H_pho, 1.0, (colour, np.eye(4), f2f))
    return agreement


def test_no_weight_before_colour_was_measured():
    assert ColourAgreement().weight() == 0.0


def test_colours_weight_is_the_ratio_of_the_measured_variance_factors():
    """Along depth's strongest directions (the translations) depth claims a variance of
    1e-8 m^2 and colour 2.5e-7: with both scattering 0.1 mm, depth's factor is 1, colour's 0.04,
    so colour weighs 25 (its information times 25 against depth's)."""
    same = _agreement(1e-4, 1e-4)
    assert same.weight() == pytest.approx(25.0, rel=0.5)
    # colour 10x worse than depth's own scatter (as on tum-fr1-xyz): 100x less weight
    worse = _agreement(1e-3, 1e-4)
    assert worse.weight() == pytest.approx(same.weight() / 100.0, rel=0.5)


def test_only_the_recent_frames_count():
    agreement = _agreement(1e-3, 1e-4)
    old = agreement.weight()
    _agreement(1e-4, 1e-4, seed=1, agreement=agreement)  # colour got better
    assert len(agreement.factors) == WINDOW
    assert agreement.weight() == pytest.approx(_agreement(1e-4, 1e-4, seed=1).weight())
    assert agreement.weight() > 10 * old


def test_colour_refine_follows_colour_where_depth_is_blind_and_weighs_both_elsewhere():
    """The frame-to-frame colour step of tracking (``tracking.colour.colour_step_weight``): a frame
    whose depth estimate slid 8 mm along a textured wall (depth is blind there) and is 3 mm
    off along the wall's normal (where depth is sure: its estimate is the prior the step starts
    from). Colour moves it along the wall onto the truth at any weight; along the normal the two
    are weighed: colour at a thousandth of depth's weight (as on tum-fr1-xyz) leaves the frame
    where depth put it, at equal weight (exact images: colour sees the normal motion as the
    texture's scale) it goes part of the way. At weight 0 nothing moves."""
    motion = exp_se3(np.array([0.0, 0.0, np.radians(1.0), 0.02, -0.01, 0.0]))
    _, source, target = wall_views(motion)
    # the camera looks along +z at the wall: x slides along it, z moves along its normal
    start = exp_se3(np.array([0.0, 0.0, 0.0, 0.008, 0.0, 0.003])) @ motion
    first = colour_equations(source, target, start)
    assert first is not None and first.depth_m == pytest.approx(2.0, abs=0.05)
    assert np.array_equal(colour_refine(source, target, first, 0.0, 3), start)
    offsets = {}
    for weight in (1e-3, 1.0):
        T = colour_refine(source, target, first, weight, 3)
        offsets[weight] = (T @ inv_T(motion))[:3, 3]  # where the frame is left, target camera
        assert np.abs(offsets[weight][:2]).max() < 5e-4, offsets  # along the wall: the truth
    assert offsets[1e-3][2] == pytest.approx(0.003, abs=1e-4)  # depth's estimate holds
    assert 0.0 < offsets[1.0][2] < 0.0025  # weighed against colour


def test_colour_refine_on_the_textured_pixels_with_coarse_depth_information():
    """The default settings of the step (``tracking.colour.colour_step_textured`` 0.125,
    ``colour_step_geometry_stride`` 2): colour on the eighth of the pixels with the strongest
    gradients, depth's information on every second row and column. Along the wall the frame still ends on
    the truth; at a thousandth of depth's weight depth's estimate along the normal holds."""
    motion = exp_se3(np.array([0.0, 0.0, np.radians(1.0), 0.02, -0.01, 0.0]))
    _, source, target = wall_views(motion)
    start = exp_se3(np.array([0.0, 0.0, 0.0, 0.008, 0.0, 0.003])) @ motion
    cheap = StepSettings(textured=0.125, geometry_stride=2)
    first = colour_equations(source, target, start, cheap)
    assert first is not None and first.depth_m == pytest.approx(2.0, abs=0.05)
    full = colour_equations(source, target, start)
    assert full is not None
    # depth's information has the same shape on a quarter of the points
    shape = first.H_geo / np.trace(first.H_geo)
    np.testing.assert_allclose(shape, full.H_geo / np.trace(full.H_geo), atol=0.02)
    for weight in (1e-3, 1.0):
        T = colour_refine(source, target, first, weight, 3, cheap)
        offset = (T @ inv_T(motion))[:3, 3]
        assert np.abs(offset[:2]).max() < 5e-4, offset
        if weight == 1e-3:
            assert offset[2] == pytest.approx(0.003, abs=1e-4)
