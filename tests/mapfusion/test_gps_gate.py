"""The GPS gate after an odometry outage: where a re-initialised odometry resumed is a guess, so the first
fixes that agree with each other place the estimate anew, and the correction reaches back to the outage."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from mapfusion import FusionConfig, MapFusion
from mapfusion.config import OutageStep, StateModel
from mapfusion.gps_gate import GpsGate, Verdict
from mapfusion.roadmap import RoadMap
from mapfusion.track import Track
from tests.helpers import straight_road, write_osm

CFG = FusionConfig()


def _track(n: int = 200, speed_mps: float = 10.0) -> Track:
    """Frames at 10 Hz along x, each with an online estimate on the truth."""
    track = Track(StateModel.planar, 0.1, flat=True)
    for k in range(n):
        track.append(0.1 * k, gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(speed_mps * 0.1 if k else 0.0, 0.0, 0.0)))
        track.online[k] = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(speed_mps * 0.1 * k, 0.0, 0.0))
    return track


@given(dx=st.floats(-300.0, 300.0), dy=st.floats(-300.0, 300.0))
def test_after_an_outage_two_agreeing_fixes_re_anchor(dx, dy):
    """Fixes offset by (dx, dy) from an estimate that moves as they do: beyond the ordinary gate they are
    rejected until three agree; after :meth:`GpsGate.open` the second already re-anchors, back to the outage."""
    track = _track()
    off = math.hypot(dx, dy)
    ordinary = CFG.gps_gate_sigma * math.sqrt(2.0**2 + CFG.gps_gate_floor_m**2)

    def fix(gate, k):  # (the estimate's own σ 0: an opened gate ignores it, the closed one adds it)
        return gate.check(track, k, 10.0 * 0.1 * k + dx, dy, 2.0, 0.0)

    closed, opened = GpsGate(CFG), GpsGate(CFG)
    opened.open(100.0, 90)
    if off <= ordinary:
        assert fix(closed, 100) is Verdict.accept and fix(opened, 100) is Verdict.accept
        assert opened.open_m == 0.0  # an accepted fix closes it
        return
    assert fix(closed, 100) is Verdict.reject and fix(closed, 110) is Verdict.reject
    assert fix(opened, 100) is Verdict.reject
    if off > CFG.gps_gate_sigma * math.hypot(math.sqrt(4.0 + CFG.gps_gate_floor_m**2), 100.0):
        assert fix(opened, 110) is Verdict.reject  # beyond even the widened gate
        return
    assert fix(opened, 110) is Verdict.relocalise
    r = opened.relocalisation(track, 2.0)
    assert r.since_k == 90 and [k for _, _, k in r.fixes] == [100, 110]
    assert math.hypot(r.pose.x() - (110.0 + dx), r.pose.y() - dy) < 1e-6


def test_fixes_that_disagree_with_the_odometry_do_not_re_anchor_after_an_outage():
    """Two far fixes whose distance apart is not the odometry's (a GPS outlier and a good fix) do not move it."""
    track = _track()
    gate = GpsGate(CFG)
    gate.open(100.0, 90)
    assert gate.check(track, 100, 100.0 + 150.0, 0.0, 2.0, 1.0) is Verdict.reject
    assert gate.check(track, 110, 110.0 + 40.0, 60.0, 2.0, 1.0) is Verdict.reject


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    return RoadMap.from_osm(write_osm(tmp_path_factory.mktemp("osm"), [(straight_road(4000.0, 0.0, (-2000.0, 0.0)),
                                                                      {"highway": "primary", "lanes": "2"})]))


