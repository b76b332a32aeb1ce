"""Global re-localisation on the road network (issue 17): particles stay on legal roads, the
posterior is a distribution, and a drive's shape alone finds it in a 1 km region of a real city."""

from __future__ import annotations

import collections
import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from mapfusion import FusionConfig, RoadMap
from mapfusion.config import OutageStep
from mapfusion.relocalise import SEARCH_PARAMS, SEARCH_PARTICLES, Guess, Region, Relocaliser, RoadFollower, RoadParticles, Search, \
    _edge_travel, _median, _weighted_mean_xy, guess_log_weights
from mapfusion.roadmap import can_drive
from tests.helpers import MAPS, drifting_odometry, graph_route, odometry_step, search_params

CFG = FusionConfig()
PARTICLES = SEARCH_PARTICLES
SEARCH = SEARCH_PARAMS


@pytest.fixture(scope="module")
def road():
    return RoadMap.from_osm(MAPS / "helsinki.osm.pbf")


def test_every_exit_is_legal_and_leaves_the_vertex_the_edge_leads_to(road):
    p = RoadParticles(road, PARTICLES)
    ex = p._exits
    for e in range(0, len(road.edge_u), 7):
        for d in (1, -1):
            key = 2 * e + (d < 0)
            vertex = int(road.edge_v[e] if d > 0 else road.edge_u[e])
            for j in range(ex.start[key], ex.start[key + 1]):
                ne, nd = int(ex.edge[j]), int(ex.direction[j])
                assert ne != e
                assert int(road.edge_u[ne] if nd > 0 else road.edge_v[ne]) == vertex  # it starts where e ends
                far = int(road.edge_v[ne] if nd > 0 else road.edge_u[ne])
                assert can_drive(road, ne, far)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), steps=st.integers(1, 30), step_m=st.floats(0.5, 40.0),
       turn=st.floats(-math.pi, math.pi), uturn=st.sampled_from([0.0, 0.1, 1.0]))
def test_particles_stay_on_their_roads_and_the_posterior_sums_to_one(road, seed, steps, step_m, turn, uturn):
    p = RoadParticles(road, dataclasses.replace(PARTICLES, uturn_at_vertex=uturn), seed)
    rng = np.random.default_rng(seed)
    x0, y0 = road.xy_m[int(rng.integers(len(road)))]
    assert p.start(Region(float(x0), float(y0), 300.0), 0.0, n=500) > 0
    for k in range(steps):
        p.step(step_m, np.array([step_m * math.cos(turn * k / steps), step_m * math.sin(turn * k / steps)]))
        assert math.isclose(float(np.exp(p.logw).sum()), 1.0, rel_tol=1e-9)
        assert np.all(p.along >= 0.0) and np.all(p.along <= road.edge_length_m[p.edge] + 1e-9)
        xy = p.positions()
        for i in range(0, len(p), 50):  # each lies on its own edge's polyline (way-points ~1 m apart)
            pts = road.xy_m[road.edge_start[p.edge[i]]:road.edge_end[p.edge[i]]]
            assert np.min(np.hypot(*(pts - xy[i]).T)) <= road.config.spacing_m + 1e-6


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), uturn=st.floats(0.05, 3.0))
def test_turning_back_at_a_vertex_takes_its_prior_share_of_the_posterior(road, seed, uturn):
    """Particles just before the far vertex of a two-way edge drive past it with a target that says nothing (σ huge):
    whichever exits the proposal picks, the importance weights leave turning back its prior share, uturn / (exits +
    uturn), and every legal exit 1 / (exits + uturn)."""
    p = RoadParticles(road, dataclasses.replace(PARTICLES, uturn_at_vertex=uturn), seed)
    rng = np.random.default_rng(seed)
    ex = p._exits
    two_way = [e for e in range(len(road.edge_u)) if p._two_way[e] and ex.start[2 * e + 1] - ex.start[2 * e] >= 1
               and road.edge_length_m[e] > 20.0]
    e = int(two_way[int(rng.integers(len(two_way)))])
    n = 40_000
    exits = int(ex.start[2 * e + 1] - ex.start[2 * e])
    p.edge, p.direction = np.full(n, e), np.ones(n, dtype=np.int64)
    p.along, p.offset, p.log_scale = np.full(n, road.edge_length_m[e] - 1.0), np.zeros(n), np.zeros(n)
    p.logw = np.full(n, -math.log(n))
    p._drive(np.full(n, 5.0), np.zeros((n, 2)), 1e6)
    w = np.exp(p.logw - np.max(p.logw))
    w /= w.sum()
    back = float(w[(p.edge == e) & (p.direction < 0)].sum())
    assert back == pytest.approx(uturn / (exits + uturn), abs=0.02)
    # on a one-way road nothing turns back (but at a dead end, as without the option)
    travel = _edge_travel(road)
    one_way = [f for f in range(len(road.edge_u)) if travel[f] == 1 and ex.start[2 * f + 1] > ex.start[2 * f]]
    f = int(one_way[int(rng.integers(len(one_way)))])
    p.edge, p.direction, p.along = np.full(n, f), np.ones(n, dtype=np.int64), np.full(n, road.edge_length_m[f] - 1.0)
    p.logw = np.full(n, -math.log(n))
    p._drive(np.full(n, 5.0), np.zeros((n, 2)), 1e6)
    assert not np.any((p.edge == f) & (p.direction < 0))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), steps=st.integers(0, 10), r1=st.floats(0.0, 500.0), r2=st.floats(0.0, 500.0),
       dx=st.floats(-400.0, 400.0), dy=st.floats(-400.0, 400.0))
def test_the_mass_within_a_disc_grows_with_it_from_none_to_all(road, seed, steps, r1, r2, dx, dy):
    p = RoadParticles(road, PARTICLES, seed)
    rng = np.random.default_rng(seed)
    x0, y0 = (float(v) for v in road.xy_m[int(rng.integers(len(road)))])
    assert p.mass_within(x0, y0, 100.0) == 0.0  # (no particles yet)
    p.start(Region(x0, y0, 300.0), 0.0, n=500)
    for _ in range(steps):
        p.step(10.0, np.array([10.0, 0.0]))
    cx, cy = x0 + dx, y0 + dy
    lo, hi = sorted((r1, r2))
    assert 0.0 <= p.mass_within(cx, cy, lo) <= p.mass_within(cx, cy, hi) + 1e-12
    assert math.isclose(p.mass_within(cx, cy, 1e7), 1.0, rel_tol=1e-9)
    # outside a second disc (the rival's mass beside an answer): what lies in the first and not the second
    ox, oy = x0 - dy, y0 + dx
    xy, w = p.positions(), np.exp(p.logw)
    first, second = np.hypot(*(xy - [cx, cy]).T) <= hi, np.hypot(*(xy - [ox, oy]).T) <= lo
    assert math.isclose(p.mass_within(cx, cy, hi, (ox, oy, lo)), float(w[first & ~second].sum()), abs_tol=1e-12)
    assert p.mass_within(cx, cy, hi, (ox, oy, lo)) <= p.mass_within(cx, cy, hi) + 1e-12
    assert p.mass_within(cx, cy, hi, (cx, cy, hi)) == 0.0  # (a disc outside itself holds nothing)


def _relocalise(road, seed, length_m, offset_m=300.0, radius_m=1000.0):
    x, y, yaw, _ = graph_route(road, seed, length_m)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, scale=1.02, yaw_drift_rad_per_m=math.radians(1.0) / 100,
                                     heading_rad=1.0, noise_m=0.02)
    a = np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi)
    r = Relocaliser(road, PARTICLES, Region(x[0] + offset_m * math.cos(a), y[0] + offset_m * math.sin(a), radius_m),
                    seed)
    for k in range(len(x)):
        loc = r.add(ox[k], oy[k], oyaw[k])
        if loc is not None:
            return k, math.hypot(loc.x_m - x[k], loc.y_m - y[k]), math.remainder(loc.yaw_rad - yaw[k], 2 * math.pi)
    return None


@pytest.mark.slow
def test_a_drives_shape_finds_it_in_a_1_km_region(road):
    """Legal drives over Helsinki's graph with a 2% scale error and 1°/100 m heading drift, each from a region
    of 1 km radius whose centre lies 300 m from the start: every one found within 1 km of driving, within 10 m
    and 10° (no wrong convergence), and at least 7 of 8 within 500 m (issue 17: ≥ 90% within 500 m)."""
    found = {}
    for seed in range(8):
        got = _relocalise(road, seed, 1000.0)
        assert got is not None, f"seed {seed}: not converged within 1 km"
        driven_m, err_m, yaw_err = got
        assert err_m < 10.0 and abs(math.degrees(yaw_err)) < 10.0, (seed, got)
        found[seed] = driven_m
    assert sum(d <= 500 for d in found.values()) >= 7, found


def test_a_region_without_roads_finds_nothing(road):
    r = Relocaliser(road, PARTICLES, Region(1e6, 1e6, 500.0))
    assert all(r.add(float(k), 0.0, 0.0) is None for k in range(300))
    assert r.way_points_in_region == 0 and len(r.particles) == 0


def test_the_same_seed_gives_the_same_answer(road):
    assert _relocalise(road, 3, 500.0) == _relocalise(road, 3, 500.0)


