"""Recorded-input formats: a GPS σ is the fix's own or the configured one, never silently replaced."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

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


@given(st.lists(st.tuples(st.floats(0.001, 10.0), st.floats(-1e4, 1e4), st.floats(-1e4, 1e4), st.floats(-50, 50),
                          st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1), st.floats(0.1, 1)),
                min_size=1, max_size=40),
       st.booleans())
def test_read_tum_in_one_pass_reads_what_the_checking_parser_reads(rows, comments):
    """read_tum's numpy fast path (issue 21) gives the streamed parser's values to the bit, comments too."""
    import tempfile
    from pathlib import Path

    from mapfusion.formats import read_tum, tum_rows

    t = 0.0
    lines = ["# t tx ty tz qx qy qz qw"] if comments else []
    for dt, x, y, z, qx, qy, qz, qw in rows:
        t += dt
        n = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        lines.append(" ".join(repr(v) for v in (t, x, y, z, qx / n, qy / n, qz / n, qw / n)))
        if comments:
            lines.append("")
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "t.tum"
        p.write_text("\n".join(lines) + "\n")
        ts, xyz, q = read_tum(p)
        ref = np.array(list(tum_rows(p)))
    assert np.array_equal(ts, ref[:, 0]) and np.array_equal(xyz, ref[:, 1:4]) and np.array_equal(q, ref[:, 4:8])
