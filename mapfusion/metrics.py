"""Metrics (DESIGN "Metrics", contract): ATE as the paper measures it, and helpers.

ATE: align the estimate's positions to the truth with a rigid SE(3) Umeyama fit (no scale),
project both onto the x/y plane, and take the RMSE of the position differences.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError


class MetricsError(InputError):
    """Trajectories that cannot be compared (too few common poses, NaN, mismatched shapes)."""


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares R, t (and s) with dst ≈ s·R·src + t (Umeyama 1991). src, dst: (N, d)."""
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or len(src) < 2:
        raise MetricsError(f"umeyama: need two (N, d) arrays of equal shape with N ≥ 2, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    u, d, vt = np.linalg.svd(cov)
    s_fix = np.eye(src.shape[1])
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s_fix[-1, -1] = -1.0
    r = u @ s_fix @ vt
    scale = 1.0
    if with_scale:
        var = np.mean(np.sum(a * a, axis=1))
        scale = float(np.trace(np.diag(d) @ s_fix) / var) if var > 0 else 1.0
    t = mu_d - scale * r @ mu_s
    return r, t, scale


def associate(t_a: np.ndarray, t_b: np.ndarray, max_dt_s: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) of poses whose timestamps match within ``max_dt_s`` (nearest neighbour)."""
    t_a = np.asarray(t_a, dtype=float)
    t_b = np.asarray(t_b, dtype=float)
    j = np.clip(np.searchsorted(t_b, t_a), 1, len(t_b) - 1)
    left = np.abs(t_b[j - 1] - t_a) <= np.abs(t_b[j] - t_a)
    j = np.where(left, j - 1, j)
    ok = np.abs(t_b[j] - t_a) <= max_dt_s
    return np.flatnonzero(ok), j[ok]


def ate(truth_xyz: np.ndarray, estimate_xyz: np.ndarray) -> float:
    """Absolute trajectory error (m) of associated position pairs, as the paper computes it."""
    gt = np.asarray(truth_xyz, dtype=float)
    est = np.asarray(estimate_xyz, dtype=float)
    if gt.shape != est.shape or gt.ndim != 2 or gt.shape[1] != 3:
        raise MetricsError(f"ate: need two (N, 3) arrays of equal shape, got {gt.shape} and {est.shape}")
    if len(gt) < 3:
        raise MetricsError(f"ate: need at least 3 common poses, got {len(gt)}")
    if not (np.all(np.isfinite(gt)) and np.all(np.isfinite(est))):
        raise MetricsError("ate: NaN or infinite positions")
    r, t, _ = umeyama(est, gt)
    aligned = est @ r.T + t
    d = aligned[:, :2] - gt[:, :2]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))
