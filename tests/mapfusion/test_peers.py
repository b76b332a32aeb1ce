"""The reference peers: the GPS + odometry EKF and the offline map matching."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapfusion import RoadMap
from mapfusion.peers import GpsOdometryEkf, OfflineMapMatching, _similarity_2d
from tests.helpers import drifting_odometry, odometry_step, straight_road, synthetic_truth, wheel_gyro_samples, write_osm


@pytest.fixture(scope="module")
def road(tmp_path_factory):
    """Two parallel east-west roads 12 m apart, not joined, and a third far away (the map's frame)."""
    d = tmp_path_factory.mktemp("peers")
    return RoadMap.from_osm(write_osm(d, [(straight_road(3000.0, origin=(-500.0, 0.0)), {"highway": "primary"}),
                                          (straight_road(3000.0, origin=(-500.0, 12.0)), {"highway": "primary"}),
                                          (straight_road(500.0, origin=(0.0, 800.0)), {"highway": "primary"})]),
                            cache=False)


def _feed(est, road, truth, ox, oy, oyaw, gps_every: int, gps_until_s: float, sigma_m: float, rng,
          wheel=None, gyro=None, outlier_at: int | None = None):
    """Frames at the truth's times, a fix every ``gps_every`` frames until ``gps_until_s`` (noise σ), wheel and gyro
    samples in time order; the estimates after each frame."""
    events = [(float(truth.t_s[k]), 3, k) for k in range(len(truth.t_s))]
    events += [(float(truth.t_s[k]), 2, k) for k in range(0, len(truth.t_s), gps_every) if truth.t_s[k] <= gps_until_s]
    if wheel is not None:
        events += [(float(t), 0, i) for i, t in enumerate(wheel[0])] + [(float(t), 1, i) for i, t in enumerate(gyro[0])]
    out = []
    for t, kind, i in sorted(events):
        if kind == 0:
            est.add_wheel_speed(t, float(wheel[1][i]))
        elif kind == 1:
            est.add_imu(t, np.zeros(3), np.array([0.0, 0.0, gyro[1][i]]))
        elif kind == 2:
            x, y = truth.x_m[i] + rng.normal(0, sigma_m), truth.y_m[i] + rng.normal(0, sigma_m)
            if i == outlier_at:
                x += 200.0
            lat, lon = road.projection.to_geo(x, y)
            est.add_gps(t, float(lat), float(lon), None, sigma_m)
        elif i > 0:
            est.add_odometry(t, odometry_step(ox, oy, oyaw, i))
            p = est.estimate()
            out.append(None if p is None else (p[0, 3], p[1, 3], math.atan2(p[1, 0], p[0, 0])))
    return out


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.floats(0.5, 2.0), heading=st.floats(-math.pi, math.pi))
def test_the_ekf_learns_the_odometrys_scale_and_heading_from_the_fixes(road, seed, scale, heading):
    """A random drive, its odometry at another scale and turned into its own frame, a fix a second (σ 1 m): the
    filter's scale ends within 3% of the truth's metres per odometry metre and its position within 3 m."""
    truth = synthetic_truth("random", n=1200, seed=seed)
    ox, oy, oyaw = drifting_odometry(truth.x_m, truth.y_m, truth.yaw_rad, seed, scale=scale, heading_rad=heading,
                                     spacing_m=1.0)
    ekf = GpsOdometryEkf(road)
    out = _feed(ekf, road, truth, ox, oy, oyaw, gps_every=10, gps_until_s=1e9, sigma_m=1.0,
                rng=np.random.default_rng(seed))
    assert out[-1] is not None
    assert abs(ekf.scale * scale - 1.0) < 0.03, (ekf.scale, 1.0 / scale)
    assert math.hypot(out[-1][0] - truth.x_m[-1], out[-1][1] - truth.y_m[-1]) < 3.0


def test_an_outlying_fix_is_left_out_and_many_in_a_row_start_it_again(road):
    truth = synthetic_truth("straight", n=1200)
    ox, oy, oyaw = drifting_odometry(truth.x_m, truth.y_m, truth.yaw_rad, 1)
    ekf = GpsOdometryEkf(road)
    out = _feed(ekf, road, truth, ox, oy, oyaw, 10, 1e9, 1.0, np.random.default_rng(1), outlier_at=600)
    err = [math.hypot(p[0] - truth.x_m[k + 1], p[1] - truth.y_m[k + 1]) for k, p in enumerate(out) if p is not None]
    assert ekf.fixes_rejected == 1 and ekf.restarts == 0 and max(err[100:]) < 3.0


