"""Property tests of the road matcher: D = E + w·A, lateral distance L, map pose, stress test."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from mapfusion import RoadMap, RoadMapConfig
from mapfusion.geometry import point_segment_distance
from mapfusion.matcher import angle_deg, map_pose, match_candidates, quaternion_angle_deg
from tests.helpers import MAPS, circle_road, polylines, straight_road, write_osm

ORIGIN = (60.2, 24.9)
FIXTURE_OK = settings(suppress_health_check=[HealthCheck.function_scoped_fixture], max_examples=25)


def _road(tmp_path, roads):
    path = write_osm(tmp_path, roads, origin=ORIGIN)
    return RoadMap.from_osm(path, RoadMapConfig(origin_lat_deg=ORIGIN[0], origin_lon_deg=ORIGIN[1]), cache=False)


def _perp(road, way_id, x, y):
    """Distance from (x, y) to the map's own polyline of a way."""
    idx = road.waypoints_of_way(way_id)
    p = road.xy_m[idx]
    return float(point_segment_distance(np.array([[x, y]]), p[:-1], p[1:])[0])


angles = st.floats(-math.pi, math.pi)


# --------------------------------------------------------------------------- L on straight and circular roads
@FIXTURE_OK
@given(heading=angles, along=st.floats(20.0, 280.0), offset=st.floats(-10.0, 10.0), yaw=angles)
def test_lateral_on_straight_road_is_perpendicular_distance(tmp_path, heading, along, offset, yaw):
    road = _road(tmp_path, [(straight_road(300.0, heading), {"highway": "primary", "lanes": "2"})])
    d = np.array([math.cos(heading), math.sin(heading)])
    n = np.array([-d[1], d[0]])
    x, y = along * d + offset * n
    m = road.match(x, y, yaw)
    assert m is not None
    assert m.lateral_m == pytest.approx(_perp(road, m.way_id, x, y), abs=0.01)
    assert m.lateral_m == pytest.approx(abs(offset), abs=0.02)  # and to the OSM line (1 cm rounding)


@FIXTURE_OK
@given(theta=st.floats(0.0, 2 * math.pi), offset=st.floats(-8.0, 8.0), radius=st.floats(60.0, 300.0),
       backwards=st.booleans())
def test_lateral_on_circular_road_is_perpendicular_distance(tmp_path, theta, offset, radius, backwards):
    road = _road(tmp_path, [(circle_road(radius, n=360), {"highway": "primary"})])
    x, y = (radius + offset) * math.cos(theta), (radius + offset) * math.sin(theta)
    yaw = theta + math.pi / 2 + (math.pi if backwards else 0.0)  # tangent, either direction
    m = road.match(x, y, yaw)
    assert m is not None
    assert m.lateral_m == pytest.approx(_perp(road, m.way_id, x, y), abs=0.01)
    # the circle is drawn counter-clockwise: the tangent direction is the drawing direction
    assert m.reversed == backwards or m.is_join


# --------------------------------------------------------------------------- invariance
@given(
    n=st.integers(1, 40), seed=st.integers(0, 2**31 - 1), rot=angles,
    tx=st.floats(-1e4, 1e4), ty=st.floats(-1e4, 1e4), w=st.floats(0.0, 3.0),
)
def test_rigid_motion_of_map_and_pose_keeps_the_match(n, seed, rot, tx, ty, w):
    rng = np.random.default_rng(seed)
    cxy = rng.uniform(-20, 20, (n, 2))
    cyaw = rng.uniform(-math.pi, math.pi, n)
    px, py, pyaw = rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-math.pi, math.pi)
    k, rev, e, a, d = match_candidates(px, py, pyaw, cxy, np.cos(cyaw), np.sin(cyaw), w)
    # skip near-ties: which of two equal candidates wins is arbitrary
    all_d = np.hypot(*(cxy - (px, py)).T) + w * np.degrees(np.arccos(np.abs(np.cos(cyaw - pyaw))))
    assume(np.sum(all_d < d + 1e-6) == 1)
    c, s = math.cos(rot), math.sin(rot)
    R = np.array([[c, -s], [s, c]])
    cxy2 = cxy @ R.T + (tx, ty)
    cyaw2 = cyaw + rot
    p2 = R @ (px, py) + (tx, ty)
    k2, rev2, e2, a2, d2 = match_candidates(p2[0], p2[1], pyaw + rot, cxy2, np.cos(cyaw2), np.sin(cyaw2), w)
    assert (k2, rev2) == (k, rev)
    assert e2 == pytest.approx(e, abs=1e-6) and a2 == pytest.approx(a, abs=1e-5) and d2 == pytest.approx(d, abs=1e-5)


