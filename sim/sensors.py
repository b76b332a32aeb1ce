"""Sensor error-model parameters: the odometry presets (kind × weather).

Every field is documented with its unit; a scenario's ``[odometry]`` table may override any of
them. Rates are per kilometre driven, random walks per square root of metres or seconds.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from mapfusion.config import param

from .scenario import OdometryKind, WeatherKind


@dataclass(frozen=True)
class OdometryParams:
    """Error model of a visual (or visual-inertial) odometry, per run."""

    scale_error_sigma: float = param(0.005, "σ of the run's constant relative scale error.", unit="1")
    scale_rw_per_sqrt_m: float = param(0.0002, "Random walk of the relative scale error.", unit="1/√m")
    yaw_bias_sigma_rad_per_m: float = param(2e-5, "σ of the run's constant yaw drift per metre driven.", unit="rad/m")
    yaw_bias_rw_rad_per_m_sqrt_m: float = param(2e-6, "Random walk of the yaw drift rate.", unit="rad/m/√m")
    translation_noise_m: float = param(0.01, "White noise on each translation axis of each step.", unit="m")
    rotation_noise_rad: float = param(0.0005, "White noise on roll, pitch and yaw of each step.", unit="rad")
    lateral_bias_sigma_m_per_m: float = param(0.002, "σ of the run's constant lateral drift per metre driven.", unit="m/m")
    dropout_rate_per_km: float = param(0.0, "Outages (dropped frames) per km outside tunnels.", unit="1/km")
    dropout_duration_s: float = param(1.0, "Mean outage duration.", unit="s")
    reinit_jump_sigma_m: float = param(2.0, "σ of the position jump when tracking re-initialises after an outage.", unit="m")
    tunnel_lose_track: float = param(1.0, "1: tracking is lost inside GPS-denied zones (vo); 0: it continues (vio).")
    tunnel_drift_factor: float = param(1.0, "Multiplier of yaw and lateral drift inside GPS-denied zones.", unit="1")
    rain_episode_rate_per_km: float = param(0.0, "Drops on the lens: episodes of strong lateral drift per km.", unit="1/km")
    rain_episode_duration_s: float = param(8.0, "Mean duration of a rain episode.", unit="s")
    rain_lateral_drift_m_per_m: float = param(0.0, "Lateral drift per metre during a rain episode.", unit="m/m")
    rain_noise_factor: float = param(1.0, "Multiplier of the white noise in rain.", unit="1")
    map_reset_rate_per_km: float = param(0.0, "Map resets (pose discontinuities) per km.", unit="1/km")
    map_reset_jump_sigma_m: float = param(5.0, "σ of the position jump at a map reset.", unit="m")

    def with_overrides(self, overrides: tuple[tuple[str, float], ...]) -> OdometryParams:
        return dataclasses.replace(self, **dict(overrides))


def odometry_preset(kind: OdometryKind, weather: WeatherKind) -> OdometryParams:
    """The preset parameters of an odometry kind in a weather."""
    base = OdometryParams()
    if kind is OdometryKind.vio:
        base = dataclasses.replace(base, scale_error_sigma=0.002, scale_rw_per_sqrt_m=0.0001,
                                   tunnel_lose_track=0.0, tunnel_drift_factor=3.0)
    if weather is WeatherKind.rain:
        base = dataclasses.replace(base, rain_episode_rate_per_km=2.0, rain_lateral_drift_m_per_m=0.05,
                                   rain_noise_factor=2.0, dropout_rate_per_km=1.0)
    elif weather is WeatherKind.heavy_rain:
        base = dataclasses.replace(base, rain_episode_rate_per_km=4.0, rain_lateral_drift_m_per_m=0.08,
                                   rain_noise_factor=3.0, dropout_rate_per_km=2.0,
                                   map_reset_rate_per_km=0.3 if kind is OdometryKind.vio else 0.0)
    return base
