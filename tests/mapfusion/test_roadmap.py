"""The processed road map: graph, way-points, flags, spatial index, cache and bad input."""

from __future__ import annotations

import gzip
import math
import shutil

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapfusion import MapContentError, MapFileError, RoadMap, RoadMapConfig
from mapfusion.osm import parse_lanes
from tests.helpers import MAPS, circle_road, polylines, straight_road, write_osm

ORIGIN = (60.2, 24.9)


def _road(tmp_path, roads, **cfg):
    path = write_osm(tmp_path, roads, origin=ORIGIN)
    return RoadMap.from_osm(path, RoadMapConfig(origin_lat_deg=ORIGIN[0], origin_lon_deg=ORIGIN[1], **cfg), cache=False)


@settings(suppress_health_check=[HealthCheck.function_scoped_fixture], max_examples=25)
@given(poly=polylines(max_turn_deg=120.0), direction=st.floats(0, 2 * math.pi))
def test_every_waypoint_found_from_half_a_metre(tmp_path, poly, direction):
    road = _road(tmp_path, [(poly, {"highway": "residential"})])
    d = 0.5 * np.array([math.cos(direction), math.sin(direction)])
    for i, p in enumerate(road.xy_m):
        found = road.query_radius(p[0] + d[0], p[1] + d[1], 0.5 + 1e-6)
        assert i in found


def test_query_radius_matches_brute_force(helsinki):
    rng = np.random.default_rng(3)
    lo, hi = road_bounds = helsinki.xy_m.min(0), helsinki.xy_m.max(0)
    for _ in range(50):
        q = rng.uniform(lo, hi)
        r = rng.uniform(1.0, 40.0)
        got = np.sort(helsinki.query_radius(q[0], q[1], r))
        want = np.flatnonzero(np.hypot(*(helsinki.xy_m - q).T) <= r)
        assert np.array_equal(got, want)
    assert road_bounds


def test_graph_of_a_crossroads(tmp_path):
    ew = np.array([[-200.0, 0.0], [0.0, 0.0], [200.0, 0.0]])
    ns = np.array([[0.0, -200.0], [0.0, 0.0], [0.0, 200.0]])
    road = _road(tmp_path, [(ew, {"highway": "primary", "lanes": "2"}), (ns, {"highway": "residential"})])
    assert len(road.edge_u) == 4  # both ways split at the shared node
    assert np.sum(road.vertex_degree >= 3) == 1 and road.vertex_degree.max() == 4
    centre = road.vertex_xy_m[np.argmax(road.vertex_degree)]
    assert np.allclose(centre, (0.0, 0.0), atol=0.02)
    # four right-angle turns get a rounded join each; straight-on gets none
    assert road.is_join.any()
    join_yaw = road.yaw_rad[road.is_join]
    assert np.any(np.abs(np.sin(2 * join_yaw)) > 0.5)  # diagonal headings inside the turns
    # width = lanes × lane width, lanes missing → 1
    w = {int(road.way_ids[i]): road.way_lanes[i] for i in range(len(road.ways))}
    assert sorted(w.values()) == [1, 2]
    assert set(np.unique(road.width_m(3.0))) == {3.0, 6.0}
    assert set(np.unique(road.width_m(2.5))) == {2.5, 5.0}  # the lane width applies at match time


def test_heading_is_towards_next_waypoint(tmp_path):
    road = _road(tmp_path, [(straight_road(300.0, math.radians(30)), {"highway": "primary"})])
    assert np.allclose(road.yaw_rad, math.radians(30), atol=math.radians(0.05))


def test_circle_road_is_smooth_and_on_the_circle(tmp_path):
    # a 360-gon: its own corners turn 1°, so the map's headings can be held to the true tangent
    road = _road(tmp_path, [(circle_road(100.0, n=360), {"highway": "primary", "junction": "roundabout"})])
    r = np.hypot(*road.xy_m.T)
    assert np.all(np.abs(r - 100.0) < 0.3)
    assert road.way(road.way_ids[0]).oneway  # roundabouts are implied oneway
    tangent = np.arctan2(road.xy_m[:, 1], road.xy_m[:, 0]) + math.pi / 2
    err = np.degrees(np.abs(np.angle(np.exp(1j * (road.yaw_rad - tangent)))))
    assert np.all(err[:-1] < 1.0), err.max()


def test_flags_and_lane_overrides(tmp_path):
    roads = [
        (straight_road(200.0), {"highway": "primary", "tunnel": "yes", "layer": "-1", "lanes": "2;3"}),
        (straight_road(200.0, origin=(0, 50)), {"highway": "secondary", "bridge": "yes", "layer": "1", "oneway": "yes"}),
        (straight_road(200.0, origin=(0, 100)), {"highway": "footway"}),
        (straight_road(200.0, origin=(0, 150)), {"highway": "service", "covered": "yes"}),
    ]
    road = _road(tmp_path, roads, lane_overrides=((2, 6),))
    assert len(road.ways) == 3  # the footway is not drivable
    w1, w2, w4 = road.way(1), road.way(2), road.way(4)
    assert w1.tunnel and w1.layer == -1 and w1.lanes == 2 and not w1.oneway
    assert w2.bridge and w2.layer == 1 and w2.oneway and w2.lanes == 6 and not w2.lanes_tagged
    assert w4.tunnel
    assert road.stats().tunnel_km == pytest.approx(0.4, abs=0.01)
    assert not road.has_way(3)


@pytest.mark.parametrize("value,expected", [("2", 2), ("2;3", 2), (" 4 ", 4), ("x", None), ("", None), ("0", None), ("1.0", 1)])
def test_parse_lanes(value, expected):
    assert parse_lanes(value) == expected