@pytest.mark.slow
@FIXTURE_OK
@given(rot=angles, tx=st.floats(-2000, 2000), ty=st.floats(-2000, 2000), seed=st.integers(0, 1000))
def test_rigid_motion_on_a_real_road_map(tmp_path, rot, tx, ty, seed):
    ew = np.array([[-200.0, 0.0], [0.0, 0.0], [200.0, 0.0]])
    ns = np.array([[0.0, -200.0], [0.0, 0.0], [0.0, 200.0]])
    c, s = math.cos(rot), math.sin(rot)
    R = np.array([[c, -s], [s, c]])
    (tmp_path / "a").mkdir(exist_ok=True)
    (tmp_path / "b").mkdir(exist_ok=True)
    a = _road(tmp_path / "a", [(ew, {"highway": "primary"}), (ns, {"highway": "residential"})])
    b = _road(tmp_path / "b", [(ew @ R.T + (tx, ty), {"highway": "primary"}), (ns @ R.T + (tx, ty), {"highway": "residential"})])
    rng = np.random.default_rng(seed)
    for _ in range(10):
        p = rng.uniform(-60, 60, 2)
        yaw = rng.uniform(-math.pi, math.pi)
        ma = a.match(p[0], p[1], yaw)
        q = R @ p + (tx, ty)
        mb = b.match(q[0], q[1], yaw + rot)
        if ma is None:
            assert mb is None
            continue
        # a near-tie (two way-points within 5 cm of D; OSM rounds coordinates to ~1 cm) may break either way
        near = a.query_radius(p[0], p[1], 20.0)
        ds = np.sort(np.hypot(*(a.xy_m[near] - p).T) + angle_deg(yaw, a.yaw_rad[near]).clip(max=180.0 - angle_deg(yaw, a.yaw_rad[near])))
        if len(ds) > 1 and ds[1] - ds[0] < 0.05:
            continue
        assert mb.way_id == ma.way_id
        assert mb.lateral_m == pytest.approx(ma.lateral_m, abs=0.03)
        assert mb.cost == pytest.approx(ma.cost, abs=0.05)


# --------------------------------------------------------------------------- on the centreline, parallel roads
@FIXTURE_OK
@given(poly=polylines(max_turn_deg=90.0), other=polylines(), pick=st.floats(0.0, 1.0), backwards=st.booleans())
def test_pose_on_centreline_matches_its_road_with_zero_cost(tmp_path, poly, other, pick, backwards):
    road = _road(tmp_path, [(poly, {"highway": "primary"}), (other, {"highway": "secondary"})])
    own = np.flatnonzero((road.way_id == 1) & ~road.is_join)
    i = int(own[int(pick * (len(own) - 1))])
    x, y = road.xy_m[i]
    # the other road must not pass through the very same spot with the same heading
    rival = np.flatnonzero(road.way_id != 1)
    if rival.size:
        dd = np.hypot(*(road.xy_m[rival] - (x, y)).T) + np.degrees(np.arccos(np.abs(np.cos(road.yaw_rad[rival] - road.yaw_rad[i]))))
        assume(dd.min() > 0.05)
    m = road.match(x, y, road.yaw_rad[i] + (math.pi if backwards else 0.0))
    assert m.way_id == 1
    assert m.cost == pytest.approx(0.0, abs=1e-5)  # arccos near 1 leaves ~1e-6° of rounding
    assert m.reversed == backwards


