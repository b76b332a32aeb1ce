"""Road fixes (issues 16 and 17): road-network particles follow the vehicle while GPS is silent and their
confident answer pulls the estimate back onto the roads — even when the odometry's scale has wandered
away from the one GPS measured."""

from __future__ import annotations

import dataclasses
import math

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapfusion import FusionConfig, MapFusion, RoadMap
from mapfusion.counters import Counters
from mapfusion.relocalise import SEARCH_PARTICLES, Located
from mapfusion.tracking import ROAD_FIX_PARAMS, RoadFixes
from tests.helpers import MAPS, drifting_odometry, graph_route, odometry_step, search_params

ON = FusionConfig(road_fixes=True)
OFF = FusionConfig(road_fixes=False)
P = ROAD_FIX_PARAMS


@pytest.fixture(scope="module")
def road():
    return RoadMap.from_osm(MAPS / "helsinki.osm.pbf")


def _wandering(road, seed, length_m=2500.0, gps_frames=400, scale_after=1.2):
    """A 10 m/s drive over Helsinki's graph (10 Hz) whose odometry reports 1/``scale_after`` of each metre once
    GPS (every second for the first ``gps_frames``) has ended — a monocular VO's scale wandering by 20% — and
    whose heading drifts 2°/100 m."""
    x, y, yaw, _ = graph_route(road, seed, length_m)
    scale = np.where(np.arange(len(x) - 1) < gps_frames + 50, 1.0, 1.0 / scale_after)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, scale=scale, yaw_drift_rad_per_m=math.radians(2.0) / 100,
                                     heading_rad=0.7, noise_m=0.02)
    return x, y, ox, oy, oyaw


def _run(road, cfg, x, y, ox, oy, oyaw, gps_frames, params=ROAD_FIX_PARAMS):
    """The engine over the drive (its road fixes built with ``params``): (engine, mean online error after GPS,
    final error)."""
    eng = MapFusion(road, cfg, odometry_rate_hz=10.0)
    eng._road_fixes.params = params
    errs = []
    for k in range(len(x)):
        if k % 10 == 0 and k < gps_frames:
            lat, lon = road.projection.to_geo(x[k], y[k])
            eng.add_gps(0.1 * k, float(lat), float(lon), None, 1.0)
        eng.add_odometry(0.1 * k, odometry_step(ox, oy, oyaw, k))
        p = eng.estimate()
        if p is not None and k >= gps_frames:
            errs.append(math.hypot(p.x() - x[k], p.y() - y[k]))
    eng.finish()
    p = eng.estimate()
    return eng, float(np.mean(errs)) if errs else math.nan, math.hypot(p.x() - x[-1], p.y() - y[-1])


@pytest.mark.slow
@pytest.mark.parametrize("widths", [1.0, P.agree_widths])
def test_road_fixes_hold_a_drive_whose_scale_wandered_after_gps(road, widths):
    """Four drives whose odometry's scale moves 20% from the one GPS measured once GPS ends: without road
    fixes the estimate runs along (and off) the roads — mean online error after GPS 54 m over the four when
    measured, each over 10 m; with them it stays near the roads' answer and the map re-measures the scale.
    With fixes wherever the estimate strays beyond the road's width (RoadFixParams.agree_widths 1) 9.5 m when
    measured: at most 12 m. The default lets an estimate stray 2.5 widths before a fix (the simulated VO on
    KITTI's drives was pulled to the particles' errors): 14.1 m when measured; under a third of the error
    without, and better on every drive, in both."""
    on_params = dataclasses.replace(P, agree_widths=widths)
    off_errs, on_errs = [], []
    for seed in (1, 2, 3, 4):
        drive = _wandering(road, seed)
        _, off, _ = _run(road, OFF, *drive, 400)
        on_eng, on, _ = _run(road, ON, *drive, 400, on_params)
        assert on_eng.counters.road_fixes > 0
        assert on < off, (seed, off, on)
        off_errs.append(off)
        on_errs.append(on)
    assert min(off_errs) > 10.0, off_errs
    assert np.mean(on_errs) < np.mean(off_errs) / 3.0, (off_errs, on_errs)
    if widths == 1.0:
        assert np.mean(on_errs) <= 12.0, on_errs