def _cold_start(road, seed, length_m, cfg, scale=1.0):
    """A cold start on a graph route (10 Hz, 1°/100 m heading drift, the odometry's lengths × ``scale``) from a
    1 km region 300 m off its start: the engine, (frame, error) of its first estimate, the truth's x and y."""
    from mapfusion import MapFusion

    x, y, yaw, _ = graph_route(road, seed, length_m)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, scale=scale, yaw_drift_rad_per_m=math.radians(1.0) / 100,
                                     heading_rad=2.0, noise_m=0.02)
    eng = MapFusion(road, cfg, odometry_rate_hz=10.0)
    a = np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi)
    lat, lon = road.projection.to_geo(x[0] + 300.0 * math.cos(a), y[0] + 300.0 * math.sin(a))
    eng.start_in_region(float(lat), float(lon), 1000.0)
    first = None
    for k in range(len(x)):
        eng.add_odometry(0.1 * k, odometry_step(ox, oy, oyaw, k))
        p = eng.estimate()
        if p is not None and first is None:
            first = (k, math.hypot(p.x() - x[k], p.y() - y[k]))
    eng.finish()
    return eng, first, x, y


@pytest.mark.parametrize("seed", [0, 1])
def test_a_cold_start_without_gps_begins_where_the_vehicle_is(road, seed):
    """MapFusion.start_in_region with no GPS: no estimate until the search converges, then one within 5 m of
    the truth, and the drive tracked on to its end within 25 m (10 m/s, 10 Hz, 1°/100 m heading drift)."""
    eng, first, x, y = _cold_start(road, seed, 1200.0, FusionConfig())
    assert first is not None and eng.counters.map_relocalisations == 1
    assert first[1] < 5.0, first
    assert eng.initialised_at == pytest.approx(0.1 * first[0])
    p = eng.estimate()
    assert math.hypot(p.x() - x[-1], p.y() - y[-1]) < 25.0


@pytest.mark.parametrize("factor,learned,expected", [(2.5, True, 2.5), (0.5, True, 0.5), (2.5, False, 1.0)])
def test_a_cold_start_takes_odometry_sigma_cold_factor_on_its_odometry_sigma(road, factor, learned, expected):
    """A cold start has no GPS window to learn its odometry's σ from: with ``odometry_sigma_learned`` on, its
    odometry factors take ``odometry_sigma_cold_factor`` times the configured σ (off: as configured), from the
    batch of the frames the search drove over on."""
    import gtsam

    from mapfusion import factors

    cfg = FusionConfig(odometry_sigma_cold_factor=factor, odometry_sigma_learned=learned)
    eng, first, _, _ = _cold_start(road, 0, 700.0, cfg)
    assert first is not None and eng.odometry_sigma_factor == expected
    step = gtsam.Pose3(gtsam.Rot3.Yaw(0.01), gtsam.Point3(1.0, 0.0, 0.0))
    plain = factors.odometry_noise(cfg, step, 1.0, 0.1).sigmas()
    between = eng._estimate.between(len(eng.track) - 1, step=step).noiseModel().sigmas()
    # (the planar state's roll, pitch and z hold fixed tiny σ; yaw, x and y carry the odometry's)
    assert np.allclose(between[2:5], expected * plain[2:5]) and np.allclose(between[[0, 1, 5]], plain[[0, 1, 5]])


def test_a_start_region_is_refused_after_the_first_frame_or_when_not_finite(road):
    from mapfusion import MapFusion
    from mapfusion.errors import EngineError

    eng = MapFusion(road, FusionConfig())
    with pytest.raises(EngineError):
        eng.start_in_region(60.17, 24.94, float("nan"))
    with pytest.raises(EngineError):
        eng.start_in_region(60.17, 24.94, 0.0)
    eng.add_odometry(0.0, np.eye(4))
    with pytest.raises(EngineError):
        eng.start_in_region(60.17, 24.94, 500.0)


def test_a_lost_estimate_is_found_again_on_the_road_network(road):
    """GPS at the start puts the estimate 150 m off (a biased fix window, then no GPS): with
    map_relocalisation the engine searches the roads and re-anchors on the truth (since SearchParams.gps_replay_m the
    search begun when GPS falls silent may find it before the estimate is called lost); without it
    (and without road fixes) the estimate stays off. The road fixes alone (the default) also bring it back:
    8.6 m from the truth at the end when measured."""
    from mapfusion import MapFusion

    seed = 2
    x, y, yaw, _ = graph_route(road, seed, 2000.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, heading_rad=0.5, noise_m=0.02)
    n_gps = 400  # 40 s of fixes, all 150 m north-east of the truth

    def run(relocalise: bool, road_fixes: bool = False):
        cfg = FusionConfig(map_relocalisation=relocalise, road_fixes=road_fixes)
        eng = MapFusion(road, cfg, odometry_rate_hz=10.0)
        for k in range(len(x)):
            eng.add_odometry(0.1 * k, odometry_step(ox, oy, oyaw, k))
            if k % 10 == 0 and k < n_gps:
                lat, lon = road.projection.to_geo(x[k] + 106.0, y[k] + 106.0)
                eng.add_gps(0.1 * k, float(lat), float(lon), None, 2.0)
        eng.finish()
        p = eng.estimate()
        return eng, math.hypot(p.x() - x[-1], p.y() - y[-1])

    off, err_off = run(False)
    on, err_on = run(True)
    assert err_off > 50.0  # the bias stays without the search
    assert on.counters.map_relocalisations >= 1
    assert err_on < 15.0, (err_on, on.relocalised_at)
    fixed, err_fixed = run(False, road_fixes=True)
    assert fixed.counters.road_fixes >= 1 and err_fixed < 15.0, err_fixed


def _feed(road, cfg, x, y, ox, oy, oyaw, fixes_until_k: int, fix_offset=(0.0, 0.0), skip=range(0),
          search: dict | None = None):
    """The engine over a drive: odometry every frame but those in ``skip`` (an outage), a fix every 10 frames
    before ``fixes_until_k`` (moved by ``fix_offset``), its search's ``SearchParams`` changed by ``search``;
    returns the engine and its final error."""
    with search_params(**(search or {})):
        return _fed(road, cfg, x, y, ox, oy, oyaw, fixes_until_k, fix_offset, skip)


def _fed(road, cfg, x, y, ox, oy, oyaw, fixes_until_k: int, fix_offset, skip):
    from mapfusion import MapFusion

    eng = MapFusion(road, cfg, odometry_rate_hz=10.0)
    last = None
    for k in range(len(x)):
        if k % 10 == 0 and k < fixes_until_k:
            lat, lon = road.projection.to_geo(x[k] + fix_offset[0], y[k] + fix_offset[1])
            eng.add_gps(0.1 * k, float(lat), float(lon), None, 2.0)
        if k in skip:
            continue
        rel = odometry_step(ox, oy, oyaw, k) if last is None or last == k - 1 else \
            np.linalg.inv(_abs(ox, oy, oyaw, last)) @ _abs(ox, oy, oyaw, k)
        eng.add_odometry(0.1 * k, rel)
        last = k
    eng.finish()
    p = eng.estimate()
    return eng, math.hypot(p.x() - x[-1], p.y() - y[-1])


def _abs(ox, oy, oyaw, k):
    m = np.eye(4)
    m[:2, :2] = [[math.cos(oyaw[k]), -math.sin(oyaw[k])], [math.sin(oyaw[k]), math.cos(oyaw[k])]]
    m[0, 3], m[1, 3] = ox[k], oy[k]
    return m


def _resumed_off(road, seed):
    """A drive whose VO loses track for 8 s after 600 m and resumes 120 m off with a 20° heading error (GPS for
    the first 40 s only): the truth and the broken odometry."""
    x, y, yaw, _ = graph_route(road, seed, 2200.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, heading_rad=0.3, noise_m=0.02)
    k = 681  # the first frame after the outage
    c, s_ = math.cos(math.radians(20.0)), math.sin(math.radians(20.0))
    jx, jy = ox[k:] - ox[k], oy[k:] - oy[k]
    ox, oy, oyaw = ox.copy(), oy.copy(), oyaw.copy()
    ox[k:], oy[k:] = ox[k] + 120.0 + c * jx - s_ * jy, oy[k] + s_ * jx + c * jy
    oyaw[k:] += math.radians(20.0)
    return x, y, ox, oy, oyaw


@pytest.mark.slow
def test_a_vo_that_resumes_in_the_wrong_place_after_an_outage_is_found_again(road):
    """Four drives (Helsinki, GPS long gone when the VO resumes 120 m off): without map_relocalisation (and without
    the road fixes, which also act here) every one ends more than 50 m off; with it the gap starts a search and at
    least 3 of 4 end within 15 m (route 4, which U-turns at a dead end, converged to a place 90 m off when measured:
    the search's open failure)."""
    found = 0
    for seed in (2, 3, 4, 6):
        x, y, ox, oy, oyaw = _resumed_off(road, seed)
        # (the odometry's own step over the gap, as the VO reports it: the engine's own guess would not be off)
        _, err_off = _feed(road, FusionConfig(outage_step=OutageStep.odometry, road_fixes=False), x, y, ox, oy,
                           oyaw, 400, skip=range(601, 681))
        on, err_on = _feed(road, FusionConfig(map_relocalisation=True, outage_step=OutageStep.odometry,
                                              road_fixes=False), x, y, ox, oy, oyaw, 400, skip=range(601, 681))
        assert err_off > 50.0, (seed, err_off)
        found += on.counters.map_relocalisations >= 1 and err_on < 15.0
    assert found >= 3


