"""SUMO drives on real networks (real SUMO, no mocks): frames, kinematics, determinism, tunnels."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapfusion import RoadMap
from mapfusion.geometry import point_segment_distance
from sim.drive import run_drive
from sim.network import RouteError, build_network, run_netconvert
from mapfusion.harness.rundir import write_truth
from sim.scenario import scenario_from_dict
from tests.helpers import MAPS

pytestmark = pytest.mark.sumo


def _scenario(**kw):
    base = {"name": "t", "map": "helsinki", "seed": 1, "duration_s": 300.0, "min_route_m": 1500.0}
    base.update(kw)
    return scenario_from_dict(base, "test")


@pytest.fixture(scope="module")
def helsinki_net():
    return build_network(MAPS / "helsinki.osm.pbf")


@pytest.fixture(scope="module")
def drives(helsinki, helsinki_net):
    return {seed: run_drive(_scenario(seed=seed), helsinki, helsinki_net) for seed in (1, 2, 3)}


def _artefact_free(track, margin_s: float = 1.0) -> np.ndarray:
    """Frames away from SUMO's junction artefacts.

    SUMO advances a vehicle along lane *lengths* that inside junctions can differ from the drawn
    lane shapes several-fold; there its speed and the truth path's speed disagree. Frames within
    ``margin_s`` of such a disagreement (over 10%) are set aside.
    """
    bad = np.abs(track.speed_mps - track.sumo_speed_mps) > 0.1 * np.maximum(track.sumo_speed_mps, 0.5)
    k = int(round(margin_s / np.median(np.diff(track.t_s))))
    near = np.convolve(bad.astype(float), np.ones(2 * k + 1), mode="same") > 0
    return ~near


def test_displacement_over_time_matches_speed(drives):
    for d in drives.values():
        e = d.ego
        step = np.hypot(np.diff(e.x_m), np.diff(e.y_m))
        dt = np.diff(e.t_s)
        v = 0.5 * (e.speed_mps[1:] + e.speed_mps[:-1]) * dt
        # the written speed against the written positions, in every 10 s window while moving
        for i in range(0, len(step) - 100, 50):
            if v[i:i + 100].sum() > 10.0:
                assert step[i:i + 100].sum() == pytest.approx(v[i:i + 100].sum(), rel=0.05)
        # and SUMO's own speed against the distance covered, over the whole drive
        assert step.sum() == pytest.approx(np.sum(e.sumo_speed_mps[1:] * dt), rel=0.05)
        assert step.sum() > 500.0  # it really drove


def test_yaw_follows_direction_of_motion(drives):
    for d in drives.values():
        e = d.ego
        motion = np.arctan2(e.y_m[2:] - e.y_m[:-2], e.x_m[2:] - e.x_m[:-2])
        sel = (e.speed_mps[1:-1] > 2.0) & _artefact_free(e)[1:-1]
        assert sel.sum() > 0.6 * np.sum(e.speed_mps[1:-1] > 2.0)  # not vacuous: most moving frames count
        err = np.degrees(np.abs(np.angle(np.exp(1j * (motion - e.yaw_rad[1:-1])))))
        assert err[sel].max() < 5.0, f"max {err[sel].max():.1f}°"


def test_every_point_within_width_of_its_named_way(drives, helsinki):
    for d in drives.values():
        e = d.ego
        on_way = e.osm_way >= 0
        assert on_way.mean() > 0.6  # most frames are outside junctions
        for w in np.unique(e.osm_way[on_way]):
            pts = helsinki.xy_m[helsinki.waypoints_of_way(int(w))]
            sel = e.osm_way == w
            q = np.column_stack([e.x_m[sel], e.y_m[sel]])
            dist = point_segment_distance(q, pts[:-1], pts[1:]) if len(pts) > 1 else np.hypot(*(q - pts[0]).T)
            limit = helsinki.way(int(w)).lanes * 3.0 + 2.0
            assert dist.max() <= limit, (int(w), float(dist.max()), limit)


def test_same_seed_same_bytes_other_seed_other_route(helsinki, helsinki_net, tmp_path, drives):
    a = write_truth(tmp_path / "a", _scenario(seed=1), run_drive(_scenario(seed=1), helsinki, helsinki_net))
    b = write_truth(tmp_path / "b", _scenario(seed=1), drives[1])
    assert (a / "truth.csv").read_bytes() == (b / "truth.csv").read_bytes()
    assert (a / "truth.tum").read_bytes() == (b / "truth.tum").read_bytes()
    assert drives[1].route_edges != drives[2].route_edges


def test_route_length_and_time(drives):
    for d in drives.values():
        assert d.route_length_m >= 1500.0
        assert np.all(np.diff(d.ego.t_s) > 0)


def test_front_bumper_moved_to_the_centre(helsinki, helsinki_net):
    # standing start: SUMO puts the front bumper at the lane start; the centre is half a
    # length (4.5 m car) behind it, on the edge the car starts on
    d = run_drive(_scenario(seed=4, duration_s=5.0), helsinki, helsinki_net)
    assert d.ego.distance_m[0] == pytest.approx(0.0, abs=0.1)
    assert d.ego.speed_mps[0] < 1.0


def test_geo_conversion_equals_sumo(helsinki_net):
    import libsumo as ls

    from sim.network import ensure_sumo_env

    ensure_sumo_env()
    ls.start(["sumo", "-n", str(helsinki_net.net_path), "--no-step-log", "true", "--no-warnings", "true"])
    try:
        rng = np.random.default_rng(0)
        xs, ys = rng.uniform(0, 1000, 20), rng.uniform(0, 1600, 20)
        lat, lon = helsinki_net.sumo_xy_to_geo(xs, ys)
        for i in range(20):
            lon_s, lat_s = ls.simulation.convertGeo(float(xs[i]), float(ys[i]))
            assert lat[i] == pytest.approx(lat_s, abs=1e-7) and lon[i] == pytest.approx(lon_s, abs=1e-7)
    finally:
        ls.close()


@pytest.mark.slow
def test_background_traffic_slows_the_ego(helsinki, helsinki_net):
    alone = run_drive(_scenario(seed=5, duration_s=200.0), helsinki, helsinki_net)
    busy = run_drive(_scenario(seed=5, duration_s=200.0, traffic={"background_vehicles": 60, "fleet": True}),
                     helsinki, helsinki_net)
    assert busy.vehicles > 1
    assert len(busy.fleet) > 10  # fleet mode records every vehicle
    assert all(len(t) > 0 for t in busy.fleet.values())
    # the same route, but other cars: the ego cannot drive faster than alone
    assert busy.route_edges == alone.route_edges
    assert busy.ego.distance_m[-1] <= alone.ego.distance_m[-1] + 1.0


# ----------------------------------------------------------------------------- tunnels
def test_in_tunnel_exactly_on_the_tunnel_section():
    road = RoadMap.from_osm(MAPS / "synthetic" / "tunnel.osm")
    sc = scenario_from_dict({"name": "tun", "map": "tunnel", "seed": 1, "duration_s": 400.0,
                             "route": {"edges": ["1", "3"]}}, "test")
    d = run_drive(sc, road)
    e = d.ego
    tunnel_way = next(w.way_id for w in road.ways if w.tunnel)
    on = e.osm_way == tunnel_way
    assert on.sum() > 100
    assert np.all(e.in_tunnel[on])
    assert not np.any(e.in_tunnel[(e.osm_way >= 0) & ~on])
    # and in space: every frame flagged in a tunnel lies on the tunnel's road
    pts = road.xy_m[road.waypoints_of_way(tunnel_way)]
    flagged = np.column_stack([e.x_m[e.in_tunnel], e.y_m[e.in_tunnel]])
    assert point_segment_distance(flagged, pts[:-1], pts[1:]).max() < 10.0


def test_tunnel_zones_by_distance(helsinki, helsinki_net):
    sc = _scenario(seed=2, tunnels=[{"start_m": 300.0, "end_m": 600.0}])
    e = run_drive(sc, helsinki, helsinki_net).ego
    in_zone = (e.distance_m >= 300.0) & (e.distance_m <= 600.0)
    assert np.all(e.in_tunnel[in_zone])
    osm_tunnel = np.array([helsinki_net.edges[s].tunnel if s in helsinki_net.edges else False for s in e.sumo_edge])
    assert not np.any(e.in_tunnel & ~in_zone & ~osm_tunnel & np.array([not s.startswith(":") for s in e.sumo_edge]))


# ----------------------------------------------------------------------------- network and bad input
def test_network_edges_trace_to_osm_ways(helsinki_net, helsinki):
    ways = [w for e in helsinki_net.edges.values() for w in e.osm_ways]
    assert len(helsinki_net.edges) > 500
    assert all(e.osm_ways for e in helsinki_net.edges.values())
    assert np.mean([helsinki.has_way(w) for w in ways]) > 0.99
    assert any(e.tunnel for e in helsinki_net.edges.values())


def test_network_is_cached(tmp_path):
    a = build_network(MAPS / "synthetic" / "grid.osm", cache_dir=tmp_path)
    mtime = a.net_path.stat().st_mtime_ns
    b = build_network(MAPS / "synthetic" / "grid.osm", cache_dir=tmp_path)
    assert b.net_path == a.net_path and b.net_path.stat().st_mtime_ns == mtime


def test_netconvert_finds_proj_data(tmp_path):
    p = run_netconvert(["--osm-files", str(MAPS / "synthetic" / "grid.osm"), "-o", str(tmp_path / "n.net.xml")])
    assert p.returncode == 0
    assert "proj.db" not in p.stderr + p.stdout


def test_unknown_route_edge(helsinki, helsinki_net):
    with pytest.raises(RouteError, match="unknown SUMO edge"):
        run_drive(_scenario(route={"edges": ["no-such-edge"]}), helsinki, helsinki_net)


def test_route_too_long_for_the_map():
    road = RoadMap.from_osm(MAPS / "synthetic" / "y-split.osm")
    sc = scenario_from_dict({"name": "y", "map": "y-split", "min_route_m": 150000.0, "route": {"max_trips": 5}}, "test")
    with pytest.raises(RouteError, match="no route"):
        run_drive(sc, road)


def test_heading_is_enu_not_sumo_grid():
    # Helsinki lies 2° west of UTM zone 35's central meridian: SUMO's grid north is rotated by
    # about 1.8° there. A straight east-west road must still come out at yaw 0 or π in ENU.
    road = RoadMap.from_osm(MAPS / "synthetic" / "y-split.osm")
    sc = scenario_from_dict({"name": "y", "map": "y-split", "duration_s": 120.0, "route": {"edges": ["1#0", "1#3"]}}, "test")
    e = run_drive(sc, road).ego
    main = road.ways_named("Main Road")[0].way_id
    sel = (e.osm_way == main) & (e.speed_mps > 2.0)
    assert sel.sum() > 50
    off = np.degrees(np.abs(np.sin(e.yaw_rad[sel])))
    assert off.max() < 0.5, off.max()
    assert math.isfinite(float(e.yaw_rad.sum()))


def test_route_via_tunnel_passes_a_tunnel(helsinki, helsinki_net):
    # Helsinki's SUMO network has two short tunnel edges; random routes of these seeds miss them
    tunnels = {e for e, info in helsinki_net.edges.items() if info.tunnel}
    for via in (False, True):
        sc = _scenario(seed=1, duration_s=600.0, route={"via_tunnel": via, "tunnel_after_m": 300.0})
        d = run_drive(sc, helsinki, helsinki_net)
        assert bool(tunnels & set(d.route_edges)) == via
        assert d.ego.in_tunnel.any() == via
        assert d.route_length_m >= sc.min_route_m
    grid = RoadMap.from_osm(MAPS / "synthetic" / "grid.osm")
    sc = scenario_from_dict({"name": "g", "map": "grid", "route": {"via_tunnel": True}}, "test")
    with pytest.raises(RouteError, match="no tunnel"):
        run_drive(sc, grid)
