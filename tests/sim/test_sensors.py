"""Sensor models: exactness without noise, error statistics as configured, GPS denial, determinism."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapfusion.formats import read_gps_csv, read_imu_csv, read_tum, tum_to_matrices
from sim.scenario import GpsConfig, GpsMode, OdometryKind, WeatherKind, scenario_from_dict
from sim.sensors import (
    GRAVITY_MPS2,
    ImuParams,
    OdometryParams,
    gps_fix_frames,
    odometry_preset,
    simulate_gps,
    simulate_imu,
    simulate_odometry,
    truth_poses,
    apply_kidnap,
    fast_frames,
    imu_gap_resets,
)
from tests.helpers import synthetic_truth

#: Fields whose "no error" value is not 0: the odometry's unit (metres), the noise multiplier while
#: standing, and the start bias's decay length (a length, never 0).
_NEUTRAL = {"unit_m_min": 1.0, "unit_m_max": 1.0, "standstill_noise_factor": 1.0, "start_scale_bias_m": 200.0,
            "fast_speed_mps": 22.0}
ZERO = OdometryParams(**{f.name: _NEUTRAL.get(f.name, 0.0) for f in dataclasses.fields(OdometryParams)})


def _quiet(**changes) -> OdometryParams:
    return dataclasses.replace(ZERO, **changes)


@given(kind=st.sampled_from(["straight", "circle", "random"]), seed=st.integers(0, 1000),
       speed=st.floats(0.5, 30.0), n=st.integers(20, 400))
def test_noise_free_odometry_integrates_back_to_the_truth(kind, seed, speed, n):
    truth = synthetic_truth(kind, n=n, speed_mps=speed, seed=seed)
    out = simulate_odometry(truth, ZERO, np.random.default_rng(seed))
    assert np.allclose(out.poses[0], np.eye(4))
    T = truth_poses(truth)
    world = np.einsum("ij,njk->nik", T[0], out.poses)  # the odometry frame put at the first truth pose
    assert np.abs(world[:, :3, 3] - T[out.frame_index, :3, 3]).max() < 1e-6
    assert len(out.t_s) == n and np.all(np.diff(out.t_s) > 0)


def _final_errors(truth, params, seeds):
    T = truth_poses(truth)
    out = []
    for s in seeds:
        o = simulate_odometry(truth, params, np.random.default_rng(s))
        rel = np.linalg.inv(T[-1]) @ (T[0] @ o.poses[-1])  # final pose error in the true body frame
        out.append((rel[0, 3], rel[1, 3], math.atan2(rel[1, 0], rel[0, 0])))
    return np.array(out)


def _sd_ok(sample: np.ndarray, expected: float) -> bool:
    """Sample standard deviation within the 99.9% chi-square band of N(0, expected²)."""
    n = len(sample)
    sd = float(np.sqrt(np.mean(sample**2)))
    tol = 3.3 / math.sqrt(2 * n)
    return abs(sd / expected - 1.0) < tol


SEEDS = range(400)


def test_scale_error_matches_its_sigma():
    truth = synthetic_truth("straight", n=200, speed_mps=10.0)  # 199 m
    err = _final_errors(truth, _quiet(scale_error_sigma=0.01), SEEDS)
    assert _sd_ok(err[:, 0] / 199.0, 0.01)


def test_scale_random_walk_matches_its_rate():
    truth = synthetic_truth("straight", n=401, speed_mps=10.0)  # 400 m in 1 m steps
    err = _final_errors(truth, _quiet(scale_rw_per_sqrt_m=1e-3), SEEDS)
    # the along-track error of a scale random walk is Σ_k s_k · 1 m with s_k = Σ_{j≤k} w_j, w_j ~ N(0, q²):
    # increment w_j weighs on the N − j + 1 steps after it, so Var = q² · Σ_{m=1..N} m²
    m = np.arange(1, 401)
    expected = 1e-3 * math.sqrt(np.sum(m.astype(float) ** 2))
    assert _sd_ok(err[:, 0], expected)


def test_yaw_drift_matches_its_rate():
    truth = synthetic_truth("straight", n=301, speed_mps=10.0)  # 300 m
    err = _final_errors(truth, _quiet(yaw_bias_sigma_rad_per_m=1e-4), SEEDS)
    assert _sd_ok(err[:, 2], 1e-4 * 300.0)


def test_lateral_bias_matches_its_rate():
    truth = synthetic_truth("straight", n=301, speed_mps=10.0)
    err = _final_errors(truth, _quiet(lateral_bias_sigma_m_per_m=0.01), SEEDS)
    assert _sd_ok(err[:, 1], 0.01 * 300.0)


def test_white_noise_matches_its_sigma():
    truth = synthetic_truth("straight", n=2, speed_mps=10.0)
    err = _final_errors(truth, _quiet(translation_noise_m=0.05, rotation_noise_rad=0.002), range(2000))
    assert _sd_ok(err[:, 0], 0.05) and _sd_ok(err[:, 1], 0.05)
    assert _sd_ok(err[:, 2], 0.002)


def test_vo_loses_track_in_degraded_zones_and_reinitialises():
    truth = synthetic_truth("straight", n=600, denied=(200, 399))
    out = simulate_odometry(truth, _quiet(tunnel_lose_track=1.0, reinit_jump_sigma_m=2.0), np.random.default_rng(1))
    assert not np.isin(np.arange(200, 400), out.frame_index).any()  # dropped in the zone
    assert [k for _, k in out.events] == ["reinit"]
    # vio keeps tracking, drifting faster inside
    vio = simulate_odometry(truth, _quiet(tunnel_lose_track=0.0), np.random.default_rng(1))
    assert len(vio.t_s) == 600


def test_rain_episodes_push_sideways():
    truth = synthetic_truth("straight", n=3000, speed_mps=10.0)  # 3 km
    p = _quiet(rain_episode_rate_per_km=3.0, rain_episode_duration_s=5.0, rain_lateral_drift_m_per_m=0.05)
    lat = []
    for s in range(50):
        out = simulate_odometry(truth, p, np.random.default_rng(s), rain=True)
        assert out.rain_episode.any() or s > 40
        lat.append(out.poses[-1, 1, 3])
    # 9 episodes of ~50 m at 0.05 m/m → ±2.5 m each, random signs: RMS around 7.5 m
    rms = float(np.sqrt(np.mean(np.square(lat))))
    assert 4.0 < rms < 12.0


def test_map_resets_are_discontinuities():
    truth = synthetic_truth("straight", n=2000, speed_mps=10.0)
    out = simulate_odometry(truth, _quiet(map_reset_rate_per_km=3.0, map_reset_jump_sigma_m=5.0), np.random.default_rng(4))
    resets = [t for t, k in out.events if k == "map_reset"]
    assert resets
    steps = np.hypot(*np.diff(out.poses[:, :2, 3], axis=0).T)
    assert steps.max() > 2.0  # a normal step is 1 m


def test_presets_by_kind_and_weather():
    assert odometry_preset("vo", "heavy_rain").map_reset_rate_per_km == 0.0
    assert odometry_preset(OdometryKind.vio, WeatherKind.heavy_rain).map_reset_rate_per_km > 0.0
    assert odometry_preset("vo", "rain").rain_noise_factor > odometry_preset("vo", "clear").rain_noise_factor


# ----------------------------------------------------------------------------- GPS
def test_gps_error_statistics_match_sigma():
    truth = synthetic_truth("random", n=20000, seed=3)
    cfg = GpsConfig(mode=GpsMode.continuous, rate_hz=10.0, sigma_m=2.0, outlier_probability=0.0)
    g = simulate_gps(truth, cfg, np.random.default_rng(0))
    ex = g.x_m - truth.x_m[g.frame_index]
    ey = g.y_m - truth.y_m[g.frame_index]
    assert len(g.t_s) == 20000
    assert _sd_ok(ex, 2.0) and _sd_ok(ey, 2.0)
    assert abs(ex.mean()) < 0.05 and abs(ey.mean()) < 0.05


def test_gps_outliers_are_tens_of_metres():
    truth = synthetic_truth("random", n=20000, seed=4)
    cfg = GpsConfig(mode=GpsMode.continuous, rate_hz=10.0, sigma_m=2.0, outlier_probability=0.05, outlier_sigma_m=30.0)
    g = simulate_gps(truth, cfg, np.random.default_rng(1))
    err = np.hypot(g.x_m - truth.x_m[g.frame_index], g.y_m - truth.y_m[g.frame_index])
    assert 0.04 < g.outlier.mean() < 0.06
    assert np.median(err[g.outlier]) > 20.0 and np.median(err[~g.outlier]) < 3.0


@given(mode=st.sampled_from(list(GpsMode)), a=st.integers(0, 500), length=st.integers(1, 300), rate=st.sampled_from([0.5, 1.0, 5.0]))
@settings(max_examples=30)
def test_no_fix_inside_a_denied_zone(mode, a, length, rate):
    truth = synthetic_truth("straight", n=1200, denied=(a, a + length))
    g = simulate_gps(truth, GpsConfig(mode=mode, rate_hz=rate, init_window_s=60.0), np.random.default_rng(2))
    assert not np.any(truth.gps_denied[g.frame_index])
    assert np.all(np.diff(g.t_s) > 0)


def test_gps_modes():
    truth = synthetic_truth("straight", n=3000)  # 300 s
    t = lambda cfg: truth.t_s[gps_fix_frames(truth, cfg)]  # noqa: E731
    init = t(GpsConfig(mode=GpsMode.init_only, rate_hz=1.0, init_window_s=60.0))
    assert init.max() <= 60.0 + 1e-9 and len(init) == 61
    inter = t(GpsConfig(mode=GpsMode.interval, rate_hz=1.0, init_window_s=60.0, interval_s=5.0))
    assert np.allclose(np.diff(inter[inter > 61.0]), 5.0)
    cont = t(GpsConfig(mode=GpsMode.continuous, rate_hz=2.0))
    assert np.allclose(np.diff(cont), 0.5)


# ----------------------------------------------------------------------------- IMU
def test_imu_on_a_circle_without_noise():
    truth = synthetic_truth("circle", n=600, speed_mps=10.0, radius_m=50.0)
    p = ImuParams(accel_noise_density=0.0, gyro_noise_density=0.0, accel_bias_sigma=0.0, gyro_bias_sigma=0.0,
                  accel_bias_rw=0.0, gyro_bias_rw=0.0)
    imu = simulate_imu(truth, p, np.random.default_rng(0))
    mid = slice(100, -100)  # away from the spline's free ends
    assert np.allclose(imu.accel_mps2[mid, 1], 10.0**2 / 50.0, rtol=0.02)  # centripetal, to the left
    assert np.allclose(imu.accel_mps2[mid, 0], 0.0, atol=0.05)
    assert np.allclose(imu.accel_mps2[mid, 2], GRAVITY_MPS2, atol=1e-6)
    assert np.allclose(imu.gyro_radps[mid, 2], 10.0 / 50.0, rtol=0.01)
    assert np.allclose(np.diff(imu.t_s), 0.01)


def test_imu_noise_density():
    truth = synthetic_truth("straight", n=1000)
    p = ImuParams(accel_bias_sigma=0.0, gyro_bias_sigma=0.0, accel_bias_rw=0.0, gyro_bias_rw=0.0)
    imu = simulate_imu(truth, p, np.random.default_rng(0))
    assert _sd_ok(imu.accel_mps2[50:-50, 1], p.accel_noise_density * 10.0)
    assert _sd_ok(imu.gyro_radps[50:-50, 0], p.gyro_noise_density * 10.0)


# ----------------------------------------------------------------------------- simulate: files and determinism
@pytest.mark.sumo
def test_simulate_writes_sensor_files_identically_for_a_seed(tmp_path):
    from typer.testing import CliRunner

    from mapfusion.harness.cli import app

    sc = tmp_path / "s.toml"
    sc.write_text('name = "s"\nmap = "tunnel"\nseed = 5\nduration_s = 150.0\n[weather]\nkind = "rain"\n'
                  '[route]\nedges = ["1", "3"]\n[gps]\nmode = "interval"\ninit_window_s = 30.0\n')
    runner = CliRunner()
    for out in ("a", "b"):
        r = runner.invoke(app, ["simulate", str(sc), "--out", str(tmp_path / out)])
        assert r.exit_code == 0, r.output
    for f in ("odometry.tum", "gps.csv", "imu.csv", "truth.csv"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    t, xyz, q = read_tum(tmp_path / "a" / "odometry.tum")
    assert np.allclose(tum_to_matrices(xyz[:1], q[:1])[0], np.eye(4), atol=1e-6)
    gps = read_gps_csv(tmp_path / "a" / "gps.csv")
    ti, acc, gyr = read_imu_csv(tmp_path / "a" / "imu.csv")
    assert np.all(np.diff(t) > 0) and np.all(np.diff(gps.t_s) > 0) and np.all(np.diff(ti) > 0)
    # no fix while in the tunnel
    import csv

    rows = list(csv.DictReader(open(tmp_path / "a" / "truth.csv")))
    tunnel_t = np.array([float(r["t"]) for r in rows if r["in_tunnel"] == "1"])
    assert len(tunnel_t) > 0
    assert not np.isin(np.round(gps.t_s, 3), np.round(tunnel_t, 3)).any()
    # another seed, other noise
    sc.write_text(sc.read_text().replace("seed = 5", "seed = 6"))
    runner.invoke(app, ["simulate", str(sc), "--out", str(tmp_path / "c")])
    assert (tmp_path / "a" / "odometry.tum").read_bytes() != (tmp_path / "c" / "odometry.tum").read_bytes()


def test_scenario_overrides_reach_the_model():
    sc = scenario_from_dict({"name": "o", "map": "grid", "odometry": {"kind": "vio", "rain_noise_factor": 7.0}}, "t")
    p = odometry_preset(sc.odometry.kind, sc.weather.kind).with_overrides(sc.odometry.overrides)
    assert p.rain_noise_factor == 7.0 and p.tunnel_lose_track == 0.0


def test_imu_parameters_come_from_the_scenario():
    sc = scenario_from_dict({"name": "i", "map": "grid", "imu": {"rate_hz": 200.0, "gyro_noise_density": 0.0}}, "t")
    assert sc.imu.rate_hz == 200.0
    truth = synthetic_truth("straight", n=100)
    imu = simulate_imu(truth, sc.imu, np.random.default_rng(0))
    assert np.allclose(np.diff(imu.t_s), 1 / 200.0)


@given(steps=st.lists(st.floats(0.01, 3.0), min_size=1, max_size=400), mode=st.sampled_from(list(GpsMode)),
       rate=st.sampled_from([0.5, 1.0, 10.0]), window=st.floats(0.0, 100.0), interval=st.floats(0.5, 20.0))
def test_gps_fix_times_are_the_first_times_after_each_tick(steps, mode, rate, window, interval):
    """Irregular recorded times: a fix at the first time at or after each tick of the schedule."""
    from sim.sensors import gps_fix_times

    t = np.concatenate(([0.0], np.cumsum(steps)))
    cfg = GpsConfig(mode=mode, rate_hz=rate, init_window_s=window, interval_s=interval)
    if mode is GpsMode.continuous:
        ticks = np.arange(0.0, t[-1] + 1e-9, 1.0 / rate)
    else:
        ticks = np.arange(0.0, min(window, t[-1]) + 1e-9, 1.0 / rate)
        if mode is GpsMode.interval:
            ticks = np.concatenate([ticks, np.arange(window, t[-1] + 1e-9, interval)])
    want = sorted({next(i for i in range(len(t)) if t[i] >= k - 1e-9) for k in ticks if k <= t[-1] + 1e-9})
    assert gps_fix_times(t, cfg).tolist() == want


# ----------------------------------------------------------------------------- wheel speed (issue 18)
def _wheel(truth, weather=WeatherKind.clear, seed=0, **changes):
    from sim.sensors import WheelParams, simulate_wheel

    return simulate_wheel(truth, dataclasses.replace(WheelParams(), **changes), np.random.default_rng(seed), weather)


def _path_m(truth) -> float:
    return float(np.sum(np.hypot(np.diff(truth.x_m), np.diff(truth.y_m))))


@given(seed=st.integers(0, 10_000), kind=st.sampled_from(["straight", "circle", "random"]),
       error=st.floats(0.0, 0.05))
@settings(max_examples=25, deadline=None)
def test_noise_free_wheel_speed_integrates_to_the_path_length_times_its_scale(seed, kind, error):
    truth = synthetic_truth(kind, n=800, speed_mps=12.0, seed=seed)
    w = _wheel(truth, seed=seed, scale_error_min=error, scale_error_max=error, speed_noise_mps=0.0, quantum_mps=0.0)
    assert abs(w.scale_error) == pytest.approx(error)
    # left Riemann sum: each sample holds for one period (the truth steps its speed every 0.1 s)
    driven = float(np.sum(w.speed_mps[:-1] * np.diff(w.t_s)))
    assert driven == pytest.approx(_path_m(truth) * (1.0 + w.scale_error), rel=1e-3)


def test_wheel_scale_error_is_drawn_in_its_range_with_either_sign():
    truth = synthetic_truth("straight", n=50)
    errors = np.array([_wheel(truth, seed=s).scale_error for s in range(200)])
    assert np.all((np.abs(errors) >= 0.005) & (np.abs(errors) <= 0.02))
    assert (errors > 0).mean() == pytest.approx(0.5, abs=0.15)


def test_wheel_noise_quantisation_and_standstill():
    truth = synthetic_truth("straight", n=600, speed_mps=10.0)
    w = _wheel(truth, scale_error_min=0.0, scale_error_max=0.0, speed_noise_mps=0.05, quantum_mps=0.0)
    assert np.std(w.speed_mps - 10.0) == pytest.approx(0.05, rel=0.1)
    q = _wheel(truth, quantum_mps=0.05)
    assert np.allclose(q.speed_mps / 0.05, np.round(q.speed_mps / 0.05), atol=1e-9)
    stopped = synthetic_truth("straight", n=100, speed_mps=0.0)
    assert np.all(_wheel(stopped, speed_noise_mps=0.5).speed_mps == 0.0)  # no pulses, no creeping


def test_wheels_slip_only_in_rain_and_only_under_hard_acceleration():
    n = 600
    t = np.arange(n) * 0.1
    v = np.clip(3.0 * t, 0.0, 15.0)  # 3 m/s² up to 15 m/s, then steady
    x = np.concatenate(([0.0], np.cumsum(v[:-1] * 0.1)))
    z = np.zeros(n)
    from tests.helpers import TruthTrack

    truth = TruthTrack(t, x, z, z, z, z.astype(bool), z.astype(bool))
    quiet = dict(scale_error_min=0.0, scale_error_max=0.0, speed_noise_mps=0.0, quantum_mps=0.0)
    clear, rain, heavy = (_wheel(truth, wx, **quiet)
                          for wx in (WeatherKind.clear, WeatherKind.rain, WeatherKind.heavy_rain))
    accel = (clear.t_s > 0.6) & (clear.t_s < 4.4)
    steady = clear.t_s > 7.0
    over_rain = rain.speed_mps[accel] / clear.speed_mps[accel] - 1.0
    assert np.median(over_rain) == pytest.approx(0.02 * (3.0 - 1.0), rel=0.1)  # slip_per_mps2 × (a − 1 m/s²)
    over_heavy = heavy.speed_mps[accel] / clear.speed_mps[accel] - 1.0
    assert np.median(over_heavy) == pytest.approx(2 * np.median(over_rain), rel=0.05)
    assert np.allclose(rain.speed_mps[steady], clear.speed_mps[steady])


def test_the_wheel_leaves_every_other_sensor_as_it_was():
    """A vo+wheel run has the very VO, IMU and GPS of the vo run of the same seed: its own seeded stream."""
    from sim.sensors import synthesise

    truth = synthetic_truth("random", n=1500, speed_mps=10.0, seed=4)
    a = synthesise(scenario_from_dict({"seed": 7, "odometry": {"kind": "vo"}}, "t", resolve=False), truth)
    b = synthesise(scenario_from_dict({"seed": 7, "odometry": {"kind": "vo+wheel"}}, "t", resolve=False), truth)
    assert a.wheel is None and b.wheel is not None
    assert np.array_equal(a.odometry.poses, b.odometry.poses) and np.array_equal(a.imu.gyro_radps, b.imu.gyro_radps)
    assert np.array_equal(a.gps.x_m, b.gps.x_m)


@given(st.tuples(*[st.floats(-2.0, 2.0)] * 3), st.sampled_from([1e-6, 1e-4, 1e-3, 0.01, 1.0]))
def test_the_closed_form_rotation_is_scipys_to_the_bit(v, size):
    """The sensor model's rotation-vector exponential (issue 21: a sixth of scipy's cost per frame) gives
    scipy's matrix to the bit, so every simulated drive is unchanged; and it is a rotation."""
    from scipy.spatial.transform import Rotation

    from sim.sensors import _exp_se3

    rv = np.array(v) * size
    m = _exp_se3(np.concatenate([[1.0, -2.0, 0.5], rv]))
    assert np.array_equal(m[:3, :3], Rotation.from_rotvec(rv).as_matrix())
    assert np.array_equal(m[:3, 3], [1.0, -2.0, 0.5]) and np.array_equal(m[3], [0.0, 0.0, 0.0, 1.0])
    assert np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-12)


