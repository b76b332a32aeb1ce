"""The odometry jump guard (issue 19): impossible steps are bridged, plausible ones never touched."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from hypothesis import assume, example, given
from hypothesis import strategies as st

from mapfusion.config import FusionConfig, StateModel
from mapfusion.counters import Counters
from mapfusion.engine import MapFusion
from mapfusion.roadmap import RoadMap
from mapfusion.track import SLIDE_FRAMES, JumpGuard, LeverArm, Track, along_heading, slide_of, spread_back
from tests.helpers import straight_road, synthetic_truth, write_osm


def _step(d_m: float, yaw_rad: float = 0.0) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Yaw(yaw_rad), gtsam.Point3(d_m, 0.0, 0.0))


@given(speeds=st.lists(st.floats(0.0, 45.0), min_size=5, max_size=200), dt=st.floats(0.02, 0.5),
       scale=st.one_of(st.none(), st.floats(0.2, 5.0)))
def test_a_drive_at_road_speeds_is_never_touched(speeds, dt, scale):
    g = JumpGuard(70.0)
    for k, v in enumerate(speeds):
        rel = _step(v * dt / (scale or 1.0))
        out, jump = g.check(k * dt, rel, scale)
        assert not jump and out is rel


@given(cruise=st.floats(1.0, 30.0), jump_m=st.floats(1e3, 1e10), dt=st.floats(0.05, 0.2), at=st.integers(10, 60))
def test_an_impossible_jump_is_bridged_with_the_last_motion(cruise, jump_m, dt, at):
    g = JumpGuard(70.0)
    t = 0.0
    g.check(t, gtsam.Pose3(), None)
    for _ in range(at):
        t += dt
        assert not g.check(t, _step(cruise * dt, 0.01), None)[1]
    t += dt
    out, jump = g.check(t, _step(jump_m), None)
    assert jump
    assert math.isclose(float(np.linalg.norm(out.translation())), cruise * dt, rel_tol=1e-9)


@given(cruise=st.floats(1.0, 30.0), dt=st.floats(0.05, 0.2), gap_s=st.floats(0.0, 60.0),
       resumed=st.tuples(st.floats(-500.0, 500.0), st.floats(-500.0, 500.0), st.floats(-3.0, 3.0)))
def test_a_step_over_a_gap_longer_than_the_limit_is_the_last_velocity_straight_on(cruise, dt, gap_s, resumed):
    """Whatever the odometry says it did over a gap longer than gap_s (3 s), the step is the last step's
    velocity over the gap, with no turn (not a jump); over a shorter gap the odometry's own step stands
    (unless it implies an impossible speed: a jump, as before)."""
    g = JumpGuard(70.0, gap_s=3.0)
    t = 0.0
    g.check(t, gtsam.Pose3(), None)
    for _ in range(20):
        t += dt
        g.check(t, _step(cruise * dt, 0.01), None)
    own = gtsam.Pose3(gtsam.Rot3.Yaw(resumed[2]), gtsam.Point3(resumed[0], resumed[1], 0.0))
    out, jump = g.check(t + dt + gap_s, own, None)
    if dt + gap_s <= 3.0:  # (the jump guard's own test still applies)
        assert not g.gap_bridged and (out is own or jump)
        return
    assert g.gap_bridged and not jump
    assert out.rotation().equals(gtsam.Rot3(), 1e-12)
    assert np.allclose(out.translation(), [cruise * (dt + gap_s), 0.0, 0.0], rtol=1e-9, atol=1e-9)


def test_a_monocular_odometry_in_small_units_is_not_flagged_for_its_units():
    """A mono VO whose unit is a thirtieth of a metre reads 300 units/s at 10 m/s before its scale
    is known: its steps are judged against its own typical speed, so a steady drive is no jump."""
    g = JumpGuard(70.0)
    for k in range(100):
        assert not g.check(0.1 * k, _step(30.0), None)[1]  # 300 units/s, steady


def test_the_engine_bridges_a_10000_km_spike_and_counts_it(tmp_path):
    road = RoadMap.from_osm(write_osm(tmp_path, [(straight_road(3000.0, 0.0, (-1500.0, 0.0)),
                                                   {"highway": "primary", "lanes": "2"})]))
    tr = synthetic_truth("straight", n=1500, speed_mps=10.0)
    x = tr.x_m - 700.0
    eng = MapFusion(road)
    lat, lon = road.projection.to_geo(x, tr.y_m)
    prev = np.eye(4)
    counters_before = Counters()
    for k in range(len(tr)):
        cur = np.eye(4)
        cur[0, 3] = x[k] + (1e7 if k == 900 else 0.0)  # one corrupt pose, 10,000 km away
        if k % 10 == 0 and k < 1200:
            eng.add_gps(tr.t_s[k], lat[k], lon[k], None, 2.0)
        eng.add_odometry(tr.t_s[k], np.linalg.inv(prev) @ cur)
        prev = cur
    eng.finish()
    assert counters_before.odometry_jumps == 0
    assert eng.counters.odometry_jumps == 2  # into the spike and back out of it
    _, online = eng.online_estimates()
    err = [abs(p.x() - x[k]) for k, p in enumerate(online) if p is not None]
    assert max(err) < 10.0  # followed, the spike would be 1e7 m


def _tilted(d_m: float, yaw_rad: float, pitch_rad: float, roll_rad: float) -> gtsam.Pose3:
    """A body-frame step forward, turned by yaw, carrying a pitch and roll increment (a VO's attitude noise)."""
    return gtsam.Pose3(gtsam.Rot3.Ypr(yaw_rad, pitch_rad, roll_rad), gtsam.Point3(d_m, 0.0, 0.0))


@given(steps=st.lists(st.tuples(st.floats(0.0, 3.0), st.floats(-0.2, 0.2), st.floats(-0.05, 0.05),
                                st.floats(-0.05, 0.05)), min_size=2, max_size=120))
def test_planar_steps_from_the_body_frame_ignore_the_odometry_frames_tilt(steps):
    """Attitude increments that tilt the odometry's world frame (a VO re-initialised in a pitched frame) do not
    shorten or turn the planar steps taken from the body frame: each is the step's own forward distance and yaw
    (in the world projection a frame pitched by θ shortens every step by cos θ)."""
    from mapfusion.config import StateModel
    from mapfusion.track import Track

    track = Track(StateModel.planar, 0.1, flat=True)
    for k, (d, yaw, pitch, roll) in enumerate(steps):
        track.append(0.1 * k, _tilted(d, yaw, pitch, roll))
    for k, (d, yaw, _, _) in enumerate(steps[1:], start=1):
        s = track.step(k, 2.0)
        assert math.isclose(s.x(), 2.0 * d, abs_tol=1e-9) and abs(s.y()) < 1e-9
        assert math.isclose(s.rotation().yaw(), gtsam.Rot3.Ypr(yaw, 0.0, 0.0).yaw(), abs_tol=1e-9)


def test_a_frame_pitched_by_60_degrees_shrinks_world_steps_but_not_body_steps():
    """The failure the body steps mend, shown: the same steps after the odometry frame pitched by 60°."""
    from mapfusion.config import StateModel
    from mapfusion.track import Track

    pitched = [gtsam.Pose3(gtsam.Rot3.Ypr(0.0, math.radians(60.0), 0.0), gtsam.Point3(0.0, 0.0, 0.0))] + \
        [_tilted(1.0, 0.0, 0.0, 0.0)] * 10
    got = {}
    for flat in (False, True):
        track = Track(StateModel.planar, 0.1, flat=flat)
        for k, rel in enumerate([gtsam.Pose3()] + pitched):
            track.append(0.1 * k, rel)
        got[flat] = track.step(5, 1.0).x()
    assert math.isclose(got[False], 0.5, abs_tol=1e-9) and math.isclose(got[True], 1.0, abs_tol=1e-9)


@given(pitch=st.floats(-1.4, 1.4), roll=st.floats(-1.4, 1.4),
       steps=st.lists(st.tuples(st.floats(0.1, 3.0), st.floats(-0.1, 0.1)), min_size=2, max_size=40))
def test_local_level_levels_a_frame_that_resumed_tilted_after_an_outage(pitch, roll, steps):
    """An odometry that resumes after a 20 s outage in a frame pitched and rolled by up to 80°: the local level
    restarts at the gap, so each later step is the body's own forward motion and turn, not its shadow on the
    tilted frame's horizontal."""
    from mapfusion.track import LocalLevel

    level = LocalLevel(window=600, reset_after_s=1.0)
    for k in range(20):
        level.step(0.1 * k, _tilted(1.0, 0.0, 0.0, 0.0))
    level.step(22.0, gtsam.Pose3(gtsam.Rot3.Ypr(0.0, pitch, roll), gtsam.Point3(0.0, 0.0, 0.0)))
    for k, (d, yaw) in enumerate(steps):
        s = level.step(22.1 + 0.1 * k, _tilted(d, yaw, 0.0, 0.0))
        assert math.hypot(s.x(), s.y()) == pytest.approx(d, abs=1e-9)
        assert s.rotation().yaw() == pytest.approx(yaw, abs=1e-9)


def test_local_level_keeps_a_level_frame_level_against_body_roll_and_pitch():
    """In a level frame a body that rolls and pitches on the road (±3°) turns by the frame's yaw: after four
    full circles the summed yaw is the truth's within 0.2° (body-frame yaw carries the roll-pitch-yaw coupling:
    ten times more)."""
    from mapfusion.track import LocalLevel, flatten

    level = LocalLevel(window=600, reset_after_s=1.0)
    level.step(0.0, gtsam.Pose3())  # frame 0: where the chain starts
    prev = gtsam.Pose3()
    heading = yaw_level = yaw_body = 0.0
    for k in range(1, 2000):
        heading += 8.0 * math.pi / 2000
        att = gtsam.Rot3.Ypr(heading, math.radians(3.0) * math.sin(k / 7.0), math.radians(3.0) * math.cos(k / 11.0))
        cur = gtsam.Pose3(att, gtsam.Point3(*(prev.translation() + [math.cos(heading), math.sin(heading), 0.0])))
        rel = prev.between(cur)
        yaw_level += level.step(0.1 * k, rel).rotation().yaw()
        yaw_body += flatten(rel).rotation().yaw()
        prev = cur
    # measured: 0.14° (the window's mean up is not quite vertical) against the body frame's 1.9°
    assert abs(yaw_level - heading) < math.radians(0.2), math.degrees(yaw_level - heading)
    assert abs(yaw_body - heading) > 10.0 * abs(yaw_level - heading)  # (the coupling the local level avoids)


@given(up=st.tuples(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0)).filter(
    lambda u: math.hypot(*u) > 1e-3))
