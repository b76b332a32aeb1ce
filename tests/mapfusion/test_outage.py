"""An odometry outage with no GPS after it: where a VO that lost track says it resumed is its own guess,
so the engine carries the last velocity over the gap — straight on without the map, along the road graph
with it (``outage_step``)."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from mapfusion import FusionConfig, MapFusion
from mapfusion.config import OutageStep
from mapfusion.roadmap import RoadMap
from tests.helpers import write_osm

RADIUS_M = 400.0
STRAIGHT_M = 1500.0


def _pose_at(s_m: float) -> tuple[float, float, float]:
    """(x, y, heading) at arc length s along a road east to the origin, a 90° left arc of 400 m radius, then north."""
    if s_m <= STRAIGHT_M:
        return s_m - STRAIGHT_M, 0.0, 0.0
    arc = RADIUS_M * math.pi / 2.0
    if s_m <= STRAIGHT_M + arc:
        phi = (s_m - STRAIGHT_M) / RADIUS_M
        return RADIUS_M * math.sin(phi), RADIUS_M * (1.0 - math.cos(phi)), phi
    return RADIUS_M, RADIUS_M + (s_m - STRAIGHT_M - arc), math.pi / 2.0


@pytest.fixture(scope="module")
def bend(tmp_path_factory) -> tuple[RoadMap, np.ndarray]:
    """The road map and the offset of _pose_at's frame in the map's (centred) ENU frame."""
    pts = np.array([_pose_at(s)[:2] for s in np.arange(0.0, STRAIGHT_M * 2 + RADIUS_M * math.pi / 2.0, 10.0)])
    road = RoadMap.from_osm(write_osm(tmp_path_factory.mktemp("osm"), [(pts, {"highway": "primary", "lanes": "2"})]))
    return road, road.xy_m[0] - pts[0]


def _feed(bend: tuple[RoadMap, np.ndarray], cfg: FusionConfig, s_at, resumed: gtsam.Pose3 | None = None) -> MapFusion:
    """An engine fed 190 s along the bend at arc length ``s_at(t)``: a fix every second for the first 130 s, the VO
    out from 140 s to 180 s and resuming with ``resumed`` as its step (its own guess), or the true one."""
    road, (ox, oy) = bend
    eng = MapFusion(road, cfg, odometry_rate_hz=10.0)
    prev = None
    for k in range(1901):
        x, y, yaw = _pose_at(s_at(0.1 * k))
        x, y = x + ox, y + oy
        if k % 10 == 0 and k <= 1300:
            lat, lon = road.projection.to_geo(x, y)
            eng.add_gps(0.1 * k, float(lat), float(lon), None, 2.0)
        if 1400 < k < 1800:
            continue
        pose = gtsam.Pose3(gtsam.Rot3.Yaw(yaw), gtsam.Point3(x, y, 0.0))
        rel = gtsam.Pose3() if prev is None else prev.between(pose)
        if k == 1800 and resumed is not None:
            rel = resumed
        eng.add_odometry(0.1 * k, rel.matrix())
        prev = pose
    return eng


def _drive(bend: tuple[RoadMap, np.ndarray], mode: OutageStep, use_map: bool = True):
    """10 m/s from the start, a fix every second for the first 130 s only; the VO out from 140 s to 180 s (in the
    bend) and resuming with a 500 m step the wrong way (its own guess, at a plausible speed). Returns the
    online error at 180 s and 190 s (m)."""
    road, (ox, oy) = bend
    eng = _feed(bend, FusionConfig(outage_step=mode, use_map=use_map), lambda t: 10.0 * t,
                resumed=gtsam.Pose3(gtsam.Rot3.Yaw(0.4), gtsam.Point3(-500.0, 0.0, 0.0)))
    t_s, online = eng.online_estimates()
    out = []
    for t in (180.0, 190.0):
        i = int(np.argmin(np.abs(np.asarray(t_s) - t)))
        x, y, _ = _pose_at(10.0 * t)
        out.append(math.hypot(online[i].x() - x - ox, online[i].y() - y - oy))
    return out


def test_the_map_carries_the_estimate_round_the_bend_across_an_outage(bend):
    """With the map the last velocity is carried 400 m along the road (100 m to the bend, 300 m round it):
    within 15 m of the truth on resuming and 10 s later. Straight on, it resumes where 400 m of straight road
    would end — off the bend by the geometry's own figure (to 5 m); the VO's own guess is 900 m off."""
    road_err = _drive(bend, OutageStep.road)
    assert max(road_err) < 15.0, road_err
    straight = _drive(bend, OutageStep.constant_velocity)
    theta = 300.0 / RADIUS_M
    chord_off_m = math.hypot(300.0 - RADIUS_M * math.sin(theta), RADIUS_M * (1.0 - math.cos(theta)))
    assert abs(straight[0] - chord_off_m) < 5.0, (straight, chord_off_m)
    own = _drive(bend, OutageStep.odometry)
    assert own[0] > 500.0, own


def test_without_the_map_the_road_mode_is_straight_on(bend):
    """The baseline (no map) cannot follow a road: ``road`` falls back to the last velocity straight on."""
    assert _drive(bend, OutageStep.road, use_map=False) == _drive(bend, OutageStep.constant_velocity, use_map=False)


@pytest.fixture(scope="module")
def tee(tmp_path_factory) -> tuple[RoadMap, np.ndarray]:
    """A road east through a junction at the origin (on to x = 1000 m) and a branch north from it; the offset
    of the test's frame in the map's ENU frame."""
    east = np.array([[-2000.0, 0.0], [0.0, 0.0], [1000.0, 0.0]])
    north = np.array([[0.0, 0.0], [0.0, 1000.0]])
    tags = {"highway": "primary", "lanes": "2"}
    road = RoadMap.from_osm(write_osm(tmp_path_factory.mktemp("osm"), [(east, tags), (north, dict(tags))]))
    i = int(np.argmin(np.hypot(*(road.xy_m - road.xy_m.min(axis=0)).T)))  # the west end
    return road, road.xy_m[i] - east[0]


def _turn_at(s_m: float) -> tuple[float, float, float]:
    """East to the junction at arc length 2000 m, then north (a 90° left turn)."""
    return (s_m - 2000.0, 0.0, 0.0) if s_m <= 2000.0 else (0.0, s_m - 2000.0, math.pi / 2.0)


def _last_on_the_tee(tee, cfg: FusionConfig, pose_at, gap: tuple[int, int], resumed, frames: int | None = None):
    """A drive on the tee at 10 m/s, 1 m a frame (``pose_at``: arc length → (x, y, yaw) from the junction's
    approach), a fix every second up to frame 1900, the VO silent over the frames strictly inside ``gap`` and its
    step on resuming at ``gap[1]`` passed through ``resumed``; ``frames`` (default: up to the resumption) in
    all. Returns the last online estimate's (x, y) in the tee's own frame."""
    road, (ox, oy) = tee
    eng = MapFusion(road, cfg, odometry_rate_hz=10.0)
    prev = None
    for k in range(gap[1] + 1 if frames is None else frames):
        x, y, yaw = pose_at(1.0 * k)
        if k % 10 == 0 and k <= 1900:
            lat, lon = road.projection.to_geo(x + ox, y + oy)
            eng.add_gps(0.1 * k, float(lat), float(lon), None, 2.0)
        if gap[0] < k < gap[1]:
            continue
        pose = gtsam.Pose3(gtsam.Rot3.Yaw(yaw), gtsam.Point3(x + ox, y + oy, 0.0))
        rel = gtsam.Pose3() if prev is None else prev.between(pose)
        if k == gap[1]:
            rel = resumed(rel)
        eng.add_odometry(0.1 * k, rel.matrix())
        prev = pose
    last = eng.online_estimates()[1][-1]
    return last.x() - ox, last.y() - oy


def test_a_turn_at_a_junction_inside_the_gap_follows_the_odometrys_own_turn(tee):
    """The VO is out for 10 s from 40 m before the junction, in which the vehicle turns left; it resumes
    reporting the turn (90°) but 150 m too far. The engine carries the last velocity along the road into the
    branch the odometry's turn points to: within 15 m (straight on, into the road east, it would end about 85 m
    off)."""
    # the VO's own guess on resuming: the turn, but 150 m too far on
    x, y = _last_on_the_tee(tee, FusionConfig(), _turn_at, (1960, 2060),
                            lambda rel: rel.compose(gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(150.0, 0.0, 0.0))))
    assert math.hypot(x, y - 60.0) < 15.0, (x, y)


def test_the_carried_step_ends_on_the_road_whose_heading_the_guess_has(tee):
    """Straight east through the junction: the VO is out for 5.3 s from 50 m before it and resumes 3 m past it,
    its own turn over the gap 13° (a re-initialisation's heading error). Of the drives along the graph, one
    that turned north at the junction ends nearer the guess's position (3.9 m) than the one that went on
    (6.0 m), its heading 90° off the guess's 13°. With ``outage_end_weight_m_per_deg`` (D = E + w·A) the step
    ends on the road east and the estimate follows the vehicle (within 15 m 20 s later); by position alone
    it takes the branch north and drives up it (over 100 m off)."""
    errs = {}
    for weight in (1.0, 0.0):
        # the re-initialised VO: the motion, turned by its heading error
        x, y = _last_on_the_tee(tee, FusionConfig(outage_end_weight_m_per_deg=weight),
                                lambda s_m: (s_m - 2000.0, 0.0, 0.0), (1950, 2003),
                                lambda rel: gtsam.Pose3(gtsam.Rot3.Yaw(math.radians(13.0)), rel.translation()),
                                frames=2204)
        errs[weight] = math.hypot(x - 203.0, y)
    assert errs[1.0] < 15.0 and errs[0.0] > 100.0, errs


def _reinit_after(bend: tuple[RoadMap, np.ndarray], gap_s: float, cfg: FusionConfig) -> float:
    """10 m/s east on the straight, a fix every second for the first 100 s only; the VO out for ``gap_s`` from
    110 s and resuming with its constant-velocity guess turned 150° (a re-initialisation that carried a wrong
    turn over the gap), its steps true in that frame from then on. Returns the online error 20 s later (m)."""
    road, (ox, oy) = bend
    eng = MapFusion(road, cfg, odometry_rate_hz=10.0)
    prev = None
    resume = 1100 + round(10 * gap_s)
    for k in range(resume + 201):
        x, y, yaw = _pose_at(1.0 * k)
        if k % 10 == 0 and k <= 1000:
            lat, lon = road.projection.to_geo(x + ox, y + oy)
            eng.add_gps(0.1 * k, float(lat), float(lon), None, 2.0)
        if 1100 < k < resume:
            continue
        pose = gtsam.Pose3(gtsam.Rot3.Yaw(yaw), gtsam.Point3(x + ox, y + oy, 0.0))
        rel = gtsam.Pose3() if prev is None else prev.between(pose)
        if k == resume:
            rel = gtsam.Pose3(gtsam.Rot3.Yaw(math.radians(150.0)), rel.translation())
        eng.add_odometry(0.1 * k, rel.matrix())
        prev = pose
    x, y, _ = _pose_at(float(resume + 200))
    est = eng.online_estimates()[1][-1]
    return math.hypot(est.x() - x - ox, est.y() - y - oy)


def test_a_gap_of_two_and_a_half_seconds_is_a_lost_track(bend):
    """A VO out for 2.5 s re-initialised (it could not re-match the gap): its guessed turn is not the motion.
    With the default ``reloc_gap_s`` (2 s) the step across the gap follows the road and the estimate stays on
    it (within 10 m 200 m later); taken as a bridged gap (``reloc_gap_s`` 3 s, the old default) the guess turns
    the estimate off the road and it runs the wrong way (over 100 m off)."""
    assert FusionConfig().reloc_gap_s < 2.5
    assert _reinit_after(bend, 2.5, FusionConfig()) < 10.0
    assert _reinit_after(bend, 2.5, FusionConfig(reloc_gap_s=3.0)) > 100.0


def _speeding_drive(bend: tuple[RoadMap, np.ndarray], cfg: FusionConfig) -> float:
    """10 m/s for 140 s with a fix every second for the first 130 s; the VO out for 40 s while the vehicle speeds
    up evenly to 20 m/s (600 m driven unseen), then 20 m/s. Returns the online error 10 s after it resumed (m)."""
    road, (ox, oy) = bend

    def s_at(t: float) -> float:
        if t <= 140.0:
            return 10.0 * t
        if t <= 180.0:
            return 1400.0 + 10.0 * (t - 140.0) + 0.125 * (t - 140.0) ** 2
        return 2000.0 + 20.0 * (t - 180.0)

    eng = _feed(bend, cfg, s_at)
    t_s, online = eng.online_estimates()
    x, y, _ = _pose_at(s_at(190.0))
    return math.hypot(online[-1].x() - x - ox, online[-1].y() - y - oy)


def test_a_gap_is_carried_again_at_the_speeds_on_both_sides(bend):
    """The vehicle sped up from 10 to 20 m/s while the VO was out for 40 s: carried at the speed before the gap the
    estimate resumes 200 m short along the road and stays so; with ``outage_speed_after_s`` (1 s, the default) the
    gap is carried again a second after the VO resumed, at the mean of both speeds (15 m/s, the truth's 600 m), and
    the estimate is within 15 m of the truth 10 s later."""
    before = _speeding_drive(bend, FusionConfig(outage_speed_after_s=0.0))
    after = _speeding_drive(bend, FusionConfig())
    assert FusionConfig().outage_speed_after_s == 1.0
    assert before > 150.0, before
    assert after < 15.0, (before, after)