# ----------------------------------------------------------------------------- issue 22's error terms
@given(seed=st.integers(0, 1000), lo=st.floats(0.005, 2.0), ratio=st.floats(1.0, 20.0))
def test_the_odometry_unit_divides_every_position(seed, lo, ratio):
    """A monocular VO's arbitrary unit: noise-free, the positions times the drawn unit are the truth's,
    and the unit lies in [unit_m_min, unit_m_max]."""
    truth = synthetic_truth("random", n=120, seed=seed)
    out = simulate_odometry(truth, _quiet(unit_m_min=lo, unit_m_max=lo * ratio), np.random.default_rng(seed))
    T = truth_poses(truth)
    true_d = np.linalg.norm(T[-1, :3, 3] - T[0, :3, 3])
    unit = true_d / np.linalg.norm(out.poses[-1, :3, 3])
    assert lo * (1 - 1e-9) <= unit <= lo * ratio * (1 + 1e-9)
    world = np.einsum("ij,njk->nik", T[0], out.poses * np.array([1, 1, 1, unit])[None, None, :])
    world[:, 3, 3] = 1.0
    assert np.abs(world[:, :3, 3] - T[out.frame_index, :3, 3]).max() < 1e-6 * max(1.0, true_d)


def test_unit_range_the_wrong_way_round_is_an_error():
    truth = synthetic_truth("straight", n=10)
    with pytest.raises(ValueError, match="unit_m_max"):
        simulate_odometry(truth, _quiet(unit_m_min=0.5, unit_m_max=0.1), np.random.default_rng(0))


