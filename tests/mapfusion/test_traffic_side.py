"""The driving side (issue 17, ``traffic_side``): on a two-way road the map prior's band is centred on the lane the
vehicle keeps to, not on OSM's centre line."""

from __future__ import annotations

import math

import gtsam
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mapfusion.association import MapAssociation
from mapfusion.config import FusionConfig, PriorTarget, TrafficSide
from mapfusion.counters import Counters
from mapfusion.matcher import lateral_bound_ok, map_pose
from mapfusion.roadmap import RoadMap
from tests.helpers import straight_road, write_osm

_ROADS: dict[tuple[bool, int], RoadMap] = {}


def _road(tmp_path_factory, oneway: bool, lanes: int) -> RoadMap:
    """A 400 m straight road heading east (drawn west to east), built once per kind."""
    key = (oneway, lanes)
    if key not in _ROADS:
        tags = {"highway": "primary", "lanes": str(lanes)}
        if oneway:
            tags["oneway"] = "yes"
        d = tmp_path_factory.mktemp("side")
        _ROADS[key] = RoadMap.from_osm(write_osm(d, [(straight_road(400.0), tags)]), cache=False)
    return _ROADS[key]


def _prior(road: RoadMap, cfg: FusionConfig, lateral_m: float, westward: bool):
    """The association's prior for a pose mid-road, ``lateral_m`` to the left of its direction of travel."""
    yaw = math.pi if westward else 0.0
    y = _centre_y(road) + (-lateral_m if westward else lateral_m)
    pred = gtsam.Pose3(gtsam.Rot3.Yaw(yaw), gtsam.Point3(200.0, y, 0.0))
    step = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(1.0, 0.0, 0.0))
    assoc = MapAssociation(road, cfg, Counters())
    return assoc, assoc.prior(10, pred, step, 0.1, 100.0)


def _centre_y(road: RoadMap) -> float:
    """The centre line's y (m) mid-road: the OSM file's rounded coordinates put it within centimetres of 0."""
    m = road.match(200.0, 0.0, 0.0, 30.0)
    assert m is not None
    return m.y_m


def _across_of(factor, road: RoadMap, westward: bool) -> float:
    """The prior's mean, left of the direction of travel (m)."""
    y = factor.prior().y() - _centre_y(road)
    return -y if westward else y


@given(lateral=st.floats(-15.0, 15.0), lanes=st.sampled_from([1, 2, 4]), westward=st.booleans(),
       side=st.sampled_from(list(TrafficSide)))
def test_the_band_is_centred_on_the_driving_side_of_a_two_way_road(tmp_path_factory, lateral, lanes, westward, side):
    road = _road(tmp_path_factory, oneway=False, lanes=lanes)
    cfg = FusionConfig(traffic_side=side, prior_spacing_m=0.0, prior_target=PriorTarget.edge)
    width = lanes * cfg.lane_width_m
    half = max(1, lanes // 2) * 0.5 * cfg.lane_width_m
    centre = {TrafficSide.right: -half, TrafficSide.left: half, TrafficSide.none: 0.0}[side]
    assoc, (m, factor) = _prior(road, cfg, lateral, westward)
    assert m is not None and assoc.side_m(m) == pytest.approx(centre)
    off = lateral - centre
    if abs(abs(off) - width) < 1e-6:
        return  # (on the band's edge itself: either answer is right)
    if abs(off) < width:
        assert factor is None  # inside the band: the map has nothing to say
    else:
        assert factor is not None
        # the edge target: the band's nearer edge, around the driving side's lane
        assert _across_of(factor, road, westward) == pytest.approx(centre + math.copysign(width, off), abs=1e-6)


@given(lateral=st.floats(-15.0, 15.0))
def test_a_one_way_road_keeps_its_centre_line(tmp_path_factory, lateral):
    """Driven along its direction (east), a one-way road's band is centred on its centre line."""
    road = _road(tmp_path_factory, oneway=True, lanes=2)
    cfg = FusionConfig(traffic_side=TrafficSide.right, prior_spacing_m=0.0)
    assoc, (m, factor) = _prior(road, cfg, lateral, False)
    width = 2 * cfg.lane_width_m
    assert m is not None and assoc.side_m(m) == 0.0
    if abs(abs(lateral) - width) > 1e-6:
        assert (factor is None) == (abs(lateral) < width)


@given(lateral=st.floats(-20.0, 20.0), lon=st.floats(-3.0, 3.0), centre=st.floats(-6.0, 6.0),
       width=st.floats(0.5, 12.0), pitch=st.floats(-0.2, 0.2), roll=st.floats(-0.2, 0.2))
def test_the_quick_lateral_test_never_says_inside_when_the_pose_is_outside(tmp_path_factory, lateral, lon, centre,
                                                                          width, pitch, roll):
    road = _road(tmp_path_factory, oneway=True, lanes=1)
    pose = gtsam.Pose3(gtsam.Rot3.Ypr(0.0, pitch, roll), gtsam.Point3(200.0 + lon, lateral, 0.0))
    m = road.match(pose.x(), pose.y(), 0.0, 30.0)
    if m is None:
        return
    if lateral_bound_ok(m, pose.matrix(), width, centre):
        r, _ = map_pose(m, pose)
        signed = r.transformTo(pose.translation())[1]
        assert abs(signed - centre) <= width + 1e-9
