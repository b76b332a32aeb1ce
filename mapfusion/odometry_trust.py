"""The odometry's σ learned from the GPS window (issue 17, ``odometry_sigma_learned``).

The engine's odometry σ (``odometry_sigma_per_m``, ``odometry_rot_sigma_deg_per_m`` and their per-frame floors) is one
figure for every odometry: KITTI's own poses and a rain VO get the same trust. The GPS window of the initialisation
tells them apart. A similarity fit of the raw odometry to the window's fixes leaves a residual made of the fixes'
noise and the odometry's drift; the drift part, against the residual the configured σ would leave on the same path,
is the factor by which the configured σ over- or under-states this odometry's error.

The configured σ's residual is computed, not simulated: each step's translation noise moves every later position by
itself, each step's yaw noise turns the rest of the path about that step's position, so the positions at the fixes
have a covariance Σ = U·Uᵀ + T (U: the yaw noise's columns, T: the translation noise's); the fit removes the
similarity's four directions (shift, rotation, scale: the matrix A), and the expected squared residual per fix is
trace((I − A·A⁺)·Σ) / m.

The drift part of the observed residual is its mean square less the fixes' own 2σ² (the fit's four degrees of
freedom deducted), bounded two standard errors of a χ² mean either side. The σ is loosened only by the lower bound and
tightened only by the upper: with metre-level fixes the window shows neither, and the configured σ stay.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError

__all__ = ["OdometryTrust", "OdometryTrustError", "drift_residual_m", "model_residual_m", "learn_factor"]

#: Fixes a least-squares scale fit needs. Source: by measurement.
SCALE_FIT_MIN_FIXES = 10

#: The fit drops fixes farther than this many median σ (plus SCALE_FIT_OUTLIER_FLOOR_M) from a first fit. Source:
#: by measurement.
SCALE_FIT_OUTLIER_SIGMA = 3.0

#: Added to the fit's outlier bound. Unit: m. Source: by measurement.
SCALE_FIT_OUTLIER_FLOOR_M = 1.0


class OdometryTrustError(InputError):
    """Inputs to the learned odometry σ that cannot describe a path and its fixes."""


@dataclass(frozen=True)
class OdometryTrust:
    """What the window said of the odometry: the factor on its σ and the two residuals it came from."""

    factor: float  # the configured odometry σ is multiplied by this (1: as configured)
    drift_low_m: float  # RMS drift residual the fit left, lower bound, m
    drift_m: float  # the same, upper bound, m
    model_m: float  # RMS residual the configured σ would leave on the same path and fixes, m
    fixes: int


def _similarity_basis(points_m: np.ndarray) -> np.ndarray:
    """(2m, 4): how the points move under a small shift (x, y), rotation and scale about their centroid."""
    q = points_m - points_m.mean(axis=0)
    a = np.zeros((2 * len(q), 4))
    a[0::2, 0] = 1.0
    a[1::2, 1] = 1.0
    a[0::2, 2], a[1::2, 2] = -q[:, 1], q[:, 0]
    a[0::2, 3], a[1::2, 3] = q[:, 0], q[:, 1]
    return a


def model_residual_m(xy_m: np.ndarray, sigma_xy_m: np.ndarray, sigma_yaw_rad: np.ndarray,
                     at: np.ndarray) -> float:
    """RMS residual (m) a similarity fit to positions at frames ``at`` would leave if the odometry erred as its σ say.

    ``xy_m``: (n, 2) frame positions in metres; ``sigma_xy_m``, ``sigma_yaw_rad``: (n,) the σ of the step into each
    frame (per axis; entry 0 unused); ``at``: (m,) frame indices of the fixes, m ≥ 3."""
    xy = np.asarray(xy_m, dtype=float)
    st = np.asarray(sigma_xy_m, dtype=float)
    sr = np.asarray(sigma_yaw_rad, dtype=float)
    at = np.asarray(at, dtype=int)
    n = len(xy)
    if xy.ndim != 2 or xy.shape[1] != 2 or st.shape != (n,) or sr.shape != (n,):
        raise OdometryTrustError(f"positions (n, 2) and σ (n,) expected, got {xy.shape}, {st.shape}, {sr.shape}")
    if len(at) < 3 or at.min() < 0 or at.max() >= n:
        raise OdometryTrustError(f"need at least 3 fix frames within the {n} frames, got {len(at)}")
    if not (np.isfinite(xy).all() and np.isfinite(st).all() and np.isfinite(sr).all()) or (st < 0).any() \
            or (sr < 0).any():
        raise OdometryTrustError("positions and σ must be finite, σ ≥ 0")
    p = xy[at]
    m = len(at)
    j = np.arange(1, n)  # the step into frame j turns every later position about frame j's
    after = at[:, None] >= j[None, :]  # (m, n-1)
    dx = (p[:, 0, None] - xy[None, j, 0]) * after * sr[None, j]
    dy = (p[:, 1, None] - xy[None, j, 1]) * after * sr[None, j]
    u = np.empty((2 * m, n - 1))
    u[0::2], u[1::2] = -dy, dx  # J·(p − p_j), J the quarter turn
    cum_t = np.concatenate([[0.0], np.cumsum(st[1:] ** 2)])  # each step's shift moves every later frame
    common = cum_t[np.minimum.outer(at, at)]
    t = np.zeros((2 * m, 2 * m))
    t[0::2, 0::2] = common
    t[1::2, 1::2] = common
    a = _similarity_basis(p)
    a_pinv = np.linalg.pinv(a)
    pu = u - a @ (a_pinv @ u)
    trace = float(np.sum(pu * pu)) + float(np.trace(t) - np.trace(a_pinv @ t @ a))
    return math.sqrt(max(trace, 0.0) / m)


def drift_residual_m(residual_m: np.ndarray, fix_sigma_m: np.ndarray, confidence: float = 2.0) -> float:
    """RMS (m) of the part of a similarity fit's residuals the fixes' noise does not explain, at a bound:
    ``confidence`` standard errors of the fixes' χ² mean added (the upper bound; negative: the lower, at least 0)."""
    r = np.asarray(residual_m, dtype=float)
    s2 = np.asarray(fix_sigma_m, dtype=float) ** 2
    m = len(r)
    if m < 5 or s2.shape != r.shape or not (np.isfinite(r).all() and np.isfinite(s2).all()):
        raise OdometryTrustError(f"need at least 5 finite residuals with their fixes' σ, got {m}")
    noise = 2.0 * float(s2.mean()) * (1.0 - 2.0 / m)  # a 2D fix's expected squared error, less the fit's 4 dof
    excess = max(float(np.mean(r * r)) - noise, 0.0)
    return math.sqrt(max(excess + confidence * 2.0 * float(s2.mean()) / math.sqrt(m), 0.0))


