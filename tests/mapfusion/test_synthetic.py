"""Synthetic OSM maps: valid, tagged as promised, shaped as promised, reproducible to the byte."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapfusion import InputError, RoadMap, RoadMapConfig, synthetic
from mapfusion.geometry import wrap_angle
from tests.helpers import MAPS


@pytest.mark.parametrize("kind", [k.value for k in synthetic.SMALL_KINDS])
def test_committed_maps_regenerate_byte_identically(kind):
    committed = (MAPS / "synthetic" / f"{kind}.osm").read_bytes()
    assert synthetic.generate(kind).encode("utf-8") == committed


def _map(tmp_path, kind, **params):
    path = synthetic.write(kind, tmp_path / f"{kind}.osm", **params)
    return RoadMap.from_osm(path, RoadMapConfig(origin_lat_deg=synthetic.DEFAULT_ORIGIN[0],
                                                origin_lon_deg=synthetic.DEFAULT_ORIGIN[1]), cache=False)


def _way_dir(road, way):
    idx = road.waypoints_of_way(way.way_id)
    p = road.xy_m[idx]
    return math.atan2(p[-1, 1] - p[0, 1], p[-1, 0] - p[0, 0])


def test_grid_has_a_diagonal_avenue_and_mixed_junctions(tmp_path):
    road = _map(tmp_path, "grid")
    diag = road.ways_named("Diagonal Avenue")
    assert len(diag) == 1 and diag[0].highway == "primary" and diag[0].lanes == 4
    angle = math.degrees(_way_dir(road, diag[0]))
    assert 20 < angle < 70
    degrees = set(road.vertex_degree.tolist())
    assert {3, 4}.issubset(degrees) and max(degrees) >= 5  # T, X and where the diagonal crosses
    assert any(w.oneway for w in road.ways)


def test_roundabout_ring(tmp_path):
    road = _map(tmp_path, "roundabout")
    ring = [w for w in road.ways if w.roundabout]
    assert len(ring) == 1 and ring[0].oneway
    idx = road.waypoints_of_way(ring[0].way_id)
    r = np.hypot(*road.xy_m[idx].T)
    assert np.all(np.abs(r - 25.0) < 1.0)
    assert np.sum(road.vertex_degree >= 3) == 4


def test_y_split_branch_angles(tmp_path):
    road = _map(tmp_path, "y-split")
    main = road.ways_named("Main Road")[0]
    main_dir = _way_dir(road, main)
    angles = sorted(abs(math.degrees(wrap_angle(_way_dir(road, w) - main_dir))) for w in road.ways if w.name.startswith("Branch"))
    assert len(angles) == 3
    assert all(15.0 - 0.5 <= a <= 30.0 + 0.5 for a in angles), angles


def test_parallel_service_road(tmp_path):
    road = _map(tmp_path, "parallel")
    primary = road.ways_named("Harbour Road")[0]
    service = road.ways_named("Harbour Service Road")[0]
    assert primary.highway == "primary" and service.highway == "service"
    ps = road.xy_m[road.waypoints_of_way(primary.way_id)]
    ss = road.xy_m[road.waypoints_of_way(service.way_id)]
    # distance of each service way-point to the primary road
    from scipy.spatial import cKDTree

    d, _ = cKDTree(ps).query(ss)
    interior = ss[(ss[:, 0] > ss[:, 0].min() + 10) & (ss[:, 0] < ss[:, 0].max() - 10)]
    di, _ = cKDTree(ps).query(interior)
    assert np.all((di >= 6.0) & (di <= 10.0))
    assert ss[:, 0].max() - ss[:, 0].min() >= 500.0 - 1.0
    assert d.max() <= 10.0


def test_parallel_offset_validated():
    with pytest.raises(InputError, match="6–10"):
        synthetic.generate("parallel", offset_m=20.0)


def test_tunnel_section_with_bend(tmp_path):
    road = _map(tmp_path, "tunnel")
    tunnel_ways = [w for w in road.ways if w.tunnel]
    assert len(tunnel_ways) == 1 and tunnel_ways[0].layer == -1
    idx = road.waypoints_of_way(tunnel_ways[0].way_id)
    length = road.edge_length_m[np.unique(road.edge[idx])].sum()
    assert length >= 600.0
    yaw = np.unwrap(road.yaw_rad[idx])
    assert math.degrees(yaw.max() - yaw.min()) > 20.0  # a bend inside the tunnel
    assert any(w.bridge and w.layer == 1 for w in road.ways)
    # the street over the tunnel is not connected to it
    hill = {w.way_id for w in road.ways if w.name == "Hill Street"}
    tunnel_edges = set(np.unique(road.edge[idx]).tolist())
    hill_vertices = {int(v) for e in range(len(road.edge_u)) if int(road.ways[road.edge_way_index[e]].way_id) in hill
                     for v in (road.edge_u[e], road.edge_v[e])}
    tunnel_vertices = {int(v) for e in tunnel_edges for v in (road.edge_u[e], road.edge_v[e])}
    assert not hill_vertices & tunnel_vertices


def test_tunnel_length_validated():
    with pytest.raises(InputError, match="600"):
        synthetic.generate("tunnel", tunnel_m=300.0)


def test_city_size(tmp_path):
    road = _map(tmp_path, "city", width_km=2.0, height_km=3.0, block_m=200.0)
    span = road.xy_m.max(0) - road.xy_m.min(0)
    assert span[0] == pytest.approx(2000.0, abs=1.0) and span[1] == pytest.approx(3000.0, abs=1.0)
    assert road.stats().junctions >= 100
    with pytest.raises(InputError):
        synthetic.generate("city", width_km=11.0)


def test_generated_maps_carry_real_tags():
    text = "".join(synthetic.generate(k) for k in synthetic.SMALL_KINDS)
    for key in ("highway", "lanes", "oneway", "name", "tunnel", "bridge", "layer"):
        assert f'k="{key}"' in text, key


def test_unknown_kind():
    with pytest.raises(InputError, match="unknown"):
        synthetic.generate("spiral")