def test_the_levelling_rotation_takes_the_mean_up_to_vertical(up):
    """The first two rows of the levelling rotation are orthonormal and normal to ``up``: the levelled up is
    vertical, whatever its direction (upside down included)."""
    from mapfusion.track import _levelling_rows

    a, b = np.array(_levelling_rows(*up))
    u = np.array(up) / np.linalg.norm(up)
    assert abs(a @ u) < 1e-9 and abs(b @ u) < 1e-9
    assert abs(a @ a - 1.0) < 1e-9 and abs(b @ b - 1.0) < 1e-9 and abs(a @ b) < 1e-9
    assert np.cross(a, b) @ u == pytest.approx(1.0, abs=1e-9)  # (a proper rotation: up goes to +z, not -z)


@given(headings=st.lists(st.floats(-math.pi, math.pi), min_size=2, max_size=60), steps=st.floats(0.5, 30.0),
       off=st.tuples(st.floats(-200.0, 200.0), st.floats(-200.0, 200.0)))
def test_the_compass_rule_undoes_an_error_that_grows_with_the_distance_driven(headings, steps, off):
    """A winding estimated path whose error at each pose is ``off`` times the fraction of its length driven
    to it (a drift proportional to distance): spreading the end's correction back restores the true path,
    and the first pose (known to be right) is left out."""
    est = [np.zeros(2)]
    for h in headings:
        est.append(est[-1] + np.array([math.cos(h), math.sin(h)]) * steps)
    driven = np.concatenate(([0.0], np.cumsum([steps] * len(headings))))
    true = [p + np.array(off) * (s / driven[-1]) for p, s in zip(est, driven)]
    poses = [gtsam.Pose3(gtsam.Rot3.Yaw(0.1), gtsam.Point3(p[0], p[1], 0.0)) for p in est]
    now = gtsam.Pose3(gtsam.Rot3.Yaw(0.1), gtsam.Point3(true[-1][0], true[-1][1], 0.0))
    out = spread_back(poses[:-1], poses[-1], now)
    assert len(out) == len(poses) - 2
    for p, q in zip(out, true[1:-1]):
        assert math.hypot(p.x() - q[0], p.y() - q[1]) < 1e-6 and abs(p.rotation().yaw() - 0.1) < 1e-9