def test_a_search_after_a_long_fast_outage_covers_where_the_vehicle_went():
    """The synthetic tunnel road at 28 m/s, GPS for the first 15 s, then the VO blind for 25 s (700 m, the tunnel):
    the engine carries its last velocity along the road, so it resumes near the truth; the search begun there must
    cover the truth, though the vehicle drove faster than SearchParams.gap_speed_mps assumes. With a radius from that speed
    alone (measured before the change), the 476 m region missed the truth by 198 m, and the search re-anchored a
    good estimate 1.1 km later on a place ~690 m off, where each drive ended."""
    from mapfusion import MapFusion

    road = RoadMap.from_osm(MAPS / "synthetic" / "tunnel.osm")
    for seed in (1, 2):
        x, y, yaw, _ = graph_route(road, seed, 3000.0, spacing_m=2.8, start_edge=0)
        ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, heading_rad=0.3, noise_m=0.02, spacing_m=2.8)
        eng = MapFusion(road, FusionConfig(map_relocalisation=True, road_fixes=False), odometry_rate_hz=10.0)
        resumed, last, region = 420, None, None
        for k in range(len(x)):
            if k % 2 == 0 and k < 150:
                lat, lon = road.projection.to_geo(x[k], y[k])
                eng.add_gps(0.1 * k, float(lat), float(lon), None, 2.0)
            if 170 <= k < resumed:
                continue
            rel = odometry_step(ox, oy, oyaw, k) if last is None or last == k - 1 else \
                np.linalg.inv(_abs(ox, oy, oyaw, last)) @ _abs(ox, oy, oyaw, k)
            eng.add_odometry(0.1 * k, rel)
            last = k
            if k == resumed:
                assert eng._map_search.search.active is not None
                region = eng._map_search.search.active.region
        assert region is not None
        assert math.hypot(x[resumed] - region.x_m, y[resumed] - region.y_m) < region.radius_m - 50.0, (seed, region)
        eng.finish()
        p = eng.estimate()
        assert math.hypot(p.x() - x[-1], p.y() - y[-1]) < 15.0, seed



def _sped_up_in_the_gap(road, seed: int, gap: range, v_mps: float, v_gap_mps: float):
    """A drive at ``v_mps`` that goes ``v_gap_mps`` through the frames of ``gap`` (10 Hz): truth and odometry."""
    x1, y1, yaw1, _ = graph_route(road, seed, 4000.0, spacing_m=0.5, start_edge=0)
    speed = np.where(np.isin(np.arange(1, 2000), gap), v_gap_mps, v_mps)
    s_m = np.concatenate(([0.0], np.cumsum(0.1 * speed)))
    idx = np.minimum(np.round(s_m / 0.5).astype(int), len(x1) - 1)
    x, y, yaw = x1[idx], y1[idx], yaw1[idx]
    n = int(np.searchsorted(idx, len(x1) - 1))  # (the route's end)
    ox, oy, oyaw = drifting_odometry(x[:n], y[:n], yaw[:n], seed, heading_rad=0.3, noise_m=0.02)
    return x[:n], y[:n], ox, oy, oyaw


def test_a_search_after_a_gap_covers_a_vehicle_that_sped_up_in_it():
    """The synthetic tunnel road at 20 m/s, GPS for the first 20 s, then the VO blind for 25 s in which the vehicle
    drives 26 m/s: the step carried over the gap (the speeds at both ends, 20 m/s) falls 150 m short, so a region
    of the carried step's length alone (100 m + 500 m) misses the truth by ~50 m. SearchParams.gap_reach_sigmas = 1 adds
    the carried step's σ (ParticleParams.sigma_m + outage_step_fraction × 500 m). Rain-tunnel Andorra vo s2 (27 m/s in a
    106 s tunnel carried at 19-25 m/s) is where this was found: its search converged 860 m off."""
    from mapfusion import MapFusion

    road = RoadMap.from_osm(MAPS / "synthetic" / "tunnel.osm")
    lost, resumed = 220, 470
    x, y, ox, oy, oyaw = _sped_up_in_the_gap(road, 1, range(lost, resumed + 1), 20.0, 26.0)
    for sigmas, inside in ((0.0, False), (1.0, True)):
        with search_params(gap_reach_sigmas=sigmas):
            eng = MapFusion(road, FusionConfig(map_relocalisation=True, road_fixes=False), odometry_rate_hz=10.0)
            last, region = None, None
            for k in range(resumed + 1):
                if k % 2 == 0 and k < 200:
                    lat, lon = road.projection.to_geo(x[k], y[k])
                    eng.add_gps(0.1 * k, float(lat), float(lon), None, 2.0)
                if lost <= k < resumed:
                    continue
                rel = odometry_step(ox, oy, oyaw, k) if last is None or last == k - 1 else \
                    np.linalg.inv(_abs(ox, oy, oyaw, last)) @ _abs(ox, oy, oyaw, k)
                eng.add_odometry(0.1 * k, rel)
                last = k
            assert eng.initialised_at is not None and eng.initialised_at < 0.1 * lost
            assert eng._map_search.search.active is not None
            region = eng._map_search.search.active.region
            off = math.hypot(x[resumed] - region.x_m, y[resumed] - region.y_m)
            assert (off < region.radius_m - 25.0) is inside and (off > region.radius_m) is not inside, (sigmas, off, region)


def test_no_search_acts_while_gps_comes(road):
    """With fixes every second to the end, GPS places the estimate: map_relocalisation adds no re-anchoring,
    and the estimate is the one without it."""
    seed = 5
    x, y, yaw, _ = graph_route(road, seed, 1200.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, heading_rad=0.3, noise_m=0.02)
    off, err_off = _feed(road, FusionConfig(), x, y, ox, oy, oyaw, len(x))
    on, err_on = _feed(road, FusionConfig(map_relocalisation=True), x, y, ox, oy, oyaw, len(x))
    assert on.counters.map_relocalisations == 0 and err_on == pytest.approx(err_off, abs=1e-9)


def _biased_window(road, seed: int, fixes_until_k: int):
    """A drive whose 70 s of fixes all lie 150 m off; the silence's search is begun at the silence (no replay of the
    path under GPS, SearchParams.gps_replay_m 0) and the fixes are not registered on the roads first (SearchParams.register_ratio
    0: test_register.py), so that what the tests using it see is the search beside GPS alone."""
    x, y, yaw, _ = graph_route(road, seed, 2400.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, heading_rad=0.3, noise_m=0.02)
    cfg = FusionConfig(map_relocalisation=True, road_fixes=False)
    return _feed(road, cfg, x, y, ox, oy, oyaw, fixes_until_k, fix_offset=(106.0, 106.0),
                 search=dict(gps_replay_m=0.0, register_ratio=0.0))


@pytest.mark.slow
def test_a_search_beside_a_biased_gps_re_anchors_once_gps_falls_silent(road):
    """70 s of fixes all 150 m off, then none: the estimate is lost long before GPS ends, and a search runs beside
    GPS from then (a search begun only at the silence re-anchored later: first re-anchoring on routes 3, 4, 5 at
    145.1, 92.8, 95.2 s against 97.2, 83.3, 94.6 s beside GPS). It re-anchors only once GPS is silent, and every
    run ends on the truth."""
    for seed in (3, 4, 5):
        on, err_on = _biased_window(road, seed, 700)
        assert on.relocalised_at and err_on < 15.0, (seed, on.relocalised_at, err_on)
        assert 69.0 + SEARCH.after_gps_s <= on.relocalised_at[0][0], seed  # never while fixes come


@pytest.mark.slow
def test_a_search_begun_back_under_a_biased_gps_re_anchors_at_the_silence(road):
    """70 s of fixes all 150 m off, then none, on routes the map did not call lost under GPS: with
    SearchParams.gps_replay_m (250 m) the search begun at the silence has already been fed the last 250 m driven under the
    fixes, so it re-anchors sooner, mostly at the silence itself (measured, routes 6-9: 79.0 / 101.9 / 79.1 / 81.6 s
    against 101.1 / 110.3 / 105.3 / 98.9 s begun at the silence; each ending within 7 m of the truth either way).
    SearchParams.gps_fit_min is off here: route 7's biased fixes leave the estimate on parallel streets for most of the
    last 300 m, so by default GPS's silence begins no search there (the estimate is called lost later instead:
    first re-anchoring at 153.8 s). The fixes are not registered on the roads first (SearchParams.register_ratio 0: that
    would re-anchor at the silence without a search, test_register.py)."""
    last_fix_s = 69.0
    at_silence = 0
    for seed in (6, 7, 8, 9):
        x, y, yaw, _ = graph_route(road, seed, 2400.0)
        ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, heading_rad=0.3, noise_m=0.02)
        times = []
        for replay_m in (0.0, 250.0):
            cfg = FusionConfig(map_relocalisation=True, road_fixes=False)
            eng, err = _feed(road, cfg, x, y, ox, oy, oyaw, 700, fix_offset=(106.0, 106.0),
                             search=dict(gps_replay_m=replay_m, gps_fit_min=0.0, register_ratio=0.0))
            assert eng.relocalised_at and err < 15.0, (seed, replay_m, err)
            times.append(eng.relocalised_at[0][0])
        silent_s = last_fix_s + SEARCH.after_gps_s
        assert silent_s - 0.5 <= times[1] < times[0], (seed, times)
        at_silence += times[1] <= silent_s + 3.0
    assert at_silence >= 3


