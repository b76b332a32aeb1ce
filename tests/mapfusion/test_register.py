"""Registering a window of GPS fixes on the roads (issue 17, ``mapfusion.register``): a shifted drive is found
by its shape, never confidently in the wrong place, a straight road is never a clear answer, and the engine
moves an estimate that a biased fix window left off the roads at the moment GPS falls silent."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from mapfusion import FusionConfig, RoadMap
from mapfusion.register import register_on_roads, thin_path
from mapfusion.relocalise import SEARCH_PARAMS
from tests.helpers import MAPS, drifting_odometry, graph_route, six_lane_ring, straight_road, write_osm
from tests.mapfusion.test_relocalise import _feed

#: what the engine asks of a registration before it acts (the search's defaults)
CFG = SEARCH_PARAMS


@pytest.fixture(scope="module")
def road():
    return RoadMap.from_osm(MAPS / "helsinki.osm.pbf")


#: the search begun at GPS's silence examines every window and replays nothing of the path under GPS
ANY_FIT = dict(gps_fit_min=0.0, gps_replay_m=0.0)


def _confident(reg) -> bool:
    return reg.decisive(CFG.register_ratio, CFG.register_rms_m, CFG.register_separation_m)


def _shifted_drive(road, seed: int, bias_m: float, angle: float, length_m: float):
    """A legal drive on the map's roads, a point every 10 m with 2 m of noise, all shifted by one bias: (points,
    the bias's dx, dy)."""
    x, y, _, _ = graph_route(road, seed, length_m, spacing_m=10.0)
    rng = np.random.default_rng(seed)
    dx, dy = bias_m * math.cos(angle), bias_m * math.sin(angle)
    return np.column_stack([x + dx, y + dy]) + rng.normal(0.0, 2.0, (len(x), 2)), dx, dy


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), bias_m=st.floats(50.0, 250.0), angle=st.floats(0.0, 2 * math.pi),
       length_m=st.floats(300.0, 1000.0))
def test_a_shifted_drives_best_fit_is_no_worse_than_undoing_its_bias(road, seed, bias_m, angle, length_m):
    """A shifted drive on Helsinki's roads (:func:`_shifted_drive`): the best shift's RMS is no worse than its
    runner-up's and the unshifted one's, and no worse than that of undoing the bias exactly, measured with exact
    nearest way-points (a k-d tree), beyond the grid's quantisation. (Whether a decisive answer is the right one:
    the next test.)"""
    pts, dx, dy = _shifted_drive(road, seed, bias_m, angle, length_m)
    reg = register_on_roads(road, pts, 300.0)
    assert reg is not None
    assert reg.rms_m <= reg.runner_up_rms_m and reg.rms_m <= reg.rms_unshifted_m
    kept = thin_path(pts, 5.0)
    d, _ = cKDTree(road.xy_m).query(kept - (dx, dy))
    exact = math.sqrt(float(np.mean(np.minimum(d, 10.0) ** 2)))
    assert reg.rms_m <= exact + 2.5, (reg, exact)  # (the grid: 2 m cells for the points, the shifts and the roads)


#: Shifted drives (seed, bias m, angle rad, length m) whose look-alike won decisively: two of 300 random Helsinki drives
#: (numpy seed 7 drawing seed, bias 50-250 m, angle and length 300-1000 m), and one hypothesis found.
LOOK_ALIKES = [(3394, 245.91934608966346, 5.916192639472387, 461.46702761077165),
               (4328, 162.8999899161845, 4.221613447282325, 861.6348164998618), (126, 50.0, 0.0, 300.0)]


@pytest.mark.xfail(strict=True, raises=AssertionError, reason="on 300 random Helsinki drives shifted "
                   "50-250 m (2 m noise), 266 answers were decisive and 2 of them were look-alikes 54 and 213 m from "
                   "the truth, ratios 1.26 and 1.27 against the 1.25 required; hypothesis found a third (a 300 m "
                   "drive, 232 m off, ratio 1.31). The ratio of two RMS over a few dozen noisy points does not tell "
                   "a look-alike from the truth every time; the engine's watch and lost search are what remain")
