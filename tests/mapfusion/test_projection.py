"""The one projection object: lat/lon ↔ ENU."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mapfusion import InputError, LocalProjection


@given(
    st.floats(-70, 70), st.floats(-179, 179),
    st.floats(-0.4, 0.4), st.floats(-0.4, 0.4),
)
def test_round_trip_under_a_millimetre(lat0, lon0, dlat, dlon):
    proj = LocalProjection(lat0, lon0)
    lat, lon = lat0 + dlat, lon0 + dlon
    x, y = proj.to_enu(lat, lon)
    lat2, lon2 = proj.to_geo(x, y)
    x2, y2 = proj.to_enu(lat2, lon2)
    assert np.hypot(x2 - x, y2 - y) < 1e-3
    # and in degrees: 1 mm is about 1e-8 degrees of latitude
    assert abs(lat2 - lat) < 1e-8 and abs(lon2 - lon) < 1e-8 / max(np.cos(np.radians(lat)), 0.3)


def test_origin_maps_to_zero_and_axes_point_east_north():
    proj = LocalProjection(60.17, 24.94)
    assert np.allclose(proj.to_enu(60.17, 24.94), (0.0, 0.0), atol=1e-9)
    x, y = proj.to_enu(60.17 + 0.001, 24.94)
    assert abs(x) < 0.01 and 110.0 < y < 112.0  # 0.001° of latitude is about 111 m, north
    x, y = proj.to_enu(60.17, 24.94 + 0.001)
    assert 55.0 < x < 56.0 and abs(y) < 0.01  # east, shortened by cos(60°)


def test_vectorised_and_picklable():
    proj = LocalProjection(48.0, 11.0)
    lat = np.array([48.0, 48.01, 47.99])
    lon = np.array([11.0, 11.02, 10.97])
    x, y = proj.to_enu(lat, lon)
    assert x.shape == (3,)
    other = pickle.loads(pickle.dumps(proj))
    assert np.allclose(other.to_enu(lat, lon), (x, y))


@pytest.mark.parametrize("lat,lon", [(float("nan"), 0.0), (91.0, 0.0), (0.0, 200.0)])
def test_bad_origin(lat, lon):
    with pytest.raises(InputError):
        LocalProjection(lat, lon)