def learn_factor(drift_low_m: float, drift_high_m: float, model_m: float, lo: float, hi: float) -> float:
    """The factor on the configured σ, moved only as far as the window shows: the drift's lower bound over the model's
    residual where that exceeds 1 (within hi), its upper bound's where that is below 1 (within lo), else 1. (With
    the upper bound alone, 2 m fixes loosened a perfect odometry: their noise's uncertainty read as drift.)"""
    if not (model_m > 0 and math.isfinite(drift_low_m) and math.isfinite(drift_high_m)):
        return 1.0
    if drift_low_m > model_m:
        return min(drift_low_m / model_m, max(hi, 1.0))
    if drift_high_m < model_m:
        return max(drift_high_m / model_m, min(lo, 1.0))
    return 1.0


def step_sigmas(cfg, length_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The configured translation σ (per axis, m) and yaw σ (rad) of steps of these lengths (one frame each)."""
    st = np.hypot(cfg.odometry_sigma_after_init_m, cfg.odometry_sigma_per_m * length_m)
    sr = np.radians(np.hypot(cfg.odometry_rot_sigma_deg, cfg.odometry_rot_sigma_deg_per_m * length_m))
    return st, sr


def from_window(cfg, track, alignment, fixes: list[tuple[float, float, float, float]]) -> OdometryTrust | None:
    """What the initialisation window's fixes say of the odometry's σ, or None with too few fixes or too little
    motion to say it (fewer than ``SCALE_FIT_MIN_FIXES`` kept, a model residual under 1 mm)."""
    from .metrics import umeyama  # (numpy only; kept local like the fit's own use)

    lo, hi = track.t[track.first] - 0.5, track.t[-1] + 0.5
    g = np.array([f for f in fixes if lo <= f[0] <= hi]).reshape(-1, 4)
    if len(g) < max(SCALE_FIT_MIN_FIXES, 5):
        return None
    o = np.array([track.raw_at(t).translation()[:2] for t in g[:, 0]])
    keep = np.ones(len(g), dtype=bool)
    for _ in range(2):  # the initialisation fit's outlier rule (Initialiser.fit)
        r, tr, sc = umeyama(o[keep], g[keep, 1:3], with_scale=True)
        resid = np.hypot(*(g[:, 1:3] - (sc * o @ r.T + tr)).T)
        keep = resid <= SCALE_FIT_OUTLIER_SIGMA * np.median(g[:, 3]) + SCALE_FIT_OUTLIER_FLOOR_M
        if keep.sum() < max(SCALE_FIT_MIN_FIXES, 5):
            return None
    drift = drift_residual_m(resid[keep], g[keep, 3])
    drift_low = drift_residual_m(resid[keep], g[keep, 3], confidence=-2.0)
    xy = np.array([track.to_map(raw, alignment).translation()[:2] for raw in track.raw])
    length = np.concatenate([[0.0], np.hypot(*np.diff(xy, axis=0).T)])
    st, sr = step_sigmas(cfg, length)
    at = np.array([track.frame_at(t) for t in g[keep, 0]]) - track.first
    at = at[:: max(1, len(at) // 300)]  # (the model's mean over ~300 fixes is the mean over all)
    if len(np.unique(at)) < 3:
        return None
    model = model_residual_m(xy, st, sr, at)
    if model < 1e-3:
        return None
    f = learn_factor(drift_low, drift, model, cfg.odometry_sigma_factor_min, cfg.odometry_sigma_factor_max)
    return OdometryTrust(f, drift_low, drift, model, int(keep.sum()))
