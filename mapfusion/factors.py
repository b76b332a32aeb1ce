"""Every noise model and factor of the engine, built in one place.

The state of frame k is a gtsam.Pose3 under key ``x<k>``. GTSAM's Pose3 noise lives in the
pose's tangent space, ordered (rotation x, y, z, translation x, y, z), translation in the pose's
own frame. With the planar state (DESIGN item 7) roll, pitch and z are held level by a tight σ
(:data:`HELD_SIGMA`) in every factor; with the free Pose3 they get their own σ.

The map prior (paper III.B Eq. 6, DESIGN item 3): in the world's x/y plane Σ = E Λ E⁻¹, with e₁
the normalised direction of motion, e₂ ⟂ e₁, λ₁ = |v_lon| and λ₂ = |v_lat| (as variances, m²),
floored so Σ is never singular; the x/y block is rotated into the prior's mean frame. Roll, pitch
and z get zero precision (the 2D map says nothing about them); yaw gets 1/σ_yaw². With
``along_free`` the precision along the road is zero too. The result is a square-root information
matrix R (RᵀR = Λ), which GTSAM accepts with zero rows.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from . import relocalise
from .config import FusionConfig, PriorMode, RobustKernel, StateModel
from .track import OUTAGE_S

#: Least rotation σ of an outage step. Unit: deg. Source: by measurement.
OUTAGE_ROT_SIGMA_DEG = 20.0


def world_covariance(motion_dir_rad: float, v_lon_mps: float, v_lat_mps: float, floor_m2: float,
                     map_var_m2: float = 0.0) -> np.ndarray:
    """Σ = E Λ E⁻¹ in the world x/y plane (2×2, symmetric positive definite); ``map_var_m2`` (the
    map geometry's own variance) is added to both eigenvalues."""
    e1 = np.array([math.cos(motion_dir_rad), math.sin(motion_dir_rad)])
    e2 = np.array([-e1[1], e1[0]])
    e = np.column_stack([e1, e2])
    lam = np.diag([max(abs(v_lon_mps), floor_m2) + map_var_m2, max(abs(v_lat_mps), floor_m2) + map_var_m2])
    return e @ lam @ np.linalg.inv(e)


def prior_sqrt_information(
    road_yaw_rad: float,
    motion_dir_rad: float,
    v_lon_mps: float,
    v_lat_mps: float,
    yaw_sigma_rad: float,
    floor_m2: float,
    mode: PriorMode,
    map_var_m2: float = 0.0,
) -> np.ndarray:
    """6×6 R with RᵀR the information of the map prior in the tangent space at the prior's mean."""
    sigma_w = world_covariance(motion_dir_rad, v_lon_mps, v_lat_mps, floor_m2, map_var_m2)
    c, s = math.cos(road_yaw_rad), math.sin(road_yaw_rad)
    rot = np.array([[c, -s], [s, c]])  # mean frame → world
    sigma_b = rot.T @ sigma_w @ rot
    info_b = np.linalg.inv(sigma_b)
    if mode is PriorMode.along_free:
        # keep only the information across the road (the mean frame's y axis)
        info_b = np.array([[0.0, 0.0], [0.0, 1.0 / sigma_b[1, 1]]])
    w, v = np.linalg.eigh(0.5 * (info_b + info_b.T))
    r_xy = np.diag(np.sqrt(np.clip(w, 0.0, None))) @ v.T
    r = np.zeros((6, 6))
    r[2, 2] = 1.0 / yaw_sigma_rad
    r[3:5, 3:5] = r_xy
    return r


def band_update(mu_m: float, sigma_m: float, half_width_m: float) -> tuple[float, float] | None:
    """The map's band as a Gaussian measurement: an estimate N(μ, σ²) of the lateral offset, told
    that the offset lies in [−h, h], has the truncated normal as posterior; returns the (mean, σ)
    of the Gaussian factor that turns N(μ, σ²) into a Gaussian with that posterior's mean and
    variance, or None when the band adds (next to) no information (the estimate is inside it with
    room to spare)."""
    from scipy.special import log_ndtr

    if not (sigma_m > 0 and half_width_m > 0 and math.isfinite(mu_m)):
        raise ValueError(f"band_update: need σ > 0, h > 0 and a finite μ, got {mu_m}, {sigma_m}, {half_width_m}")
    sign = -1.0 if mu_m < 0 else 1.0
    mu = abs(mu_m)  # the band is symmetric: work on the positive side
    a, b = (-half_width_m - mu) / sigma_m, (half_width_m - mu) / sigma_m
    log_pb, log_pa = float(log_ndtr(b)), float(log_ndtr(a))
    log_z = log_pb + math.log1p(-math.exp(log_pa - log_pb))
    log_phi = lambda x: -0.5 * x * x - 0.5 * math.log(2.0 * math.pi)
    ra, rb = math.exp(log_phi(a) - log_z), math.exp(log_phi(b) - log_z)
    mean = mu + sigma_m * (ra - rb)
    var = sigma_m**2 * max(1.0 + a * ra - b * rb - (ra - rb) ** 2, 1e-12)
    prec = 1.0 / var - 1.0 / sigma_m**2
    if prec <= 1e-6 / sigma_m**2:
        return None
    target = (mean / var - mu / sigma_m**2) / prec
    return sign * target, 1.0 / math.sqrt(prec)


def band_sqrt_information(sigma_lat_m: float, yaw_sigma_rad: float) -> np.ndarray:
    """6×6 R of a prior with information across the road (the mean frame's y) and in yaw only."""
    r = np.zeros((6, 6))
    r[2, 2] = 1.0 / yaw_sigma_rad
    r[4, 4] = 1.0 / sigma_lat_m
    return r


def information(r: np.ndarray) -> np.ndarray:
    return r.T @ r


# ----------------------------------------------------------------------------- keys, sigmas, factors
X = gtsam.symbol_shorthand.X

#: σ of roll, pitch (rad) and z (m) in the planar state: held level, never free (GTSAM needs a
#: finite σ, and a level ground vehicle's are zero up to numerical slack).
HELD_SIGMA = 1e-3


def pose_sigmas(state: StateModel, yaw_rad: float, xy_m: float, *, tilt_rad: float | None = None,
                z_m: float | None = None) -> np.ndarray:
    """σ vector (rotation x, y, z, translation x, y, z) of a pose factor. Planar: roll, pitch and z
    held level. Pose3: roll and pitch get ``tilt_rad`` (default: the yaw σ), z gets ``z_m``
    (default: the x/y σ)."""
    if state is StateModel.planar:
        return np.array([HELD_SIGMA, HELD_SIGMA, yaw_rad, xy_m, xy_m, HELD_SIGMA])
    tilt = yaw_rad if tilt_rad is None else tilt_rad
    z = xy_m if z_m is None else z_m
    return np.array([tilt, tilt, yaw_rad, xy_m, xy_m, z])


def diagonal(sigmas: np.ndarray) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, dtype=float))


