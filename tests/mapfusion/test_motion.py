"""Wheel speed and gyro (issue 18): integration, calibration, the odometry cross-check, frames of their own."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapfusion import RoadMap
from mapfusion.config import FusionConfig
from mapfusion.engine import MapFusion
from mapfusion.errors import InputError
from mapfusion.formats import GpsFixes
from mapfusion.motion import MotionInputError, PlanarStep, WheelGyro, agrees, fuse_steps
from mapfusion.replay import MotionSamples, fuse
from tests.helpers import MAPS, synthetic_truth, wheel_gyro_samples


@pytest.fixture(scope="module")
def grid():
    return RoadMap.from_osm(MAPS / "synthetic" / "grid.osm")


def _path_m(truth, upto: int | None = None) -> float:
    x, y = truth.x_m[:upto], truth.y_m[:upto]
    return float(np.sum(np.hypot(np.diff(x), np.diff(y))))


def _fixes(road, truth, until_s: float, sigma: float = 2.0, seed: int = 0) -> GpsFixes:
    rng = np.random.default_rng(seed)
    idx = np.flatnonzero((np.round(truth.t_s, 6) % 1 == 0) & (truth.t_s <= until_s))
    x = truth.x_m[idx] + rng.normal(0, sigma, len(idx))
    y = truth.y_m[idx] + rng.normal(0, sigma, len(idx))
    lat, lon = road.projection.to_geo(x, y)
    n = len(idx)
    return GpsFixes(truth.t_s[idx], np.asarray(lat), np.asarray(lon), np.full(n, np.nan), np.full(n, sigma))


def _motion(samples) -> MotionSamples:
    (tw, v), (tg, w) = samples
    return MotionSamples(tw, v, tg, w)


def _errors(res, truth) -> np.ndarray:
    out = []
    for t, p in zip(res.t_s, res.online):
        if p is not None:
            k = int(round(t / 0.1))
            out.append(math.hypot(p.x() - truth.x_m[k], p.y() - truth.y_m[k]))
    return np.asarray(out)


# ----------------------------------------------------------------------------- integration
@given(seed=st.integers(0, 10_000), kind=st.sampled_from(["straight", "circle", "random"]),
       speed=st.floats(2.0, 30.0))
@settings(max_examples=25, deadline=None)
def test_noise_free_wheel_and_gyro_reproduce_the_path_length_within_0_1_percent(seed, kind, speed):
    """Issue 18's property: wheel + gyro alone on a noise-free drive reproduce the truth's path length
    within 0.1%, step by step as the engine asks for them."""
    truth = synthetic_truth(kind, n=600, speed_mps=speed, seed=seed)
    wg = WheelGyro(FusionConfig())
    (tw, v), (tg, w) = wheel_gyro_samples(truth)
    for a, b in zip(tw, v):
        wg.add_wheel(a, b)
    for a, b in zip(tg, w):
        wg.add_yaw_rate(a, b)
    t = truth.t_s[truth.t_s <= min(tw[-1], tg[-1])]
    length = sum(wg.step(t0, t1).length_m for t0, t1 in zip(t[:-1], t[1:]))
    assert length == pytest.approx(_path_m(truth, len(t)), rel=1e-3)


def test_the_engine_makes_its_own_frames_from_wheel_and_gyro_alone(grid):
    """With no odometry frame at all, wheel and gyro make the frames (one per nominal period), and
    their raw path is the truth's path."""
    truth = synthetic_truth("random", n=600, speed_mps=10.0, seed=2)
    eng = MapFusion(grid, FusionConfig())
    (tw, v), (tg, w) = wheel_gyro_samples(truth)
    events = sorted([(a, 0, b) for a, b in zip(tw, v)] + [(a, 1, b) for a, b in zip(tg, w)])
    for a, kind, b in events:
        (eng.add_wheel_speed if kind == 0 else eng.add_yaw_rate)(a, b)
    n = len(eng.track)
    assert eng.counters.wheel_frames == n - 1 and n >= 0.95 * len(truth)
    assert np.allclose(np.diff([eng.track.t[k] for k in range(n)]), 0.1, atol=1e-6)
    raw = np.array([eng.track.raw[k].translation() for k in range(n)])
    assert float(np.sum(np.linalg.norm(np.diff(raw, axis=0), axis=1))) == pytest.approx(
        _path_m(truth, int(round(eng.track.t[n - 1] / 0.1)) + 1) - _path_m(truth, int(round(eng.track.t[0] / 0.1)) + 1),
        rel=2e-3)