@given(n=st.integers(3, 40), dyaw=st.floats(-3.0, 3.0), dx=st.floats(-100.0, 100.0))
def test_the_compass_rule_turns_each_pose_by_its_share_of_the_heading_correction(n, dyaw, dx):
    """On an evenly spaced straight path, pose i of n is turned by i/n of the end's heading change and moved
    by i/n of its position change; the first pose is never in the output (it was right)."""
    poses = [gtsam.Pose3(gtsam.Rot3.Yaw(0.3), gtsam.Point3(10.0 * i, 0.0, 1.0)) for i in range(n + 1)]
    now = gtsam.Pose3(gtsam.Rot3.Yaw(0.3 + dyaw), gtsam.Point3(10.0 * n + dx, 0.0, 1.0))
    out = spread_back(poses[:-1], poses[-1], now)
    for i, p in enumerate(out, start=1):
        assert abs(math.remainder(p.rotation().yaw() - 0.3 - dyaw * i / n, 2.0 * math.pi)) < 1e-9
        assert abs(p.x() - (10.0 * i + dx * i / n)) < 1e-9 and p.z() == 1.0


# ---------------------------------------------------------------- odometry_nonholonomic (issue 17)
@given(x=st.floats(-30.0, 30.0), y=st.floats(-30.0, 30.0), z=st.floats(-2.0, 2.0), yaw=st.floats(-1.5, 1.5))
def test_a_step_along_its_heading_keeps_its_length_height_and_rotation(x, y, z, yaw):
    step = gtsam.Pose3(gtsam.Rot3.Yaw(yaw), gtsam.Point3(x, y, z))
    out = along_heading(step)
    d = math.hypot(x, y)
    assert math.hypot(out.x(), out.y()) == pytest.approx(d, abs=1e-9)
    assert out.z() == z and out.rotation().equals(step.rotation(), 1e-12)
    if d > 1e-6:  # along the mean of the start heading (0) and the end heading (yaw), as the step went
        direction = math.atan2(out.y(), out.x())
        expected = 0.5 * yaw if x >= 0.0 else 0.5 * yaw + math.pi
        assert abs(math.remainder(direction - expected, 2.0 * math.pi)) < 1e-9