def _outage_drive(road: RoadMap, resume_off_m: float, resume_turn_rad: float, every: int = 10, at: int = 600):
    """10 m/s along the road with GPS every second, every ``every`` frames after the outage; the VO out for 20 s
    (frames ``at`` to ``at`` + 199) and resuming ``resume_off_m`` to the side with its heading turned by
    ``resume_turn_rad``. Returns (engine, truth x)."""
    n = at + 800
    x = -1500.0 + np.arange(n) * 1.0
    odo = [gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(float(xi), 0.0, 0.0)) for xi in x]
    jump = gtsam.Pose3(gtsam.Rot3.Yaw(resume_turn_rad), gtsam.Point3(0.0, resume_off_m, 0.0))
    resumed = odo[at + 200]
    for k in range(at + 200, n):  # the odometry after the outage: its own path, moved and turned about where it resumed
        odo[k] = resumed.compose(jump).compose(resumed.between(odo[k]))
    # (the odometry's own step over the outage, as a VO reports it: the engine's own guess would not be off)
    eng = MapFusion(road, FusionConfig(outage_step=OutageStep.odometry), odometry_rate_hz=10.0)
    last = None
    for k in range(n):
        if k % (every if k >= at else 10) == 0:
            lat, lon = road.projection.to_geo(float(x[k]), 0.0)
            eng.add_gps(0.1 * k, float(lat), float(lon), None, 2.0)
        if at <= k < at + 200:
            continue
        rel = gtsam.Pose3() if last is None else odo[last].between(odo[k])
        eng.add_odometry(0.1 * k, rel.matrix())
        last = k
    eng.finish()
    return eng, x


@pytest.mark.parametrize(("every", "at"), [(10, 600), (10, 1000), (50, 1000)],
                         ids=["in-initialisation", "after-initialisation", "after-initialisation-5s"])
def test_a_vo_resuming_300_m_off_and_turned_is_placed_by_the_next_two_fixes_back_to_the_outage(straight, every, at):
    """GPS every second (or every 5 s after the outage); after the outage the VO resumes 300 m off, turned by 90° (inside
    the initialisation's window — it initialises at 83 s — or after it). The gate opens, the next two fixes
    re-anchor, and every smoothed frame after the outage ends within 10 m of the truth (before: three fixes were
    needed and the frames before the re-anchoring stayed 300 m off)."""
    eng, x = _outage_drive(straight, 300.0, math.radians(90.0), every, at)
    assert eng.counters.gps_relocalisations >= 1
    traj = eng.trajectory()
    errs = [math.hypot(p.x() - x[round(t / 0.1)], p.y()) for t, p in traj.items() if t >= 0.1 * (at + 200) - 1e-9]
    assert len(errs) == 600 and max(errs) < 10.0, max(errs)


@given(bad=st.tuples(st.floats(-300.0, 300.0), st.floats(-300.0, 300.0)).filter(lambda b: math.hypot(*b) > 40.0),
       dx=st.floats(150.0, 300.0), opened=st.booleans())
def test_a_run_drops_a_first_fix_that_disagrees_and_re_anchors_on_the_rest(bad, dx, opened):
    """A far fix that disagrees with the later ones (taken in an outage and attached to the frame after it, or
    an outlier) no longer blocks the run until it ages out of the window: the run is its longest consistent
    tail, so the later fixes re-anchor as soon as there are enough of them (two after an outage, else three)."""
    assume(math.hypot(dx + bad[0], bad[1]) > 60.0)  # far from the estimate: not taken
    assume(abs(math.hypot(10.0 - bad[0], bad[1]) - 10.0) > 15.0)  # and 10 m on, the next fix disagrees with it
    track = _track()
    gate = GpsGate(CFG)
    if opened:
        gate.open(400.0, 90)

    def fix(k, extra=(0.0, 0.0)):
        return gate.check(track, k, 10.0 * 0.1 * k + dx + extra[0], extra[1], 2.0, 0.0)

    assert fix(100, bad) is Verdict.reject
    assert fix(110) is Verdict.reject  # (it and the bad one disagree: the bad one leaves the run)
    assert len(gate.run) == 1
    if opened:
        assert fix(120) is Verdict.relocalise
    else:
        assert fix(120) is Verdict.reject and fix(130) is Verdict.relocalise
    r = gate.relocalisation(track, 2.0)
    assert math.hypot(r.pose.x() - (10.0 * 0.1 * r.k + dx), r.pose.y()) < 1e-6


