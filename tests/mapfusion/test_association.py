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
from tests.helpers import circle_road, straight_road, write_osm

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


# ---------------------------------------------------------------- heading priors (issue 17)
@pytest.fixture(scope="module")
def east_road(tmp_path_factory) -> RoadMap:
    """A straight one-lane road 400 m long heading east, centred on the map's origin."""
    d = tmp_path_factory.mktemp("east")
    return RoadMap.from_osm(write_osm(d, [(straight_road(400.0, 0.0, (-200.0, 0.0)), {"highway": "primary",
                                                                                    "lanes": "1"})]), cache=False)


@pytest.fixture(scope="module")
def ring_road(tmp_path_factory) -> RoadMap:
    """A one-lane ring road of 40 m radius around the map's origin (it turns 1.4 degrees per metre)."""
    d = tmp_path_factory.mktemp("ring")
    return RoadMap.from_osm(write_osm(d, [(circle_road(40.0), {"highway": "primary", "lanes": "1"})]), cache=False)


def _heading_prior(road: RoadMap, x_m: float, y_m: float, yaw_rad: float, moved_m: float = 100.0,
                   yaw_sigma_deg: float = math.inf, sigma_factor: float = 1.0, **cfg):
    assoc = MapAssociation(road, FusionConfig(**({"heading_prior_sigma_deg": 3.0} | cfg)), Counters())
    pred = gtsam.Pose3(gtsam.Rot3.Yaw(yaw_rad), gtsam.Point3(x_m, y_m, 0.0))
    return assoc, pred, assoc.heading_prior(7, pred, assoc.match(pred), moved_m, math.radians(yaw_sigma_deg),
                                            sigma_factor)


@given(x=st.floats(-150.0, 150.0), y=st.floats(-2.9, 2.9), off_deg=st.floats(-9.9, 9.9), backwards=st.booleans())
def test_a_heading_prior_turns_the_yaw_alone_onto_a_straight_road(east_road, x, y, off_deg, backwards):
    road_yaw = math.pi if backwards else 0.0
    _, pred, factor = _heading_prior(east_road, x, y, road_yaw + math.radians(off_deg))
    assert factor is not None
    target = factor.prior()
    assert abs(math.remainder(target.rotation().yaw() - road_yaw, 2.0 * math.pi)) < 1e-9
    assert np.allclose(target.translation(), pred.translation(), atol=1e-9)
    values = gtsam.Values()
    # anywhere on the road's heading the prior costs nothing: it says nothing of the position
    values.insert(gtsam.symbol_shorthand.X(7), gtsam.Pose3(target.rotation(), gtsam.Point3(x + 30.0, y - 20.0, 5.0)))
    assert factor.error(values) < 1e-12
    turned = gtsam.Values()
    turned.insert(gtsam.symbol_shorthand.X(7), pred)
    # the yaw's own cost: 0.5 (δ/σ)² (within the robust kernel's quadratic part), 5.6e-6 at δ = 0.01°, σ = 3°
    if abs(off_deg) >= 0.01:
        assert factor.error(turned) > 5e-6
    elif abs(off_deg) < 0.001:
        assert factor.error(turned) < 1e-7


@pytest.mark.parametrize("case", ["off", "too far off the road's heading", "off the road", "on a curve",
                                  "too soon after the last", "its own heading known better"])
def test_no_heading_prior_where_the_road_says_nothing_sure_of_the_heading(east_road, ring_road, case):
    if case == "off":
        assoc, _, factor = _heading_prior(east_road, 0.0, 0.0, 0.05, heading_prior_sigma_deg=0.0)
    elif case == "too far off the road's heading":
        assoc, _, factor = _heading_prior(east_road, 0.0, 0.0, math.radians(12.0))
    elif case == "off the road":  # farther than the road is wide: the map prior's case
        assoc, _, factor = _heading_prior(east_road, 0.0, 3.5, 0.0)
    elif case == "on a curve":
        assoc, _, factor = _heading_prior(ring_road, 40.0, 0.0, math.pi / 2)
    elif case == "its own heading known better":  # its yaw σ 2.9 degrees, under the gate's 1 × 3
        assoc, _, factor = _heading_prior(east_road, 0.0, 0.0, 0.05, yaw_sigma_deg=2.9, heading_prior_gate=1.0)
        assert _heading_prior(east_road, 0.0, 0.0, 0.05, yaw_sigma_deg=3.1, heading_prior_gate=1.0)[2] is not None
    else:  # one 10 m (heading_prior_spacing_m) after another, then 9 m on
        assoc, pred, first = _heading_prior(east_road, 0.0, 0.0, 0.0)
        assert first is not None
        factor = assoc.heading_prior(8, pred, assoc.match(pred), 9.0)
        assert factor is None and assoc.counters.heading_priors == 1
        assert assoc.heading_prior(9, pred, assoc.match(pred), 1.0) is not None
        return
    assert factor is None and assoc.counters.heading_priors == 0
    if case == "on a curve":  # the same estimate on a straight road gets one
        assert _heading_prior(east_road, 0.0, 0.0, 0.0)[2] is not None


@pytest.mark.parametrize("factor, expected", [(1.0, False), (1.5, False), (3.0, True)])
def test_a_learned_odometry_sigma_over_the_open_factor_opens_the_gate(east_road, factor, expected):
    """The estimate's marginal yaw σ (1 degree) is under the gate (1 × 3 degrees); the GPS window's verdict on the
    odometry (its σ × factor) opens it when over heading_prior_open_factor (1.5)."""
    _, _, factor_ = _heading_prior(east_road, 0.0, 0.0, 0.05, yaw_sigma_deg=1.0, sigma_factor=factor,
                                   heading_prior_gate=1.0, heading_prior_open_factor=1.5)
    assert (factor_ is not None) == expected


def _drive_off_the_road(tmp_path, cfg: FusionConfig):
    """GPS along a lone road for 120 s, then the odometry turns 90° and leaves the network for 600 m."""
    from mapfusion import MapFusion

    road = RoadMap.from_osm(write_osm(tmp_path, [(straight_road(3000.0, 0.0, (-1500.0, 0.0)), {"highway": "primary"})]),
                            cache=False)
    (x0, y0) = road.xy_m[0]
    eng = MapFusion(road, cfg, gps_rate_hz=1.0, odometry_rate_hz=10.0)
    for k in range(2100):
        t = 0.1 * k
        if k % 10 == 0 and t <= 120.0:
            lat, lon = road.projection.to_geo(x0 + 100.0 + 10.0 * t, y0)
            eng.add_gps(t, float(lat), float(lon), None, 1.0)
        rel = np.eye(4)
        rel[0, 3] = 0.0 if k == 0 else 1.0
        if k == 1500:  # a 90° turn where there is no road
            rel[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]
        eng.add_odometry(t, rel)
    eng.finish()
    return eng


def test_leaving_the_network_is_a_lost_event(tmp_path):
    """With map_relocalisation the association watches for lost: 600 m at 10 m/s off a lone road is one lost event,
    from about lost_after_m (100 m: 10 s) past the point where no road within lost_cost_m explains the estimate."""
    eng = _drive_off_the_road(tmp_path, FusionConfig(map_relocalisation=True))
    assert eng.initialised
    assert eng.counters.lost_events == 1
    assert 10.0 < eng.lost_s < 60.0
    (tmp_path / "default").mkdir()
    default = _drive_off_the_road(tmp_path / "default", FusionConfig())
    assert default.counters.lost_events == 0 and default.lost_s == 0.0  # lost is watched only where it is acted on