@FIXTURE_OK
@given(heading=angles, gap=st.floats(6.0, 30.0), frac=st.floats(0.0, 1.0), yaw=angles, flip=st.booleans(),
       along=st.floats(50.0, 250.0))
def test_between_parallel_roads_the_nearer_wins(tmp_path, heading, gap, frac, yaw, flip, along):
    d = np.array([math.cos(heading), math.sin(heading)])
    n = np.array([-d[1], d[0]])
    r1 = straight_road(300.0, heading)
    r2 = np.array([r1[1], r1[0]]) + gap * n if flip else r1 + gap * n  # drawn either way
    road = _road(tmp_path, [(r1, {"highway": "primary"}), (r2, {"highway": "service"})])
    x, y = along * d + frac * gap * n
    d1, d2 = _perp(road, 1, x, y), _perp(road, 2, x, y)
    assume(abs(d1 - d2) > 0.5)  # way-points are 1 m apart: closer than that is a tie
    m = road.match(x, y, yaw)
    assert m.way_id == (1 if d1 < d2 else 2)


# --------------------------------------------------------------------------- ranges and bad input
finite = st.floats(allow_nan=False, allow_infinity=False)


@given(fx=st.floats(-0.2, 1.2), fy=st.floats(-0.2, 1.2), yaw=finite, w=st.floats(0.0, 100.0),
       radius=st.floats(0.01, 300.0))
def test_no_nan_and_angle_in_range(fx, fy, yaw, w, radius):
    """Anywhere in and around the grid (its box and a fifth of it beyond each side): a match exactly when a
    way-point lies within the radius, and every field of it finite and in range."""
    road = _grid()
    lo, hi = road.xy_m.min(axis=0), road.xy_m.max(axis=0)
    x, y = lo + np.array([fx, fy]) * (hi - lo)
    m = road.match(x, y, yaw, radius=radius, angle_weight_m_per_deg=w)
    nearest = float(np.min(np.hypot(road.xy_m[:, 0] - x, road.xy_m[:, 1] - y)))
    assume(abs(nearest - radius) > 1e-6)  # (a way-point on the circle itself: either answer is right)
    if nearest > radius:
        assert m is None
        return
    assert m is not None
    for v in (m.x_m, m.y_m, m.yaw_rad, m.lateral_m, m.longitudinal_m, m.along_m, m.distance_m, m.angle_deg, m.cost):
        assert math.isfinite(v)
    assert 0.0 <= m.angle_deg <= 180.0
    assert nearest - 1e-9 <= m.distance_m <= radius + 1e-9


@given(a=st.floats(-1e6, 1e6), b=st.floats(-1e6, 1e6))
def test_angle_is_the_papers_quaternion_formula(a, b):
    ours = float(angle_deg(a, b))
    q = lambda t: np.array([math.cos(t / 2), 0.0, 0.0, math.sin(t / 2)])  # noqa: E731
    paper = float(quaternion_angle_deg(q(a), q(b)))
    assert 0.0 <= ours <= 180.0
    assert ours == pytest.approx(paper, abs=1e-3)


_GRID = None


def _grid():
    global _GRID
    if _GRID is None:
        _GRID = RoadMap.from_osm(MAPS / "synthetic" / "grid.osm")
    return _GRID