@given(d=st.floats(0.0, 30.0), yaw=st.floats(-1.5, 1.5), backwards=st.booleans())
def test_a_step_already_along_its_mean_heading_is_unchanged(d, yaw, backwards):
    s = -d if backwards else d
    step = gtsam.Pose3(gtsam.Rot3.Yaw(yaw), gtsam.Point3(s * math.cos(0.5 * yaw), s * math.sin(0.5 * yaw), 0.0))
    assert along_heading(step).equals(step, 1e-9)


def _sliding_drive(tmp_path, nonholonomic: bool) -> tuple[float, float]:
    """A straight drive east at 10 m/s: GPS for 60 s, then none; from 80 s to 100 s the odometry slides 0.1 m
    to the left per metre driven (a rain episode's drift), heading true. Returns the estimate's final (x, y)
    error (m). No map priors: the odometry's step alone decides."""
    road = RoadMap.from_osm(write_osm(tmp_path, [(straight_road(3000.0, 0.0, (-1500.0, 0.0)),
                                                  {"highway": "primary"})]), cache=False)
    eng = MapFusion(road, FusionConfig(use_map=False, odometry_nonholonomic=nonholonomic), gps_rate_hz=1.0,
                    odometry_rate_hz=10.0)
    for k in range(1500):
        t = 0.1 * k
        if k % 10 == 0 and t <= 60.0:
            lat, lon = road.projection.to_geo(-1400.0 + 10.0 * t, 0.0)
            eng.add_gps(t, float(lat), float(lon), None, 1.0)
        rel = np.eye(4)
        rel[0, 3] = 0.0 if k == 0 else 1.0
        rel[1, 3] = 0.1 if 80.0 < t <= 100.0 else 0.0
        eng.add_odometry(t, rel)
    eng.finish()
    p = eng.estimate()
    return p.x() - (-1400.0 + 149.9 * 10.0), p.y()


