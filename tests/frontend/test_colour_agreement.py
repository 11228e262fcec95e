import numpy as np
import pytest

from slam.frontend.colour_agreement import WINDOW, ColourAgreement
from slam.geometry import exp_se3


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
