"""Which ways are a match's rivals for the ambiguity gate (issue 17, ``prior_ambiguity_line_m``): another way that
continues the match's road on its line is the same road, not a coin toss."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mapfusion.association import MapAssociation
from mapfusion.config import FusionConfig
from mapfusion.counters import Counters
from mapfusion.geometry import on_line
from mapfusion.roadmap import RoadMap
from tests.helpers import straight_road, write_osm

_TOL_M = 1.0
_MAX = math.radians(10.0)


@given(x=st.floats(-1e3, 1e3), y=st.floats(-1e3, 1e3), heading=st.floats(-math.pi, math.pi),
       along=st.floats(-200.0, 200.0), across=st.floats(-0.99, 0.99), turn=st.floats(-0.99, 0.99),
       backwards=st.booleans())
def test_a_point_on_the_line_heading_along_it_either_way_is_on_it(x, y, heading, along, across, turn, backwards):
    c, s = math.cos(heading), math.sin(heading)
    p = np.array([[x + along * c - across * _TOL_M * s, y + along * s + across * _TOL_M * c]])
    own = heading + turn * _MAX + (math.pi if backwards else 0.0)
    assert on_line(np.array([x, y]), heading, p, np.array([own]), _TOL_M, _MAX)[0]


@given(heading=st.floats(-math.pi, math.pi), along=st.floats(-200.0, 200.0), across=st.floats(1.01, 50.0),
       side=st.sampled_from([-1.0, 1.0]), turn=st.floats(-0.99, 0.99))
def test_a_point_off_the_line_is_not_on_it_whatever_its_heading(heading, along, across, side, turn):
    c, s = math.cos(heading), math.sin(heading)
    p = np.array([[along * c - side * across * _TOL_M * s, along * s + side * across * _TOL_M * c]])
    assert not on_line(np.zeros(2), heading, p, np.array([heading + turn * _MAX]), _TOL_M, _MAX)[0]


@given(heading=st.floats(-math.pi, math.pi), along=st.floats(-200.0, 200.0), turn=st.floats(1.01, 17.0),
       side=st.sampled_from([-1.0, 1.0]))
def test_a_point_on_the_line_crossing_it_is_not_on_it(heading, along, turn, side):
    # turned by more than the limit, and by less than 180° minus it: a crossing road, not this one
    c, s = math.cos(heading), math.sin(heading)
    p = np.array([[along * c, along * s]])
    own = heading + side * min(turn * _MAX, math.pi - 1.01 * _MAX)
    assert not on_line(np.zeros(2), heading, p, np.array([own]), _TOL_M, _MAX)[0]


@pytest.fixture(scope="module")
def split_road(tmp_path_factory) -> RoadMap:
    """A straight one-lane road heading east, drawn as two ways meeting at x = 200 m, and a separate one-lane road
    parallel to it 14 m to the north from x = 260 m to 380 m."""
    tags = {"highway": "primary", "lanes": "1"}
    d = tmp_path_factory.mktemp("split")
    return RoadMap.from_osm(write_osm(d, [(straight_road(200.0), tags),
                                          (straight_road(200.0, origin=(200.0, 0.0)), tags),
                                          (straight_road(120.0, origin=(260.0, 14.0)), tags)]), cache=False)


def _prior(road: RoadMap, line_m: float, x_m: float, lateral_m: float):
    """The prior for a pose heading east ``x_m`` along the drawing and ``lateral_m`` north of the first road (the
    map's frame is centred on the map: the drawing's origin is its south-west corner)."""
    cfg = FusionConfig(prior_spacing_m=0.0, prior_ambiguity_line_m=line_m)
    x0, y0 = road.xy_m.min(axis=0)
    assoc = MapAssociation(road, cfg, Counters())
    pred = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(x0 + x_m, y0 + lateral_m, 0.0))
    m, factor = assoc.prior(10, pred, gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(1.0, 0.0, 0.0)), 0.1, 100.0)
    return assoc, m, factor


@pytest.mark.parametrize("x_m", [196.0, 199.5, 203.0])
def test_the_next_way_of_the_same_road_does_not_gate_the_prior(split_road, x_m):
    # 5 m off a 3 m wide road, near where its two ways meet: both ways' best D are within 3 m of each other
    assoc, m, factor = _prior(split_road, 0.0, x_m, 5.0)
    assert m is not None and factor is None and assoc.counters.priors_gated == 1  # the gate as it was
    assoc, m, factor = _prior(split_road, _TOL_M, x_m, 5.0)
    assert factor is not None and assoc.counters.priors_gated == 0
    assert factor.prior().y() == pytest.approx(m.y_m + 3.0, abs=0.05)  # the band's edge (the edge target)


def test_a_parallel_road_still_gates_the_prior(split_road):
    # half-way between two parallel roads 14 m apart: a coin toss, whatever the option
    for line_m in (0.0, _TOL_M):
        assoc, m, factor = _prior(split_road, line_m, 320.0, 7.0)
        assert m is not None and factor is None and assoc.counters.priors_gated == 1