@pytest.mark.slow
def test_turn_scale_error_matches_its_sigma():
    """Every measured yaw change reads (1 + ε) times the true one: after a full circle the heading is
    off by ε · 2π, ε ~ N(0, σ²) per run."""
    truth = synthetic_truth("circle", n=629, speed_mps=10.0, radius_m=100.0)  # 2π rad in 62.8 s
    turned = float(np.sum(np.diff(np.unwrap(truth.yaw_rad))))
    err = _final_errors(truth, _quiet(turn_scale_sigma=0.05), SEEDS)
    assert _sd_ok(err[:, 2], 0.05 * turned)


@pytest.mark.slow
def test_reverting_scale_wander_has_its_stationary_sigma():
    """With a correlation length L, the scale error settles to σ = q · √(L / 2) instead of growing
    without bound: read from the last step's length, 2 km (10 L) into the drive."""
    truth = synthetic_truth("straight", n=2001, speed_mps=10.0)  # 1 m steps
    q, L = 2e-3, 200.0
    last = []
    for s in SEEDS:
        o = simulate_odometry(truth, _quiet(scale_rw_per_sqrt_m=q, scale_reversion_m=L), np.random.default_rng(s))
        last.append(np.linalg.norm(o.poses[-1, :3, 3] - o.poses[-2, :3, 3]) - 1.0)
    assert _sd_ok(np.array(last), q * math.sqrt(L / 2.0))