@pytest.mark.slow
def test_a_map_re_anchoring_mends_the_path_its_search_matched(road):
    """The same biased window: the final estimates of the frames the search matched (from its start to the
    re-anchoring) are moved with the re-anchoring, so they lie near the truth, where the online estimates keep
    GPS's 150 m bias (median over the last 15 s before it, measured: 0.5 m against 147.9 m unmended). (The fixes
    are not registered on the roads first, SearchParams.register_ratio 0: that re-anchoring reaches back to its fixes and
    re-estimates the frames since, test_register.py.)"""
    x, y, yaw, _ = graph_route(road, 3, 2400.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, 3, heading_rad=0.3, noise_m=0.02)
    cfg = FusionConfig(map_relocalisation=True, road_fixes=False)
    eng, _ = _feed(road, cfg, x, y, ox, oy, oyaw, 700, fix_offset=(106.0, 106.0), search=dict(register_ratio=0.0))
    traj = eng.trajectory()
    t_s, online = eng.online_estimates()
    at = {round(t / 0.1): p for t, p in zip(t_s, online)}
    t_found = eng.relocalised_at[0][0]
    ks = [k for k in range(len(x)) if t_found - 15.0 <= 0.1 * k < t_found]  # the last 15 s before it
    final = [math.hypot(traj[0.1 * k].x() - x[k], traj[0.1 * k].y() - y[k]) for k in ks]  # (keyed by the times fed)
    causal = [math.hypot(at[k].x() - x[k], at[k].y() - y[k]) for k in ks if at.get(k) is not None]
    assert float(np.median(final)) < 20.0 and float(np.median(causal)) > 100.0, (np.median(final), np.median(causal))


@pytest.mark.parametrize("on_roads", [True, False])
def test_a_mend_that_would_take_a_path_off_its_roads_is_not_made(road, on_roads):
    """SearchParams.mend_keep_ratio: a drive tracked on its roads under GPS; a re-anchoring whose answer turns the last frame
    by 25° would swing the 40 s before it (about 400 m of road) off the roads: with the check the final estimates
    stay as they were. The same path moved 150 m off its roads first (as a biased window leaves it), and mended
    back by the same correction that undoes it, is moved either way."""
    import gtsam

    x, y, yaw, _ = graph_route(road, 3, 1200.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, 3, heading_rad=0.3, noise_m=0.02)
    keep = dict(mend_keep_ratio=0.5 if on_roads else 0.0)
    eng, _ = _feed(road, FusionConfig(road_fixes=False), x, y, ox, oy, oyaw, len(x))
    sm = eng.smoother
    k1 = max(sm.smoothed)
    k0 = k1 - 400
    before = {j: sm.smoothed[j] for j in range(k0, k1)}
    was = sm.smoothed[k1]
    swung = gtsam.Pose3(gtsam.Rot3.Yaw(was.rotation().yaw() + math.radians(25.0)), was.translation())
    with search_params(**keep):
        eng._anchors.mend_searched(k0, k1, was, swung)
    unchanged = all(sm.smoothed[j].equals(before[j], 1e-12) for j in range(k0, k1))
    assert unchanged is on_roads
    off = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(150.0, -150.0, 0.0))
    for j in range(k0, k1 + 1):
        sm.smoothed[j] = off.compose(before.get(j, was))
    with search_params(**keep):
        eng._anchors.mend_searched(k0, k1, off.compose(was), was)
    err = max(math.hypot(sm.smoothed[j].x() - before[j].x(), sm.smoothed[j].y() - before[j].y()) for j in range(k0, k1))
    assert err < 1e-6, err


@pytest.mark.slow
def test_a_search_beside_gps_never_moves_the_estimate_while_fixes_come(road):
    """Fixes every second to the end, all 150 m off: the estimate is lost (the map disagrees) and a search runs
    beside GPS, but GPS places the estimate: no re-anchoring, and the estimate is the one without the search."""
    on, err_on = _biased_window(road, 2, 10**9)
    x, y, yaw, _ = graph_route(road, 2, 2400.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, 2, heading_rad=0.3, noise_m=0.02)
    off, err_off = _feed(road, FusionConfig(road_fixes=False), x, y, ox, oy, oyaw, 10**9, fix_offset=(106.0, 106.0))
    assert on.counters.lost_events >= 1
    assert on._map_search.search.searches >= 1  # it did search
    assert on.counters.map_relocalisations == 0 and err_on == pytest.approx(err_off, abs=1e-9)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), steps=st.integers(1, 20), step_m=st.floats(0.5, 40.0),
       lo=st.floats(0.05, 5.0), octaves=st.floats(0.1, 3.0))
def test_a_scale_search_keeps_each_scale_in_its_range_and_the_posterior_a_distribution(road, seed, steps, step_m,
                                                                                       lo, octaves):
    p = RoadParticles(road, PARTICLES, seed)
    rng = np.random.default_rng(seed)
    x0, y0 = road.xy_m[int(rng.integers(len(road)))]
    hi = lo * 2.0**octaves
    assert p.start(Region(float(x0), float(y0), 300.0), 0.0, n=500, scale_range=(lo, hi)) > 0
    assert p.scale_free and np.ptp(p.log_scale) > 0.0
    for _ in range(steps):
        p.step(step_m, np.array([step_m, 0.0]))
        assert math.isclose(float(np.exp(p.logw).sum()), 1.0, rel_tol=1e-9)
        scale = np.exp(p.log_scale)
        assert np.all(scale >= lo * (1 - 1e-12)) and np.all(scale <= hi * (1 + 1e-12))


@pytest.mark.parametrize("seed", [0, 7])
def test_a_search_for_the_scale_finds_the_place_and_the_scale(road, seed):
    """Issue 17 item 2 (--scale-unknown): an odometry that reports 1/1.4 of each metre (a biased or a
    monocular VO), searched over scales 0.5-2 in a 1 km region 300 m off: found within 10 m, its scale within
    5% of 1.4. (8 Helsinki drives: all found within 2.3 m, scales 1.40-1.45; at a true 0.7, 6 of 8.)"""
    x, y, yaw, _ = graph_route(road, seed, 1500.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, scale=1.0 / 1.4, yaw_drift_rad_per_m=math.radians(1.0) / 100,
                                     heading_rad=1.0, noise_m=0.02)
    a = np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi)
    r = Relocaliser(road, PARTICLES, Region(x[0] + 300.0 * math.cos(a), y[0] + 300.0 * math.sin(a), 1000.0), seed,
                    (0.5, 2.0))
    for k in range(len(x)):
        loc = r.add(ox[k], oy[k], oyaw[k])
        if loc is not None:
            break
    assert loc is not None, "not found"
    assert math.hypot(loc.x_m - x[k], loc.y_m - y[k]) < 10.0
    assert loc.scale == pytest.approx(1.4, rel=0.05) and 0.0 < loc.scale_spread < 0.1


def test_a_cold_start_with_an_unknown_scale_takes_the_scale_it_found(road):
    """MapFusion with reloc_scale_min < reloc_scale_max: the estimate begins where the vehicle is, at the
    scale the search found, and follows the drive to its end."""
    eng, first, x, y = _cold_start(road, 0, 1500.0, FusionConfig(reloc_scale_min=0.5, reloc_scale_max=2.0),
                                   scale=1.0 / 1.4)
    assert first is not None and first[1] < 10.0, first
    assert eng.scale == pytest.approx(1.4, rel=0.05)
    p = eng.estimate()
    assert math.hypot(p.x() - x[-1], p.y() - y[-1]) < 25.0


def test_a_scale_range_upside_down_is_refused():
    from mapfusion.errors import ConfigError

    with pytest.raises(ConfigError, match="reloc_scale_min"):
        FusionConfig(reloc_scale_min=2.0, reloc_scale_max=0.5)


@settings(max_examples=60, deadline=None)
@given(gaps=st.lists(st.sampled_from([0.0, 0.01, 0.3, 0.5, 0.999, 1.0, 1.7, 3.0, 12.5]), min_size=1, max_size=60),
       queries=st.lists(st.floats(-5.0, 200.0), min_size=1, max_size=40))
def test_the_arc_index_answers_as_a_binary_search(gaps, queries):
    """The particles' lookup of the way-point at or before an arc length is numpy's searchsorted to the
    index, repeated values (zero gaps), whole metres and values beyond either end included."""
    from mapfusion.relocalise import _ArcIndex

    values = np.cumsum(gaps)
    g = np.concatenate((np.asarray(queries), values, values + 1e-12, np.floor(values)))
    expected = np.searchsorted(values, g, side="right") - 1
    assert np.array_equal(_ArcIndex(values).last_at_or_before(g), expected)


@settings(max_examples=60, deadline=None)
@given(cells=st.lists(st.tuples(st.integers(-3000, 3000), st.integers(-3000, 3000)), min_size=1, max_size=50),
       narrow=st.booleans())