def test_wheel_and_gyro_carry_it_where_the_odometry_jumps(road):
    """GPS for the first 30 s only; at frame 700 the odometry jumps 4 m sideways and turns 30° (a speed it could
    have). With the wheel and gyro the step is replaced and the drive ends where the same drive without the jump
    ends, within 2 m, the scale held by the wheel; without them the turn is taken, and it ends hundreds of metres
    off."""
    truth = synthetic_truth("straight", n=1500)
    clean = drifting_odometry(truth.x_m, truth.y_m, truth.yaw_rad, 2, scale=0.9)
    ox, oy, oyaw = (a.copy() for a in clean)
    turn = math.radians(30.0)
    c, s = math.cos(turn), math.sin(turn)  # the path from frame 700 on: 4 m aside and turned with the jump
    rx, ry = ox[700:] - ox[699], oy[700:] - oy[699]
    ox[700:], oy[700:] = ox[699] + c * rx - s * ry, oy[699] + s * rx + c * ry + 4.0
    oyaw[700:] += turn
    wheel, gyro = wheel_gyro_samples(truth, seed=2)
    ends = {}
    for name, odo, fed in (("reference", clean, True), ("wheel", (ox, oy, oyaw), True), ("none", (ox, oy, oyaw), False)):
        ekf = GpsOdometryEkf(road)
        out = _feed(ekf, road, truth, *odo, 10, 30.0, 1.0, np.random.default_rng(2),
                    wheel=wheel if fed else None, gyro=gyro if fed else None)
        ends[name] = np.array(out[-1][:2])
        if name == "wheel":
            assert ekf.steps_vetoed >= 1 and abs(ekf.scale * 0.9 - 1.0) < 0.02
    assert np.linalg.norm(ends["wheel"] - ends["reference"]) < 2.0, ends
    assert np.linalg.norm(ends["none"] - ends["reference"]) > 100.0, ends


@settings(max_examples=50, deadline=None)
@given(turn=st.floats(-3.1, 3.1), scale=st.floats(0.1, 10.0), sx=st.floats(-1e3, 1e3), sy=st.floats(-1e3, 1e3),
       seed=st.integers(0, 1000))
def test_the_planar_similarity_is_recovered(turn, scale, sx, sy, seed):
    src = np.random.default_rng(seed).normal(0.0, 50.0, (20, 2))
    c, s = math.cos(turn), math.sin(turn)
    dst = scale * src @ np.array([[c, -s], [s, c]]).T + np.array([sx, sy])
    got = _similarity_2d(src, dst)
    assert got is not None
    assert abs(math.remainder(got[0] - turn, 2 * math.pi)) < 1e-9 and abs(got[1] / scale - 1.0) < 1e-9
    assert np.allclose(got[2], [sx, sy], atol=1e-6 * max(1.0, scale * 100.0))
    assert _similarity_2d(np.zeros((5, 2)), dst[:5]) is None


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_the_match_keeps_to_the_road_the_track_follows(road, seed):
    """A track along the southern road with 4 m of noise across it (so that a third of its points lie nearer the
    northern one, 12 m away): every matched position is on the southern road, which a point-by-point snap
    is not; the roads are not joined, so changing costs a jump the network does not have."""
    rng = np.random.default_rng(seed)
    mm = OfflineMapMatching(road)
    south = float(road.xy_m[:, 1].min())  # (the map's frame has its own origin)
    x0 = float(road.xy_m[:, 0].min()) + 100.0
    t = np.arange(600) * 0.1
    x, y = x0 + t * 10.0, south + rng.normal(0.0, 4.0, len(t))
    for k in range(len(t)):
        m = np.eye(4)
        m[0, 3], m[1, 3] = x[k], y[k]
        mm._t.append(float(t[k]))
        mm._pose.append(m)
    nearer_north = np.mean(y > south + 6.0)
    t_out, poses = mm.final_estimates()
    assert len(poses) == len(t) and np.array_equal(t_out, t)
    edges = range(len(road.edge_u))
    southern = min(edges, key=lambda e: road.xy_m[road.edge_start[e]:road.edge_end[e], 1].mean())
    way = road.xy_m[road.edge_start[southern]:road.edge_end[southern]]
    off = [np.min(np.hypot(*(way - p[:2, 3]).T)) for p in poses]
    assert max(off) < 0.5, (nearer_north, max(off))
    assert mm.estimate() is None


def test_bad_parameters_are_refused(road):
    with pytest.raises(ValueError, match="must be > 0"):
        GpsOdometryEkf(road, gps_sigma_m=0.0)
    with pytest.raises(ValueError, match="must be > 0"):
        OfflineMapMatching(road, radius_m=-1.0)
