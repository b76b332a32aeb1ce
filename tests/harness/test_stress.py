"""The matcher stress test (``mapfusion maps stress``): junction kinds, pose bounds, rates."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mapfusion import RoadMap
from mapfusion.matcher import angle_deg
from mapfusion.harness.stress import JunctionKind, StressConfig, classify_junctions, run_stress, stress_poses
from tests.helpers import DATA, MAPS, data_required


def test_stress_classifies_the_synthetic_junctions():
    kinds = lambda name: set(classify_junctions(RoadMap.from_osm(MAPS / "synthetic" / f"{name}.osm")).values())  # noqa: E731
    assert kinds("roundabout") == {JunctionKind.roundabout}
    assert kinds("y-split") == {JunctionKind.y_split}
    assert JunctionKind.parallel in kinds("parallel")
    assert {JunctionKind.T, JunctionKind.X}.issubset(kinds("grid"))


@pytest.mark.parametrize("name", ["grid", "roundabout", "y-split", "parallel", "helsinki"])
def test_stress_poses_respect_their_bounds(name):
    road = RoadMap.from_osm(MAPS / ("helsinki.osm.pbf" if name == "helsinki" else f"synthetic/{name}.osm"))
    cfg = StressConfig(offset_extra_m=2.0, heading_error_deg=15.0)
    p = stress_poses(road, cfg)
    assert len(p) > 0
    offset = np.hypot(p.x_m - road.xy_m[p.station, 0], p.y_m - road.xy_m[p.station, 1])
    assert np.all(offset <= road.width_m(cfg.lane_width_m)[p.station] + cfg.offset_extra_m + 1e-9)
    assert np.all(angle_deg(p.yaw_rad, p.heading_rad) <= cfg.heading_error_deg + 1e-9)
    assert np.all(p.way_id == road.way_id[p.station])
    # stations lie on the approaches and exits: within the farthest station distance of their junction
    d = np.hypot(*(road.xy_m[p.station] - road.vertex_xy_m[p.vertex]).T)
    assert np.all(d <= max(cfg.distances_m) + 1.0)


@pytest.mark.parametrize("name", ["grid", "roundabout", "y-split", "parallel"])
def test_stress_stations_on_the_centreline_all_match(name):
    # a pose exactly at its station with the road's heading has D = 0 there: it must match its way
    road = RoadMap.from_osm(MAPS / "synthetic" / f"{name}.osm")
    p = stress_poses(road, StressConfig())
    res = road.match_many(road.xy_m[p.station, 0], road.xy_m[p.station, 1], p.heading_rad)
    assert np.all(res["way_id"] == p.way_id)
    assert np.all(res["cost"] <= 1e-5)  # arccos near 1 leaves ~1e-6° of rounding


def test_stress_rates_are_fractions_and_reproducible():
    road = RoadMap.from_osm(MAPS / "synthetic" / "grid.osm")
    a = run_stress(road, StressConfig(seed=1))
    b = run_stress(road, StressConfig(seed=1))
    assert a.to_dict() == b.to_dict()
    assert 0.0 <= a.rate <= 1.0
    assert sum(k.poses for k in a.by_kind) == a.poses
    assert sum(k.junctions for k in a.by_kind) == a.junctions


def test_sequence_stress_json_and_the_sequence_beats_single_frames_at_a_y_split():
    import json

    from typer.testing import CliRunner

    from mapfusion.harness.cli import app

    r = CliRunner().invoke(app, ["maps", "stress", str(MAPS / "synthetic" / "y-split.osm"), "--sequence", "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.output)
    assert {"match_rate", "match_rate_single", "by_kind", "stations"} <= set(d)
    assert d["poses"] > 100 and set(d["by_kind"]) == {"y-split"}
    # the same poses: the filter, started on the entering road, picks the exit road at least as well
    assert d["match_rate"] >= d["match_rate_single"] and d["match_rate"] >= 0.99
    assert d["stations"]["match_rate"] == pytest.approx(run_stress(RoadMap.from_osm(MAPS / "synthetic" / "y-split.osm")).rate)


def test_stress_drives_keep_to_one_way_roads(monkeypatch):
    """The grid's one-way streets and the roundabout's ring are driven only their legal way: no station
    pose heads against one, and the sequence stress of the grid scores fewer drives than it would if
    every road could be driven both ways."""
    from mapfusion.harness import stress

    for name in ("grid", "roundabout"):
        road = RoadMap.from_osm(MAPS / "synthetic" / f"{name}.osm")
        poses = stress_poses(road)
        t = road.travel[poses.station]
        legal_heading = road.yaw_rad[poses.station] + np.where(t < 0, np.pi, 0.0)
        one_way = t != 0
        assert one_way.sum() > 50
        assert np.all(np.abs(angle_deg(poses.heading_rad[one_way], legal_heading[one_way])) < 1.0)
    grid = RoadMap.from_osm(MAPS / "synthetic" / "grid.osm")
    legal = sum(k.drives for k in stress.run_sequence_stress(grid).by_kind)
    monkeypatch.setattr(stress, "can_drive", lambda road, edge, to_vertex: True)
    every = sum(k.drives for k in stress.run_sequence_stress(grid).by_kind)
    assert 0 < legal < every


OSM = Path(DATA) / "osm" if DATA else None
needs_osm = data_required("osm")


def _sequence_rates(path: Path, seed: int) -> tuple[float, float]:
    from mapfusion.harness.stress import run_sequence_stress

    r = run_sequence_stress(RoadMap.from_osm(path), StressConfig(seed=seed))
    return r.rate, r.rate_single


# Issue 16: the sequence matches ≥ 99% of the junction drives' poses to their way. Seed 0 is the command's
# default; 5 was not among the seeds (0–3) the filter's scales were chosen on.
@pytest.mark.parametrize("seed", [0, 5])
@pytest.mark.parametrize("name", ["y-split", "roundabout", "parallel", "grid"])
def test_the_sequence_matches_99_percent_on_every_synthetic_junction_map(name, seed):
    rate, single = _sequence_rates(MAPS / "synthetic" / f"{name}.osm", seed)
    assert rate >= 0.99 and rate >= single


@needs_osm
@pytest.mark.parametrize("seed", [0, 5])
def test_the_sequence_matches_99_percent_at_the_grosser_stern(seed):
    """Berlin's Großer Stern: a five-way roundabout of one-way six-lane edges with slip roads."""
    rate, single = _sequence_rates(OSM / "berlin-siegessaeule.osm.gz", seed)
    assert rate >= 0.99 and rate > single


@pytest.mark.full
@needs_osm
def test_the_sequence_matches_99_percent_in_north_bayreuth():
    """97,000 poses through 1,700 drives (about a minute): with the larger scenario set."""
    rate, single = _sequence_rates(OSM / "north-bayreuth.osm.gz", 0)
    assert rate >= 0.99 and rate > single