@pytest.mark.slow
def test_start_scale_bias_decays():
    """The start-up scale error has its σ on the first step and is gone after many decay lengths."""
    truth = synthetic_truth("straight", n=1501, speed_mps=10.0)  # 1.5 km in 1 m steps
    first, last = [], []
    for s in SEEDS:
        o = simulate_odometry(truth, _quiet(start_scale_bias_sigma=0.2, start_scale_bias_m=100.0),
                              np.random.default_rng(s))
        steps = np.linalg.norm(np.diff(o.poses[:, :3, 3], axis=0), axis=1)
        first.append(steps[0] - 1.0)
        last.append(steps[-1] - 1.0)
    assert _sd_ok(np.array(first) / math.exp(-1 / 100.0), 0.2)  # the first step is 1 m in
    assert np.abs(last).max() < 0.2 * math.exp(-14.0) * 5


def test_noise_while_standing_is_scaled_down():
    truth = synthetic_truth("straight", n=2, speed_mps=0.0)
    err = _final_errors(truth, _quiet(translation_noise_m=0.05, rotation_noise_rad=0.002,
                                      standstill_noise_factor=0.1), range(2000))
    assert _sd_ok(err[:, 0], 0.005) and _sd_ok(err[:, 2], 0.0002)


@pytest.mark.parametrize("weather", ["clear", "rain", "heavy_rain"])
def test_vio_sets_none_of_the_fitted_terms(weather):
    """vio keeps the paper-calibrated model: none of issue 22's terms is set (unset, they draw nothing,
    so its noise streams and its families' results are the same as before them)."""
    p = odometry_preset("vio", weather)
    assert (p.turn_scale_sigma, p.start_scale_bias_sigma, p.scale_reversion_m) == (0.0, 0.0, 0.0)
    assert (p.unit_m_min, p.unit_m_max, p.standstill_noise_factor) == (1.0, 1.0, 1.0)


