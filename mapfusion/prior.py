"""The map prior's noise (paper III.B Eq. 6, DESIGN item 3), in GTSAM's Pose3 tangent space.

In the world's x/y plane Σ = E Λ E⁻¹, with e₁ the normalised direction of motion, e₂ ⟂ e₁,
λ₁ = |v_lon| and λ₂ = |v_lat| (as variances, m²), floored so Σ is never singular. A Pose3
prior's error lives in the tangent space at its mean, ordered (rotation x, y, z, translation
x, y, z) with translation in the mean pose's own frame: the x/y block is rotated into that frame.
Roll, pitch and z get zero precision (the 2D map says nothing about them); yaw gets 1/σ_yaw².
With ``along_free`` the precision along the road is zero too. The result is a square-root
information matrix R (RᵀR = Λ), which GTSAM accepts with zero rows.
"""

from __future__ import annotations

import math

import numpy as np

from .config import PriorMode


def world_covariance(motion_dir_rad: float, v_lon_mps: float, v_lat_mps: float, floor_m2: float) -> np.ndarray:
    """Σ = E Λ E⁻¹ in the world x/y plane (2×2, symmetric positive definite)."""
    e1 = np.array([math.cos(motion_dir_rad), math.sin(motion_dir_rad)])
    e2 = np.array([-e1[1], e1[0]])
    e = np.column_stack([e1, e2])
    lam = np.diag([max(abs(v_lon_mps), floor_m2), max(abs(v_lat_mps), floor_m2)])
    return e @ lam @ np.linalg.inv(e)


def prior_sqrt_information(
    road_yaw_rad: float,
    motion_dir_rad: float,
    v_lon_mps: float,
    v_lat_mps: float,
    yaw_sigma_rad: float,
    floor_m2: float,
    mode: PriorMode,
) -> np.ndarray:
    """6×6 R with RᵀR the information of the map prior in the tangent space at the prior's mean."""
    sigma_w = world_covariance(motion_dir_rad, v_lon_mps, v_lat_mps, floor_m2)
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


def information(r: np.ndarray) -> np.ndarray:
    return r.T @ r
