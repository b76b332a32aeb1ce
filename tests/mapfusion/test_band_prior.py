"""The band prior (issue 16): the map says the vehicle is on its road, not on the centre line."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.stats import truncnorm

from mapfusion.config import FusionConfig, PriorTarget
from mapfusion.factors import band_sqrt_information, band_update, information, odometry_noise

import gtsam


def _fuse(mu: float, s: float, target: float, sigma_f: float) -> tuple[float, float]:
    """N(μ, s²) times N(target, σ_f²): the product's mean and variance."""
    prec = 1 / s**2 + 1 / sigma_f**2
    return (mu / s**2 + target / sigma_f**2) / prec, 1 / prec


@given(mu=st.floats(-60, 60), s=st.floats(0.05, 30), h=st.floats(0.5, 15))
def test_band_factor_turns_the_estimate_into_the_truncated_posterior(mu, s, h):
    upd = band_update(mu, s, h)
    a, b = (-h - mu) / s, (h - mu) / s
    mean, var = truncnorm.stats(a, b, loc=mu, scale=s, moments="mv")
    if upd is None:
        # no information worth a factor: the band barely truncates the estimate
        assert float(var) > s**2 * (1 - 1e-5)
        return
    target, sigma_f = upd
    assert sigma_f > 0 and math.isfinite(target)
    m, v = _fuse(mu, s, target, sigma_f)
    if not (math.isfinite(float(mean)) and float(var) > 1e-10 * s**2):
        return  # scipy's own moments fail this deep in the tail
    assert m == pytest.approx(float(mean), abs=1e-6 * max(s, h))
    assert v == pytest.approx(float(var), rel=1e-5, abs=1e-10 * s**2)
    assert -h - 1e-9 <= m <= h + 1e-9  # the posterior lies inside the band


@given(mu=st.floats(0.0, 60), s=st.floats(0.05, 30), h=st.floats(0.5, 15))
def test_band_update_is_symmetric(mu, s, h):
    up, down = band_update(mu, s, h), band_update(-mu, s, h)
    if up is None:
        assert down is None
    else:
        assert down is not None
        assert down[0] == pytest.approx(-up[0], abs=1e-9) and down[1] == pytest.approx(up[1])


def test_a_certain_estimate_goes_to_the_edge_an_uncertain_one_to_the_centre():
    edge, _ = band_update(5.0, 0.1, 3.0)
    assert edge == pytest.approx(3.0, abs=0.05)
    centre, _ = band_update(5.0, 50.0, 3.0)
    assert abs(centre) < 0.5


def test_band_update_refuses_nonsense():
    for args in ((1.0, 0.0, 3.0), (1.0, 1.0, 0.0), (math.nan, 1.0, 3.0)):
        with pytest.raises(ValueError):
            band_update(*args)


def test_band_prior_holds_only_across_the_road_and_yaw():
    info = information(band_sqrt_information(0.5, math.radians(10)))
    assert info[4, 4] == pytest.approx(4.0) and info[2, 2] == pytest.approx(1 / math.radians(10) ** 2)
    assert np.count_nonzero(info) == 2


@given(length=st.floats(0.0, 40.0))
def test_odometry_sigma_grows_with_the_distance_not_the_frames(length):
    cfg = FusionConfig(odometry_sigma_after_init_m=0.001, odometry_rot_sigma_deg=0.001, odometry_sigma_per_m=0.02,
                       odometry_rot_sigma_deg_per_m=0.1)
    step = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(length, 0.0, 0.0))
    sig = odometry_noise(cfg, step, 1.0, 0.1).sigmas()
    assert sig[3] == pytest.approx(math.hypot(0.001, 0.02 * length))
    assert sig[2] == pytest.approx(math.radians(math.hypot(0.001, 0.1 * length)))


def test_prior_target_is_an_enum_loaded_from_text():
    from mapfusion.config import from_mapping

    assert from_mapping(FusionConfig, {"prior_target": "band"}).prior_target is PriorTarget.band