def test_online_estimates_stay_causal_when_a_re_anchoring_reaches_back(straight):
    """After the outage the next fixes come every 5 s: the frames between the VO's resumption and the
    re-anchoring keep the estimate the engine had then (300 m off: the online error is causal), while their
    smoothed estimates are mended."""
    eng, x = _outage_drive(straight, 300.0, math.radians(90.0), 50, 1000)
    t_s, online = eng.online_estimates()
    traj = eng.trajectory()
    waiting = [i for i, t in enumerate(t_s) if 120.0 - 1e-9 <= t < 124.9]  # resumed at 120 s; fixes at 120, 125 s
    assert len(waiting) == 49
    assert min(math.hypot(online[i].x() - x[round(t_s[i] / 0.1)], online[i].y()) for i in waiting) > 200.0
    assert max(math.hypot(traj[t_s[i]].x() - x[round(t_s[i] / 0.1)], traj[t_s[i]].y()) for i in waiting) < 10.0


def _denied_drive(road: RoadMap, stretch: float = 1.2):
    """10 m/s along the road with a fix every second, except in a 60 s GPS-denied zone (frames 1000–1599)
    where the odometry overstates the distance by ``stretch``: the estimate leaves the zone 120 m ahead."""
    n = 2200
    x = -1000.0 + np.arange(n) * 1.0
    eng = MapFusion(road, FusionConfig(), odometry_rate_hz=10.0)
    for k in range(n):
        if k % 10 == 0 and not 1000 <= k < 1600:
            lat, lon = road.projection.to_geo(float(x[k]), 0.0)
            eng.add_gps(0.1 * k, float(lat), float(lon), None, 2.0)
        dx = 0.0 if k == 0 else stretch if 1000 <= k < 1600 else 1.0
        eng.add_odometry(0.1 * k, gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(dx, 0.0, 0.0)).matrix())
    eng.finish()
    return eng, x


def test_a_gps_re_localisation_after_a_denied_zone_mends_the_zone_in_the_smoothed_trajectory(straight):
    """GPS returns 120 m from the estimate, three fixes re-localise; the correction is spread back over the zone
    (its smoothed frames within 10 m of the truth, where the online estimates drifted 120 m): the online
    estimates in the zone stay what the engine had then."""
    eng, x = _denied_drive(straight)
    assert eng.counters.gps_relocalisations == 1
    t_s, online = eng.online_estimates()
    traj = eng.trajectory()
    zone = [i for i, t in enumerate(t_s) if 100.0 <= t < 160.0]
    smoothed_err = max(abs(traj[t_s[i]].x() - x[round(t_s[i] / 0.1)]) for i in zone)
    assert abs(online[zone[-1]].x() - x[round(t_s[zone[-1]] / 0.1)]) > 100.0
    assert smoothed_err < 10.0, smoothed_err


def _stalled_track(n: int = 300) -> Track:
    """Frames at 10 Hz whose odometry has stalled: every online estimate at the origin."""
    track = Track(StateModel.planar, 0.1, flat=True)
    for k in range(n):
        track.append(0.1 * k, gtsam.Pose3())
        track.online[k] = gtsam.Pose3()
    return track


@given(speed=st.floats(20.0, 60.0), ahead=st.floats(30.0, 500.0), needed=st.integers(3, 30),
       sigma=st.floats(0.2, 0.5))