@pytest.mark.parametrize("kind", ["vo", "mono"])
def test_fitted_presets_differ_from_the_paper_calibrated_base(kind):
    """vo and mono carry the fitted terms (docs/sensors.md); mono writes in an arbitrary unit."""
    p = odometry_preset(kind, "clear")
    assert p.rotation_noise_rad > OdometryParams().rotation_noise_rad
    assert (p.unit_m_max < 1.0) == (kind == "mono")


def _kidnap_inputs(seed: int):
    truth = synthetic_truth("random", n=6000, seed=seed)
    odo = simulate_odometry(truth, _quiet(), np.random.default_rng(seed))
    g = simulate_gps(truth, GpsConfig(mode=GpsMode.init_only, init_window_s=60.0, outlier_probability=0.0),
                     np.random.default_rng(seed))
    return truth, odo, g


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 500))
def test_a_gps_bias_kidnap_moves_every_fix_by_one_vector_in_range(seed):
    from sim.scenario import KidnapConfig, KidnapKind

    truth, odo, g = _kidnap_inputs(seed)
    cfg = KidnapConfig(kind=KidnapKind.gps_bias, bias_min_m=50.0, bias_max_m=200.0)
    odo2, g2, k = apply_kidnap(cfg, truth, odo, g, np.random.default_rng(seed))
    shift = np.column_stack([g2.x_m - g.x_m, g2.y_m - g.y_m])
    assert np.allclose(shift, shift[0]) and 50.0 <= np.hypot(*shift[0]) <= 200.0
    assert odo2 is odo and k.kind == "gps_bias" and k.t_s == g.t_s[-1]  # counted from the last (biased) fix
    assert math.isclose(k.distance_m, float(np.hypot(*shift[0])))