def pose_prior(k: int, pose: gtsam.Pose3, noise: gtsam.noiseModel.Base) -> gtsam.PriorFactorPose3:
    """A prior on frame k's pose."""
    return gtsam.PriorFactorPose3(X(k), pose, noise)


def between(k: int, step: gtsam.Pose3, noise: gtsam.noiseModel.Base) -> gtsam.BetweenFactorPose3:
    """The odometry factor from frame k − 1 to frame k."""
    return gtsam.BetweenFactorPose3(X(k - 1), X(k), step, noise)


def outage_sigma_m(cfg: FusionConfig, step: gtsam.Pose3, gap_s: float) -> float:
    """How far the estimate after an odometry outage may be from the truth (σ, m; 0 for an ordinary step):
    the step across it is a re-initialised odometry's guess (``outage_step_fraction`` of its length), and the
    vehicle may have moved ``SearchParams.gap_speed_mps`` × the gap in any direction."""
    sp = relocalise.SEARCH_PARAMS
    if gap_s <= OUTAGE_S:
        return 0.0
    tr = step.translation()
    return max(cfg.outage_step_fraction * math.sqrt(tr.dot(tr)), sp.gap_speed_mps * gap_s)


def odometry_noise(cfg: FusionConfig, step: gtsam.Pose3, gap_frames: float, period_s: float, *,
                   before_init: bool = False, scale_sigma: float | None = None,
                   sigma_factor: float = 1.0) -> gtsam.noiseModel.Base:
    """σ of one odometry step. A step across dropped frames is looser in proportion to the frames
    it spans, and one across an outage (over ``OUTAGE_S``) is at least ``outage_step_fraction`` of
    its length: a re-initialised odometry guesses the motion it did not see. Before initialisation
    the step is either loose (``loose_before_init``) or inflated by the scale's relative σ
    (``scale_sigma``: σ / scale). ``sigma_factor`` multiplies the configured σ (the learned odometry σ)."""
    n = max(1.0, gap_frames)
    tr = step.translation()
    length_m = math.sqrt(tr.dot(tr))  # (np.linalg.norm's own arithmetic, less its overhead)
    st = sigma_factor * math.hypot(cfg.odometry_sigma_after_init_m * n, cfg.odometry_sigma_per_m * length_m)
    sr = sigma_factor * math.hypot(math.radians(cfg.odometry_rot_sigma_deg) * n,
                                   math.radians(cfg.odometry_rot_sigma_deg_per_m) * length_m)
    if n * period_s > OUTAGE_S:
        st = max(st, cfg.outage_step_fraction * length_m)
        sr = max(sr, math.radians(OUTAGE_ROT_SIGMA_DEG))
    if before_init and cfg.loose_before_init:
        st, sr = cfg.odometry_sigma_before_init_m, 10.0 * sr
    elif before_init:
        # the batch is solved once the scale is known: its uncertainty scales the step's length
        st = math.hypot(st, (scale_sigma or 0.0) * length_m)
    return diagonal(pose_sigmas(cfg.state, sr, st, tilt_rad=sr, z_m=st))