@pytest.mark.parametrize("nonholonomic", [False, True])
def test_a_sideways_slide_of_the_odometry_is_not_taken_for_motion(tmp_path, nonholonomic):
    ex, ey = _sliding_drive(tmp_path, nonholonomic)
    if nonholonomic:
        assert abs(ey) < 1.0 and abs(ex) < 2.0, (ex, ey)
    else:  # as measured: 200 m of sliding, 20 m to the left
        assert ey > 15.0, (ex, ey)


def _kinematic_step(d_m: float, yaw_rad: float, lever_m: float, slide_m: float = 0.0) -> gtsam.Pose3:
    """The step of a frame ``lever_m`` ahead of the rear axle when the axle drives an arc's chord of ``d_m``
    turning ``yaw_rad``, plus a sideways slide of ``slide_m`` (to the left)."""
    half = 0.5 * yaw_rad
    x = d_m * math.cos(half) + lever_m * (math.cos(yaw_rad) - 1.0)
    y = d_m * math.sin(half) + lever_m * math.sin(yaw_rad) + slide_m
    return gtsam.Pose3(gtsam.Rot3.Yaw(yaw_rad), gtsam.Point3(x, y, 0.0))


@given(d=st.floats(-20.0, 20.0), yaw=st.floats(-1.0, 1.0), lever=st.floats(-3.0, 3.0))
def test_a_frame_ahead_of_the_axle_keeps_its_swing_in_a_turn(d, yaw, lever):
    step = _kinematic_step(d, yaw, lever)
    assert along_heading(step, lever).equals(step, 1e-9)


@given(d=st.floats(0.1, 20.0), yaw=st.floats(-1.0, 1.0), lever=st.floats(-3.0, 3.0), slide=st.floats(-0.5, 0.5),
       backwards=st.booleans())
@example(d=0.125, yaw=-1.0, lever=0.0, slide=0.5, backwards=False)  # the slide outruns the drive: found by CI
def test_a_steps_slide_is_its_motion_across_its_heading_beyond_the_levers_swing(d, yaw, lever, slide, backwards):
    s = -1.0 if backwards else 1.0
    want_across, want_along = slide * math.cos(0.5 * yaw), d + slide * math.sin(0.5 * yaw)
    assume(abs(want_along) > 1e-6)
    if want_along < 0.0:  # a slide larger than the drive moves the frame backwards: along is counted >= 0
        want_across, want_along = -want_across, -want_along
    across, along = slide_of(_kinematic_step(s * d, yaw, lever, s * slide), lever)
    assert across == pytest.approx(want_across, abs=1e-9)
    assert along == pytest.approx(want_along, abs=1e-9)


