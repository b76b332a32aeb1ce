"""Calibrating the sensor presets against the paper's odometry-only results (Tables I–IV).

The paper's baselines are odometry initialised with GPS (heading, scale and position) and run
without the map. Until the engine's own baseline is used here, :func:`gps_initialise` stands in
for its initialisation: a 2D similarity (scale, rotation, translation) fitted between the
odometry and the GPS fixes of the initialisation window, applied to the whole odometry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mapfusion.metrics import ate, umeyama

from .sensors import GpsOutput, OdometryOutput, Truth


def gps_initialise(odo: OdometryOutput, gps: GpsOutput, init_window_s: float) -> np.ndarray:
    """Odometry positions (M, 3) in the map frame after GPS initialisation from the fixes of the
    first ``init_window_s`` seconds (2D similarity; heights are left as the odometry has them)."""
    t0 = odo.t_s[0]
    sel = (gps.t_s <= t0 + init_window_s) & ~gps.outlier
    if sel.sum() < 3:
        raise ValueError("gps_initialise: fewer than 3 fixes in the initialisation window")
    ox = np.interp(gps.t_s[sel], odo.t_s, odo.poses[:, 0, 3])
    oy = np.interp(gps.t_s[sel], odo.t_s, odo.poses[:, 1, 3])
    r, t, s = umeyama(np.column_stack([ox, oy]), np.column_stack([gps.x_m[sel], gps.y_m[sel]]), with_scale=True)
    xy = s * odo.poses[:, :2, 3] @ r.T + t
    return np.column_stack([xy, odo.poses[:, 2, 3]])


@dataclass(frozen=True)
class OdometryOnlyResult:
    ate_m: float
    driven_m: float
    frames_out: int
    frames: int
    reinits: int

    @property
    def delocalized(self) -> bool:
        return self.ate_m > 20.0


def odometry_only_ate(truth: Truth, odo: OdometryOutput, gps: GpsOutput, init_window_s: float) -> OdometryOnlyResult:
    """ATE of GPS-initialised odometry against the truth (the paper's odometry baseline)."""
    est = gps_initialise(odo, gps, init_window_s)
    gt = np.column_stack([truth.x_m, truth.y_m, truth.z_m])[odo.frame_index]
    driven = float(np.sum(np.hypot(np.diff(truth.x_m), np.diff(truth.y_m))))
    reinits = sum(1 for _, k in odo.events if k == "reinit")
    return OdometryOnlyResult(ate(gt, est), driven, len(odo.t_s), len(truth), reinits)


def _finite(x: float) -> float:
    return x if math.isfinite(x) else float("nan")