# --------------------------------------------------------------------------- real Helsinki map
def test_helsinki_counts_are_plausible(helsinki):
    s = helsinki.stats()
    assert 500 <= s.ways <= 3000
    assert 100 <= s.junctions <= 1000
    assert 20.0 <= s.road_km <= 80.0
    assert 0.0 < s.tunnel_km < s.road_km
    assert abs(s.mean_spacing_m - 1.0) < 0.05
    # a centre extract about 1 km × 1.6 km around the origin
    span = helsinki.xy_m.max(0) - helsinki.xy_m.min(0)
    assert 500 < span[0] < 2000 and 1000 < span[1] < 2500


def test_helsinki_named_street_where_it_is(helsinki):
    # Pohjoisesplanadi runs along the north side of the Esplanadi park, about 60.1680 N between
    # 24.944 E and 24.953 E (city map); Mannerheimintie runs north-west from the Esplanadi.
    ways = helsinki.ways_named("Pohjoisesplanadi")
    assert ways
    idx = np.concatenate([helsinki.waypoints_of_way(w.way_id) for w in ways])
    lat, lon = helsinki.projection.to_geo(helsinki.xy_m[idx, 0], helsinki.xy_m[idx, 1])
    assert np.all((lat > 60.1665) & (lat < 60.1695))
    assert np.all((lon > 24.940) & (lon < 24.956))
    # and a radius query at its middle finds it
    x, y = helsinki.projection.to_enu(60.1679, 24.9485)
    near = helsinki.query_radius(x, y, 30.0)
    assert any(helsinki.ways[helsinki.way_index[i]].name == "Pohjoisesplanadi" for i in near)


def test_kotka_builds():
    road = RoadMap.from_osm(MAPS / "kotka.osm.pbf")
    s = road.stats()
    assert s.ways > 100 and s.junctions > 50 and s.road_km > 20


# --------------------------------------------------------------------------- cache
def test_cache_round_trip_and_keying(tmp_path):
    path = write_osm(tmp_path, [(straight_road(300.0), {"highway": "primary"})])
    cache = tmp_path / "cache"
    a = RoadMap.from_osm(path, cache_dir=cache)
    b = RoadMap.from_osm(path, cache_dir=cache)
    assert not a.from_cache and b.from_cache
    assert np.array_equal(a.xy_m, b.xy_m) and a.ways == b.ways
    c = RoadMap.from_osm(path, RoadMapConfig(spacing_m=2.0), cache_dir=cache)
    assert not c.from_cache and len(c) < len(a)
    assert len(list(cache.glob("*.npz"))) == 2
    # a corrupt cache file is rebuilt, not trusted
    for f in cache.glob("*.npz"):
        f.write_bytes(b"garbage")
    d = RoadMap.from_osm(path, cache_dir=cache)
    assert not d.from_cache and np.array_equal(d.xy_m, a.xy_m)


def test_compressed_formats(tmp_path):
    src = write_osm(tmp_path, [(straight_road(300.0), {"highway": "primary"})])
    gz = tmp_path / "map.osm.gz"
    with open(src, "rb") as fi, gzip.open(gz, "wb") as fo:
        shutil.copyfileobj(fi, fo)
    assert len(RoadMap.from_osm(gz, cache=False)) == len(RoadMap.from_osm(src, cache=False))


# --------------------------------------------------------------------------- bad input
def test_missing_file(tmp_path):
    with pytest.raises(MapFileError, match="no such file"):
        RoadMap.from_osm(tmp_path / "nope.osm")


def test_not_osm(tmp_path):
    p = tmp_path / "notes.osm"
    p.write_text("this is not xml at all\n")
    with pytest.raises(MapFileError, match="notes.osm"):
        RoadMap.from_osm(p, cache=False)


def test_truncated_xml(tmp_path):
    src = write_osm(tmp_path, [(straight_road(300.0), {"highway": "primary"})])
    p = tmp_path / "cut.osm"
    p.write_bytes(src.read_bytes()[: len(src.read_bytes()) // 2])
    with pytest.raises(MapFileError, match="cut.osm"):
        RoadMap.from_osm(p, cache=False)


def test_truncated_pbf(tmp_path):
    data = (MAPS / "helsinki.osm.pbf").read_bytes()
    p = tmp_path / "cut.osm.pbf"
    p.write_bytes(data[: len(data) // 3])
    with pytest.raises(MapFileError, match="cut.osm.pbf"):
        RoadMap.from_osm(p, cache=False)


def _frames_of(exc: BaseException | None):
    while exc is not None:
        tb = exc.__traceback__
        while tb is not None:
            yield tb.tb_frame
            tb = tb.tb_next
        exc = exc.__cause__ or exc.__context__


def test_an_unreadable_file_leaves_no_osmium_frame_alive(tmp_path):
    # osmium's frames hold its reader thread pool: kept alive in an exception (a CLI test keeps its result's
    # exc_info), the pool would be destroyed later, in a forked run worker without its threads, and hang it
    p = tmp_path / "t.osm.pbf"
    p.write_bytes(b"PBF")
    with pytest.raises(MapFileError, match="not a readable OSM file") as info:
        RoadMap.from_osm(p, cache=False)
    assert [f.f_code.co_filename for f in _frames_of(info.value) if "osmium" in f.f_code.co_filename] == []


def test_no_drivable_road(tmp_path):
    p = write_osm(tmp_path, [(straight_road(300.0), {"highway": "footway"})])
    with pytest.raises(MapContentError, match="no drivable road"):
        RoadMap.from_osm(p, cache=False)


def test_bad_config():
    with pytest.raises(ValueError, match="spacing_m"):
        RoadMapConfig(spacing_m=0.0)
    with pytest.raises(ValueError, match="origin"):
        RoadMapConfig(origin_lat_deg=60.0)