def test_cell_ids_group_and_order_cells_as_unique_does(cells, narrow):
    """The posterior's grid cells get ids that group the same cells and order them as np.unique orders
    their keys (x, then y): the densest cell and its ties resolve the same way."""
    from mapfusion.relocalise import _cell_ids

    c = np.array(cells, dtype=np.int64) % 7 if narrow else np.array(cells, dtype=np.int64)
    ids = _cell_ids(c[:, 0], c[:, 1])
    _, expected = np.unique(c[:, 0] * 1_000_003 + c[:, 1], return_inverse=True)
    order = np.argsort(ids[np.unique(expected, return_index=True)[1]])  # each unique cell's id, in unique's order
    assert np.array_equal(order, np.arange(len(order)))
    assert np.array_equal(ids[:, None] == ids[None, :], expected[:, None] == expected[None, :])


@settings(max_examples=40, deadline=None)
@given(bins=st.integers(2, 100_000), epsilon=st.floats(0.005, 0.5))
def test_kld_count_is_the_chi_square_bound(bins, epsilon):
    """Fox's count: the 99% quantile of χ² with bins - 1 degrees of freedom over 2ε (its Wilson-Hilferty
    approximation is within 2% from a few bins on), more for more bins and for a tighter bound."""
    from scipy.stats import chi2

    from mapfusion.relocalise import kld_count

    n = kld_count(bins, epsilon)
    exact = chi2.ppf(0.99, bins - 1) / (2.0 * epsilon)
    assert abs(n - exact) <= 0.02 * exact + 1.0 or bins < 5
    assert kld_count(bins + 1, epsilon) >= n and kld_count(bins, epsilon / 2) >= n


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), steps=st.integers(5, 40), turn=st.floats(-math.pi, math.pi))
def test_an_adaptive_count_stays_between_its_floor_and_the_start_and_shrinks_once_sure(road, seed, steps, turn):
    """With KLD-sampling the particles never exceed the count they started with nor fall under the floor, the
    posterior stays a distribution on legal roads, and a drive that settles the posterior uses fewer particles
    than it started with."""
    import dataclasses

    cfg = dataclasses.replace(PARTICLES, kld_epsilon=0.05, particles_min=200)
    p = RoadParticles(road, cfg, seed)
    x, y, yaw, _ = graph_route(road, seed, 5.0 * steps + 50.0)
    assert p.start(Region(float(x[0]), float(y[0]), 60.0), float(yaw[0])) > 0
    n0 = len(p)
    k_prev = 0
    for k in range(1, len(x)):
        if math.hypot(x[k] - x[k_prev], y[k] - y[k_prev]) < 5.0:
            continue
        moved = float(np.sum(np.hypot(np.diff(x[k_prev:k + 1]), np.diff(y[k_prev:k + 1]))))
        p.step(moved, np.array([x[k] - x[k_prev], y[k] - y[k_prev]]))
        k_prev = k
        assert min(200, n0) <= len(p) <= n0
        assert math.isclose(float(np.exp(p.logw).sum()), 1.0, rel_tol=1e-9)
        assert np.all(p.along >= 0.0) and np.all(p.along <= road.edge_length_m[p.edge] + 1e-9)
    if p.located(float(yaw[k_prev])) is not None:  # settled: the count came down
        assert len(p) < n0


@settings(max_examples=200, deadline=None)
@given(ax=st.floats(-1e4, 1e4), ay=st.floats(-1e4, 1e4), ar=st.floats(0.0, 3e3),
       bx=st.floats(-1e4, 1e4), by=st.floats(-1e4, 1e4), br=st.floats(0.0, 3e3))
def test_the_enclosing_disc_holds_both_and_is_the_smallest(ax, ay, ar, bx, by, br):
    """A doubted re-anchoring's next search covers both regions (issue 17): the disc holds each disc (its
    centre's distance plus its radius within the radius) and is no larger than it must be — as large as the
    larger disc, or as half their span along the line through the centres."""
    from mapfusion.relocalise import Region, enclosing_disc

    a, b = Region(ax, ay, ar), Region(bx, by, br)
    e = enclosing_disc(a, b)
    tol = 1e-6 * (1.0 + abs(ax) + abs(ay) + abs(bx) + abs(by) + ar + br)
    for r in (a, b):
        assert math.hypot(r.x_m - e.x_m, r.y_m - e.y_m) + r.radius_m <= e.radius_m + tol
    d = math.hypot(bx - ax, by - ay)
    assert e.radius_m <= max(ar, br, 0.5 * (d + ar + br)) + tol
    assert e.radius_m >= max(ar, br) - tol


def test_a_search_soon_after_a_map_re_anchoring_also_covers_that_search_s_region(road):
    """Lost within SearchParams.doubt_m of driving after a map re-anchoring, the engine searches a region that holds both
    the lost region and the re-anchoring's own search region grown by the distance driven since (the re-anchoring
    may have been wrong); farther on, or with SearchParams.doubt_m 0, the lost region alone."""
    x, y, yaw, _ = graph_route(road, 3, 800.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, 3, noise_m=0.02)
    cfg = FusionConfig(map_relocalisation=True)
    eng, _ = _feed(road, cfg, x, y, ox, oy, oyaw, 300)
    k = len(x) - 1
    k0 = k - 300  # 300 frames (about 300 m) before the last
    driven = float(np.sum(np.hypot(np.diff(x[k0:]), np.diff(y[k0:]))))
    old, lost = Region(x[k0] + 500.0, y[k0], 300.0), Region(x[k], y[k], 300.0)
    eng._anchors.last = (k0, old)
    got = eng._map_search._doubting(k, lost)
    for r, radius in ((lost, lost.radius_m), (old, old.radius_m + 0.9 * driven)):
        assert math.hypot(r.x_m - got.x_m, r.y_m - got.y_m) + radius <= got.radius_m + 1e-6
    assert got.radius_m <= SEARCH.max_radius_m
    assert eng._map_search._doubting(k, lost) != lost
    with search_params(doubt_m=0.0):
        assert eng._map_search._doubting(k, lost) == lost
    with search_params(doubt_m=0.5 * driven):
        assert eng._map_search._doubting(k, lost) == lost


@settings(max_examples=20, deadline=None)
@given(st.floats(-3000.0, 3000.0), st.floats(-3000.0, 3000.0), st.floats(10.0, 1500.0), st.floats(0.0, 800.0),
       st.floats(10.0, 600.0), st.floats(0.0, 300.0))
def test_a_gap_while_a_search_runs_also_covers_the_running_search_s_region(road, dx, dy, old_r, driven, new_r, reach):
    """An odometry gap while a search still runs: the gap's search covers its own region and the running search's
    grown by the distance driven since it began and by the gap's reach (at most SearchParams.max_radius_m); with no
    search running, its own region alone."""
    from mapfusion import MapFusion

    cfg = FusionConfig(map_relocalisation=True)
    eng = MapFusion(road, cfg, odometry_rate_hz=10.0)
    x0, y0 = (float(v) for v in road.xy_m[0])
    mine = Region(x0, y0, new_r)
    assert eng._map_search._still_open(mine, reach) == mine  # (nothing running)
    running = Relocaliser(road, PARTICLES, Region(x0 + dx, y0 + dy, old_r))
    running.particles.driven_m = driven
    eng._map_search.search.active = running
    got = eng._map_search._still_open(mine, reach)
    grown = old_r + driven + reach
    if got.radius_m < SEARCH.max_radius_m:
        for r, radius in ((mine, new_r), (running.region, grown)):
            assert math.hypot(r.x_m - got.x_m, r.y_m - got.y_m) + radius <= got.radius_m + 1e-6
        assert got.radius_m <= max(new_r, grown, 0.5 * (math.hypot(dx, dy) + new_r + grown)) + 1e-6  # the smallest
    else:
        assert got.radius_m == SEARCH.max_radius_m


def test_a_watched_search_ends_after_its_distance_and_when_another_begins(road):
    x, y, yaw, _ = graph_route(road, 1, 600.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, 1, noise_m=0.02)
    off = Search(road, CFG)
    r = Relocaliser(road, PARTICLES, Region(x[0], y[0], 300.0))
    with search_params(watch_m=0.0):
        off.watch(r)
    assert off.watching is None  # SearchParams.watch_m 0: a search ends when it converges
    search = Search(road, CFG)
    with search_params(watch_m=200.0):
        search.watch(r)
    k = 0
    while search.watching is not None:
        search.watched(ox[k], oy[k], oyaw[k], k)
        k += 1
    assert 195.0 <= r.particles.driven_m <= 215.0  # (whole filter steps of ParticleParams.step_m)
    search.watch(r)
    search.begin(Region(x[k], y[k], 300.0))
    assert search.watching is None and search.watched(ox[k + 1], oy[k + 1], oyaw[k + 1]) is None