def test_a_run_of_fixes_that_agree_only_with_each_other_re_anchors_once_long_enough(speed, ahead, needed, sigma):
    """RTK fixes at 10 Hz moving at ``speed`` while the odometry has stalled (issue 16: TrianFlow on KITTI 01):
    each is rejected and no run agrees with the odometry's distances, but the fixes agree with each other as
    a track, so the ``relocalise_track_fixes``-th in a row re-anchors on the last one; with the rule off,
    none does."""
    # (over two fixes the GPS moves farther than the odometry rule's tolerance: that rule never fires)
    assume(speed * 0.2 > CFG.gps_gate_sigma * math.sqrt(2.0) * sigma)
    track = _stalled_track()
    cfg = FusionConfig(relocalise_track_fixes=needed)
    gates = {True: GpsGate(cfg), False: GpsGate(FusionConfig(relocalise_track_fixes=0))}
    for on, gate in gates.items():
        for i in range(needed + 20):
            k = 10 + i
            verdict = gate.check(track, k, ahead + speed * 0.1 * i, 0.0, sigma, 0.05)
            if on and i == needed - 1:
                assert verdict is Verdict.relocalise
                r = gate.relocalisation(track, sigma)
                assert r.k == k and math.hypot(r.pose.x() - (ahead + speed * 0.1 * i), r.pose.y()) < 1e-6
                assert [kk for _, _, kk in r.fixes] == list(range(10, k + 1))
                break
            assert verdict is Verdict.reject


@given(seed=st.integers(0, 10_000))
def test_scattered_outliers_never_make_a_track(seed):
    """Fixes scattered ±300 m about a right estimate (multipath outliers, each on its own) are out of a
    vehicle's reach of each other: no run of them, whatever its length, re-anchors the estimate."""
    rng = np.random.default_rng(seed)
    track = _track(n=500)
    gate = GpsGate(CFG)
    for k in range(100, 400):
        dx, dy = rng.uniform(-300.0, 300.0, 2)
        if math.hypot(dx, dy) < 60.0:
            continue  # (near the estimate: taken, and the run ends anyway)
        assert gate.check(track, k, 10.0 * 0.1 * k + dx, dy, 0.5, 0.1) is Verdict.reject


def _collapsed_track(speed_mps: float, factor: float, n: int = 300) -> Track:
    """Frames at 10 Hz whose odometry reports 1/``factor`` of a vehicle's ``speed_mps`` (a mono VO whose scale
    collapsed): the online estimates move that slowly along x from the origin."""
    track = Track(StateModel.planar, 0.1, flat=True)
    for k in range(n):
        x = speed_mps / factor * 0.1 * k
        track.append(0.1 * k, gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(speed_mps / factor * 0.1 if k else 0.0, 0.0, 0.0)))
        track.online[k] = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(x, 0.0, 0.0))
    return track


@given(speed=st.floats(15.0, 60.0), factor=st.floats(1.5, 40.0), ahead=st.floats(30.0, 500.0),
       needed=st.integers(5, 30), sigma=st.floats(0.2, 0.5))
def test_a_track_run_measures_how_far_the_odometry_s_scale_is_off(speed, factor, ahead, needed, sigma):
    """RTK fixes at 10 Hz moving ``factor`` times as fast as the estimate: the track run that re-anchors it
    carries the ratio of the two chords (``factor``, to rounding) and its relative σ (√2 σ over the chord), when
    the chord is at least ``relocalise_rescale_min_sigmas`` σ long and the factor within
    ``relocalise_rescale_max``; else none."""
    # (the odometry rule's run of three fixes must disagree with the odometry's distances, so the track rule fires)
    assume(speed * 0.2 * (1.0 - 1.0 / factor) - 0.05 * speed * 0.2 / factor > CFG.gps_gate_sigma * math.sqrt(2.0) * sigma)
    # (a factor at the limit itself is either side of it once the chords are rounded: a full run found factor = 20.0,
    # whose ratio of chords came out just above 20 and was refused)
    assume(abs(factor - CFG.relocalise_rescale_max) > 1e-6 * CFG.relocalise_rescale_max)
    track = _collapsed_track(speed, factor)
    gate = GpsGate(FusionConfig(relocalise_track_fixes=needed))
    for i in range(needed):
        verdict = gate.check(track, 10 + i, ahead + speed * 0.1 * (10 + i), 0.0, sigma, 0.05)
    assert verdict is Verdict.relocalise
    r = gate.relocalisation(track, sigma)
    chord = speed * 0.1 * (needed - 1)
    if chord < CFG.relocalise_rescale_min_sigmas * sigma or factor > CFG.relocalise_rescale_max:
        assert r.scale_ratio is None
    else:
        assert r.scale_ratio is not None
        ratio, rel_sigma = r.scale_ratio
        assert ratio == pytest.approx(factor, rel=1e-9)
        assert rel_sigma == pytest.approx(math.sqrt(2.0) * sigma / chord, rel=1e-9)
    assert not gate.by_track  # (handed out once)


