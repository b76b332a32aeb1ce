"""The odometry's σ learned from the GPS window (issue 17): the model's residual, the drift's bound, the engine's use."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapfusion import RoadMap
from mapfusion.config import FusionConfig
from mapfusion.engine import MapFusion
from mapfusion.errors import ConfigError
from mapfusion.metrics import umeyama
from mapfusion.odometry_trust import OdometryTrustError, drift_residual_m, learn_factor, model_residual_m
from tests.helpers import MAPS, drifting_odometry, odometry_step, synthetic_truth


def _path(seed: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step lengths, yaw changes and the positions of a smooth random path of n frames (1-2 m steps)."""
    rng = np.random.default_rng(seed)
    d = rng.uniform(1.0, 2.0, n)
    d[0] = 0.0
    dyaw = np.convolve(rng.normal(0.0, 0.05, n), np.ones(15) / 15, mode="same")
    return d, dyaw, _integrate(d, dyaw)


def _integrate(d: np.ndarray, dyaw: np.ndarray) -> np.ndarray:
    """Positions of steps d, each taken along the heading of the frame before it (the sum of the earlier dyaw)."""
    head = np.concatenate([[0.0], np.cumsum(dyaw)[:-1]])
    return np.cumsum(np.column_stack([d * np.cos(head), d * np.sin(head)]), axis=0)


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 10_000), sigma_t=st.floats(0.0, 0.1), sigma_r_deg=st.floats(0.005, 0.1),
       every=st.integers(3, 20))
def test_the_model_residual_is_what_its_noise_leaves_after_a_similarity_fit(seed, sigma_t, sigma_r_deg, every):
    """The closed form against a Monte Carlo of the same noise: each step's shift and the turn of the rest of the
    path by each step's yaw error, then the least-squares similarity fit to the noise-free positions."""
    n = 300
    d, dyaw, xy = _path(seed, n)
    st_m, sr = np.full(n, sigma_t), np.full(n, math.radians(sigma_r_deg))
    at = np.arange(2, n, every)
    model = model_residual_m(xy, st_m, sr, at)
    rng = np.random.default_rng(seed + 1)
    squares = []
    for _ in range(400):
        noisy = _integrate(d, dyaw + rng.normal(0.0, sr)) + np.cumsum(rng.normal(0.0, 1.0, (n, 2)) * st_m[:, None],
                                                                       axis=0)
        r, t, s = umeyama(noisy[at], xy[at], with_scale=True)
        e = xy[at] - (s * noisy[at] @ r.T + t)
        squares.append(np.mean(np.sum(e * e, axis=1)))
    assert model == pytest.approx(math.sqrt(np.mean(squares)), rel=0.12)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), shift=st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)),
       turn=st.floats(-math.pi, math.pi), k=st.floats(0.1, 10.0))
def test_the_model_residual_ignores_where_the_path_lies_and_grows_with_its_sigma(seed, shift, turn, k):
    n = 120
    _, _, xy = _path(seed, n)
    st_m, sr = np.full(n, 0.02), np.full(n, math.radians(0.05))
    at = np.arange(1, n, 4)
    base = model_residual_m(xy, st_m, sr, at)
    c, s = math.cos(turn), math.sin(turn)
    moved = xy @ np.array([[c, s], [-s, c]]) + np.array(shift)
    assert model_residual_m(moved, st_m, sr, at) == pytest.approx(base, rel=1e-6)
    assert model_residual_m(xy, k * st_m, k * sr, at) == pytest.approx(k * base, rel=1e-6)


def test_a_straight_path_with_shift_noise_only_leaves_its_residual_in_closed_form():
    """Straight, evenly spaced, translation noise only, fixes at every frame: the residual of a random walk after the
    similarity removes its mean and its linear trend along (scale) and across (rotation) the path."""
    n = 200
    xy = np.column_stack([np.arange(n, dtype=float), np.zeros(n)])
    s = 0.1
    model = model_residual_m(xy, np.full(n, s), np.zeros(n), np.arange(n))
    # per axis: a random walk of n-1 steps, less its best line fit: E = s² (n² − 4) / (15 n) ... (Brownian bridge-like)
    i = np.arange(n, dtype=float)
    cov = s * s * np.minimum.outer(i, i)
    a = np.column_stack([np.ones(n), i - i.mean()])
    p = np.eye(n) - a @ np.linalg.pinv(a)
    per_axis = np.trace(p @ cov @ p) / n
    assert model == pytest.approx(math.sqrt(2 * per_axis), rel=1e-9)


@pytest.mark.parametrize("sigma,drift", [(0.05, 0.0), (0.05, 0.3), (2.0, 0.0), (2.0, 5.0)])
@pytest.mark.parametrize("m", [20, 300])
def test_the_drift_is_bounded_above_its_true_value_and_not_far_above(sigma, drift, m):
    """Residuals whose mean square is exactly the fixes' 2σ² (less the fit's 4 dof) plus the drift's square: the
    bound is at least the drift and at most the drift plus two standard errors of the noise's χ² mean."""
    r2 = 2 * sigma * sigma * (1 - 2 / m) + drift * drift
    got = drift_residual_m(np.full(m, math.sqrt(r2)), np.full(m, sigma))
    assert drift <= got <= math.sqrt(drift * drift + 4 * sigma * sigma / math.sqrt(m)) + 1e-12
    low = drift_residual_m(np.full(m, math.sqrt(r2)), np.full(m, sigma), confidence=-2.0)
    assert math.sqrt(max(drift * drift - 4 * sigma * sigma / math.sqrt(m), 0.0)) - 1e-12 <= low <= drift + 1e-12