@pytest.mark.slow
@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 500))
def test_a_vo_jump_kidnap_is_an_outage_then_one_jump_with_every_other_step_unchanged(seed):
    from sim.scenario import KidnapConfig, KidnapKind

    truth, odo, g = _kidnap_inputs(seed)
    cfg = KidnapConfig(kind=KidnapKind.vo_jump, at_min_m=50.0, at_max_m=200.0, gap_s=8.0)
    odo2, g2, k = apply_kidnap(cfg, truth, odo, g, np.random.default_rng(seed))
    assert g2 is g and k is not None and 30.0 <= k.distance_m <= 300.0 and abs(k.heading_rad) <= math.radians(30)
    resume = int(np.searchsorted(odo2.t_s, k.t_s))
    gap = odo2.t_s[resume] - odo2.t_s[resume - 1]
    assert 8.0 <= gap <= 8.0 + 2 * 0.1 and odo2.dropped.sum() >= 79
    rel = np.linalg.inv(odo2.poses[:-1]) @ odo2.poses[1:]  # every relative step but the jump is the VO's own
    j0 = {float(t): i for i, t in enumerate(odo.t_s)}
    for i in range(len(odo2.t_s) - 1):
        if i == resume - 1:
            continue
        a = j0[float(odo2.t_s[i])]
        assert np.allclose(rel[i], np.linalg.inv(odo.poses[a]) @ odo.poses[a + 1], atol=1e-6)
    # across the gap: the true motion, then the drawn turn and jump (in the odometry's frame)
    a, b = j0[float(odo2.t_s[resume - 1])], j0[float(odo2.t_s[resume])]
    moved = odo2.poses[resume, :2, 3] - odo.poses[b, :2, 3]
    assert math.isclose(float(np.hypot(*moved)), k.distance_m, rel_tol=1e-9)
    yaw = math.atan2(odo2.poses[resume, 1, 0], odo2.poses[resume, 0, 0]) - math.atan2(odo.poses[b, 1, 0],
                                                                                       odo.poses[b, 0, 0])
    assert math.isclose(math.remainder(yaw - k.heading_rad, 2 * math.pi), 0.0, abs_tol=1e-9)
    assert a < b