def test_a_decisive_answer_is_never_a_look_alike_beyond_the_separation(road):
    """When the engine's test calls the best shift decisive, it undoes the bias to within the separation (places
    nearer than that are not told apart: a parallel street 18 m away fitted a 341 m drive better than its own when
    first run). The claim is over every drive; checked on the look-alikes found (LOOK_ALIKES)."""
    for case in LOOK_ALIKES:
        pts, dx, dy = _shifted_drive(road, *case)
        reg = register_on_roads(road, pts, 300.0)
        if _confident(reg):
            assert math.hypot(reg.dx_m + dx, reg.dy_m + dy) <= CFG.register_separation_m + 3.0, (case, reg)


def test_most_drives_with_turns_are_found(road):
    """Not only never wrong: of 12 drives of 800 m shifted 150 m, most (measured: 11) come out clear and right."""
    found = 0
    for seed in range(12):
        x, y, _, _ = graph_route(road, seed, 800.0, spacing_m=10.0)
        reg = register_on_roads(road, np.column_stack([x + 106.0, y - 106.0]), 300.0)
        found += _confident(reg) and math.hypot(reg.dx_m + 106.0, reg.dy_m - 106.0) <= 4.0
    assert found >= 9, found


@settings(max_examples=15, deadline=None)
@given(along_m=st.floats(-150.0, 150.0), across_m=st.floats(40.0, 150.0), heading=st.floats(0.0, math.pi))
def test_a_straight_road_is_never_a_clear_answer(tmp_path_factory, along_m, across_m, heading):
    """A straight drive beside a straight road fits it as well wherever along the road it is put: the runner-up
    (farther than the separation) fits as well as the best, so the engine's ratio test refuses it."""
    tmp = tmp_path_factory.mktemp("straight")
    road = RoadMap.from_osm(write_osm(tmp, [(straight_road(2000.0, heading, (-1000.0 * math.cos(heading),
                                                                            -1000.0 * math.sin(heading))),
                                            {"highway": "residential"})]), cache=False)
    c, s = math.cos(heading), math.sin(heading)
    u = np.arange(-200.0, 200.0, 10.0) + along_m
    pts = np.column_stack([u * c - across_m * s, u * s + across_m * c])
    reg = register_on_roads(road, pts, 300.0)
    assert reg is not None and reg.rms_m < 2.0  # (it does reach the road)
    assert reg.runner_up_rms_m <= reg.rms_m + 1.0  # (another place along the road fits as well)
    assert not _confident(reg)


def test_bad_arguments_are_refused_and_too_few_points_give_nothing(road):
    with pytest.raises(ValueError):
        register_on_roads(road, np.zeros((5, 2)), 0.0)
    with pytest.raises(ValueError):
        register_on_roads(road, np.zeros((5, 2)), 100.0, cell_m=-1.0)
    assert register_on_roads(road, np.array([[0.0, 0.0], [1.0, 0.0]]), 100.0) is None
    assert register_on_roads(road, np.array([[0.0, 0.0], [np.nan, 20.0], [0.0, 40.0]]), 100.0) is None


def test_thinning_keeps_points_at_least_that_far_apart_along_the_path():
    pts = np.column_stack([np.arange(0.0, 100.0, 1.0), np.zeros(100)])
    kept = thin_path(pts, 5.0)
    assert kept[0].tolist() == [0.0, 0.0] and len(kept) == 20
    assert np.all(np.hypot(*np.diff(kept, axis=0).T) >= 5.0)


@pytest.mark.slow
def test_the_engine_moves_a_biased_window_onto_the_roads_when_gps_falls_quiet(road):
    """70 s of fixes all 150 m off, then none (routes 6-9 of the search's tests): with the registration (the
    default) the first map re-anchoring comes SearchParams.register_after_s after the last fix (or at the first frame after
    the initialisation, which waits for the fixes to stall: 74.2 s on routes 8 and 9), before GPS's silence would
    begin a search, and moves the estimate onto the truth; with it off, a search re-anchors 99-110 s into the drive
    (measured). SearchParams.gps_fit_min is off, as in the search's test, so that the fixes are examined on every route."""
    last_fix_s = 69.0
    at_silence = 0
    for seed in (6, 7, 8, 9):
        x, y, yaw, _ = graph_route(road, seed, 2400.0)
        ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, heading_rad=0.3, noise_m=0.02)
        cfg = FusionConfig(map_relocalisation=True, road_fixes=False)
        eng, err = _feed(road, cfg, x, y, ox, oy, oyaw, 700, fix_offset=(106.0, 106.0), search=ANY_FIT)
        assert eng.relocalised_at and err < 15.0, (seed, err)
        t, searched = eng.relocalised_at[0]
        at_silence += last_fix_s + CFG.register_after_s - 0.5 <= t < last_fix_s + CFG.after_gps_s \
            and searched == 0.0
    assert at_silence >= 3