def test_residuals_below_the_fixes_noise_do_not_make_the_odometry_better_than_the_fixes_can_tell():
    got = drift_residual_m(np.full(50, 0.01), np.full(50, 2.0))
    assert got == pytest.approx(math.sqrt(2 * 2 * 4.0 / math.sqrt(50)))


def test_bad_inputs_raise_a_specific_error():
    xy = np.zeros((10, 2))
    with pytest.raises(OdometryTrustError):
        model_residual_m(xy, np.zeros(10), np.zeros(10), np.array([1, 2]))
    with pytest.raises(OdometryTrustError):
        model_residual_m(xy, np.full(10, np.nan), np.zeros(10), np.array([1, 2, 3]))
    with pytest.raises(OdometryTrustError):
        drift_residual_m(np.ones(3), np.ones(3))
    with pytest.raises(ConfigError):
        FusionConfig(odometry_sigma_factor_min=2.0, odometry_sigma_factor_max=1.0)


def test_the_factor_moves_only_as_far_as_the_window_shows():
    """Loosened by the drift's lower bound, tightened by its upper bound, within the limits; 1 where the bounds
    straddle the model's residual (metre-level fixes over a short window: they cannot tell)."""
    assert learn_factor(2.0, 3.0, 1.0, 0.05, 10.0) == 2.0
    assert learn_factor(0.001, 0.002, 1.0, 0.05, 10.0) == 0.05
    assert learn_factor(50.0, 60.0, 1.0, 0.05, 10.0) == 10.0
    assert learn_factor(0.5, 2.0, 1.0, 0.05, 10.0) == 1.0
    assert learn_factor(0.0, 0.3, 1.0, 1.0, 3.0) == 1.0  # a floor of 1: never tightened
    assert learn_factor(1.0, 2.0, 0.0, 0.05, 10.0) == 1.0


def test_noise_only_residuals_under_metre_fixes_leave_the_sigma_alone():
    """The residuals a perfect odometry leaves under 2 m fixes (exactly their noise): the bounds straddle any model
    residual between them, and the lower one is 0."""
    m, sigma = 40, 2.0
    r = np.full(m, math.sqrt(2 * sigma * sigma * (1 - 2 / m)))
    low = drift_residual_m(r, np.full(m, sigma), confidence=-2.0)
    high = drift_residual_m(r, np.full(m, sigma))
    assert low == 0.0 and high > 1.0
    assert learn_factor(low, high, 0.2, 1.0, 3.0) == 1.0


@pytest.fixture(scope="module")
def grid():
    return RoadMap.from_osm(MAPS / "synthetic" / "grid.osm")


def _fused_factor(road: RoadMap, cfg: FusionConfig, ox, oy, oyaw, truth, gps_sigma: float, seed: int = 0) -> float:
    rng = np.random.default_rng(seed)
    lat, lon = road.projection.to_geo(truth.x_m + rng.normal(0, gps_sigma, len(truth.x_m)),
                                      truth.y_m + rng.normal(0, gps_sigma, len(truth.y_m)))
    eng = MapFusion(road, cfg, gps_rate_hz=1.0, odometry_rate_hz=10.0)
    for k in range(len(truth.t_s)):
        t = float(truth.t_s[k])
        if k % 10 == 0 and t <= 150.0:
            eng.add_gps(t, float(lat[k]), float(lon[k]), None, gps_sigma)
        eng.add_odometry(t, odometry_step(ox, oy, oyaw, k))
    eng.finish()
    assert eng.initialised
    return eng.odometry_sigma_factor


@pytest.mark.parametrize("case", ["both ways", "defaults", "off"])
def test_the_engine_trusts_a_perfect_odometry_more_and_a_drifting_one_less(grid, case):
    """A perfect odometry under centimetre fixes is learned better than the configured σ say; one whose heading
    drifts 0.5°/100 m and whose steps carry 5 cm of noise, under 1 m fixes, worse. With the default limits it only
    loosens (at most 3×), and it is on by default; not learned: 1 either way."""
    truth = synthetic_truth("random", n=2000, speed_mps=10.0, seed=4)
    truth.x_m += 100.0
    truth.y_m += 100.0
    cfg = {"both ways": FusionConfig(use_map=False, odometry_sigma_learned=True, odometry_sigma_factor_min=0.05,
                                     odometry_sigma_factor_max=10.0),
           "defaults": FusionConfig(use_map=False),
           "off": FusionConfig(use_map=False, odometry_sigma_learned=False)}[case]
    perfect = _fused_factor(grid, cfg, truth.x_m, truth.y_m, truth.yaw_rad, truth, 0.01)
    ox, oy, oyaw = drifting_odometry(truth.x_m, truth.y_m, truth.yaw_rad, seed=1,
                                     yaw_drift_rad_per_m=math.radians(0.005), noise_m=0.05)
    drifting = _fused_factor(grid, cfg, ox, oy, oyaw, truth, 1.0)
    if case == "both ways":
        assert perfect < 0.5 and drifting > 1.5, (perfect, drifting)
    elif case == "defaults":
        assert perfect == 1.0 and 1.5 < drifting <= 3.0, (perfect, drifting)
    else:
        assert perfect == drifting == 1.0


def test_a_cold_start_has_no_window_to_learn_from(grid):
    """No GPS: the configured σ stay (the factor is 1) whatever the limits allow."""
    eng = MapFusion(grid, FusionConfig(odometry_sigma_learned=True, odometry_sigma_factor_min=0.05,
                                       odometry_sigma_factor_max=10.0))
    truth = synthetic_truth("random", n=300, speed_mps=10.0, seed=4)
    for k in range(len(truth.t_s)):
        eng.add_odometry(float(truth.t_s[k]), odometry_step(truth.x_m, truth.y_m, truth.yaw_rad, k))
    eng.finish()
    assert eng.odometry_sigma_factor == 1.0