# ----------------------------------------------------------------------------- calibration
@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_a_2_percent_wheel_scale_error_is_known_to_0_3_percent_after_60_s_of_gps(grid, seed):
    """Issue 18's acceptance: 2% too fast a wheel, 60 s of 1 Hz GPS (σ 2 m), a noisy gyro with a
    bias: the engine's wheel scale is 1/1.02 within 0.3%."""
    truth = synthetic_truth("random", n=1200, speed_mps=10.0, seed=seed)
    samples = wheel_gyro_samples(truth, scale_error=0.02, bias_radps=0.004, speed_noise_mps=0.02,
                                 gyro_noise_radps=2e-3, seed=seed)
    keep = truth.t_s <= 60.0
    res = fuse(grid, truth.t_s[keep], truth.poses()[keep], _fixes(grid, truth, 60.0, seed=seed),
               FusionConfig(use_map=False), motion=_motion(samples))
    assert res.engine.wheel_scale == pytest.approx(1.0 / 1.02, rel=3e-3)


def test_the_gyro_bias_is_learnt_apart_from_the_odometrys_own_yaw_drift():
    """The gyro's excess over the odometry's yaw is b·dt + c·ds: with the speed varying, a bias of
    3e-3 rad/s is found beside an odometry drifting 2e-5 rad/m."""
    wg = WheelGyro(FusionConfig())
    rng = np.random.default_rng(0)
    t, b, c = 0.0, 3e-3, 2e-5
    for k in range(6000):  # 10 minutes of stop-and-go
        v = 15.0 * max(0.0, math.sin(k / 300.0))
        wg.add_wheel(t, v)
        wg.add_yaw_rate(t, b + rng.normal(0.0, 1e-3))
        if k:
            wg.observe_yaw(t - 0.1, t, -c * v * 0.1, v * 0.1)
        t += 0.1
    assert wg.bias_radps == pytest.approx(b, abs=2e-4)


# ----------------------------------------------------------------------------- the cross-check and the gaps
def _jumping_vo(truth, at: int, jump_m: float, axis: int = 1) -> np.ndarray:
    """The truth's poses as an odometry that jumps ``jump_m`` sideways (``axis`` 1; 0: forwards) at frame ``at``
    (and stays there)."""
    poses = truth.poses().copy()
    shift = np.eye(4)
    shift[axis, 3] = jump_m
    poses[at:] = np.einsum("ij,njk->nik", poses[at] @ shift @ np.linalg.inv(poses[at]), poses[at:])
    return poses


@pytest.mark.slow
def test_an_odometry_jump_the_speed_limit_misses_is_caught_by_wheel_and_gyro(grid):
    """A 4 m jump forwards in 0.1 s (50 m/s, under the jump guard's 70 m/s) is followed without wheel and gyro
    and replaced with them: the estimate ends where the same engine on the jump-free odometry ends. (Forwards: a
    jump sideways is turned along the heading by the steps along the heading, odometry_nonholonomic, and followed
    as a shorter jump ahead.)"""
    truth = synthetic_truth("random", n=2500, speed_mps=10.0, seed=5)
    gps = _fixes(grid, truth, 120.0)
    cfg = FusionConfig(use_map=False)
    motion = _motion(wheel_gyro_samples(truth, 0.01, 0.002, 0.02, 2e-3))
    end = {}
    for jump in (0.0, 4.0):
        vo = _jumping_vo(truth, 2000, jump, axis=0)
        alone, with_wheel = fuse(grid, truth.t_s, vo, gps, cfg), fuse(grid, truth.t_s, vo, gps, cfg, motion=motion)
        end[jump] = (alone.online[-1], with_wheel.online[-1])
        assert alone.engine.counters.odometry_jumps == 0
        assert with_wheel.engine.counters.odometry_vetoed == (1 if jump else 0)

    def apart(p, q) -> float:
        return math.hypot(p.x() - q.x(), p.y() - q.y())

    assert apart(end[4.0][0], end[0.0][0]) > 3.5
    assert apart(end[4.0][1], end[0.0][1]) < 0.5


