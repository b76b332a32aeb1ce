"""mapfusion bench: every benchmark line carries the anchor measured in the same run and its ratio."""

from __future__ import annotations

import collections
import math
import tempfile

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapfusion import RoadMap
from mapfusion.config import FusionConfig
from mapfusion.harness import bench
from mapfusion.harness.bench import run_benchmarks
from mapfusion.roadmap import can_drive
from tests.helpers import MAPS


def _median(xs):
    xs = sorted(xs)
    n = len(xs)
    return xs[n // 2] if n % 2 else 0.5 * (xs[n // 2 - 1] + xs[n // 2])


@pytest.mark.slow
def test_bench_lines_carry_their_anchors_and_ratios(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    rows = {r["benchmark"]: r for r in run_benchmarks(duration_s=300.0, city_km=(2.0, 2.0), repeats=3)}
    assert list(tmp_path.iterdir()) == []  # its synthetic city's files are not left behind
    assert set(rows) == {"roadmap_build", "engine", "matcher", "relocalise"}
    rel = rows["relocalise"]
    assert rel["particles"] > 0 and math.isclose(rel["realtime_factor"], rel["drive_s"] / rel["compute_s"])
    eng = rows["engine"]
    assert eng["map_priors"] > 0  # the drive exercises the map
    # growth over the drive after its GPS (300 s: 170 s of it) as well as over the whole drive
    assert math.isfinite(eng["growth_after_gps"]) and eng["growth_after_gps"] > 0
    # each round's ratio is to the anchor measured beside it; the line gives their median
    r = eng["rounds"]
    assert len(r["ratio_to_bare"]) == 3
    for fps, bare, ratio in zip(r["frames_per_s"], r["bare_chain_frames_per_s"], r["ratio_to_bare"]):
        assert math.isclose(ratio, fps / bare)
    assert math.isclose(eng["ratio_to_bare"], _median(r["ratio_to_bare"]))
    assert math.isclose(eng["frames_per_s"], _median(r["frames_per_s"]))
    # the floor: GTSAM's updates and the road fixes' particles are part of every engine frame's time, so no round's
    # ratio exceeds the bound they leave (a timing that missed them would leave an infinite or a lower bound)
    for line in (eng,):
        rr = line["rounds"]
        assert all(u > 0 for u in rr["gtsam_update_us_per_frame"]) and all(p > 0 for p in rr["road_fixes_us_per_frame"])
        for ratio, bound in zip(rr["ratio_to_bare"], rr["ratio_to_bare_at_most"]):
            assert ratio <= bound
        for bare, u, p, bound in zip(r["bare_chain_frames_per_s"], rr["gtsam_update_us_per_frame"],
                                     rr["road_fixes_us_per_frame"], rr["ratio_to_bare_at_most"]):
            assert math.isclose(bound, 1e6 / bare / (u + p))
        assert math.isclose(line["ratio_to_bare_at_most"], _median(rr["ratio_to_bare_at_most"]))
    m = rows["matcher"]
    ratios = [s / k for s, k in zip(m["rounds"]["single_matches_per_s"], m["rounds"]["kdtree_queries_per_s"])]
    assert math.isclose(m["single_ratio_to_kdtree"], _median(ratios))
    assert 0.0 < m["batch_first_pass_settled"] <= 1.0


def test_the_engine_lines_measure_the_configuration_given(monkeypatch):
    """``mapfusion bench --config``: the engine line runs the configuration given: without road fixes no frame
    spends time in their particles."""
    seen = []
    real = bench.bench_engine

    def spy(road, **kw):
        seen.append(kw["config"])
        return real(road, **kw)

    monkeypatch.setattr(bench, "bench_engine", spy)
    rows = run_benchmarks(duration_s=150.0, city_km=(1.0, 1.0), repeats=1, config=FusionConfig(road_fixes=False))
    got = {r["benchmark"]: r for r in (next(rows), next(rows))}
    assert [c.road_fixes for c in seen] == [False]
    assert got["engine"]["road_fixes_us_per_frame"] == 0.0 and got["engine"]["gtsam_update_us_per_frame"] > 0


@pytest.fixture(scope="module", params=["synthetic/grid.osm", "helsinki.osm.pbf"])
def one_way_map(request):
    """A map with one-way streets: the synthetic grid's every other street, a real city's."""
    return RoadMap.from_osm(MAPS / request.param)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_the_benchmark_drive_keeps_to_one_way_streets(one_way_map, seed):
    """The engine benchmark's drive drives every edge the way its tags allow, each from the vertex the one before
    it reached: a drive against a one-way street is one no road particle may follow, and measured the engine on
    a failure of its own benchmark (the bundled Helsinki map's drive went the wrong way 2 km in)."""
    road = one_way_map
    states = bench.route_states(road, 3000.0, seed)
    assert sum(road.edge_length_m[s // 2] for s in states) >= 3000.0
    ends = []
    for s in states:
        e, backward = divmod(s, 2)
        start, end = (int(road.edge_v[e]), int(road.edge_u[e])) if backward else \
            (int(road.edge_u[e]), int(road.edge_v[e]))
        assert can_drive(road, e, end)
        if ends:
            assert start == ends[-1]
        ends.append(end)


def test_on_a_map_of_two_way_roads_the_drive_turns_every_way_and_back_only_at_dead_ends():
    """Where every road is two-way (the engine benchmark's synthetic city) a 20 km drive goes straight on, turns
    left and turns right at junctions, and drives back along its own edge only where no other road leaves."""
    from mapfusion import synthetic

    with tempfile.TemporaryDirectory() as d:
        road = RoadMap.from_osm(synthetic.write("city", f"{d}/city.osm", width_km=1.0, height_km=1.0))
    degree = collections.Counter(road.edge_u.tolist() + road.edge_v.tolist())
    states = bench.route_states(road, 20000.0, 0)
    turns: collections.Counter = collections.Counter()

    def heading(state: int, at_end: bool) -> float:
        e, backward = divmod(state, 2)
        i = road.edge_end[e] - 2 if at_end != bool(backward) else road.edge_start[e]
        return float(road.yaw_rad[i]) + math.pi * backward

    for a, b in zip(states, states[1:]):
        if a // 2 == b // 2:
            vertex = int(road.edge_u[a // 2] if a % 2 else road.edge_v[a // 2])
            assert degree[vertex] == 1  # back along its own edge: a dead end
            turns["back"] += 1
            continue
        d = math.degrees(math.remainder(heading(b, False) - heading(a, True), 2 * math.pi))
        turns["straight" if abs(d) < 30 else "left" if d > 0 else "right"] += 1
    assert turns["straight"] > 0 and turns["left"] > 0 and turns["right"] > 0, turns


@pytest.mark.slow
def test_the_bench_measures_a_map_given_in_place_of_the_synthetic_city():
    """``mapfusion bench --map helsinki``: every line is measured on the bundled Helsinki map, and says so."""
    rows = {r["benchmark"]: r for r in run_benchmarks(duration_s=200.0, repeats=1, map_path="helsinki")}
    assert set(rows) == {"roadmap_build", "engine", "matcher", "relocalise"}
    assert all(r["map"] == "helsinki" for r in rows.values())
    assert rows["roadmap_build"]["waypoints"] == len(RoadMap.from_osm(MAPS / "helsinki.osm.pbf"))
    assert rows["engine"]["frames"] == 2000 and rows["engine"]["ratio_to_bare"] > 0
