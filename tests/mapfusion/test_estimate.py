"""The estimate's one owner (:class:`~mapfusion.estimate.Estimate`) and the parts that propose to it, each tested
without the engine: a restart tells the road parts in order, the scale and the final poses change only through it,
a carried step replaces the odometry's (also when a restart re-adds the frames), and the map's re-anchoring path
(:class:`~mapfusion.registering.MapAnchors`) steps back no further than the last one."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapfusion import factors
from mapfusion.config import FusionConfig, StateModel
from mapfusion.counters import Counters
from mapfusion.estimate import Estimate
from mapfusion.initialisation import Initialiser
from mapfusion.motion import MotionFusion
from mapfusion.registering import MapAnchors
from mapfusion.relocalise import Region
from mapfusion.track import Alignment, track_for
from tests.helpers import straight_road, write_osm


def _no_prior(k, pred, sigma_m):
    return None


def _estimate(frames: int = 40, scale: float = 2.0, step_units: float = 0.5, on_restart=()) -> Estimate:
    """An estimate begun on ``frames`` odometry frames straight along x, ``step_units`` a frame at ``scale``."""
    cfg = FusionConfig()
    counters = Counters()
    track = track_for(cfg, 10.0)
    est = Estimate(cfg, track, counters, MotionFusion(cfg, counters), Initialiser(cfg, 1.0, 10.0),
                   on_restart=on_restart)
    for k in range(frames):
        track.append(0.1 * k, gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(step_units if k else 0.0, 0.0, 0.0)))
    est.begin(Alignment(scale, 0.01 * scale, 0.0, np.zeros(2)))
    return est


def _drive(est: Estimate, frames: int, step_units: float = 0.5) -> None:
    """More frames, each added as the engine adds one (its odometry factor, its prediction, no map)."""
    track = est.track
    for _ in range(frames):
        k = len(track)
        track.append(0.1 * k, gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(step_units, 0.0, 0.0)))
        step = est.step(k)
        pred = track.online[k - 1].compose(step)
        est.add(est.between(k, step=step))
        est.sm.insert(k, pred)
        est.frame(k, pred, False, _no_prior)


def test_a_begun_estimate_puts_the_odometry_at_its_scale():
    est = _estimate(frames=40, scale=2.0, step_units=0.5)
    assert est.track.online[39].x() == pytest.approx(39 * 0.5 * 2.0, abs=1e-6)
    _drive(est, 20)
    assert est.track.online[59].x() == pytest.approx(59.0, abs=1e-3)


def test_a_restart_tells_the_road_parts_in_order_and_sets_the_sigma():
    told: list[str] = []
    est = _estimate(on_restart=(lambda: told.append("road fixes"), lambda: told.append("association")))
    _drive(est, 10)
    k = len(est.track) - 1
    pose = gtsam.Pose3(gtsam.Rot3.Yaw(0.2), gtsam.Point3(100.0, 5.0, 0.0))
    est.restart_from(k, pose, factors.diagonal(factors.pose_sigmas(StateModel.planar, 0.01, 0.7)), 0.7)
    assert told == ["road fixes", "association"]
    assert est.pos_sigma_m == est.lat_sigma_m == 0.7
    est.update()
    assert est.track.online[k].x() == pytest.approx(100.0) and est.track.online[k].y() == pytest.approx(5.0)


@settings(max_examples=20, deadline=None)
@given(ratio=st.floats(0.5, 2.0), sigma=st.one_of(st.none(), st.floats(1e-4, 0.1)))
def test_the_scale_changes_and_nothing_else(ratio, sigma):
    est = _estimate()
    before = est.aligned
    est.set_scale(before.scale * ratio, sigma)
    after = est.aligned
    assert after.scale == before.scale * ratio
    assert after.scale_sigma == (before.scale_sigma if sigma is None else sigma)
    assert after.rot_rad == before.rot_rad and np.array_equal(after.trans_m, before.trans_m)
    k = len(est.track)
    est.track.append(0.1 * k, gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(0.5, 0.0, 0.0)))
    assert est.step(k).x() == pytest.approx(0.5 * after.scale)


def test_a_carried_step_replaces_the_odometrys_also_when_a_restart_re_adds_the_frames():
    est = _estimate()
    _drive(est, 5)
    k = len(est.track)
    est.track.append(0.1 * k, gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(0.5, 0.0, 0.0)))
    carried = gtsam.Pose3(gtsam.Rot3.Yaw(0.5), gtsam.Point3(30.0, 4.0, 0.0))
    est.carry_step(k, carried)
    assert est.step(k).equals(carried, 1e-12)
    pred = est.track.online[k - 1].compose(carried)
    est.add(est.between(k))
    est.sm.insert(k, pred)
    est.frame(k, pred, False, _no_prior)
    _drive(est, 5)
    k0 = k - 2
    start = est.track.online[k0]
    est.restart_from(k0, start, factors.diagonal(factors.pose_sigmas(StateModel.planar, 0.01, 0.5)), 0.5)
    est.update()
    got = est.sm.pose(k - 1).between(est.sm.pose(k))
    assert got.x() == pytest.approx(30.0, abs=1e-3) and got.rotation().yaw() == pytest.approx(0.5, abs=1e-4)


def test_final_poses_are_replaced_only_where_moved():
    est = _estimate()
    _drive(est, 60)
    est.update()
    before = dict(est.sm.smoothed)
    moved = {k: gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(-1.0, -1.0, 0.0)) for k in (3, 4)}
    est.move_final(moved)
    for k, p in est.sm.smoothed.items():
        assert p is not None
        assert p.equals(moved[k] if k in moved else before[k], 0.0)


@pytest.fixture(scope="module")
def road(tmp_path_factory):
    return __import__("mapfusion").RoadMap.from_osm(write_osm(tmp_path_factory.mktemp("line"), [
        (straight_road(3000.0, 0.0, (-1500.0, 0.0)), {"highway": "primary"})]), cache=False)


def test_the_replay_steps_back_no_further_than_the_last_map_re_anchoring(road):
    """MapAnchors.replay_start: the frame a given driving back (metres at the estimate's scale), but never before
    the last map re-anchoring, whose estimates before it are where the engine then thought."""
    est = _estimate(frames=40, scale=2.0, step_units=0.5)  # 1 m a frame
    _drive(est, 60)
    anchors = MapAnchors(road, est.cfg, est.track, est, est.counters)
    k = len(est.track) - 1
    assert anchors.replay_start(k, 30.0) == k - 30
    assert anchors.replay_start(k, 0.0) == k
    pred = est.track.online[k]
    anchors.reanchor(k - 10, est.track.online[k - 10], est.track.online[k - 10], 1.0, math.radians(2.0), k - 10,
                     Region(pred.x(), pred.y(), 100.0), 0.0, now=k - 10)
    assert anchors.last is not None and anchors.last[0] == k - 10
    assert anchors.replay_start(k, 30.0) == k - 10
    assert est.counters.map_relocalisations == 1 and anchors.relocalised_at == [(est.track.t[k - 10], 0.0)]