@pytest.mark.slow
def test_a_watched_search_takes_a_wrong_re_anchoring_back_to_where_its_posterior_gathers(road):
    """A search that has tracked the truth re-anchors the estimate 200 m off it (as a look-alike path would):
    watched (SearchParams.watch_m), its posterior, which holds the truth, re-anchors it back at its next filter steps;
    not watched, the estimate stays off to the end of the drive (nothing calls it lost: it is on roads)."""
    from mapfusion.track import planar_of

    seed = 4
    x, y, yaw, _ = graph_route(road, seed, 1700.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, heading_rad=0.3, noise_m=0.02)
    k_search, k_wrong = 500, 900

    def run(watch_m: float):
        with search_params(watch_m=watch_m):
            return _run(watch_m)

    def _run(watch_m: float):
        from mapfusion import MapFusion

        cfg = FusionConfig(map_relocalisation=True, road_fixes=False)
        eng = MapFusion(road, cfg, odometry_rate_hz=10.0)
        r = Relocaliser(road, PARTICLES, Region(x[k_search], y[k_search], 300.0), seed=1)
        for k in range(len(x)):
            if k % 10 == 0 and k < 400:
                lat, lon = road.projection.to_geo(x[k], y[k])
                eng.add_gps(0.1 * k, float(lat), float(lon), None, 2.0)
            eng.add_odometry(0.1 * k, odometry_step(ox, oy, oyaw, k))
            if k_search <= k <= k_wrong:
                px, py, pyaw = planar_of(eng.track.raw[k])
                s = eng.alignment.scale
                loc = r.add(px * s, py * s, pyaw, k)
            if k == k_wrong:
                assert loc is not None and math.hypot(loc.x_m - x[k], loc.y_m - y[k]) < 15.0
                wrong = dataclasses.replace(loc, x_m=loc.x_m + 200.0)
                pred = eng.track.online[k]
                eng._map_search._map_reanchor(k, pred, wrong, r)  # (which also watches r on)
                p = eng.track.online[k]
                assert math.hypot(p.x() - x[k] - 200.0, p.y() - y[k]) < 10.0  # (re-anchored where it was told)
        eng.finish()
        p = eng.estimate()
        return eng, math.hypot(p.x() - x[-1], p.y() - y[-1])

    unwatched, err_unwatched = run(0.0)
    watched, err_watched = run(500.0)
    assert err_unwatched > 100.0, err_unwatched
    assert watched.counters.map_relocalisations >= 2 and watched.counters.lost_events == \
        unwatched.counters.lost_events, watched.relocalised_at  # (the watch, not a search begun when lost)
    assert watched.relocalised_at[1][1] - watched.relocalised_at[0][1] < 50.0  # metres of the search's driving
    assert err_watched < 15.0, (err_watched, watched.relocalised_at)


