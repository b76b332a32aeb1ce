"""Sensor models: drifting visual / visual-inertial odometry, IMU and GPS, from a ground truth.

Every preset parameter is documented with its unit; a scenario's ``[odometry]`` table may
override any :class:`OdometryParams` field. Rates are per kilometre driven, random walks per
square root of metres driven. Each sensor draws from its own seeded stream, so changing one
sensor's settings never changes another's noise.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

from mapfusion.config import param
from mapfusion.geometry import cumulative_length

from .scenario import GpsConfig, GpsMode, ImuParams, OdometryKind, Scenario, Vehicle, WeatherKind


@dataclass(frozen=True)
class OdometryParams:
    """Error model of a visual (or visual-inertial) odometry, per run."""

    scale_error_sigma: float = param(0.002, "σ of the run's constant relative scale error.", unit="1", min=0.0, max=0.5)
    scale_rw_per_sqrt_m: float = param(1e-4, "Random walk of the relative scale error.", unit="1/√m", min=0.0, max=0.1)
    yaw_bias_sigma_rad_per_m: float = param(8e-6, "σ of the run's constant yaw drift per metre driven.", unit="rad/m", min=0.0, max=0.01)
    yaw_bias_rw_rad_per_m_sqrt_m: float = param(2e-7, "Random walk of the yaw drift rate.", unit="rad/m/√m", min=0.0, max=0.001)
    translation_noise_m: float = param(0.01, "White noise on each translation axis of each step.", unit="m", min=0.0, max=10.0)
    rotation_noise_rad: float = param(1e-4, "White noise on roll, pitch and yaw of each step.", unit="rad", min=0.0, max=1.0)
    lateral_bias_sigma_m_per_m: float = param(5e-4, "σ of the run's constant lateral drift per metre driven.", unit="m/m", min=0.0, max=0.5)
    dropout_rate_per_km: float = param(0.0, "Outages (dropped frames) per km outside tunnels.", unit="1/km", min=0.0, max=1000.0)
    dropout_duration_s: float = param(0.5, "Mean outage duration (exponential).", unit="s", min=0.0, max=600.0)
    reinit_jump_sigma_m: float = param(2.0, "σ of the position jump when tracking re-initialises after an outage "
                                       "(full for a gap of 10 s or more, proportionally less for shorter).", unit="m", min=0.0, max=1000.0)
    relocalise_max_gap_s: float = param(2.0, "Outages up to this long are bridged by re-matching to the map: the motion "
                                        "over the gap is recovered (with noise growing with the gap); longer ones "
                                        "re-initialise with a constant-velocity guess and a jump.", unit="s", min=0.0, max=600.0)
    relocalise_noise_m_per_s: float = param(0.05, "σ of the bridged motion per second of gap, per axis.", unit="m/s", min=0.0, max=100.0)
    tunnel_lose_track: float = param(1.0, "1: tracking is lost inside GPS-denied zones (vo); 0: it continues (vio).", min=0.0, max=1.0)
    tunnel_drift_factor: float = param(1.0, "Multiplier of yaw and lateral drift inside GPS-denied zones.", unit="1", min=0.0, max=100.0)
    rain_episode_rate_per_km: float = param(0.0, "Drops on the lens: episodes of strong lateral drift per km.", unit="1/km", min=0.0, max=1000.0)
    rain_episode_duration_s: float = param(8.0, "Mean duration of a rain episode.", unit="s", min=0.0, max=600.0)
    rain_lateral_drift_m_per_m: float = param(0.0, "Lateral drift per metre during a rain episode.", unit="m/m", min=0.0, max=1.0)
    rain_noise_factor: float = param(1.0, "Multiplier of the white noise in rain.", unit="1", min=0.0, max=100.0)
    map_reset_rate_per_km: float = param(0.0, "Map resets (pose discontinuities) per km.", unit="1/km", min=0.0, max=1000.0)
    map_reset_jump_sigma_m: float = param(5.0, "σ of the position jump at a map reset.", unit="m", min=0.0, max=1000.0)
    scale_reversion_m: float = param(0.0, "Correlation length of the scale error's wander: it reverts to the run's "
                                     "constant error over this distance (an Ornstein-Uhlenbeck process whose stationary "
                                     "σ is scale_rw_per_sqrt_m · √(length / 2)); 0: a pure random walk.", unit="m",
                                     min=0.0, max=1e6)
    start_scale_bias_sigma: float = param(0.0, "σ of the run's extra scale error at the start (a monocular VO's "
                                          "depth at start-up), decaying exponentially over start_scale_bias_m.",
                                          unit="1", min=0.0, max=0.9)
    start_scale_bias_m: float = param(200.0, "Decay length of the start-up scale error.", unit="m", min=1.0, max=1e5)
    turn_scale_sigma: float = param(0.0, "σ of the run's relative error of every measured yaw change (a turn of "
                                    "90° reads (1 + error) · 90°).", unit="1", min=0.0, max=0.5)
    standstill_noise_factor: float = param(1.0, "Multiplier of the white noise while the vehicle stands (moves under "
                                           "STANDSTILL_STEP_M in a step): below 1, a VO that sees a static scene; "
                                           "above 1, a VIO whose IMU bias makes it creep while the car stands.",
                                           unit="1",
                                           min=0.0, max=100.0)
    standstill_noise_s: float = param(0.0, "standstill_noise_factor applies over the first this many seconds of a "
                                      "stand; the stand's later frames are still (no noise). 0: the whole stand.",
                                      unit="s", min=0.0, max=3600.0)
    unit_m_min: float = param(1.0, "Smallest length (m) of the odometry's unit: a monocular VO writes positions in an "
                              "arbitrary unit, drawn log-uniformly per run in [unit_m_min, unit_m_max]; 1 = metres.",
                              unit="m", min=1e-3, max=1e3)
    unit_m_max: float = param(1.0, "Largest length of the odometry's unit.", unit="m", min=1e-3, max=1e3)
    fast_speed_mps: float = param(22.0, "Speed (mean over the last FAST_WINDOW_S) above which fast_scale_loss acts: "
                                  "motorway speeds.", unit="m/s", min=0.0, max=100.0)
    fast_scale_loss: float = param(0.0, "Share of each step's motion a VO misses above fast_speed_mps: at motorway "
                                   "speed the open, feature-poor scene leaves the forward motion unobserved.",
                                   unit="1", min=0.0, max=0.9)
    yaw_bias_sigma_rad_per_s: float = param(0.0, "σ of the run's constant yaw drift per second (a VIO's residual "
                                            "gyro bias: its heading drifts with time, not with distance).",
                                            unit="rad/s", min=0.0, max=0.1)
    imu_gap_reset_prob: float = param(0.0, "Probability that a VIO resets its map when its IMU resumes after a gap "
                                      "(Truth.imu_missing: the stretches a recorded drive's GPS/INS filled).",
                                      unit="1", min=0.0, max=1.0)

    def with_overrides(self, overrides: tuple[tuple[str, float], ...]) -> OdometryParams:
        return dataclasses.replace(self, **dict(overrides))


#: A step shorter than this is the vehicle standing (below 0.5 m/s at 10 Hz).
STANDSTILL_STEP_M = 0.05

#: Preset changes from the base, by odometry kind and by weather. The base was calibrated on the paper's
#: odometry-only ATE ranges (scenarios/test_calibration.py); vio keeps it with the IMU's smaller rotation
#: drift. vo and mono are fitted (issue 22) to the real VO outputs in $MAPFUSION_DATA/vo/ on the five
#: KITTI drives, statistic by statistic (`mapfusion odometry-stats`, means over the drives, simulated on
#: the same drives' truth; docs/method.md "Sensors fitted to real odometry" has the table):
#:   vo ← cvo_stereo_{00,01,02,05,07}.txt (frame-to-frame stereo, no loop closure):
#:     rotation_noise_rad 2.2e-3 ← KITTI r_err 1.19–1.76 deg/100 m (mean 1.46) and the per-step yaw error
#:       σ 0.7–2.4e-3 rad; yaw_bias_sigma 1e-4 rad/m ← |yaw drift| 0.24–1.07 deg/100 m (mean 0.62);
#:     scale_error_sigma 0.025 ← the global scales 0.91–1.00; scale_rw 8e-4/√m reverting over 400 m ←
#:       σ of the scale per 100 m window 0.35–1.7 % (mean 0.89 %) and the start bias (first 30 s) |·| mean 1.9 %;
#:     translation_noise_m 0.01 (kept) ← KITTI t_err 2.33–4.69 % (mean 3.46 %) once the above are set.
#:   mono ← trianflow_{00,01,02,05,07}.txt (monocular, learned depth), after one fitted scale:
#:     rotation_noise_rad 7e-3 ← r_err 2.75–6.89 deg/100 m, per-step yaw error σ 6.5–8.4e-3 rad;
#:     yaw_bias_sigma 1.5e-4 rad/m ← |yaw drift| 0.02–1.62 deg/100 m; turn_scale_sigma 0.07 ← the fitted
#:       share of each turn's angle in the heading error, −0.07…+0.11; scale wander 6e-3/√m reverting over
#:       200 m ← window σ 4.2–11 % (01: 108 %); start_scale_bias 0.15 over 300 m ← start bias −24…+145 %
#:       (median |·| 17 %); translation_noise_m 0.06 ← t_err 10.8–59.3 % and the step errors' lag-1
#:       autocorrelation 0.19–0.32 (01: 0.94); map resets 0.5/km with 2 m jumps ← jumps 0–2.9/km;
#:     unit_m 0.01–0.05 ← the scale that maps each file onto metres, ×20.7…×113.5.
#:   standstill_noise_factor 0.1 (vo, mono) is not fitted (the KITTI drives barely stand): a VO's
#:   estimate of a standing car's motion sees a static scene.
#: droid and orb-vio are the paper's odometries (DROID-SLAM stereo, ORB-SLAM3 stereo VIO), fitted to its Table I
#: without the map on the same five drives (00, 01, 02, 05, 07), GPS for the first 30 s only: the median over
#: seeds 1–50 of each drive's no-map ATE within ±35% of the paper's, de-localised where the paper's is
#: (`python -m mapfusion.harness.paper --seeds 1-50`; docs/method.md has the table, held-out seeds beside it):
#:   droid ← DROID-SLAM 2.98 / x / 5.77 / 2.29 / 1.01 m: a windowed bundle adjustment's small rotation drift
#:     (rotation_noise 4e-4 rad, yaw_bias 1e-5 rad/m), scale wander 3e-4/√m, translation noise 0.03 m; it loses
#:     the forward motion at motorway speed (fast_scale_loss 0.1 above 22 m/s: 01, the paper's "lack of temporal
#:     visual features to determine longitudinal motion", is the only drive above 15 m/s).
#:   orb-vio ← ORB-SLAM3 VIO (with loop closure) x / 3.93 / 13.43 / 2.60 / 2.32 m: the IMU's scale (σ 0.1%), a
#:     residual gyro bias (yaw_bias_sigma_rad_per_s 1.6e-4 rad/s, 33 deg/h) beside a small per-metre yaw drift
#:     (3e-5 rad/m), a creep while the car stands (standstill_noise_factor 30: 0.3 m a frame; 05 and 07 stand
#:     7–8 s) over the first 8 s of a stand only (standstill_noise_s: KITTI's longest stand is 7.6 s, so the fit
#:     saw no longer one; the paper's ORB-SLAM3 stays within 0.5–0.6 m of 4Seasons' city drives, traffic lights
#:     and all, with GPS every 5 s, where an unbounded creep puts a 60-s stop 7 m off), and a map reset with
#:     probability 0.12 when the IMU resumes after a gap (imu_gap_reset_prob: the
#:     GPS/INS gaps a KITTI drive's track was filled over, 8 on 00, 3 on 02, 1 on 05; the paper names missing
#:     IMU data as the cause of its de-localisations). A reset de-localises the run, as the paper counts it.
#:   Their KITTI relative errors (mean of seeds 1–4, `mapfusion.harness.realism.simulated_stats`): droid t_err
#:   0.86–0.94% (01: 7.5%), r_err 0.17–0.33 deg/100 m; orb-vio 0.45–1.21%, 0.16–0.43 deg/100 m — the order of
#:   ORB-SLAM2 stereo's published KITTI figures (t_rel 0.5–1.4%, r_rel 0.2–0.3 deg/100 m, Mur-Artal and Tardós
#:   2017); DROID-SLAM's authors publish none on KITTI.
KIND_PRESETS: dict[OdometryKind, dict[str, float]] = {
    OdometryKind.vo: {"rotation_noise_rad": 2.2e-3, "yaw_bias_sigma_rad_per_m": 1e-4, "scale_error_sigma": 0.025,
                      "scale_rw_per_sqrt_m": 8e-4, "scale_reversion_m": 400.0, "standstill_noise_factor": 0.1},
    OdometryKind.mono: {"rotation_noise_rad": 7e-3, "yaw_bias_sigma_rad_per_m": 1.5e-4, "turn_scale_sigma": 0.07,
                        "scale_error_sigma": 0.0, "scale_rw_per_sqrt_m": 6e-3, "scale_reversion_m": 200.0,
                        "start_scale_bias_sigma": 0.15, "start_scale_bias_m": 300.0, "translation_noise_m": 0.06,
                        "map_reset_rate_per_km": 0.5, "map_reset_jump_sigma_m": 2.0, "unit_m_min": 0.01,
                        "unit_m_max": 0.05, "standstill_noise_factor": 0.1},
    OdometryKind.droid: {"rotation_noise_rad": 4e-4, "yaw_bias_sigma_rad_per_m": 1e-5, "scale_error_sigma": 0.01,
                         "scale_rw_per_sqrt_m": 3e-4, "scale_reversion_m": 400.0, "translation_noise_m": 0.03,
                         "standstill_noise_factor": 0.1, "fast_scale_loss": 0.1},
    OdometryKind.orb_vio: {"scale_error_sigma": 0.001, "scale_rw_per_sqrt_m": 1e-5, "tunnel_lose_track": 0.0,
                           "tunnel_drift_factor": 3.0, "yaw_bias_sigma_rad_per_m": 3e-5,
                           "yaw_bias_sigma_rad_per_s": 1.6e-4, "lateral_bias_sigma_m_per_m": 1e-3,
                           "standstill_noise_factor": 30.0, "standstill_noise_s": 8.0,
                           "imu_gap_reset_prob": 0.12},
    OdometryKind.vio: {"scale_error_sigma": 0.001, "scale_rw_per_sqrt_m": 1e-5, "tunnel_lose_track": 0.0,
                       "tunnel_drift_factor": 3.0, "yaw_bias_sigma_rad_per_m": 1.5e-5, "lateral_bias_sigma_m_per_m": 1e-3},
}
WEATHER_PRESETS: dict[WeatherKind, dict[str, float]] = {
    WeatherKind.clear: {},
    WeatherKind.rain: {"rain_episode_rate_per_km": 4.0, "rain_episode_duration_s": 6.0,
                       "rain_lateral_drift_m_per_m": 0.1, "rain_noise_factor": 2.0, "dropout_rate_per_km": 1.0},
    WeatherKind.heavy_rain: {"rain_episode_rate_per_km": 5.0, "rain_episode_duration_s": 8.0,
                             "rain_lateral_drift_m_per_m": 0.1, "rain_noise_factor": 3.0, "dropout_rate_per_km": 2.0},
}
#: In heavy rain the VIO's map resets (ORB-SLAM3 resetting its local map, paper IV.B).
VIO_HEAVY_RAIN = {"map_reset_rate_per_km": 0.5}


def odometry_preset(kind: OdometryKind | str, weather: WeatherKind | str) -> OdometryParams:
    """The preset parameters of an odometry kind in a weather."""
    kind, weather = OdometryKind(kind).visual, WeatherKind(weather)
    changes = {**KIND_PRESETS[kind], **WEATHER_PRESETS[weather]}
    if kind is OdometryKind.vio and weather is WeatherKind.heavy_rain:
        changes.update(VIO_HEAVY_RAIN)
    return dataclasses.replace(OdometryParams(), **changes)


# ----------------------------------------------------------------------------- wheel speed
@dataclass(frozen=True)
class WheelParams:
    """Error model of a wheel-speed sensor (the ABS/ESC wheel speeds as the car's bus reports them)."""

    rate_hz: float = param(50.0, "Sample rate.", unit="Hz", min=1.0, max=1000.0)
    scale_error_min: float = param(0.005, "Smallest |scale error| of a run (tyre radius: wear, pressure, load); "
                                   "each run draws |error| uniformly in [min, max] with a random sign.", unit="1",
                                   min=0.0, max=0.2)
    scale_error_max: float = param(0.02, "Largest |scale error| of a run.", unit="1", min=0.0, max=0.2)
    speed_noise_mps: float = param(0.02, "White noise on each sample.", unit="m/s", min=0.0, max=10.0)
    quantum_mps: float = param(0.02, "Resolution of the reported speed (samples are rounded to it).", unit="m/s",
                               min=0.0, max=10.0)
    slip_per_mps2: float = param(0.02, "In rain: over-read of the speed per m/s² of acceleration or braking beyond "
                                 "slip_min_accel_mps2 (wheels spin up or lock briefly); doubled in heavy rain.",
                                 unit="1/(m/s²)", min=0.0, max=1.0)
    slip_min_accel_mps2: float = param(1.0, "Acceleration or braking below this slips no wheel.", unit="m/s²", min=0.0,
                                       max=20.0)

    def with_overrides(self, overrides: tuple[tuple[str, float], ...]) -> WheelParams:
        return dataclasses.replace(self, **dict(overrides))


#: Preset changes from the base (a passenger car), by vehicle.
VEHICLE_PRESETS: dict[Vehicle, dict[str, float]] = {
    Vehicle.car: {},
    Vehicle.truck: {"rate_hz": 20.0, "scale_error_min": 0.01, "scale_error_max": 0.03, "quantum_mps": 0.05,
                    "slip_per_mps2": 0.04, "slip_min_accel_mps2": 0.7},
}


def wheel_preset(vehicle: Vehicle | str) -> WheelParams:
    """The preset parameters of a vehicle's wheel-speed sensor."""
    return dataclasses.replace(WheelParams(), **VEHICLE_PRESETS[Vehicle(vehicle)])


@dataclass
class WheelOutput:
    t_s: np.ndarray
    speed_mps: np.ndarray
    scale_error: float  # the run's drawn error (reported = (1 + error) × true)


def simulate_wheel(truth: Truth, p: WheelParams, rng: np.random.Generator,
                   weather: WeatherKind = WeatherKind.clear) -> WheelOutput:
    """Wheel speed at ``rate_hz`` from the truth: the distance it drives each step over the step's
    duration (so the samples integrate to the truth's path length), times (1 + the run's scale
    error), over-read under hard acceleration or braking in rain, plus white noise, rounded to
    ``quantum_mps``, never negative, and zero while the vehicle stands."""
    if p.scale_error_max < p.scale_error_min:
        raise ValueError(f"wheel: scale_error_max ({p.scale_error_max}) is below scale_error_min ({p.scale_error_min})")
    t_truth = np.asarray(truth.t_s, float)
    t = np.arange(t_truth[0], t_truth[-1] + 1e-9, 1.0 / p.rate_hz)
    step_v = np.hypot(np.diff(truth.x_m), np.diff(truth.y_m)) / np.maximum(np.diff(t_truth), 1e-9)
    k = np.clip(np.searchsorted(t_truth, t, side="right") - 1, 0, max(len(step_v) - 1, 0))
    true_v = step_v[k] if len(step_v) else np.zeros_like(t)
    # the acceleration that slips a wheel: of the speed smoothed over a second (SUMO steps its speed)
    w = max(1, int(round(1.0 / float(np.median(np.diff(t_truth)))))) if len(t_truth) > 1 else 1
    # (edges held, not zero-padded: a drive's ends are no hard braking)
    smooth = np.convolve(np.pad(step_v, (w // 2, w - 1 - w // 2), mode="edge"), np.ones(w) / w, mode="valid") \
        if len(step_v) else step_v
    step_a = np.gradient(smooth, t_truth[:-1]) if len(step_v) > 1 else np.zeros_like(step_v)
    accel = np.abs(step_a[k]) if len(step_v) else np.zeros_like(t)
    error = rng.uniform(p.scale_error_min, p.scale_error_max) * (1.0 if rng.random() < 0.5 else -1.0)
    slip = {WeatherKind.clear: 0.0, WeatherKind.rain: 1.0, WeatherKind.heavy_rain: 2.0}[WeatherKind(weather)]
    over = slip * p.slip_per_mps2 * np.maximum(accel - p.slip_min_accel_mps2, 0.0)
    v = true_v * (1.0 + error) * (1.0 + over) + rng.normal(0.0, p.speed_noise_mps, len(t))
    if p.quantum_mps > 0:
        v = np.round(v / p.quantum_mps) * p.quantum_mps
    # a standing wheel gives no pulses: exactly zero, never noise clipped to a creeping positive speed
    return WheelOutput(t, np.where(true_v > 0.0, np.maximum(v, 0.0), 0.0), float(error))


# ----------------------------------------------------------------------------- IMU
GRAVITY_MPS2 = 9.80665


# ----------------------------------------------------------------------------- the truth the models read
@dataclass
class Truth:
    """A ground-truth trajectory the sensor models read: level poses in the map's ENU frame."""

    t_s: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    z_m: np.ndarray
    yaw_rad: np.ndarray
    gps_denied: np.ndarray  # no GPS fix here (tunnel, covered road, [[tunnels]] zone, under a bridge)
    visually_degraded: np.ndarray  # tunnels and [[tunnels]] zones: VO loses track, VIO drifts
    imu_missing: np.ndarray | None = None  # no inertial measurement (a recorded drive's filled GPS/INS); None: none

    def __post_init__(self) -> None:
        if self.imu_missing is None:
            self.imu_missing = np.zeros(len(self.t_s), dtype=bool)

    def __len__(self) -> int:
        return len(self.t_s)

    @classmethod
    def from_track(cls, track, under_bridge: np.ndarray | None = None, gps: GpsConfig | None = None) -> Truth:
        """From a recorded :class:`sim.drive.Track` (or anything with the same arrays)."""
        gps = gps or GpsConfig()
        tunnel = np.asarray(track.in_tunnel, dtype=bool)
        bridge = np.zeros(len(tunnel), dtype=bool) if under_bridge is None else np.asarray(under_bridge, dtype=bool)
        denied = (tunnel if gps.deny_in_tunnels else np.zeros_like(tunnel)) | (bridge if gps.deny_under_bridges else False)
        return cls(np.asarray(track.t_s, float), np.asarray(track.x_m, float), np.asarray(track.y_m, float),
                   np.asarray(track.z_m, float), np.asarray(track.yaw_rad, float), denied, tunnel)


def under_bridges(road, x_m: np.ndarray, y_m: np.ndarray, osm_way: np.ndarray, lane_width_m: float = 3.0) -> np.ndarray:
    """Frames under a bridge: a bridge way of a higher layer passes within half its width
    (lanes × ``lane_width_m``, the scenario's ``[gps] bridge_lane_width_m``) + 1 m.

    A frame's own way (and a bridge the vehicle is itself on) never counts.
    """
    bridge_rows = np.array([w.bridge for w in road.ways], dtype=bool)
    if not bridge_rows.any():
        return np.zeros(len(x_m), dtype=bool)
    layers = np.array([w.layer for w in road.ways])
    out = np.zeros(len(x_m), dtype=bool)
    for i, (x, y) in enumerate(zip(x_m, y_m)):
        near = road.query_radius(float(x), float(y), 15.0)
        if near.size == 0:
            continue
        rows = road.way_index[near]
        cand = near[bridge_rows[rows]]
        if cand.size == 0:
            continue
        own = int(osm_way[i]) if osm_way is not None else -1
        own_layer = road.way(own).layer if own >= 0 and road.has_way(own) else 0
        crow = road.way_index[cand]
        d = np.hypot(road.xy_m[cand, 0] - x, road.xy_m[cand, 1] - y)
        ok = (layers[crow] > own_layer) & (road.way_ids[crow] != own) & (d <= 0.5 * road.lanes[cand] * lane_width_m + 1.0)
        out[i] = bool(ok.any())
    return out


# ----------------------------------------------------------------------------- helpers
def truth_poses(truth: Truth) -> np.ndarray:
    """(N, 4, 4) level truth poses."""
    n = len(truth)
    m = np.tile(np.eye(4), (n, 1, 1))
    m[:, :3, :3] = Rotation.from_euler("z", np.asarray(truth.yaw_rad)[:, None]).as_matrix()
    m[:, 0, 3], m[:, 1, 3], m[:, 2, 3] = truth.x_m, truth.y_m, truth.z_m
    return m


def _rotvec_matrix(rx: float, ry: float, rz: float) -> list[list[float]]:
    """The rotation matrix of a rotation vector, in closed form: the unit quaternion (Taylor series of
    sin(θ/2)/θ below 1 mrad) and its matrix, with the very arithmetic of scipy's
    ``Rotation.from_rotvec(v).as_matrix()`` (the same to the bit, tested) at a sixth of its cost."""
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle <= 1e-3:
        a2 = angle * angle
        scale = 0.5 - a2 / 48 + a2 * a2 / 3840
    else:
        scale = math.sin(angle / 2) / angle
    x, y, z, w = rx * scale, ry * scale, rz * scale, math.cos(angle / 2)
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return [[x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)],
            [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)],
            [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2]]


def _exp_se3(xi: np.ndarray) -> np.ndarray:
    """A small relative motion (tx, ty, tz, roll, pitch, yaw) as a 4×4 matrix (rotation by rotvec)."""
    tx, ty, tz, rx, ry, rz = (float(v) for v in xi)
    r = _rotvec_matrix(rx, ry, rz)
    return np.array([[*r[0], tx], [*r[1], ty], [*r[2], tz], [0.0, 0.0, 0.0, 1.0]])


def _poisson_intervals(rng: np.random.Generator, dist_m: np.ndarray, t_s: np.ndarray, rate_per_km: float,
                       mean_duration_s: float) -> np.ndarray:
    """Frames inside episodes that start at a Poisson rate per km and last Exp(mean) seconds."""
    out = np.zeros(len(t_s), dtype=bool)
    if rate_per_km <= 0 or len(t_s) < 2:
        return out
    total_km = dist_m[-1] / 1000.0
    n = rng.poisson(rate_per_km * total_km)
    starts = np.sort(rng.uniform(0.0, dist_m[-1], n))
    for s0 in starts:
        i0 = int(np.searchsorted(dist_m, s0))
        if i0 >= len(t_s):
            continue
        dur = rng.exponential(mean_duration_s)
        out[i0:int(np.searchsorted(t_s, t_s[i0] + dur, side="right"))] = True
    return out


# ----------------------------------------------------------------------------- odometry
#: The window of the speed that decides whether a VO moves at motorway speed (fast_speed_mps).
FAST_WINDOW_S = 5.0


def fast_frames(t_s: np.ndarray, dist_m: np.ndarray, speed_mps: float, window_s: float = FAST_WINDOW_S) -> np.ndarray:
    """Frames whose mean speed over the last ``window_s`` (s) is above ``speed_mps`` (m/s); ``dist_m``: the
    distance driven up to each frame (m). A frame less than ``window_s`` into the drive averages from its start."""
    t_s = np.asarray(t_s, dtype=float)
    start = np.searchsorted(t_s, t_s - window_s, side="left")
    span_s = t_s - t_s[start]
    moved = np.asarray(dist_m, dtype=float) - np.asarray(dist_m, dtype=float)[start]
    speed = np.divide(moved, span_s, out=np.zeros(len(t_s)), where=span_s > 0)
    return speed > speed_mps


def imu_gap_resets(imu_missing: np.ndarray, prob: float, rng: np.random.Generator) -> np.ndarray:
    """A map reset at the first frame after each gap of ``imu_missing``, with probability ``prob`` each (one
    uniform draw per gap, in order); a gap that lasts to the end resets nothing."""
    miss = np.asarray(imu_missing, dtype=bool)
    out = np.zeros(len(miss), dtype=bool)
    ends = np.flatnonzero(miss[:-1] & ~miss[1:]) + 1  # the frame the IMU resumes
    if miss[:1].any():
        ends = ends[1:]  # an IMU that starts late resumes nothing: the VIO starts with it
    for k in ends:
        if rng.random() < prob:
            out[k] = True
    return out


@dataclass
class OdometryOutput:
    """Odometry as a VO system writes it: absolute poses in its own frame, starting at identity."""

    t_s: np.ndarray  # times of the frames it output (dropped frames are absent)
    poses: np.ndarray  # (M, 4, 4)
    frame_index: np.ndarray  # index into the truth of every output frame
    dropped: np.ndarray  # (N,) per truth frame: no output
    rain_episode: np.ndarray  # (N,) per truth frame
    events: list[tuple[float, str]] = field(default_factory=list)  # (t, "reinit" | "map_reset")


def simulate_odometry(truth: Truth, p: OdometryParams, rng: np.random.Generator, rain: bool = False) -> OdometryOutput:
    """Drifting odometry from a ground truth (see :class:`OdometryParams` for every error term).

    Each step's true relative motion (body frame) is scaled by 1 + the scale error, turned by the
    yaw drift, pushed sideways by the lateral drift (and, in a rain episode, by the rain drift),
    and noised on all six axes. Frames are dropped in outages and, when ``tunnel_lose_track`` is
    set, throughout visually degraded zones; tracking then re-initialises with a constant-velocity
    guess over the gap plus a jump. Map resets add a jump without a gap.
    """
    n = len(truth)
    T = truth_poses(truth)
    rel_true = np.einsum("nij,njk->nik", np.linalg.inv(T[:-1]), T[1:])  # step k-1 → k in body frame
    steps = np.hypot(np.diff(truth.x_m), np.diff(truth.y_m))
    dist = np.concatenate(([0.0], np.cumsum(steps)))

    scale_bias = rng.normal(0.0, p.scale_error_sigma)
    yaw_rate0 = rng.normal(0.0, p.yaw_bias_sigma_rad_per_m)
    lateral0 = rng.normal(0.0, p.lateral_bias_sigma_m_per_m)
    episodes = _poisson_intervals(rng, dist, truth.t_s, p.rain_episode_rate_per_km, p.rain_episode_duration_s)
    episode_sign = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    # one sign per episode: carry the sign of each episode's first frame
    starts = np.flatnonzero(episodes & ~np.concatenate(([False], episodes[:-1])))
    sign = np.ones(n)
    for s0 in starts:
        e = s0
        while e < n and episodes[e]:
            e += 1
        sign[s0:e] = episode_sign[s0]
    dropout = _poisson_intervals(rng, dist, truth.t_s, p.dropout_rate_per_km, p.dropout_duration_s)
    lost = dropout | (truth.visually_degraded if p.tunnel_lose_track >= 0.5 else np.zeros(n, dtype=bool))
    lost[0] = False
    resets = _poisson_intervals(rng, dist, truth.t_s, p.map_reset_rate_per_km, 0.0) if p.map_reset_rate_per_km > 0 else np.zeros(n, bool)
    if p.imu_gap_reset_prob > 0:  # drawn only where set, so that the other presets keep their noise streams
        resets |= imu_gap_resets(truth.imu_missing, p.imu_gap_reset_prob, rng)
    fast = fast_frames(truth.t_s, dist, p.fast_speed_mps) if p.fast_scale_loss > 0 else np.zeros(n, bool)
    gyro_bias = rng.normal(0.0, p.yaw_bias_sigma_rad_per_s) if p.yaw_bias_sigma_rad_per_s > 0 else 0.0

    # the error terms a real VO showed (issue 22); drawn only where set, so that a preset without them
    # (vio) keeps its noise streams as before
    start_bias = rng.normal(0.0, p.start_scale_bias_sigma) if p.start_scale_bias_sigma > 0 else 0.0
    turn_scale = 1.0 + (rng.normal(0.0, p.turn_scale_sigma) if p.turn_scale_sigma > 0 else 0.0)
    if p.unit_m_max < p.unit_m_min:
        raise ValueError(f"odometry: unit_m_max ({p.unit_m_max}) is below unit_m_min ({p.unit_m_min})")
    unit_m = (math.exp(rng.uniform(math.log(p.unit_m_min), math.log(p.unit_m_max)))
              if p.unit_m_max > p.unit_m_min else p.unit_m_min)
    revert = p.scale_reversion_m

    noise_factor = p.rain_noise_factor if rain else 1.0
    sig_t = p.translation_noise_m * noise_factor
    sig_r = p.rotation_noise_rad * noise_factor

    scale_rw = 0.0
    yaw_rate = yaw_rate0
    poses = [np.eye(4)]
    idx = [0]
    events: list[tuple[float, str]] = []
    last_good = 0
    current = np.eye(4)
    velocity_rel = np.eye(4)  # the last measured step, for constant-velocity re-initialisation
    stand_t0: float | None = None  # the start of the stand the vehicle is in (None: moving)
    for k in range(1, n):
        ds = steps[k - 1]
        if revert > 0 and ds > 0:  # exact discretisation of the Ornstein-Uhlenbeck wander over ds
            a = math.exp(-ds / revert)
            scale_rw = a * scale_rw + rng.normal(0.0, p.scale_rw_per_sqrt_m * math.sqrt(0.5 * revert * (1.0 - a * a)))
        else:
            scale_rw += rng.normal(0.0, p.scale_rw_per_sqrt_m * math.sqrt(ds)) if ds > 0 else 0.0
        yaw_rate += rng.normal(0.0, p.yaw_bias_rw_rad_per_m_sqrt_m * math.sqrt(ds)) if ds > 0 else 0.0
        if lost[k]:
            continue  # no output: the frame is dropped
        scale_start = start_bias * math.exp(-dist[k] / p.start_scale_bias_m) if start_bias else 0.0
        degraded = truth.visually_degraded[k]
        drift = p.tunnel_drift_factor if degraded else 1.0
        # the measured motion since the last output frame
        gap_s = truth.t_s[k] - truth.t_s[last_good]
        if last_good != k - 1 and gap_s <= p.relocalise_max_gap_s:
            # a short outage: re-matched to the map, the motion over the gap is recovered
            r = np.linalg.inv(T[last_good]) @ T[k]
            dyaw = math.atan2(r[1, 0], r[0, 0])
            xi = np.concatenate((r[:3, 3] * (1.0 + scale_bias + scale_rw + scale_start)
                                 + rng.normal(0.0, p.relocalise_noise_m_per_s * gap_s, 3) * (1, 1, 0.2),
                                 [0.0, 0.0, turn_scale * dyaw + rng.normal(0.0, math.radians(0.05) * gap_s)]))
            meas = _exp_se3(xi)
            events.append((float(truth.t_s[k]), "relocalise"))
        elif last_good != k - 1:
            # re-initialisation: constant-velocity guess over the gap, plus a jump
            gap_steps = k - last_good
            guess = np.linalg.matrix_power(velocity_rel, gap_steps)
            jump = p.reinit_jump_sigma_m * min(1.0, gap_s / 10.0)
            xi = np.concatenate((rng.normal(0.0, jump, 3) * (1, 1, 0.2), rng.normal(0.0, math.radians(1.0) * min(1.0, gap_s / 10.0), 3) * (0.1, 0.1, 1)))
            meas = guess @ _exp_se3(xi)
            events.append((float(truth.t_s[k]), "reinit"))
        else:
            r = rel_true[k - 1]
            tx, ty, tz = r[:3, 3]
            dyaw = math.atan2(r[1, 0], r[0, 0])
            scale = (1.0 + scale_bias + scale_rw + scale_start) * (1.0 - p.fast_scale_loss if fast[k] else 1.0)
            if ds >= STANDSTILL_STEP_M:
                still, stand_t0 = 1.0, None
            else:
                stand_t0 = truth.t_s[k - 1] if stand_t0 is None else stand_t0
                settled = 0.0 < p.standstill_noise_s < truth.t_s[k] - stand_t0
                still = 0.0 if settled else p.standstill_noise_factor
            lat = (lateral0 + (sign[k] * p.rain_lateral_drift_m_per_m if episodes[k] else 0.0)) * ds * drift
            xi = np.array([
                scale * tx + rng.normal(0.0, sig_t * still),
                scale * ty + lat + rng.normal(0.0, sig_t * still),
                scale * tz + rng.normal(0.0, sig_t * still),
                rng.normal(0.0, sig_r * still),
                rng.normal(0.0, sig_r * still),
                turn_scale * dyaw + (yaw_rate * ds + gyro_bias * (truth.t_s[k] - truth.t_s[k - 1])) * drift
                + rng.normal(0.0, sig_r * still),
            ])
            meas = _exp_se3(xi)
            velocity_rel = meas
        if resets[k]:
            jump = np.concatenate((rng.normal(0.0, p.map_reset_jump_sigma_m, 2), [0.0], [0.0, 0.0],
                                   [rng.normal(0.0, math.radians(3.0))]))
            meas = meas @ _exp_se3(jump)
            events.append((float(truth.t_s[k]), "map_reset"))
        current = current @ meas
        poses.append(current.copy())
        idx.append(k)
        last_good = k
    frame_index = np.asarray(idx)
    out = np.asarray(poses)
    if unit_m != 1.0:
        out[:, :3, 3] /= unit_m
    return OdometryOutput(truth.t_s[frame_index], out, frame_index, lost, episodes, events)


# ----------------------------------------------------------------------------- IMU
@dataclass
class ImuOutput:
    t_s: np.ndarray
    accel_mps2: np.ndarray  # (M, 3) body frame specific force
    gyro_radps: np.ndarray  # (M, 3) body frame angular rate


def simulate_imu(truth: Truth, p: ImuParams, rng: np.random.Generator) -> ImuOutput:
    """Accelerometer and gyroscope at ``rate_hz`` from a spline through the truth, with white
    noise and bias random walks (body frame: x forward, y left, z up; specific force includes gravity)."""
    t0, t1 = float(truth.t_s[0]), float(truth.t_s[-1])
    t = np.arange(t0, t1 + 1e-9, 1.0 / p.rate_hz)
    yaw_u = np.unwrap(truth.yaw_rad)
    sx, sy, sz = (CubicSpline(truth.t_s, v) for v in (truth.x_m, truth.y_m, truth.z_m))
    syaw = CubicSpline(truth.t_s, yaw_u)
    a_world = np.column_stack([sx(t, 2), sy(t, 2), sz(t, 2) + GRAVITY_MPS2])
    yaw = syaw(t)
    c, s = np.cos(yaw), np.sin(yaw)
    a_body = np.column_stack([c * a_world[:, 0] + s * a_world[:, 1], -s * a_world[:, 0] + c * a_world[:, 1], a_world[:, 2]])
    w_body = np.column_stack([np.zeros_like(t), np.zeros_like(t), syaw(t, 1)])
    m = len(t)
    dt = 1.0 / p.rate_hz
    ba = rng.normal(0.0, p.accel_bias_sigma, 3) + np.cumsum(rng.normal(0.0, p.accel_bias_rw * math.sqrt(dt), (m, 3)), axis=0)
    bg = rng.normal(0.0, p.gyro_bias_sigma, 3) + np.cumsum(rng.normal(0.0, p.gyro_bias_rw * math.sqrt(dt), (m, 3)), axis=0)
    acc = a_body + ba + rng.normal(0.0, p.accel_noise_density * math.sqrt(p.rate_hz), (m, 3))
    gyr = w_body + bg + rng.normal(0.0, p.gyro_noise_density * math.sqrt(p.rate_hz), (m, 3))
    return ImuOutput(t, acc, gyr)


# ----------------------------------------------------------------------------- GPS
@dataclass
class GpsOutput:
    t_s: np.ndarray
    x_m: np.ndarray  # fix in the map's ENU frame
    y_m: np.ndarray
    alt_m: np.ndarray
    sigma_m: np.ndarray  # what the receiver reports (the nominal σ)
    outlier: np.ndarray  # which fixes are multipath outliers (for tests and plots)
    frame_index: np.ndarray


def gps_fix_times(t_s: np.ndarray, cfg: GpsConfig) -> np.ndarray:
    """Indices into ``t_s`` (seconds from the start, increasing) at which a fix is taken, before
    denial: by mode, rate and interval — the first time at or after each multiple of the period."""
    t = np.asarray(t_s, float)
    want = np.zeros(len(t), dtype=bool)
    if len(t) == 0:
        return np.flatnonzero(want)
    period = 1.0 / cfg.rate_hz

    def mark(times):
        i = np.searchsorted(t, np.asarray(times) - 1e-9)
        want[i[i < len(t)]] = True

    end = float(t[-1])
    if cfg.mode is GpsMode.continuous:
        mark(np.arange(0.0, end + 1e-9, period))
    else:
        mark(np.arange(0.0, min(cfg.init_window_s, end) + 1e-9, period))
        if cfg.mode is GpsMode.interval:
            mark(np.arange(cfg.init_window_s, end + 1e-9, cfg.interval_s))
    return np.flatnonzero(want)


def gps_fix_frames(truth: Truth, cfg: GpsConfig) -> np.ndarray:
    """Truth frames at which a fix is taken, before denial: by mode, rate and interval."""
    return gps_fix_times(truth.t_s - truth.t_s[0], cfg)


def simulate_gps(truth: Truth, cfg: GpsConfig, rng: np.random.Generator) -> GpsOutput:
    """GPS fixes: by mode, σ per axis, multipath outliers, none where the truth is GPS-denied."""
    idx = gps_fix_frames(truth, cfg)
    idx = idx[~truth.gps_denied[idx]]
    k = len(idx)
    outlier = rng.random(k) < cfg.outlier_probability
    sig = np.where(outlier, cfg.outlier_sigma_m, cfg.sigma_m)
    ex, ey = rng.normal(0.0, 1.0, k) * sig, rng.normal(0.0, 1.0, k) * sig
    ez = rng.normal(0.0, 1.0, k) * 2.0 * sig
    return GpsOutput(truth.t_s[idx], truth.x_m[idx] + ex, truth.y_m[idx] + ey, truth.z_m[idx] + ez,
                     np.full(k, cfg.sigma_m), outlier, idx)


# ----------------------------------------------------------------------------- all sensors of a scenario
@dataclass
class SensorData:
    odometry: OdometryOutput
    imu: ImuOutput
    gps: GpsOutput
    params: OdometryParams
    wheel: WheelOutput | None = None  # odometry kinds with +wheel only
    kidnap: Kidnap | None = None  # a kidnapped drive's kidnap (issue 17)


@dataclass(frozen=True)
class Kidnap:
    """What knocked the estimate off, as drawn: when (the truth's time and distance driven) and how much."""

    kind: str
    t_s: float
    at_m: float
    distance_m: float
    bearing_rad: float
    heading_rad: float = 0.0


def apply_kidnap(cfg, truth: Truth, odo: OdometryOutput, gps: GpsOutput, rng: np.random.Generator
                 ) -> tuple[OdometryOutput, GpsOutput, Kidnap | None]:
    """The ``[kidnap]`` of a scenario applied to its sensors: ``gps_bias`` moves every fix by one drawn
    vector (the kidnap counts from the last fix: until then the estimate is where the fixes say); ``vo_jump`` removes the VO's frames for ``gap_s`` from a drawn
    distance after the last fix and turns and shifts every later pose (in the odometry's own frame) by a drawn
    heading error and jump, as a VO that re-initialises in the wrong place does."""
    kind = getattr(cfg.kind, "value", cfg.kind)
    if kind == "none":
        return odo, gps, None
    bearing = float(rng.uniform(-math.pi, math.pi))
    driven = cumulative_length(np.column_stack([truth.x_m, truth.y_m]))
    last_fix = int(min(np.searchsorted(truth.t_s, gps.t_s[-1]), len(truth) - 1)) if len(gps.t_s) else 0
    if kind == "gps_bias":
        d = float(rng.uniform(cfg.bias_min_m, cfg.bias_max_m))
        moved = dataclasses.replace(gps, x_m=gps.x_m + d * math.cos(bearing), y_m=gps.y_m + d * math.sin(bearing))
        # the estimate is knocked off where the biased fixes end (while they come it is where they say)
        t_end = float(gps.t_s[-1]) if len(gps.t_s) else float(truth.t_s[0])
        return odo, moved, Kidnap(kind, t_end, float(driven[last_fix]), d, bearing)
    d = float(rng.uniform(cfg.jump_min_m, cfg.jump_max_m))
    heading = math.radians(float(rng.uniform(-cfg.heading_max_deg, cfg.heading_max_deg)))
    at_m = driven[last_fix] + float(rng.uniform(cfg.at_min_m, cfg.at_max_m))
    if at_m > driven[-1]:
        return odo, gps, None  # the drive ends first
    t_k = float(truth.t_s[int(np.searchsorted(driven, at_m))])
    t_out = truth.t_s[odo.frame_index]
    gone = (t_out > t_k) & (t_out <= t_k + cfg.gap_s)
    after = t_out > t_k + cfg.gap_s
    if not after.any():
        return odo, gps, None  # the drive ends before the VO comes back: no kidnap to recover from
    poses = odo.poses.copy()
    first = int(np.flatnonzero(after)[0])
    c = poses[first, :3, 3].copy()
    jump = np.eye(4)
    ch, sh = math.cos(heading), math.sin(heading)
    jump[:2, :2] = [[ch, -sh], [sh, ch]]
    jump[:2, 3] = c[:2] - jump[:2, :2] @ c[:2] + d * np.array([math.cos(bearing), math.sin(bearing)])
    poses[after] = jump @ poses[after]
    keep = ~gone
    dropped = odo.dropped.copy()
    dropped[odo.frame_index[gone]] = True
    out = dataclasses.replace(odo, t_s=odo.t_s[keep], poses=poses[keep], frame_index=odo.frame_index[keep],
                              dropped=dropped, events=sorted(odo.events + [(float(t_out[first]), "kidnap")]))
    return out, gps, Kidnap(kind, float(t_out[first]), float(driven[odo.frame_index[first]]), d, bearing, heading)


def sensor_streams(seed: int) -> dict[str, np.random.Generator]:
    """Independent generators per sensor from the scenario seed (changing one never moves another)."""
    # a fourth child leaves the first three as they were: spawn keys are (0,), (1,), (2,), (3,)
    children = np.random.SeedSequence([seed, 0x5E45]).spawn(5)
    return {name: np.random.default_rng(c) for name, c in zip(("odometry", "imu", "gps", "wheel", "kidnap"), children)}


def recorded_odometry(truth: Truth, path: str) -> OdometryOutput:
    """A real odometry's output (KITTI poses, camera frame) on its recorded drive: one pose per
    truth frame, at the truth's times, in the body convention (x forward, y left, z up)."""
    from mapfusion.formats import FormatError, read_kitti_poses
    from mapfusion.replay import camera_to_body

    poses = read_kitti_poses(path)
    n = len(truth)
    if len(poses) < n:  # the drive may be cut by duration_s: its first frames are the truth's
        raise FormatError(f"{path}: {len(poses)} poses, but the recorded drive has {n} frames")
    poses = poses[:n]
    none = np.zeros(n, dtype=bool)
    return OdometryOutput(np.asarray(truth.t_s, float), camera_to_body(poses), np.arange(n), none, none.copy())


def synthesise(sc: Scenario, truth: Truth, gps: GpsOutput | None = None) -> SensorData:
    """Odometry (kind × weather preset with the scenario's overrides), IMU and GPS for a truth;
    ``gps`` (recorded fixes) replaces the receiver model."""
    rng = sensor_streams(sc.seed)
    if sc.odometry.kind is OdometryKind.recorded:
        params = odometry_preset(OdometryKind.vo, sc.weather.kind)  # unused by a recorded odometry
        odo = recorded_odometry(truth, sc.odometry.file)
    else:
        params = odometry_preset(sc.odometry.kind, sc.weather.kind).with_overrides(sc.odometry.overrides)
        odo = simulate_odometry(truth, params, rng["odometry"], rain=WeatherKind(sc.weather.kind) is not WeatherKind.clear)
    imu = simulate_imu(truth, sc.imu, rng["imu"])
    gps = simulate_gps(truth, sc.gps, rng["gps"]) if gps is None else gps
    wheel = None
    if sc.odometry.kind.wheel:
        wheel = simulate_wheel(truth, wheel_preset(sc.wheel.vehicle).with_overrides(sc.wheel.overrides), rng["wheel"],
                               sc.weather.kind)
    odo, gps, kidnap = apply_kidnap(sc.kidnap, truth, odo, gps, rng["kidnap"])
    return SensorData(odo, imu, gps, params, wheel, kidnap)