@pytest.mark.slow
def test_the_engine_leaves_a_good_window_where_it_is(road):
    """The same drives with unbiased fixes, examined all the same: the registration's best shift lies within the
    separation of the estimate, so it moves nothing; no re-anchoring as GPS falls quiet."""
    for seed in (6, 7):
        x, y, yaw, _ = graph_route(road, seed, 2400.0)
        ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, heading_rad=0.3, noise_m=0.02)
        cfg = FusionConfig(map_relocalisation=True, road_fixes=False)
        eng, err = _feed(road, cfg, x, y, ox, oy, oyaw, 700, search=ANY_FIT)
        assert not any(m == 0.0 for t, m in eng.relocalised_at), eng.relocalised_at  # (a search's has driven)


def test_a_window_ending_in_a_standstill_places_the_heading_from_the_driving_before_it(road):
    """The biased window's last 20 s of fixes at a standstill: the odometry is placed on the fixes back to one
    SearchParams.register_place_m from the last (the driving before the stop), so the heading is known and the estimate
    follows the truth once the vehicle drives on (placed on the last 10 s alone, a standstill left the heading free:
    a kidnapped Helsinki run turned 138° and went 108 m off within 10 s when measured)."""
    seed = 6
    x, y, yaw, _ = graph_route(road, seed, 2400.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, seed, heading_rad=0.3, noise_m=0.02)
    stop, still = 500, 200  # frames 500-699 at a standstill: the fixes of the last 20 s (until frame 700)

    def stopped(a):
        return np.concatenate([a[:stop], np.repeat(a[stop], still), a[stop:]])

    x2, y2 = stopped(x), stopped(y)
    cfg = FusionConfig(map_relocalisation=True, road_fixes=False)
    eng, err = _feed(road, cfg, x2, y2, stopped(ox), stopped(oy), stopped(oyaw), 700, fix_offset=(106.0, 106.0),
                     search=ANY_FIT)
    assert eng.relocalised_at and eng.relocalised_at[0][1] == 0.0, eng.relocalised_at  # (the registration's)
    t_s, online = eng.online_estimates()
    after = [math.hypot(p.x() - x2[k], p.y() - y2[k]) for k, p in enumerate(online)
             if p is not None and eng.relocalised_at[0][0] <= t_s[k] <= eng.relocalised_at[0][0] + 30.0]
    assert after and max(after) < 15.0, max(after)
    assert err < 15.0, err


@pytest.mark.slow
def test_a_biased_window_on_parallel_streets_is_registered_at_the_silence(road):
    """Route 7's fixes, 150 m off diagonally, leave the estimate on parallel streets: it keeps to the roads, and
    a search would wait for the estimate to be called lost (its first re-anchoring at 153.8 s when the
    registration was only for estimates off the roads); the fixes are registered all the same, at the silence
    (SearchParams.register_after_s after the last fix, searched 0), and the drive ends on the truth."""
    last_fix_s = 69.0
    x, y, yaw, _ = graph_route(road, 7, 2400.0)
    ox, oy, oyaw = drifting_odometry(x, y, yaw, 7, heading_rad=0.3, noise_m=0.02)
    cfg = FusionConfig(map_relocalisation=True, road_fixes=False)
    eng, err = _feed(road, cfg, x, y, ox, oy, oyaw, 700, fix_offset=(106.0, 106.0), search=dict(gps_replay_m=0.0))
    assert eng.relocalised_at and err < 15.0, err
    firsts = eng.relocalised_at
    t, searched = firsts[0]
    assert last_fix_s + CFG.register_after_s - 0.5 <= t < last_fix_s + CFG.after_gps_s, firsts
    assert searched == 0.0, firsts