def test_a_watched_jump_held_back_by_rival_mass_is_weighed_again_until_the_mass_has_gone(road):
    """A watched search's answer jumps away from the estimate while its posterior still holds rival mass there: no
    re-anchoring, and the watch goes on. At the next step the same answer (moved as the vehicle drove) has still
    jumped, against the last answer that agreed with the estimate: with the rival mass gone it re-anchors there.
    (Counting the held-back answer as the last one took the next for a drift and ended the watch: VO jump Helsinki
    s11 of the kidnapped family, 1,304 m re-anchored wrong.)"""
    import gtsam

    from mapfusion import MapFusion
    from mapfusion.relocalise import Located

    x0, y0 = (float(v) for v in road.xy_m[len(road) // 2])
    eng = MapFusion(road, CFG, odometry_rate_hz=10.0)
    eng.add_odometry(0.0, np.eye(4))
    pred = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(x0, y0, 0.0))
    watched = Relocaliser(road, PARTICLES, Region(x0, y0, 60.0))
    eng._map_search.search.watching = watched
    far = 6.0 * SEARCH.watch_apart_m
    answers = iter([Located(x0 + 2.0, y0, 0.0, 0.0, 0, 1, 0.0, 0.9, 2.0, 0.01, 100.0),
                    Located(x0 + far, y0, 0.0, 0.0, 0, 1, 0.0, 0.9, 2.0, 0.01, 105.0),
                    Located(x0 + far + 5.0, y0, 0.0, 0.0, 0, 1, 0.0, 0.95, 2.0, 0.01, 110.0)])
    rivals = iter([True, False])
    anchored = []
    eng._map_search.search.watched = lambda *a, **kw: next(answers)
    eng._map_search._search_pose = lambda k, search: (0.0, 0.0, 0.0)
    eng._map_search._rival_at_estimate = lambda k, p, loc, search: next(rivals)
    eng._map_search._map_reanchor = lambda k, p, loc, search: anchored.append(loc.x_m - x0)
    eng._map_search._watch_reanchoring(0, pred)  # (agrees with the estimate)
    eng._map_search._watch_reanchoring(0, pred)  # (jumped, rival mass left at the estimate)
    assert anchored == [] and eng._map_search.search.watching is watched
    eng._map_search._watch_reanchoring(0, pred)  # (still jumped, no rival mass left)
    assert anchored == [pytest.approx(far + 5.0)]


def _engine_searching(road, cfg, answers, rivals):
    """An engine two frames in with a running search around the map's middle way-point whose next answers are
    ``answers`` (x offsets from it, m) and whose rival-mass verdicts are ``rivals``; returns the engine, the
    estimate there, the search and the list the offsets of its re-anchorings go to."""
    import gtsam

    from mapfusion import MapFusion
    from mapfusion.relocalise import Located

    x0, y0 = (float(v) for v in road.xy_m[len(road) // 2])
    eng = MapFusion(road, dataclasses.replace(cfg, map_relocalisation=True), odometry_rate_hz=10.0)
    eng.add_odometry(0.0, np.eye(4))
    eng.add_odometry(0.1, np.eye(4))
    running = Relocaliser(road, PARTICLES, Region(x0, y0, 60.0))
    eng._map_search.search.active = running
    located = iter([Located(x0 + dx, y0, 0.0, 0.0, 0, 1, 0.0, 0.95, 2.0, 0.01, 150.0 + i)
                    for i, dx in enumerate(answers)])
    verdicts = iter(rivals)
    anchored: list[float] = []
    running.add = lambda *a, **kw: next(located)
    eng._map_search._search_pose = lambda k, s: (0.0, 0.0, 0.0)
    eng._map_search._rival_at_estimate = lambda k, p, loc, s: next(verdicts)
    eng._map_search._map_reanchor = lambda k, p, loc, s: anchored.append(loc.x_m - x0)
    return eng, gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(x0, y0, 0.0)), running, anchored


def test_a_search_answer_held_back_by_rival_mass_ends_the_search(road):
    """A running search converges away from the estimate while its posterior still holds rival mass there: no
    re-anchoring, and the search ends (its answer is not weighed again)."""
    far = 3.0 * SEARCH.confirm_m
    eng, pred, running, anchored = _engine_searching(road, CFG, [far, far + 5.0], [True, False])
    eng._map_search.when_lost(1, pred)
    assert anchored == [] and eng._map_search.search.active is None


@settings(max_examples=40, deadline=None)
@given(off_m=st.floats(0.0, 40.0), confirm_m=st.floats(0.0, 30.0))
def test_a_converged_answer_farther_than_confirm_m_re_anchors_the_estimate(road, off_m, confirm_m):
    """A search that converges ``off_m`` from the estimate, with no rival mass at it, re-anchors the estimate
    there exactly when ``off_m`` exceeds ``SearchParams.confirm_m``; nearer, it only confirms it (and ends)."""
    eng, pred, _, anchored = _engine_searching(road, CFG, [off_m], [False])
    x0 = pred.x()
    with search_params(confirm_m=confirm_m):
        eng._map_search.when_lost(1, pred)
    off_m = (x0 + off_m) - x0  # (the distance as the engine sees it, to the last bit)
    assert anchored == ([pytest.approx(off_m)] if off_m > confirm_m else [])
    assert eng._map_search.search.active is None


def test_a_search_answer_12_m_from_the_estimate_is_taken_by_default(road):
    """The default SearchParams.confirm_m re-anchors an estimate 12 m from a converged answer: the kidnapped family's VO
    jump Helsinki s8, whose gap's step was carried 31 m short (the vehicle braked to a stop late in the gap), kept
    13-19 m of along-road error for 80 s after its search converged 12 m away with a 2.9 m spread (5 m from the
    truth); re-anchored there, 5 m then 1-4 m (docs/method.md)."""
    eng, pred, _, anchored = _engine_searching(road, CFG, [12.0], [False])
    eng._map_search.when_lost(1, pred)
    assert anchored == [pytest.approx(12.0)]


def test_a_search_that_still_holds_mass_at_the_estimate_does_not_move_it(road):
    """SearchParams.rival_mass: a posterior with mass near the estimate has not ruled its place out (no re-anchoring);
    one with none near it has; 0 turns the test off."""
    import gtsam

    from mapfusion import MapFusion
    from mapfusion.relocalise import Located

    x0, y0 = (float(v) for v in road.xy_m[len(road) // 2])
    r = Relocaliser(road, PARTICLES, Region(x0, y0, 60.0))
    r.add(0.0, 0.0, 0.0)  # (spreads the particles over the region's roads)
    answer = Located(x0 + 500.0, y0, 0.0, 0.0, 0, 1, 0.0, 0.9, 2.0, 0.01, 150.0)
    for rival, at, expected in ((0.05, (x0, y0), True), (0.05, (x0 + 1000.0, y0), False), (0.0, (x0, y0), False)):
        eng = MapFusion(road, CFG, odometry_rate_hz=10.0)
        eng.add_odometry(0.0, np.eye(4))
        pred = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(at[0], at[1], 0.0))
        near = r.particles.mass_within(at[0], at[1], 2.0 * PARTICLES.converge_radius_m)
        assert (near >= 0.05) == (at == (x0, y0))  # (the setup: the region's roads lie around the estimate)
        with search_params(rival_mass=rival):
            assert eng._map_search._rival_at_estimate(0, pred, answer, r) is expected


def test_an_answer_near_the_estimate_is_not_its_own_rival(road):
    """A search whose whole posterior sits in one tight cluster 30 m from the estimate has ruled the estimate's
    place out: the rival mass is counted outside the answer's own disc. Counted in full, the cluster's own mass
    inside the estimate's 50 m disc would make it its own rival and the 30 m correction would never be made."""
    import gtsam

    from mapfusion import MapFusion
    from mapfusion.relocalise import Located

    x0, y0 = (float(v) for v in road.xy_m[len(road) // 2])
    r = Relocaliser(road, PARTICLES, Region(x0, y0, 5.0))
    r.add(0.0, 0.0, 0.0)  # (every particle within 5 m of (x0, y0): the answer's cluster)
    assert r.particles.mass_within(x0, y0, 5.0) > 0.999
    answer = Located(x0, y0, 0.0, 0.0, 0, 1, 0.0, 1.0, 2.0, 0.01, 150.0)
    pred = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(x0 + 30.0, y0, 0.0))
    rr = PARTICLES.converge_radius_m
    assert r.particles.mass_within(pred.x(), pred.y(), 2.0 * rr) >= SEARCH.rival_mass  # (counted in full)
    eng = MapFusion(road, CFG, odometry_rate_hz=10.0)
    eng.add_odometry(0.0, np.eye(4))
    assert eng._map_search._rival_at_estimate(0, pred, answer, r) is False


@settings(max_examples=60, deadline=None)
@given(frames=st.lists(st.tuples(st.floats(0.0, 40.0), st.booleans()), min_size=1, max_size=120),
       window_m=st.floats(1.0, 300.0))
def test_the_road_fit_is_the_on_road_share_of_the_last_window(frames, window_m):
    """SearchParams.gps_fit_min's measure: the share (by distance) of the shortest run of latest frames that covers
    SearchParams.gps_fit_m (all frames while they cover less; within FIT_TIE_M counts as covering) whose pose lay on a
    road, in [0, 1]; None before any driving. Checked against that definition computed afresh."""
    from types import SimpleNamespace

    from mapfusion.association import FIT_TIE_M, MapAssociation
    from mapfusion.counters import Counters

    cfg = dataclasses.replace(CFG, map_relocalisation=True)
    assoc = MapAssociation.__new__(MapAssociation)  # (only the record's state: no road map needed)
    assoc.cfg, assoc.counters = cfg, Counters()
    assoc._fit, assoc._fit_m, assoc._fit_on_m = collections.deque(), 0.0, 0.0
    on_road = SimpleNamespace(angle_deg=0.0, lateral_m=1.0, lanes=1)
    off_road = SimpleNamespace(angle_deg=0.0, lateral_m=cfg.lane_width_m + SEARCH.gps_fit_margin_m + 0.5, lanes=1)
    for i, (moved, on) in enumerate(frames):
        with search_params(gps_fit_m=window_m):
            assoc._record_fit(on_road if on else (off_road if i % 2 else None), moved)
        total = on_m = 0.0
        for m, o in reversed(frames[: i + 1]):
            if total >= window_m - FIT_TIE_M:
                break
            total += m
            on_m += m if o else 0.0
        fit = assoc.road_fit()
        if total == 0.0:
            assert fit is None
        else:
            assert fit is not None and 0.0 <= fit <= 1.0
            assert fit == pytest.approx(on_m / total, abs=1e-6)


@pytest.mark.slow
def test_gps_that_left_the_estimate_on_the_roads_gets_no_second_opinion(road):
    """SearchParams.gps_fit_min: 70 s of good fixes leave the estimate on the roads, so GPS's silence begins no search
    (which could only confirm it or, converging on a look-alike path, move it away: held-out 60-run set, Helsinki
    clear s14, 3.9 -> 168 m when measured); the same drive with every fix 150 m off leaves it off the roads and
    the search begins and re-anchors; with the measure off (0) the good drive is searched again. (The fixes are not
    registered on the roads first, SearchParams.register_ratio 0: that would re-anchor the biased drive without a search,
    test_register.py.)"""
    seed = 6
    x, y, yaw, _ = graph_route(road, seed, 2400.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, heading_rad=0.3, noise_m=0.02)
    cfg = FusionConfig(map_relocalisation=True, road_fixes=False)
    nreg = dict(register_ratio=0.0)
    good, err_good = _feed(road, cfg, x, y, ox, oy, oyaw, 700, search=nreg)
    assert good._map_search.search.searches == 0 and good.counters.map_relocalisations == 0
    assert err_good < 15.0
    biased, err_biased = _feed(road, cfg, x, y, ox, oy, oyaw, 700, fix_offset=(106.0, 106.0), search=nreg)
    assert biased._map_search.search.searches >= 1 and biased.counters.map_relocalisations >= 1 and err_biased < 15.0
    always, _ = _feed(road, cfg, x, y, ox, oy, oyaw, 700, search=dict(nreg, gps_fit_min=0.0))
    assert always._map_search.search.searches >= 1


@pytest.fixture(scope="module")
def tee_road(tmp_path_factory):
    """A road east through a junction at the origin and a branch north from it (map frame: the junction's
    position is returned with it)."""
    from tests.helpers import write_osm

    tags = {"highway": "primary", "lanes": "2"}
    east, north = np.array([[-1000.0, 0.0], [0.0, 0.0], [1000.0, 0.0]]), np.array([[0.0, 0.0], [0.0, 1000.0]])
    road = RoadMap.from_osm(write_osm(tmp_path_factory.mktemp("tee"), [(east, tags), (north, dict(tags))]))
    west_end = road.xy_m[int(np.argmin(road.xy_m[:, 0]))]
    return road, west_end + np.array([1000.0, 0.0])


@settings(max_examples=30, deadline=None)
@given(before_m=st.floats(20.0, 150.0), past_m=st.floats(1.0, 12.0), err_deg=st.floats(-20.0, 20.0),
       seed=st.integers(0, 10_000))
def test_the_followed_end_has_the_guess_heading_not_only_its_position(tee_road, before_m, past_m, err_deg, seed):
    """Driving east ``before_m`` short of a junction with a branch north, ``before_m + past_m`` along the graph
    towards a guess turned by a heading error of at most 20° (a constant turn: the guess's position is off the
    road by up to 17 m to one side): the drives that went on end ``past_m`` past the junction heading east,
    those that turned end as far up the branch, 90° off. By D = E + w·A (w = 1 m/deg, A counted up to 45°) the
    end taken is on the road east whatever the position's error favours (the heading term outweighs it by at
    least 25 m against √2 × 12 m); by position alone the branch is taken whenever the guess lies on its side."""
    road, (jx, jy) = tee_road
    start_x = jx - before_m
    m = road.match(start_x, jy, 0.0, 20.0, 1.0)
    assert m is not None and not m.is_join
    length = before_m + past_m
    half = 0.5 * math.radians(err_deg)
    chord = length * (math.sin(half) / half if abs(half) > 1e-9 else 1.0)
    target = (start_x + chord * math.cos(half), jy + chord * math.sin(half))
    p = RoadFollower(road, dataclasses.replace(PARTICLES, uturn_at_vertex=0.0), seed)
    x, y, yaw = p.follow(m.edge, -1 if m.reversed else 1, m.along_m, length, target, 50.0,
                         target_yaw_rad=2.0 * half, weight_m_per_deg=1.0, max_deg=45.0)
    assert abs(math.remainder(yaw, 2.0 * math.pi)) < math.radians(1.0)
    assert math.hypot(x - (jx + past_m), y - jy) < 1.0
    if err_deg > 10.0:  # the guess lies north of the road, nearer the branch's end: position alone turns
        p = RoadFollower(road, dataclasses.replace(PARTICLES, uturn_at_vertex=0.0), seed)
        _, _, yaw0 = p.follow(m.edge, -1 if m.reversed else 1, m.along_m, length, target, 50.0)
        ends = {"east": (jx + past_m, jy), "north": (jx, jy + past_m)}
        nearer = min(ends, key=lambda k: math.hypot(ends[k][0] - target[0], ends[k][1] - target[1]))
        if nearer == "north":
            assert abs(math.remainder(yaw0 - math.pi / 2, 2.0 * math.pi)) < math.radians(1.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ends_both_far_off_the_guess_heading_are_told_apart_by_position(tee_road, seed):
    """A guess whose heading points where no road goes (100° right of east, the VO's turn over the gap wrong):
    both ends are far off it, and with A counted up to 45° the end nearer the guess's position is taken (the
    branch north); counted in full, the 70° between the two ends' A would take the road east, 7 m further off."""
    road, (jx, jy) = tee_road
    m = road.match(jx - 50.0, jy, 0.0, 20.0, 1.0)
    assert m is not None
    target, yaw_guess = (jx - 2.0, jy + 8.0), math.radians(-100.0)
    ends = {}
    for cap in (45.0, 180.0):
        p = RoadFollower(road, dataclasses.replace(PARTICLES, uturn_at_vertex=0.0), seed)
        ends[cap] = p.follow(m.edge, -1 if m.reversed else 1, m.along_m, 55.0, target, 50.0,
                             target_yaw_rad=yaw_guess, weight_m_per_deg=1.0, max_deg=cap)
    assert abs(math.remainder(ends[45.0][2] - math.pi / 2, 2.0 * math.pi)) < math.radians(1.0)  # north
    assert abs(math.remainder(ends[180.0][2], 2.0 * math.pi)) < math.radians(1.0)  # east


@pytest.fixture(scope="module")
def twin_ells(tmp_path_factory):
    """Two copies of one L-shaped road (500 m east, then a left turn and 300 m north), the second moved
    1,000 m west and 200 m south: a drive along either fits the other as well. Returns the map and the
    offset of the test's frame (the first L's corner at (500, 0)) in the map's ENU frame."""
    from tests.helpers import write_osm

    ell = np.array([[0.0, 0.0], [500.0, 0.0], [500.0, 300.0]])
    tags = {"highway": "secondary", "lanes": "2"}
    road = RoadMap.from_osm(write_osm(tmp_path_factory.mktemp("ells"),
                                      [(ell, tags), (ell + np.array([-1000.0, -200.0]), dict(tags))]))
    i = int(np.argmax(road.xy_m[:, 0] - road.xy_m[:, 1]))  # the first L's corner: east-most, south-most
    return road, road.xy_m[i] - np.array([500.0, 0.0])


def _ell_search(twin_ells, guess_floor: float | None, seed: int, guess: Guess | None = None):
    """A search over both L's from 100 m along the first, fed that L's drive (400 m east, 200 m north, in the
    odometry's own frame: a start heading of 30°); with ``guess_floor``, weighted by a guess 20 m behind the
    true start (σ 60 m, 20°), or by ``guess``. Returns the converged answer's distance from the truth (m) or None."""
    road, (ox, oy) = twin_ells
    if guess_floor is not None:
        guess = Guess(ox + 80.0, oy, 60.0, 0.0, math.radians(20.0), guess_floor)
    reloc = Relocaliser(road, PARTICLES, Region(ox - 250.0, oy - 100.0, 800.0), seed, guess=guess)
    c, s = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
    path = [(100.0 + d, 0.0, 0.0) for d in range(0, 400)] + [(500.0, float(d), math.pi / 2) for d in range(0, 201)]
    for x, y, yaw in path:
        loc = reloc.add(c * x - s * y, s * x + c * y, yaw + math.radians(30.0))
        if loc is not None:
            return math.hypot(loc.x_m - ox - x, loc.y_m - oy - y)
    return None


@pytest.mark.parametrize("seed", [1, 2])
def test_the_gaps_guess_tells_apart_places_the_roads_shape_cannot(twin_ells, seed):
    """Uniform over the region, the drive fits both L's alike and the search never holds 80% in one place; the
    engine's guess (its step carried across a gap, 20 m off) makes the right L the answer, within 10 m of the
    truth; a guess that keeps every place's weight (floor 1) is the uniform search again."""
    assert _ell_search(twin_ells, None, seed) is None
    assert _ell_search(twin_ells, 1.0, seed) is None
    err = _ell_search(twin_ells, 0.05, seed)
    assert err is not None and err < 10.0, err


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_gap_s_guess_spanning_the_carried_step_finds_a_vehicle_that_stopped_in_the_gap(twin_ells, seed):
    """The vehicle braked to a stop at the gap's start (95 m along the first L, stopped at 100 m) while the engine
    carried its last velocity 65 m on, to 160 m: the guess at the carried step's end alone weighs the truth, 2.9 σ
    away, about as little as the other L, and the search never holds 80% in one place; spanning the whole carried
    step (the engine's guess after a gap), it finds the right L within 10 m."""
    road, (ox, oy) = twin_ells
    sigma_m = PARTICLES.sigma_m + CFG.outage_step_fraction * 65.0  # (the engine's σ for a 65 m carried step)
    end_only = Guess(ox + 160.0, oy, sigma_m, 0.0, math.radians(20.0), 0.05)
    spanning = dataclasses.replace(end_only, from_xy_m=(ox + 95.0, oy))
    assert _ell_search(twin_ells, None, seed, guess=end_only) is None
    err = _ell_search(twin_ells, None, seed, guess=spanning)
    assert err is not None and err < 10.0, err


_coord = st.floats(-500.0, 500.0)


@settings(max_examples=50, deadline=None)
@given(a=st.tuples(_coord, _coord), b=st.tuples(_coord, _coord), sigma_m=st.floats(2.0, 100.0),
       floor=st.floats(0.0, 0.5), points=st.lists(st.tuples(_coord, _coord), min_size=2, max_size=30))
def test_a_guess_along_a_segment_weighs_by_the_distance_to_it(a, b, sigma_m, floor, points):
    """A guess spanning the carried step (``from_xy_m``): each weight is the point guess's law in the distance to the
    segment, measured here by brute force on 4,001 points along it; every point on the segment weighs the most;
    a segment of zero length is the point guess."""
    xy = np.array(points + [a, b, ((a[0] + b[0]) / 2, (a[1] + b[1]) / 2)])
    heading = np.zeros(len(xy))
    guess = Guess(b[0], b[1], sigma_m, 0.0, 1.0, floor, from_xy_m=a)
    got = guess_log_weights(guess, xy, heading)
    u = np.linspace(0.0, 1.0, 4001)[:, None]
    line = np.asarray(a) + u * (np.asarray(b) - np.asarray(a))
    d2 = np.min(((xy[:, None, :] - line[None, :, :]) ** 2).sum(axis=2), axis=1)
    d_m = np.sqrt(d2)
    step_m = math.dist(a, b) / 4000  # (the brute force's own spacing: the true distance lies within it)

    def law(dist_m):
        with np.errstate(divide="ignore"):
            return np.logaddexp(math.log(floor) if floor > 0 else -np.inf,
                                math.log1p(-floor) - 0.5 * (dist_m / sigma_m) ** 2)

    rel = got - got[-3]  # (normalised: compare against the segment's own end, which lies on it)
    assert np.all(rel >= law(d_m) - 1e-9)
    assert np.all(rel <= law(np.maximum(d_m - step_m, 0.0)) + 1e-9)
    assert np.allclose(got[-3:], got[-3], atol=1e-9)  # both ends and the middle: on the segment
    point = guess_log_weights(Guess(b[0], b[1], sigma_m, 0.0, 1.0, floor, from_xy_m=b), xy, heading)
    alone = guess_log_weights(Guess(b[0], b[1], sigma_m, 0.0, 1.0, floor), xy, heading)
    assert np.allclose(point, alone, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), floor=st.floats(0.0, 1.0), sigma_m=st.floats(5.0, 300.0),
       yaw_deg=st.floats(-180.0, 180.0), dx=st.floats(-300.0, 300.0), dy=st.floats(-300.0, 300.0))
def test_a_guess_weighs_the_first_particles_within_its_floor(road, seed, floor, sigma_m, yaw_deg, dx, dy):
    """The first weights are finite and sum to one; none falls below ``floor`` of the largest; nearer the guess
    (at the same heading difference) never weighs less; floor 1 leaves them equal."""
    cx, cy = road.xy_m[len(road) // 2]
    p = RoadParticles(road, PARTICLES, seed)
    guess = Guess(cx + dx, cy + dy, sigma_m, math.radians(yaw_deg), math.radians(20.0), floor)
    p.start(Region(cx, cy, 400.0), 0.0, n=3000, guess=guess)
    assert np.isfinite(p.logw).all()  # (no floor and a guess far from every particle: no underflow to 0/0)
    w = np.exp(p.logw)
    assert math.isclose(w.sum(), 1.0, rel_tol=1e-9)
    assert w.min() >= floor * w.max() * (1.0 - 1e-9)
    xy = p.positions()
    d = np.hypot(xy[:, 0] - guess.x_m, xy[:, 1] - guess.y_m)
    heading = p._heading(p.edge, p.along, p.direction)
    a = np.abs(np.remainder(heading - guess.yaw_rad + math.pi, 2 * math.pi) - math.pi)
    same = np.abs(a - a[0]) < 1e-12  # (the particles at the first one's heading difference)
    order = np.argsort(d[same])
    assert np.all(np.diff(w[same][order]) <= 1e-15)
    if floor == 1.0:
        assert np.allclose(w, 1.0 / len(w))


_finite = st.floats(-1e7, 1e7, allow_nan=False, allow_subnormal=False)


@given(hnp.arrays(np.float64, st.tuples(st.integers(1, 300), st.just(2)), elements=_finite),
       st.integers(0, 2**32 - 1))
def test_the_weighted_mean_of_the_particles_is_numpys_average_to_the_bit(xy, seed):
    """located()'s centres: the written-out weighted mean gives np.average's bits (the engine's results stay the
    same to the bit), whatever the points and the weights (from 1e-300 to 1)."""
    w = np.random.default_rng(seed).random(len(xy)) ** 8 + 1e-300
    assert np.array_equal(_weighted_mean_xy(xy, w), np.average(xy, axis=0, weights=w))


@given(hnp.arrays(np.float64, st.integers(1, 300), elements=_finite), _finite)
def test_the_median_of_the_particles_sigmas_is_numpys_to_the_bit(v, x):
    assert _median(v) == float(np.median(v))
    assert _median(x) == float(np.median(x))
