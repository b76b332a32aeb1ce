"""Recorded-input formats: a GPS σ is the fix's own or the configured one, never silently replaced."""

from __future__ import annotations

import math

import pytest

from mapfusion import FusionConfig, RoadMap
from mapfusion.engine import EngineError, MapFusion
from mapfusion.formats import FormatError, read_gps_csv
from tests.helpers import MAPS


@pytest.mark.parametrize("sigma", ["0", "-1", "inf", "1e300", "nan"])
def test_a_gps_sigma_given_must_be_one(tmp_path, sigma):
    p = tmp_path / "gps.csv"
    p.write_text(f"t,lat,lon,alt,sigma_m\n0.0,60.1,24.9,,2.0\n1.0,60.1,24.9,,{sigma}\n")
    if sigma == "nan":  # written as NaN: read as "not given", like an empty cell
        assert math.isnan(read_gps_csv(p).sigma_m[1])
        return
    with pytest.raises(FormatError, match=r"gps.csv:3: sigma_m must be > 0"):
        read_gps_csv(p)


def test_an_empty_sigma_means_the_configured_one(tmp_path):
    p = tmp_path / "gps.csv"
    p.write_text("t,lat,lon,alt,sigma_m\n0.0,60.1,24.9,,\n")
    assert math.isnan(read_gps_csv(p).sigma_m[0])


@pytest.mark.parametrize("sigma", [0.0, -2.0, math.inf])
def test_the_engine_refuses_a_sigma_that_is_none(sigma):
    eng = MapFusion(RoadMap.from_osm(MAPS / "synthetic" / "grid.osm"), FusionConfig())
    with pytest.raises(EngineError, match="sigma_m must be > 0"):
        eng.add_gps(0.0, 60.1, 24.9, None, sigma)
    eng.add_gps(0.0, 60.1, 24.9, None, math.nan)  # NaN and None: the configured σ
    eng.add_gps(1.0, 60.1, 24.9, None, None)
    assert eng.counters.gps_before_init == 2