def test_no_kidnap_changes_nothing():
    from sim.scenario import KidnapConfig

    truth, odo, g = _kidnap_inputs(1)
    assert apply_kidnap(KidnapConfig(), truth, odo, g, np.random.default_rng(0)) == (odo, g, None)


# ----------------------------------------------------------------------------- the paper's presets' terms
@given(speed=st.floats(1.0, 40.0), threshold=st.floats(1.0, 40.0), n=st.integers(2, 300))
def test_fast_frames_are_those_above_the_speed_over_the_window(speed, threshold, n):
    truth = synthetic_truth("straight", n=n, speed_mps=speed)
    dist = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(truth.x_m), np.diff(truth.y_m)))))
    fast = fast_frames(truth.t_s, dist, threshold)
    assert not fast[0]  # nothing driven yet
    if abs(speed - threshold) > 1e-6 * speed:
        assert (fast[1:] == (speed > threshold)).all()


def test_fast_frames_average_over_the_window():
    """5 s at 30 m/s after a long stop: fast only once the 5 s mean exceeds the threshold."""
    t = np.arange(200) * 0.1
    v = np.where(t >= 10.0, 30.0, 0.0)
    dist = np.concatenate(([0.0], np.cumsum(v[:-1] * 0.1)))
    fast = fast_frames(t, dist, 15.0)
    first = int(np.argmax(fast))
    assert fast[first:].all() and 12.4 <= t[first] <= 12.7  # 2.5 s of 30 m/s in 5 s: a mean of 15 m/s


@given(gaps=st.lists(st.tuples(st.integers(0, 280), st.integers(1, 15)), max_size=6), prob=st.sampled_from([0.0, 1.0]))
def test_an_imu_gap_resets_where_the_imu_resumes(gaps, prob):
    miss = np.zeros(300, dtype=bool)
    for a, length in gaps:
        miss[a:a + length] = True
    out = imu_gap_resets(miss, prob, np.random.default_rng(0))
    resumes = [k for k in range(1, 300) if miss[k - 1] and not miss[k]]
    if miss[0]:
        resumes = resumes[1:]  # the IMU starting late is no gap
    assert np.flatnonzero(out).tolist() == (resumes if prob == 1.0 else [])