def gps_factor(state: StateModel, k: int, x: float, y: float, alt: float | None, sigma: float) -> gtsam.GPSFactor:
    """A position factor; z is free (zero precision) in the planar state or without an altitude."""
    planar = state is StateModel.planar or alt is None
    z = 0.0 if planar else alt
    prec_z = 0.0 if planar else 1.0 / (4.0 * sigma * sigma)
    noise = gtsam.noiseModel.Diagonal.Precisions(np.array([1.0 / sigma**2, 1.0 / sigma**2, prec_z]))
    return gtsam.GPSFactor(X(k), gtsam.Point3(x, y, z), noise)


def robust_kernel(cfg: FusionConfig):
    """The M-estimator on map priors, or None."""
    if cfg.robust_kernel is RobustKernel.huber:
        return gtsam.noiseModel.mEstimator.Huber.Create(cfg.robust_k)
    if cfg.robust_kernel is RobustKernel.cauchy:
        return gtsam.noiseModel.mEstimator.Cauchy.Create(cfg.robust_k)
    return None


def band_prior_noise(cfg: FusionConfig, sigma_lat_m: float, robust=None) -> gtsam.noiseModel.Base:
    """The band prior's noise: σ across the road from :func:`band_update`, the map's yaw σ."""
    return sqrt_information_noise(band_sqrt_information(sigma_lat_m, math.radians(cfg.yaw_sigma_deg)), robust)


def map_prior_noise(cfg: FusionConfig, road_yaw_rad: float, motion_dir_rad: float, v_lon_mps: float,
                    v_lat_mps: float, robust=None) -> gtsam.noiseModel.Base:
    """The map prior's noise (Eq. 6 in the tangent space), under the robust kernel if given."""
    r = prior_sqrt_information(road_yaw_rad, motion_dir_rad, v_lon_mps, v_lat_mps, math.radians(cfg.yaw_sigma_deg),
                               cfg.prior_lambda_floor_m2, cfg.prior_mode, cfg.prior_map_sigma_m**2)
    return sqrt_information_noise(r, robust)


def sqrt_information_noise(r: np.ndarray, robust=None) -> gtsam.noiseModel.Base:
    """A noise model from a square-root information matrix, under the robust kernel if given."""
    noise = gtsam.noiseModel.Gaussian.SqrtInformation(r, False)
    return gtsam.noiseModel.Robust.Create(robust, noise) if robust is not None else noise