def _track_steps(slide_m_per_m: float, seed: int, n: int = 40) -> tuple[Track, list[gtsam.Pose3]]:
    """A planar track of 1 m steps straight on, each step's direction scattered by 1 degree, sliding
    ``slide_m_per_m`` to the left; with a 2 degree slip (odometry_slip_deg)."""
    rng = np.random.default_rng(seed)
    track = Track(StateModel.planar, 0.1, nonholonomic=True, slip_rad=math.radians(2.0))
    steps = []
    for k in range(n):
        a = rng.normal(0.0, math.radians(1.0))
        rel = gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(math.cos(a), math.sin(a) + slide_m_per_m, 0.0))
        track.append(0.1 * k, rel)
        steps.append(rel)
    return track, steps


@given(seed=st.integers(0, 10_000))
def test_a_good_odometrys_scattered_steps_are_kept_as_measured(seed):
    track, steps = _track_steps(0.0, seed)
    for k in range(SLIDE_FRAMES, len(track)):
        assert track.step(k, 1.0).equals(steps[k], 1e-9)


@given(seed=st.integers(0, 10_000), slide=st.sampled_from([-0.1, 0.1]))
def test_a_sustained_slide_is_not_taken_for_motion(seed, slide):
    """A VO sliding 0.1 m per metre (5.7 degrees, a rain episode's) goes straight on, its length kept."""
    track, steps = _track_steps(slide, seed)
    for k in range(SLIDE_FRAMES, len(track)):
        out = track.step(k, 1.0)
        assert abs(out.y()) < 1e-9 and out.x() == pytest.approx(float(np.hypot(*steps[k].translation()[:2])))


@given(seed=st.integers(0, 10_000), slide=st.sampled_from([-0.1, 0.1]), first=st.integers(0, 25))
def test_restated_steps_are_judged_by_the_slide_test_as_if_appended(seed, slide, first):
    """The slide test reads each frame's step as it was kept when appended (issue 21): steps restated later
    (an odometry's re-estimated past) are read as restated — the same decisions as a track built with them, at
    every frame whose look back holds restated steps only."""
    track, _ = _track_steps(0.0, seed)
    built, sliding = _track_steps(slide, seed)
    track.restate_steps({k: sliding[k] for k in range(first, len(sliding))})
    for k in range(first + SLIDE_FRAMES, len(track)):
        assert track.step(k, 1.0).equals(built.step(k, 1.0), 1e-12)


@given(lever=st.floats(-3.0, 3.0), seed=st.integers(0, 1000))
def test_the_lever_arm_is_found_from_the_turns(lever, seed):
    rng = np.random.default_rng(seed)
    arm = LeverArm()
    assert arm.lever(1.0) == 0.0
    for _ in range(400):  # 1 m steps turning up to 6 degrees, with slides that do not follow the turns
        arm.add(_kinematic_step(1.0, rng.uniform(-0.1, 0.1), lever, rng.normal(0.0, 0.01)))
    assert arm.lever(1.0) == pytest.approx(lever, abs=0.1)
    assert arm.lever(2.0) == pytest.approx(min(2.0 * lever, 5.0) if lever > 0 else max(2.0 * lever, -5.0), abs=0.2)


def test_no_lever_arm_before_the_turns_add_up():
    arm = LeverArm()
    for _ in range(1000):  # straight on: nothing tells the lever
        arm.add(_kinematic_step(1.0, 0.0, 2.0, 0.05))
    assert arm.lever(1.0) == 0.0