def test_fast_scale_loss_shortens_only_the_fast_motion():
    slow = synthetic_truth("straight", n=301, speed_mps=10.0)
    fast = synthetic_truth("straight", n=301, speed_mps=30.0)
    p = _quiet(fast_scale_loss=0.1, fast_speed_mps=22.0)
    for truth, share in ((slow, 1.0), (fast, 0.9)):
        o = simulate_odometry(truth, p, np.random.default_rng(0))
        travelled = o.poses[-1][0, 3]
        true = truth.x_m[-1] - truth.x_m[0]
        step = truth.x_m[1] - truth.x_m[0]
        assert share * true - 0.2 * step <= travelled <= share * true + 0.2 * step + (1 - share) * step


def test_a_gyro_bias_drifts_the_heading_with_time_not_distance():
    """The same seed and frame count at 5 and 20 m/s: a per-second drift gives the same final heading error;
    a per-metre drift four times as much at the higher speed."""
    for params, ratio in ((_quiet(yaw_bias_sigma_rad_per_s=1e-3), 1.0), (_quiet(yaw_bias_sigma_rad_per_m=1e-4), 4.0)):
        errs = [_final_errors(synthetic_truth("straight", n=201, speed_mps=v), params, range(5))[:, 2]
                for v in (5.0, 20.0)]
        assert np.allclose(errs[1], ratio * errs[0], rtol=1e-9, atol=1e-12)
    err = _final_errors(synthetic_truth("straight", n=201, speed_mps=10.0), _quiet(yaw_bias_sigma_rad_per_s=1e-3),
                        SEEDS)
    assert _sd_ok(err[:, 2], 1e-3 * 20.0)  # 20 s


def test_a_vio_creeps_while_standing():
    truth = synthetic_truth("straight", n=2, speed_mps=0.0)
    err = _final_errors(truth, _quiet(translation_noise_m=0.01, standstill_noise_factor=30.0), range(2000))
    assert _sd_ok(err[:, 0], 0.30)


@given(st.floats(0.5, 20.0))
@settings(max_examples=20, deadline=None)
def test_a_vio_creeps_only_for_the_first_seconds_of_a_stand(limit_s):
    """Standing 30 s: with standstill_noise_s the pose moves only over that many seconds of the stand, and
    the same seeds draw the same creep up to then (the later frames draw and discard theirs)."""
    truth = synthetic_truth("straight", n=301, speed_mps=0.0)
    p = _quiet(translation_noise_m=0.01, rotation_noise_rad=1e-3, standstill_noise_factor=30.0)
    capped = simulate_odometry(truth, dataclasses.replace(p, standstill_noise_s=limit_s), np.random.default_rng(3))
    full = simulate_odometry(truth, p, np.random.default_rng(3))
    moving = np.nonzero(np.any(np.diff(capped.poses, axis=0) != 0.0, axis=(1, 2)))[0]
    assert moving.size and truth.t_s[moving[-1] + 1] - truth.t_s[0] <= limit_s + 1e-9
    upto = moving[-1] + 2
    assert np.array_equal(capped.poses[:upto], full.poses[:upto])
    assert not np.array_equal(capped.poses[-1], full.poses[-1])


def test_orb_vio_resets_at_imu_gaps_and_droid_loses_scale_at_motorway_speed():
    truth = synthetic_truth("straight", n=600, speed_mps=25.0)
    miss = np.zeros(600, dtype=bool)
    for a in range(50, 550, 50):
        miss[a:a + 15] = True
    gappy = dataclasses.replace(truth, imu_missing=miss)
    resets = [sum(e == "map_reset" for _, e in simulate_odometry(gappy, odometry_preset("orb-vio", "clear"),
                                                                  np.random.default_rng(s)).events) for s in range(50)]
    p = odometry_preset("orb-vio", "clear").imu_gap_reset_prob
    assert abs(np.mean(resets) / 10 - p) < 4 * math.sqrt(p * (1 - p) / 500)  # 10 gaps × 50 runs
    d = simulate_odometry(truth, odometry_preset("droid", "clear"), np.random.default_rng(0))
    assert d.poses[-1][0, 3] < 0.95 * (truth.x_m[-1] - truth.x_m[0])
    assert not simulate_odometry(gappy, odometry_preset("droid", "clear"), np.random.default_rng(0)).events


@pytest.mark.parametrize("kind", ["vo", "vio", "mono"])
def test_the_other_presets_set_none_of_the_paper_presets_terms(kind):
    """Unset, the terms draw nothing: the other presets' noise streams and results stay as they were."""
    p = odometry_preset(kind, "heavy_rain")
    assert (p.fast_scale_loss, p.imu_gap_reset_prob, p.yaw_bias_sigma_rad_per_s) == (0.0, 0.0, 0.0)
    assert p.standstill_noise_s == 0.0