@pytest.mark.slow
def test_the_map_re_measures_a_scale_that_wandered(road):
    """After GPS the odometry reports 1/1.2 of each metre: the fixes' clusters carry the scale, and the engine's
    scale moves from GPS's (1) towards 1.2 — with RoadFixParams.scale_gain 0 it stays where GPS left it."""
    drive = _wandering(road, 1)
    fixed, _, _ = _run(road, ON, *drive, 400, dataclasses.replace(P, scale_gain=0.0))
    on, _, _ = _run(road, ON, *drive, 400)
    assert fixed.scale == pytest.approx(1.0, abs=0.03)
    assert on.scale > fixed.scale + 0.08


def test_no_fix_while_gps_comes(road):
    """With fixes every second to the end, the particles never start: no road fix, the same estimate as
    without them."""
    x, y, ox, oy, oyaw = _wandering(road, 5, length_m=900.0)
    off, _, err_off = _run(road, OFF, x, y, ox, oy, oyaw, len(x))
    on, _, err_on = _run(road, ON, x, y, ox, oy, oyaw, len(x))
    assert on.counters.road_fixes == 0 and on.counters.road_fixes_gated == 0
    assert err_on == pytest.approx(err_off, abs=1e-9)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.floats(0.8, 1.25))
def test_a_fix_comes_only_from_a_confident_posterior_and_is_never_tighter_than_its_floor(road, seed, scale):
    """Whatever the drive and the odometry's scale error: each fix is given only when one disc holds the
    configured mass, its σ is at least RoadFixParams.sigma_m and its place lies on the map's roads."""
    x, y, yaw, _ = graph_route(road, seed, 600.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, scale=scale, heading_rad=0.4, noise_m=0.02)
    params = dataclasses.replace(P, every_m=10.0, agree_m=0.0)  # (the estimate is the truth)
    fixes = RoadFixes(road, ON, Counters(), params)
    for k in range(len(x)):
        pred = gtsam.Pose3(gtsam.Rot3.Yaw(float(yaw[k])), gtsam.Point3(float(x[k]), float(y[k]), 0.0))
        f = fixes.step(k, 0.1 * k + 10.0, (float(ox[k]), float(oy[k]), float(oyaw[k])), 1.0, pred, 1.0)
        if f is None:
            continue
        loc = fixes.last
        assert loc is not None and loc.mass >= params.min_mass
        sigma = 1.0 / math.sqrt(f.noiseModel().precisions()[0])
        assert sigma >= params.sigma_m - 1e-9
        assert np.min(np.hypot(road.xy_m[:, 0] - f.measurementIn()[0], road.xy_m[:, 1] - f.measurementIn()[1])) <= 1.5
    assert fixes.starts >= 1


def test_particles_without_a_confident_answer_start_again_around_the_estimate(road):
    """Particles that give no fix for RoadFixParams.restart_m (the odometry zig-zags where no road does: the
    posterior spreads, or its answer runs away from the estimate) are dropped: they start again where the
    estimate is."""
    fixes = RoadFixes(road, ON, Counters(), dataclasses.replace(P, restart_m=100.0, every_m=10.0))
    x0, y0 = (float(v) for v in road.xy_m[len(road) // 2])
    fixes.step(0, 10.0, (0.0, 0.0, 0.0), 1.0, gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(x0, y0, 0.0)), 1.0)
    assert fixes.starts == 1
    for k in range(1, 400):  # 1.5 m a frame, straight on, zig-zagging sideways: no road fits it for long
        wiggle = 8.0 * math.sin(k / 3.0)
        pred = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(x0 + 1.5 * k, y0, 0.0))
        fixes.step(k, 10.0 + 0.1 * k, (1.5 * k, wiggle, 0.0), 1.0, pred, 1.0)
    assert fixes.starts >= 2


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), rival=st.floats(0.0, 0.5), threshold=st.sampled_from([0.0, 0.05, 0.2]),
       near_only=st.booleans())