@pytest.mark.parametrize(
    "kwargs,name",
    [
        ({"x": float("nan"), "y": 0.0, "yaw": 0.0}, "x"),
        ({"x": 0.0, "y": float("inf"), "yaw": 0.0}, "y"),
        ({"x": 0.0, "y": 0.0, "yaw": float("nan")}, "yaw"),
        ({"x": 0.0, "y": 0.0, "yaw": 0.0, "radius": 0.0}, "radius"),
        ({"x": 0.0, "y": 0.0, "yaw": 0.0, "radius": -3.0}, "radius"),
    ],
)
def test_bad_arguments_name_themselves(kwargs, name):
    with pytest.raises(ValueError, match=rf"\b{name}\b"):
        _grid().match(**kwargs)


def test_nothing_in_radius_gives_none():
    assert _grid().match(1e5, 1e5, 0.0) is None


# --------------------------------------------------------------------------- batch = single
def test_match_many_equals_match(helsinki):
    rng = np.random.default_rng(7)
    n = 3000
    i = rng.integers(0, len(helsinki), n)
    x = helsinki.xy_m[i, 0] + rng.normal(0, 4, n)
    y = helsinki.xy_m[i, 1] + rng.normal(0, 4, n)
    yaw = helsinki.yaw_rad[i] + rng.normal(0, 0.4, n)
    x[:5] += 5e4  # some with nothing in range
    out = helsinki.match_many(x, y, yaw)
    for j in range(n):
        m = helsinki.match(x[j], y[j], yaw[j])
        if m is None:
            assert out["index"][j] == -1
            continue
        assert out["cost"][j] == pytest.approx(m.cost, abs=1e-9)
        assert out["way_id"][j] == m.way_id or out["cost"][j] == pytest.approx(m.cost)
        assert out["lateral_m"][j] == pytest.approx(m.lateral_m, abs=1e-9) or out["index"][j] != m.index


# --------------------------------------------------------------------------- map pose
@given(x=st.floats(-50, 50), y=st.floats(-50, 50), z=st.floats(-5, 30), yaw=angles,
       pitch=st.floats(-0.3, 0.3), roll=st.floats(-0.3, 0.3))
def test_map_pose_takes_xy_yaw_from_map_and_the_rest_from_the_pose(x, y, z, yaw, pitch, roll):
    road = _grid()
    gx, gy = road.xy_m[100] + (x * 0.1, y * 0.1)
    pose = gtsam.Pose3(gtsam.Rot3.Ypr(yaw, pitch, roll), gtsam.Point3(gx, gy, z))
    m = road.match(gx, gy, yaw)
    r, lat = map_pose(m, pose)
    assert isinstance(r, gtsam.Pose3)
    ypr = r.rotation().ypr()
    assert ypr[0] == pytest.approx(math.atan2(math.sin(m.yaw_rad), math.cos(m.yaw_rad)), abs=1e-9)
    assert ypr[1] == pytest.approx(pitch, abs=1e-9) and ypr[2] == pytest.approx(roll, abs=1e-9)
    assert (r.x(), r.y(), r.z()) == pytest.approx((m.x_m, m.y_m, z))
    assert lat == pytest.approx(abs(r.between(pose).y()), abs=1e-9)
    if abs(pitch) < 1e-12 and abs(roll) < 1e-12:
        assert lat == pytest.approx(m.lateral_m, abs=1e-9)
    # and as a 4×4 array
    r2, lat2 = map_pose(m, pose.matrix())
    assert np.allclose(r2, r.matrix()) and lat2 == pytest.approx(lat)


def test_map_pose_level_pose_gives_match_lateral():
    road = _grid()
    m = road.match(152.0, 80.0, math.pi / 2)
    pose = np.eye(4)
    pose[:3, 3] = (152.0, 80.0, 0.0)
    _, lat = map_pose(m, pose)
    assert lat == pytest.approx(m.lateral_m, abs=1e-9)
    assert lat == pytest.approx(_perp(road, m.way_id, 152.0, 80.0), abs=0.01)


def test_map_pose_bad_pose():
    m = _grid().match(152.0, 80.0, 0.0)
    with pytest.raises(ValueError, match="pose"):
        map_pose(m, np.eye(3))


# --------------------------------------------------------------------------- stress test


