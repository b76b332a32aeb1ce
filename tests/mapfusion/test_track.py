"""The odometry jump guard (issue 19): impossible steps are bridged, plausible ones never touched."""

from __future__ import annotations

import math

import gtsam
import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from mapfusion.counters import Counters
from mapfusion.engine import MapFusion
from mapfusion.roadmap import RoadMap
from mapfusion.track import JumpGuard
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