@pytest.mark.slow
def test_a_30_s_camera_outage_is_bridged_frame_by_frame(grid):
    """No odometry for 30 s (300 m), then a re-initialised odometry 20 m off: wheel and gyro make a
    frame every 0.1 s through the gap, the jump is not followed, and the estimate stays within 1% of the
    gap's 300 m of where the same engine on the unbroken odometry is."""
    truth = synthetic_truth("random", n=4000, speed_mps=10.0, seed=3)
    keep = np.ones(len(truth), bool)
    keep[2500:2800] = False
    gps = _fixes(grid, truth, 150.0)
    cfg = FusionConfig(use_map=False)
    motion = _motion(wheel_gyro_samples(truth, 0.02, 0.003, 0.02, 2e-3, seed=3))
    vo = _jumping_vo(truth, 2800, 20.0)
    res = fuse(grid, truth.t_s[keep], vo[keep], gps, cfg, motion=motion)
    c = res.engine.counters
    assert 295 <= c.wheel_frames <= 301
    gap = (res.t_s > 250.0) & (res.t_s < 280.0)
    assert np.allclose(np.diff(res.t_s[gap]), 0.1, atol=1e-6)
    unbroken = fuse(grid, truth.t_s, truth.poses(), gps, cfg, motion=motion)
    ref = dict(zip(np.round(unbroken.t_s, 3), unbroken.online))
    apart = [math.hypot(p.x() - ref[round(t, 3)].x(), p.y() - ref[round(t, 3)].y())
             for t, p in zip(res.t_s, res.online) if p is not None and round(t, 3) in ref]
    assert max(apart) < 0.01 * 300.0
    without = fuse(grid, truth.t_s[keep], vo[keep], gps, cfg)
    assert math.hypot(without.online[-1].x() - ref[round(without.t_s[-1], 3)].x(),
                      without.online[-1].y() - ref[round(without.t_s[-1], 3)].y()) > 15.0


# ----------------------------------------------------------------------------- pieces
_steps = st.builds(PlanarStep, st.floats(-5, 5), st.floats(-5, 5), st.floats(-0.5, 0.5),
                   st.floats(1e-3, 1.0), st.floats(1e-3, 1.0), st.floats(1e-4, 0.1))


@given(a=_steps, b=_steps)
def test_a_fused_step_lies_between_its_inputs_and_is_more_certain(a, b):
    f = fuse_steps(a, b)
    for fa, fb, fv in ((a.dx_m, b.dx_m, f.dx_m), (a.dy_m, b.dy_m, f.dy_m), (a.dyaw_rad, b.dyaw_rad, f.dyaw_rad)):
        assert min(fa, fb) - 1e-9 <= fv <= max(fa, fb) + 1e-9
    assert f.sigma_along_m <= min(a.sigma_along_m, b.sigma_along_m) + 1e-12
    assert f.sigma_yaw_rad <= min(a.sigma_yaw_rad, b.sigma_yaw_rad) + 1e-12


@given(s=_steps, off=st.floats(0.0, 20.0), turn=st.floats(0.0, 0.3))
def test_the_gate_passes_a_step_near_the_wheels_and_refuses_one_far_off(s, off, turn):
    cfg = FusionConfig()
    moved = PlanarStep(s.dx_m, s.dy_m + off, s.dyaw_rad + turn, 0.1, 0.1, 0.01)
    near = off <= cfg.wheel_gate_m + cfg.wheel_gate_fraction * s.length_m and turn <= math.radians(cfg.wheel_gate_deg)
    assert agrees(cfg, moved, s) == near


def test_bad_wheel_and_gyro_samples_raise_a_specific_error(grid):
    eng = MapFusion(grid, FusionConfig())
    eng.add_wheel_speed(1.0, 3.0)
    with pytest.raises(MotionInputError, match="does not increase"):
        eng.add_wheel_speed(1.0, 3.0)
    with pytest.raises(MotionInputError, match="not finite"):
        eng.add_yaw_rate(2.0, math.nan)
    assert issubclass(MotionInputError, InputError)
    eng.add_imu(2.0, [0.0, 0.0, 0.1], [0.0, 0.0, 9.81])
    assert eng._motion.wg.gyro.v == [0.1]