def test_a_far_answer_is_no_fix_while_the_particles_still_hold_the_estimate(road, seed, rival, threshold, near_only):
    """An answer farther than RoadFixParams.agree_m from the estimate is a fix only when the particles have ruled the
    estimate's place out: their posterior mass near the estimate (outside the answer's own disc) is under
    RoadFixParams.rival_mass (0: always a fix). And never when the step says ``near_only`` (with
    map_relocalisation, while the estimate's recent path kept to the roads)."""
    from mapfusion.relocalise import RoadParticles

    cfg = ON
    rng = np.random.default_rng(seed)
    n_pts = int(np.count_nonzero(~road.is_join))
    i = int(rng.integers(n_pts))  # the estimate, on a way-point; the answer 40-60 m away on another
    d = np.hypot(road.xy_m[:n_pts, 0] - road.xy_m[i, 0], road.xy_m[:n_pts, 1] - road.xy_m[i, 1])
    far = np.flatnonzero((d > 40.0) & (d < 60.0))
    if far.size == 0:
        return
    j = int(far[rng.integers(far.size)])
    p = RoadParticles(road, SEARCH_PARTICLES)
    n = 1000
    at = np.where(np.arange(n) < n // 2, i, j)  # half the particles at each place, weighted rival : 1 - rival
    p.edge, p.direction = road.edge[at].astype(np.int64), np.ones(n, dtype=np.int64)
    p.along, p.offset, p.log_scale = road.s_m[at].astype(np.float64), np.zeros(n), np.zeros(n)
    w = np.where(at == i, rival, 1.0 - rival) / (n // 2) + 1e-300
    p.logw = np.log(w / w.sum())
    fixes = RoadFixes(road, cfg, Counters(), dataclasses.replace(P, rival_mass=threshold))
    fixes.particles = p
    xj, yj = (float(v) for v in road.xy_m[j])
    loc = Located(xj, yj, 0.0, 0.0, int(road.edge[j]), 1, float(road.s_m[j]), 1.0 - rival, 1.0, 0.0, 100.0)
    pred = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(float(road.xy_m[i, 0]), float(road.xy_m[i, 1]), 0.0))
    fixes._near_only = near_only
    held = fixes._agrees(loc, pred)
    assert held == (near_only or threshold > 0 and rival >= threshold - 1e-9) or abs(rival - threshold) < 1e-6


@settings(max_examples=20, deadline=None)
@given(cap=st.integers(10, 5_000), sigma_m=st.floats(1.0, 2000.0), factor=st.floats(1.0, 2.0))
def test_a_start_spreads_at_most_road_fix_particles_per_scale_band(road, cap, sigma_m, factor):
    """However large the region a start covers (3 σ of the estimate), the particles it spreads are at most
    RoadFixParams.particles per scale band (issue 21: a region grown by a long stretch without a fix costs no more);
    a cap under the 1000 a start spreads at least is the count itself."""
    from mapfusion.relocalise import SCALE_BAND
    fixes = RoadFixes(road, ON, Counters(), dataclasses.replace(P, particles=cap, scale_factor=factor))
    x0, y0 = (float(v) for v in road.xy_m[len(road) // 2])
    fixes.step(0, 10.0, (0.0, 0.0, 0.0), 1.0, gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(x0, y0, 0.0)), sigma_m)
    bands = max(1.0, 2.0 * math.log(factor) / math.log(SCALE_BAND))
    assert fixes.particles is not None and fixes.starts == 1
    assert len(fixes.particles) <= int(bands * cap)
    if cap <= 1000:
        assert len(fixes.particles) == int(bands * cap)


@settings(max_examples=20, deadline=None)
@given(unfixed_m=st.floats(0.0, 20000.0), sigma_m=st.floats(0.5, 1000.0))
def test_a_re_anchoring_restarts_the_particles_around_the_new_estimate_in_the_start_radius(road, unfixed_m, sigma_m):
    """A start after a long stretch without a fix spreads over 3 × the drift since (the estimate may be that far
    off), up to RoadFixParams.radius_max_m; after a re-anchoring the estimate is placed afresh, so the next start's
    region is the start radius (or 3 σ) again, not the old drift's."""
    fixes = RoadFixes(road, ON, Counters())
    x0, y0 = (float(v) for v in road.xy_m[len(road) // 2])
    pred = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(x0, y0, 0.0))
    fixes._unfixed_m = unfixed_m
    fixes.step(0, 10.0, (0.0, 0.0, 0.0), 1.0, pred, sigma_m)
    grown = min(max(P.radius_m, 3.0 * sigma_m, 3.0 * P.drift * unfixed_m), P.radius_max_m)
    assert fixes.starts == 1 and fixes._ref_slack_m == pytest.approx(grown)
    fixes.reanchored()
    assert fixes.particles is None
    fixes.step(1, 10.1, (0.0, 0.0, 0.0), 1.0, pred, sigma_m)
    # (a start after it waits for a straight step)
    fixes.step(2, 10.2, (SEARCH_PARTICLES.step_m, 0.0, 0.0), 1.0, pred, sigma_m)
    assert fixes.starts == 2 and fixes._ref_slack_m == pytest.approx(min(max(P.radius_m, 3.0 * sigma_m),
                                                                         P.radius_max_m))


@settings(max_examples=20, deadline=None)
@given(turn_deg_per_m=st.floats(1.5, 10.0), straight_m=st.floats(6.0, 30.0))
def test_a_steady_start_waits_for_the_turn_to_end(road, turn_deg_per_m, straight_m):
    """After a re-anchoring the particles do not start while the odometry turns by more than
    RoadFixParams.offset_max_deg over ParticleParams.step_m (here at least 7.5° per 5 m), and start once it has
    driven straight for ParticleParams.step_m; a first start is on the first frame."""
    x0, y0 = (float(v) for v in road.xy_m[len(road) // 2])
    pred = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(x0, y0, 0.0))
    fixes, eager = RoadFixes(road, ON, Counters()), RoadFixes(road, ON, Counters())
    fixes.reanchored()
    x = y = yaw = 0.0
    k, t = 0, 10.0
    for _ in range(60):  # a 60 m turn, 1 m a frame
        eager.step(k, t, (x, y, yaw), 1.0, pred, 1.0)
        fixes.step(k, t, (x, y, yaw), 1.0, pred, 1.0)
        x, y, yaw = x + math.cos(yaw), y + math.sin(yaw), yaw + math.radians(turn_deg_per_m)
        k, t = k + 1, t + 0.1
    assert eager.starts == 1 and fixes.starts == 0
    for _ in range(int(straight_m) + 1):  # then straight on
        fixes.step(k, t, (x, y, yaw), 1.0, pred, 1.0)
        x, y = x + math.cos(yaw), y + math.sin(yaw)
        k, t = k + 1, t + 0.1
    assert fixes.starts == 1


@pytest.mark.slow
def test_road_fixes_wait_while_a_search_runs(road):
    """With map_relocalisation and SearchParams.gps_fit_min 0 a search starts when GPS falls silent (a second opinion on
    where GPS left the estimate, here on the roads: the default would not search; begun at the silence, with no
    replay of the path under GPS); no road fix enters the graph while it runs (the fixes' particles start around
    the very estimate the search questions), and the fixes come once it has ended; without the map search (no
    search runs) the fixes come at once. (Route 2: on route 1 the search, seeded by the frame it begins at, does not
    end within the drive.)"""
    drive = _wandering(road, 2)
    seen = {}
    for waits in (True, False):
        eng = MapFusion(road, dataclasses.replace(ON, map_relocalisation=waits), odometry_rate_hz=10.0)
        x, y, ox, oy, oyaw = drive
        during = after = searched = 0
        with search_params(gps_fit_min=0.0, gps_replay_m=0.0):
            for k in range(len(x)):
                if k % 10 == 0 and k < 400:
                    lat, lon = road.projection.to_geo(x[k], y[k])
                    eng.add_gps(0.1 * k, float(lat), float(lon), None, 1.0)
                searching, before = eng._map_search.running, eng.counters.road_fixes
                eng.add_odometry(0.1 * k, odometry_step(ox, oy, oyaw, k))
                new = eng.counters.road_fixes - before
                searched += searching
                during += new if searching else 0
                after += new if not searching and k >= 400 else 0
        seen[waits] = (during, after, searched)
    assert seen[True][2] > 0 and seen[True][0] == 0 and seen[True][1] > 0, seen
    assert seen[False][2] == 0 and seen[False][1] > 0, seen


@pytest.mark.parametrize("relocalise", [True, False])
def test_the_road_fixes_are_kept_near_only_with_a_search_to_move_the_estimate_far(road, relocalise):
    """With map_relocalisation (whose search moves a lost estimate far), every road fix is kept near the estimate
    while the estimate's last SearchParams.gps_fit_m lay on the roads (kidnapped GPS bias Helsinki s2 and s30: good
    estimates were moved 190-460 m by road fixes otherwise) —
    measured by the association only with map_relocalisation. Without it the fixes may move an estimate far (they
    are the only way back). A drive tracked on Helsinki's roads after its GPS ends: at its end the path kept to the
    roads."""
    x, y, yaw, _ = graph_route(road, 3, 1500.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, 3, heading_rad=0.7, noise_m=0.02)
    cfg = dataclasses.replace(ON, map_relocalisation=relocalise)
    eng, _, err = _run(road, cfg, x, y, ox, oy, oyaw, 400)
    assert err < 15.0, err
    assert eng._road_fixes._near_only == relocalise


@pytest.fixture(scope="module")
def grid_city(tmp_path_factory):
    """A regular 3 km × 3 km grid of 150 m blocks: turned by 180° (or 90°), a path over it fits the same roads."""
    from mapfusion import synthetic
    return RoadMap.from_osm(synthetic.write("city", tmp_path_factory.mktemp("city") / "city.osm", width_km=3.0,
                                            height_km=3.0))


def _staircase(start_m: float, quarter_turns: int, length_m: float = 1500.0):
    """A drive up a staircase of the 150 m grid from the 3 km city's centre (the map frame's origin): a block one
    way, a block turned left, a block back the first way, ... (one metre a frame), starting ``start_m`` into its
    first block, the whole turned by ``quarter_turns`` × 90°: (x, y, yaw)."""
    corners = [(0.0, 0.0)]
    for i in range(int(length_m // 150.0) + 2):
        cx, cy = corners[-1]
        corners.append((cx + 150.0, cy) if i % 2 == 0 else (cx, cy + 150.0))
    c = np.array(corners)
    s = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(c, axis=0).T))))
    u = np.arange(start_m, start_m + length_m, 1.0)
    x, y = np.interp(u, s, c[:, 0]), np.interp(u, s, c[:, 1])
    turn = quarter_turns * math.pi / 2.0
    x, y = math.cos(turn) * x - math.sin(turn) * y, math.sin(turn) * x + math.cos(turn) * y
    return x, y, np.arctan2(np.gradient(y), np.gradient(x))


def _confident_share(road, params, x, y, yaw, after_m=400.0):
    """The road fixes fed an exact odometry of a drive, the estimate the truth (its yaw σ 1°): (share of the
    fixes' turns after ``after_m`` at which the particles were confident, starts, particles at the end)."""
    ox, oy, oyaw = drifting_odometry(x, y, yaw, 0, heading_rad=0.4)
    fixes = RoadFixes(road, ON, Counters(), params)
    turns = confident = 0
    for k in range(len(x)):
        pred = gtsam.Pose3(gtsam.Rot3.Yaw(float(yaw[k])), gtsam.Point3(float(x[k]), float(y[k]), 0.0))
        fixes.last = unset = Located(0.0, 0.0, 0.0, 0.0, 0, 1, 0.0, 0.0, 0.0, 0.0, 0.0)  # (a fix's turn sets it)
        fixes.step(k, 0.1 * k + 10.0, (float(ox[k]), float(oy[k]), float(oyaw[k])), 1.0, pred, 1.0,
                   yaw_sigma_rad=math.radians(1.0))
        if k >= after_m and fixes.last is not unset:
            turns += 1
            confident += fixes.last is not None
    return confident / max(turns, 1), fixes.starts, len(fixes.particles) if fixes.particles is not None else 0


@pytest.mark.parametrize("start_m, quarter_turns", [(0.0, 0), (75.0, 1), (149.0, 2), (30.0, 3)])
def test_on_a_regular_grid_the_estimates_heading_lets_the_particles_settle(grid_city, start_m, quarter_turns):
    """Issue 21: a start spreads both ways along every road of its region, and on a regular grid the path turned
    by 180° about a block's centre (or by 90° about a junction) fits the odometry as well as the true one for
    ever. Where such a copy lies within the start's region (50 m: not from every place in a block, and the
    particles' resampling may lose one copy by chance, so four starts where none was lost), over a drive that
    turns at every junction the particles never agree on one place, start again every RoadFixParams.restart_m over a
    wider region, and cost the most they may. Weighted by the estimate's heading
    (RoadFixParams.heading_sigma_deg) they agree after the first turns, settle to a few and never start again."""
    drive = _staircase(start_m, quarter_turns)
    share_on, starts_on, n_on = _confident_share(grid_city, dataclasses.replace(P, heading_sigma_deg=20.0),
                                                 *drive)
    share_off, starts_off, n_off = _confident_share(grid_city, dataclasses.replace(P, heading_sigma_deg=0.0),
                                                    *drive)
    assert share_on >= 0.9 and starts_on == 1 and n_on <= 2000, (share_on, starts_on, n_on)
    assert share_off <= 0.1 and starts_off >= 3 and n_off >= 5 * n_on, (share_off, starts_off, n_off)


@settings(max_examples=25, deadline=None)
@given(frac=st.floats(0.0, 1.0), turn=st.floats(-math.pi, math.pi), sigma_deg=st.floats(5.0, 60.0),
       floor=st.floats(0.0, 0.5), yaw_sigma_deg=st.floats(0.0, 10.0))
def test_a_start_weighs_each_particle_by_its_heading_against_the_estimates(road, frac, turn, sigma_deg, floor,
                                                                           yaw_sigma_deg):
    """Every particle's start weight falls with the angle between its heading and the estimate's, over a
    σ of RoadFixParams.heading_sigma_deg (or 3 × the marginal yaw σ): any particle within 1 σ outweighs any
    beyond 3 σ by at least the Gaussian's ratio under the floor; without the weighting all weigh the same."""
    i = int(frac * (len(road) - 1))
    heading = float(road.yaw_rad[i]) + turn
    pred = gtsam.Pose3(gtsam.Rot3.Yaw(heading), gtsam.Point3(float(road.xy_m[i, 0]), float(road.xy_m[i, 1]), 0.0))
    for deg in (0.0, sigma_deg):
        fixes = RoadFixes(road, ON, Counters(), dataclasses.replace(P, heading_sigma_deg=deg, heading_floor=floor))
        fixes.step(0, 10.0, (0.0, 0.0, 0.0), 1.0, pred, 1.0, yaw_sigma_rad=math.radians(yaw_sigma_deg))
        p = fixes.particles
        assert p is not None and len(p) > 0
        w = np.exp(p.logw)
        assert w.sum() == pytest.approx(1.0)
        if deg == 0.0:
            assert np.ptp(p.logw) < 1e-12
            continue
        sigma = max(math.radians(deg), 3.0 * math.radians(yaw_sigma_deg))
        a = np.abs(np.remainder(p._heading(p.edge, p.along, p.direction) - heading + math.pi, 2 * math.pi) - math.pi)
        near, far = w[a <= sigma], w[a >= 3.0 * sigma]
        if near.size and far.size:
            ratio = (floor + (1.0 - floor) * math.exp(-0.5)) / (floor + (1.0 - floor) * math.exp(-4.5))
            assert near.min() >= ratio * far.max() * (1.0 - 1e-9)


def _any_way_walk(road, length_m: float, seed: int) -> np.ndarray:
    """A drive over the graph that takes any exit at a vertex, one-way streets against their direction too (which
    `mapfusion bench`'s drive must not do): a vehicle the map says may not be there, as where a one-way
    tag is wrong."""
    rng = np.random.default_rng(seed)
    at: dict[int, list[int]] = {}
    for e, (u, v) in enumerate(zip(road.edge_u.tolist(), road.edge_v.tolist())):
        at.setdefault(u, []).append(e)
        at.setdefault(v, []).append(e)
    e, forward, pts, total = int(rng.integers(len(road.edge_u))), True, [], 0.0
    while total < length_m:
        seg = road.xy_m[road.edge_start[e]:road.edge_end[e]]
        pts.append((seg if forward else seg[::-1])[1 if pts else 0:])
        total += float(road.edge_length_m[e])
        end = int(road.edge_v[e] if forward else road.edge_u[e])
        e = int(rng.choice([x for x in at[end] if x != e] or [e]))
        forward = int(road.edge_u[e]) == end
    return np.concatenate(pts)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, raises=AssertionError, reason="a drive that goes the wrong way down a "
                   "one-way street 2 km in (GPS for its first 1.2 km) with an odometry that does not drift: the road "
                   "particles cannot follow it, all of them go on along legal roads, their normalised posterior "
                   "stays confident (mass 1.0) on a place that moves away from the vehicle, and their fixes take "
                   "the estimate 160-320 m off where odometry alone stays within 2-4 m; nothing checks how well "
                   "the particles' own paths fit the odometry in absolute terms")
def test_a_drive_the_map_says_is_illegal_is_never_made_worse_than_odometry_by_the_road_fixes(road):
    from mapfusion.geometry import resample

    pts, _ = resample(_any_way_walk(road, 3000.0, 0), 1.0)
    x, y = pts[:, 0], pts[:, 1]
    assert len(x) > 2900
    yaw = np.arctan2(np.gradient(y), np.gradient(x))
    ox, oy, oyaw = drifting_odometry(x, y, yaw, 0, noise_m=0.02)
    _, alone_m, alone_final_m = _run(road, FusionConfig(use_map=False), x, y, ox, oy, oyaw, 1200)
    eng, fused_m, fused_final_m = _run(road, ON, x, y, ox, oy, oyaw, 1200)
    assert alone_m < 5.0  # (the odometry alone keeps to the drive: what the map may not spoil)
    assert fused_m <= alone_m + 5.0 and fused_final_m <= alone_final_m + 5.0, (fused_m, fused_final_m, alone_m)