def _collapse_drive(road: RoadMap, rescale: bool, factor: float = 8.0, **cfg):
    """25 m/s along the road with 10 Hz RTK fixes (σ 0.5 m) for the first 60 s; the odometry (metric until
    then) reports 1/``factor`` of the motion from 30 s on, as TrianFlow did on KITTI 01 (26 m/s, eightfold).
    Returns (engine, truth x)."""
    n = 1500
    x = -1950.0 + 2.5 * np.arange(n)
    # (only the track rule re-anchors here, as on KITTI 01: the odometry rule's short runs keep firing on a
    # synthetic drive, its fixes taken between them dragging the estimate along)
    config = FusionConfig(relocalise_after_fixes=100, relocalise_rescale_max=20.0 if rescale else 1.0, **cfg)
    eng = MapFusion(road, config, gps_rate_hz=10.0, odometry_rate_hz=10.0)
    for k in range(n):
        if k < 600:
            lat, lon = road.projection.to_geo(float(x[k]), 0.0)
            eng.add_gps(0.1 * k, float(lat), float(lon), None, 0.5)
        dx = 0.0 if k == 0 else 2.5 / factor if k >= 300 else 2.5
        eng.add_odometry(0.1 * k, gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(dx, 0.0, 0.0)).matrix())
    eng.finish()
    return eng, x


@pytest.mark.parametrize("rescale, heading_priors", [
    pytest.param(True, True, marks=pytest.mark.xfail(strict=True, raises=AssertionError, reason=(
        "with the heading priors (the default) the track runs re-scale 1.00 -> 7.30 -> "
        "5.29 -> 7.72 and the estimate ends 79.8 m behind (heading priors off: 6.96 -> 7.84, then 8.00 from the "
        "fit, 0.3 m). A run's ratio is the GPS chord over the online estimate's, and the smoother's update every "
        "5 frames moves the online estimate inside the run (13 m forwards in one frame of the second run): the "
        "heading priors change when those updates fall. The odometry's own chord is what the ratio wants"))),
    (True, False), (False, True)])
def test_a_vo_whose_scale_collapsed_is_re_scaled_by_the_gps_track_run(straight, rescale, heading_priors):
    """The odometry's scale falls eightfold at 30 s, inside the GPS: the fixes leave the estimate behind, a track
    run re-anchors it and re-scales the odometry, and 90 s after the GPS ends the estimate is still with the
    vehicle (within 10 m). Without the re-scaling it falls behind at 22 m/s: by more than 1 km."""
    eng, x = _collapse_drive(straight, rescale, **({} if heading_priors else {"heading_prior_sigma_deg": 0.0}))
    t_s, online = eng.online_estimates()
    err_end = abs(online[-1].x() - x[-1])
    if rescale:
        assert eng.counters.gps_rescales >= 1
        assert eng.scale == pytest.approx(8.0, rel=0.05)
        assert err_end < 10.0, err_end
    else:
        assert eng.counters.gps_rescales == 0 and eng.counters.gps_relocalisations >= 1
        assert eng.scale == pytest.approx(1.0, rel=0.05)
        assert err_end > 1000.0, err_end
