"""Metrics: ATE as the paper (and evo) computes it, online error, RPE, match rate."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mapfusion.metrics import MetricsError, ate, match_rate, online_error, rpe_per_100m, zone_rmse

evo_core = pytest.importorskip("evo.core", reason="evo is a test-only dependency (pip install -e '.[test]')")


def _rand(seed: int, n: int = 150, z: float = 2.0):
    rng = np.random.default_rng(seed)
    gt = np.cumsum(rng.normal(0, 1, (n, 3)) * (5, 5, z), axis=0)
    est = gt + rng.normal(0, 1.0, (n, 3))
    return gt, est


def _rigid(seed: int):
    rng = np.random.default_rng(seed + 1)
    from scipy.spatial.transform import Rotation

    return Rotation.random(random_state=seed).as_matrix(), rng.normal(0, 100, 3)


def _evo_ape(gt, est):
    from evo.core import metrics
    from evo.core.trajectory import PoseTrajectory3D

    n = len(gt)
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    g2, e2 = gt.copy(), est.copy()
    g2[:, 2] = 0.0
    e2[:, 2] = 0.0
    tg = PoseTrajectory3D(positions_xyz=g2, orientations_quat_wxyz=q, timestamps=np.arange(n, dtype=float))
    te = PoseTrajectory3D(positions_xyz=e2, orientations_quat_wxyz=q, timestamps=np.arange(n, dtype=float))
    te.align(tg, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((tg, te))
    return ape.get_statistic(metrics.StatisticsType.rmse)


@given(seed=st.integers(0, 10**6))
def test_ate_equals_evo_on_random_trajectories(seed):
    gt, est = _rand(seed)
    assert ate(gt, est) == pytest.approx(_evo_ape(gt, est), abs=1e-6)


@given(seed=st.integers(0, 10**6), yaw=st.floats(-math.pi, math.pi), tx=st.floats(-1e4, 1e4), ty=st.floats(-1e4, 1e4))
def test_ate_invariant_to_a_rigid_motion_of_the_estimate(seed, yaw, tx, ty):
    gt, est = _rand(seed, z=0.0)
    c, s = math.cos(yaw), math.sin(yaw)
    moved = est @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + (tx, ty, 3.0)
    assert ate(gt, moved) == pytest.approx(ate(gt, est), abs=1e-6)


@given(seed=st.integers(0, 10**6))
def test_ate_zero_for_identical_and_rigidly_moved_copies(seed):
    gt, _ = _rand(seed, z=0.0)
    assert ate(gt, gt) == pytest.approx(0.0, abs=1e-9)
    yaw = (seed % 628) / 100.0
    c, s = math.cos(yaw), math.sin(yaw)
    assert ate(gt, gt @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + 50.0) == pytest.approx(0.0, abs=1e-6)


def test_ate_hand_computed():
    # truth on a line; the estimate is the truth plus +1, −1, −1, +1 m across it. Those offsets have
    # zero mean and zero correlation with x (Σ x·o = 0 − 10 − 20 + 30 = 0), so the cross-covariance
    # of the centred pair is diagonal, the best rigid alignment is the identity, every residual is
    # 1 m and the RMSE is exactly 1
    gt = np.array([[0, 0, 0], [10, 0, 0], [20, 0, 0], [30, 0, 0]], float)
    est = gt + np.array([[0, 1, 0], [0, -1, 0], [0, -1, 0], [0, 1, 0]], float)
    assert ate(gt, est) == pytest.approx(1.0, abs=1e-9)


def test_ate_bad_input():
    with pytest.raises(MetricsError):
        ate(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(MetricsError):
        ate(np.zeros((5, 3)), np.full((5, 3), np.nan))
    with pytest.raises(MetricsError):
        ate(np.zeros((5, 3)), np.zeros((4, 3)))


def test_online_error_parts():
    gt = np.column_stack([np.arange(10.0), np.zeros(10)])
    est = gt + (0.0, 2.0)  # 2 m to the left of an eastbound truth: all lateral
    e = online_error(gt, np.zeros(10), est)
    assert e.rmse_m == pytest.approx(2.0) and e.lateral_rmse_m == pytest.approx(2.0) and e.longitudinal_rmse_m == pytest.approx(0.0)
    e2 = online_error(gt, np.full(10, math.pi / 2), est)  # the same offset, northbound truth: all along
    assert e2.longitudinal_rmse_m == pytest.approx(2.0) and e2.lateral_rmse_m == pytest.approx(0.0)
    assert zone_rmse(gt, est, np.zeros(10, bool)) is None
    assert zone_rmse(gt, est, np.arange(10) < 3) == pytest.approx(2.0)



def test_the_end_error_is_where_a_found_again_estimate_ends():
    """A drive lost by 500 m for its first 240 s and 3 m off after: its RMSE says lost, its end error 3 m (the
    median over the last 60 s); without times there is none; times of another length are refused."""
    t = np.arange(0.0, 300.0, 0.1)
    gt = np.column_stack([10.0 * t, np.zeros_like(t)])
    est = gt + np.where(t < 240.0, 500.0, 3.0)[:, None] * (0.0, 1.0)
    e = online_error(gt, np.zeros_like(t), est, t)
    assert e.rmse_m > 400.0 and e.end_m == pytest.approx(3.0)
    assert online_error(gt, np.zeros_like(t), est).end_m is None
    with pytest.raises(MetricsError):
        online_error(gt, np.zeros_like(t), est, t[:-1])


@given(st.lists(st.floats(0.0, 1e4), min_size=1, max_size=200), st.floats(0.05, 5.0))
def test_the_end_error_is_the_median_over_the_last_minute(errors, period_s):
    err = np.asarray(errors)
    t = period_s * np.arange(len(err))
    gt = np.zeros((len(err), 2))
    est = np.column_stack([np.zeros_like(err), err])
    last = t >= t[-1] - 60.0
    assert online_error(gt, np.zeros_like(err), est, t).end_m == pytest.approx(float(np.median(err[last])))

def test_rpe_zero_for_a_rigid_copy_and_sensitive_to_drift():
    t = np.arange(0, 500.0)
    gt = np.column_stack([t, np.zeros_like(t)])
    yaw = np.zeros_like(t)
    c, s = math.cos(0.5), math.sin(0.5)
    moved = gt @ np.array([[c, -s], [s, c]]).T + 7.0
    assert rpe_per_100m(gt, yaw, moved, yaw + 0.5) == pytest.approx(0.0, abs=1e-9)
    drifting = np.column_stack([t * 1.01, np.zeros_like(t)])  # 1% scale error: 1 m per 100 m
    assert rpe_per_100m(gt, yaw, drifting, yaw) == pytest.approx(1.0, rel=0.02)
    assert rpe_per_100m(gt[:50], yaw[:50], gt[:50], yaw[:50]) is None


def test_match_rate():
    assert match_rate(np.array([1, 1, -1, 2]), np.array([1, 2, 7, 2])) == pytest.approx(2 / 3)
    assert match_rate(np.array([-1, -1]), np.array([1, 2])) is None


def test_match_rate_counts_continuations_only_when_asked():
    cont = {10: {11}, 11: {10}}
    true = np.array([10, 10, 10, 12])
    matched = np.array([10, 11, 13, 12])
    assert match_rate(true, matched) == pytest.approx(0.5)
    assert match_rate(true, matched, cont) == pytest.approx(0.75)  # 11 continues 10; 13 does not


def test_continuations_are_splits_not_junctions(tmp_path):
    from mapfusion import RoadMap, RoadMapConfig
    from tests.helpers import write_osm

    # one street split into two ways at x = 0, and a crossing street at x = 200 (a junction)
    w1 = np.array([[-200.0, 0.0], [0.0, 0.0]])
    w2 = np.array([[0.0, 0.0], [200.0, 0.0], [400.0, 0.0]])
    w3 = np.array([[200.0, -200.0], [200.0, 0.0], [200.0, 200.0]])
    path = write_osm(tmp_path, [(w1, {"highway": "residential"}), (w2, {"highway": "residential"}),
                                (w3, {"highway": "residential"})])
    road = RoadMap.from_osm(path, RoadMapConfig(), cache=False)
    cont = road.continuations()
    assert cont.get(1) == {2} and cont.get(2) == {1}
    assert 3 not in cont.get(2, set())


def _path_poses(n: int, step_m: float, yaw_rate: float) -> np.ndarray:
    yaw = np.arange(n) * yaw_rate
    p = np.tile(np.eye(4), (n, 1, 1))
    p[:, 0, 0], p[:, 0, 1], p[:, 1, 0], p[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
    p[:, 0, 3] = np.concatenate(([0.0], np.cumsum(step_m * np.cos(yaw[:-1]))))
    p[:, 1, 3] = np.concatenate(([0.0], np.cumsum(step_m * np.sin(yaw[:-1]))))
    return p


@given(step=st.floats(0.5, 2.0), eps=st.floats(-0.05, 0.05))
def test_kitti_errors_of_a_scaled_trajectory(step, eps):
    """KITTI's t_err: a trajectory scaled by 1 + ε is off by |ε| of every segment's driven length,
    which the development kit divides by the nominal length L (the segment ends at the first frame
    beyond L: at most one step more), so 100·|ε| ≤ t_err ≤ 100·|ε|·(1 + step/100); its rotations
    are exact; fitting one global scale first removes it; a perfect estimate scores 0. (On a straight
    road: on a bend the error is ε times the chord, shorter than the distance driven.)"""
    from mapfusion.metrics import global_scale, kitti_errors

    gt = _path_poses(1200, step, 0.0)
    est = gt.copy()
    est[:, :3, 3] *= 1.0 + eps
    k = kitti_errors(gt, est)
    assert k.segments > 0
    assert 100.0 * abs(eps) - 1e-9 <= k.t_err_percent <= 100.0 * abs(eps) * (1.0 + step / 100.0) + 1e-9
    assert k.r_err_deg_per_100m < 1e-6
    assert kitti_errors(gt, gt).t_err_percent < 1e-9
    s = global_scale(gt[:, :3, 3], est[:, :3, 3])
    assert kitti_errors(gt, est, s).t_err_percent < 1e-6


@given(drift_deg_per_100m=st.floats(0.1, 5.0))
def test_kitti_rotation_error_of_a_yaw_drift(drift_deg_per_100m):
    """An estimate whose heading drifts by d degrees per 100 m driven has r_err = d deg/100 m (up to
    the one step a segment may run past its nominal length)."""
    from mapfusion.metrics import kitti_errors

    step = 1.0
    gt = _path_poses(1000, step, 0.0)
    est = _path_poses(1000, step, np.radians(drift_deg_per_100m) / 100.0 * step)
    k = kitti_errors(gt, est)
    assert drift_deg_per_100m * (1 - 1e-6) <= k.r_err_deg_per_100m <= drift_deg_per_100m * (1.0 + step / 100.0) + 1e-9


@given(c=st.floats(0.5, 30.0), drift=st.floats(-3.0, 3.0))
def test_odometry_stats_recover_a_scale_a_drift_and_a_jump(c, drift):
    """An odometry in units of 1/c metres with a heading drift of d deg/100 m and one 30 m jump:
    its global scale is c, its yaw drift d, one jump in its 1.2 km; the truth against itself is clean."""
    from mapfusion.metrics import odometry_stats

    n, step = 1200, 1.0
    t = np.arange(n) * 0.1
    gt = _path_poses(n, step, 0.0)
    clean = odometry_stats(t, gt, gt)
    assert abs(clean.global_scale - 1) < 1e-9 and clean.kitti_t_err_percent < 1e-9 and clean.jumps_per_km == 0
    assert abs(clean.yaw_drift_deg_per_100m) < 1e-9 and clean.lateral_rmse_m < 1e-9
    od = _path_poses(n, step, np.radians(drift) / 100.0 * step)
    od[600:, 0, 3] += 30.0  # a re-initialisation's jump along the way
    od[:, :3, 3] /= c
    s = odometry_stats(t, gt, od)
    assert abs(s.yaw_drift_deg_per_100m - drift) < 1e-6 + 0.02 * abs(drift)
    assert s.jumps_per_km * s.driven_m / 1000.0 == pytest.approx(1.0)
    if abs(drift) < 0.5:  # on a nearly straight odometry the jump is the only scale error
        assert abs(s.global_scale / c - 1) < 0.05



def _relocalisation_brute(d, e, from_m, within=10.0, hold=100.0):
    sel = d >= from_m
    d, e = d[sel], e[sel]
    for i in range(len(d)):
        if not e[i] < within:
            continue
        j = i
        while j < len(d) and e[j] < within:
            j += 1
        end = d[j] if j < len(d) else d[-1]
        if end - d[i] >= hold:
            return float(d[i] - from_m)
    return None


@given(steps=st.lists(st.floats(0.0, 20.0), min_size=2, max_size=300),
       errors=st.lists(st.floats(0.0, 30.0), min_size=300, max_size=300), from_m=st.floats(0.0, 500.0))
def test_relocalisation_distance_is_where_the_error_first_stays_small_for_100_m(steps, errors, from_m):
    from mapfusion.metrics import relocalisation_m

    d = np.cumsum(steps)
    e = np.array(errors[: len(d)])
    assert relocalisation_m(d, e, from_m) == _relocalisation_brute(d, e, from_m)