# --------------------------------------------------------------------------- one-way roads (issue 16)
@FIXTURE_OK
@given(heading=angles, gap=st.floats(6.0, 20.0), frac=st.floats(0.0, 1.0), yaw_err=st.floats(-60.0, 60.0),
       reverse_tag=st.booleans(), along=st.floats(50.0, 250.0))
def test_a_dual_carriageway_is_matched_in_the_direction_of_travel(tmp_path, heading, gap, frac, yaw_err,
                                                                  reverse_tag, along):
    """Two one-way carriageways ``gap`` apart, one each way: a vehicle travelling along carriageway 1
    is matched to it wherever it lies between them (the other is nearer for frac > 0.5), and the match
    runs with the traffic. Carriageway 2 is either drawn against 1 (``oneway=yes``) or drawn the same way
    and tagged ``oneway=-1``: both mean traffic against 1's."""
    d = np.array([math.cos(heading), math.sin(heading)])
    n = np.array([-d[1], d[0]])
    r1 = straight_road(300.0, heading)
    r2 = r1 + gap * n if reverse_tag else np.array([r1[1], r1[0]]) + gap * n
    tags2 = {"highway": "primary", "oneway": "-1" if reverse_tag else "yes"}
    road = _road(tmp_path, [(r1, {"highway": "primary", "oneway": "yes"}), (r2, tags2)])
    x, y = along * d + frac * gap * n
    m = road.match(x, y, heading + math.radians(yaw_err), radius=40.0)
    assert m is not None and m.way_id == 1 and not m.reversed
    assert abs(angle_deg(m.yaw_rad, heading)) < 1.0
    # travelling the other way, the same point belongs to carriageway 2, whose legal heading is opposite
    m2 = road.match(x, y, heading + math.pi + math.radians(yaw_err), radius=40.0)
    assert m2 is not None and m2.way_id == 2 and m2.reversed == reverse_tag  # (against its drawing only if -1)
    assert abs(angle_deg(m2.yaw_rad, heading + math.pi)) < 1.0


def test_no_match_runs_against_a_one_way_road(helsinki):
    """On a real city, single and batch matches of random poses always take a one-way road in its
    legal direction (and a match's angle is then up to 180°, not folded to 90°)."""
    rng = np.random.default_rng(11)
    n = 2000
    i = rng.integers(0, len(helsinki), n)
    x = helsinki.xy_m[i, 0] + rng.normal(0, 6, n)
    y = helsinki.xy_m[i, 1] + rng.normal(0, 6, n)
    yaw = rng.uniform(-math.pi, math.pi, n)
    out = helsinki.match_many(x, y, yaw, 30.0)
    assert (helsinki.travel != 0).mean() > 0.2  # the test means something: Helsinki has many one-way roads
    checked = 0
    for j in range(n):
        m = helsinki.match(x[j], y[j], yaw[j], 30.0)
        if m is None:
            continue
        assert out["reversed"][j] == m.reversed or out["index"][j] != m.index
        t = helsinki.travel[m.index]
        if t != 0:
            checked += 1
            assert m.reversed == (t < 0)
            assert abs(angle_deg(m.yaw_rad, yaw[j]) - m.angle_deg) < 1e-6
    assert checked > 200


@pytest.mark.parametrize("tags, highway, roundabout, want", [
    ({"oneway": "yes"}, "residential", False, 1), ({"oneway": "-1"}, "residential", False, -1),
    ({"oneway": "reversible"}, "primary", False, 0), ({"oneway": "no"}, "motorway", False, 0),
    ({}, "motorway", False, 1), ({}, "primary", True, 1), ({}, "primary", False, 0), ({"oneway": "1"}, "primary", False, 1),
])
def test_the_legal_direction_of_travel_follows_the_osm_tags(tags, highway, roundabout, want):
    from mapfusion.osm import travel_direction

    assert travel_direction(tags, highway, roundabout) == want
