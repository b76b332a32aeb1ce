"""Curve fixes (``curve_fixes``, issue 17): where the estimate's recent path turned, that stretch registered on
the roads places the vehicle along its road.

Between turns nothing in the map says where along a road the vehicle is: the map priors and the band hold it across
the road, and along it the estimate drifts with the odometry's scale (a 1% wander is 10 m a kilometre). A bend or a
turn is different: the path's shape fits the roads at one place only. Every ``curve_fix_every_m`` of driving while
GPS is silent, when the estimate's last ``curve_fix_path_m`` turned by at least ``curve_fix_turn_deg`` (its axis's
turn: a turn back on the spot folds the path onto a line), that stretch is registered on the road way-points
(:func:`~mapfusion.register.register_on_roads`, on a ``curve_fix_cell_m`` grid within ``curve_fix_radius_m``). A
shift longer than ``curve_fix_min_shift_m`` and at most ``curve_fix_max_shift_m`` (short of the disc's edge, where
the true minimum may lie beyond it) that fits within ``curve_fix_max_rms_m``, beats every shift farther than
``curve_fix_separation_m`` from it by ``curve_fix_ratio`` and fits at least ``curve_fix_min_gain_m`` better than no
shift (a path that already lies on its roads cannot tell a few metres' shift from the map's drawing and the lanes)
enters the graph as a position fix on the current frame (σ ``curve_fix_sigma_m``). The path is then forgotten, so
no stretch of road is counted twice: fixes sharing one stretch's map error would outweigh the odometry
(docs/method.md, "Fixes along the road while the estimate agrees").
An odometry whose GPS window showed it drifting less than ``curve_fix_min_drift_ratio`` times what its configured σ
allows gets none: it knows where it is along the road better than a map's bends are drawn (KITTI's own poses on
OSM).
"""

from __future__ import annotations

import collections
import logging
import math

import gtsam
import numpy as np

from . import factors
from .config import FusionConfig
from .counters import Counters
from .register import register_on_roads
from .roadmap import RoadMap

log = logging.getLogger(__name__)

__all__ = ["CurveFixes"]


class CurveFixes:
    """The estimate's recent path while GPS is silent, and the fixes its turns give."""

    def __init__(self, road: RoadMap, cfg: FusionConfig, counters: Counters) -> None:
        self.road, self.cfg, self.counters = road, cfg, counters  # (counts curve_fixes)
        self.enabled = cfg.curve_fixes and cfg.use_map
        self.drift_ratio = math.inf  # the GPS window's odometry drift over the configured σ's (inf: no window)
        # (s, x, y, yaw, frame, t)
        self._path: collections.deque[tuple[float, float, float, float, int, float]] = collections.deque()
        self._s_m = 0.0  # path length since the path began
        self._since_m = 0.0  # driving since the last registration
        self.last_shift_m = (0.0, 0.0)  # the last fix's shift (map frame)
        self.last_path_k0 = -1  # the first frame of the last fix's path
        self._odo_m = 0.0  # driving since the engine began (never reset)
        self._odo_xy: tuple[float, float] | None = None
        self._priors_at: collections.deque[float] = collections.deque()  # the odometer at each recent map prior
        self._half_width_m = road.width_m(cfg.lane_width_m) / 2.0 if cfg.curve_fix_in_band else None

    def forget(self) -> None:
        """Start the path afresh: after a fix, a re-anchoring or a GPS fix the estimate moved."""
        self._path.clear()
        self._s_m = self._since_m = 0.0

    def note_priors(self, pred: gtsam.Pose3, prior: bool) -> None:
        """Count a frame's driving and whether it took a map prior (every frame, searching or not; nothing to count
        with ``curve_fix_min_priors`` 0)."""
        if self.cfg.curve_fix_min_priors <= 0:
            return
        x, y = pred.x(), pred.y()
        if self._odo_xy is not None:
            self._odo_m += math.hypot(x - self._odo_xy[0], y - self._odo_xy[1])
        self._odo_xy = (x, y)
        if prior:
            self._priors_at.append(self._odo_m)
        while self._priors_at and self._priors_at[0] < self._odo_m - self.cfg.curve_fix_prior_window_m:
            self._priors_at.popleft()

    def keeps_to_roads(self) -> bool:
        """Did the estimate take fewer than ``curve_fix_min_priors`` map priors over the last
        ``curve_fix_prior_window_m``?"""
        return len(self._priors_at) < self.cfg.curve_fix_min_priors

    def step(self, k: int, t: float, pred: gtsam.Pose3, last_gps_t: float = -math.inf) -> list[gtsam.NonlinearFactor]:
        """Frame k at time t with its predicted pose (map frame), the last used GPS fix's time: the fix's
        factors (none: no fix). Within ``road_fix_after_gps_s`` of a GPS fix the path starts afresh (GPS places
        the estimate)."""
        cfg = self.cfg
        if not self.enabled or self.drift_ratio < cfg.curve_fix_min_drift_ratio:
            return []
        if t - last_gps_t < cfg.road_fix_after_gps_s:
            self.forget()
            return []
        x, y, yaw = pred.x(), pred.y(), pred.rotation().yaw()
        if self._path:
            _, px, py, pyaw, _, _ = self._path[-1]
            moved = math.hypot(x - px, y - py)
            self._s_m += moved
            self._since_m += moved
            yaw = pyaw + math.remainder(yaw - pyaw, 2.0 * math.pi)  # unwrapped along the path
        self._path.append((self._s_m, x, y, yaw, k, t))
        while len(self._path) > 2 and self._s_m - self._path[1][0] >= cfg.curve_fix_path_m:
            self._path.popleft()
        if self._since_m < cfg.curve_fix_every_m or self._s_m - self._path[0][0] < cfg.curve_fix_path_m:
            return []
        self._since_m = 0.0
        path = np.asarray(self._path)
        # the turn of the path's axis (doubled angles): a turn back on the spot folds the path onto itself, a straight
        # line whatever its headings' range
        axis = np.unwrap(2.0 * path[:, 3]) / 2.0
        if math.degrees(axis.max() - axis.min()) < cfg.curve_fix_turn_deg:
            return []
        reg = register_on_roads(self.road, path[:, 1:3], cfg.curve_fix_radius_m, cell_m=cfg.curve_fix_cell_m,
                                cap_m=cfg.curve_fix_cap_m, separation_m=cfg.curve_fix_separation_m,
                                headings_rad=path[:, 3] if cfg.curve_fix_headings else None,
                                half_width_m=self._half_width_m)
        if reg is None or reg.shift_m > cfg.curve_fix_max_shift_m or \
                not reg.decisive(cfg.curve_fix_ratio, cfg.curve_fix_max_rms_m, cfg.curve_fix_min_shift_m):
            return []
        if self.keeps_to_roads() or reg.rms_unshifted_m - reg.rms_m < cfg.curve_fix_min_gain_m:
            self.counters.curve_fixes_gated += 1
            return []
        self.counters.curve_fixes += 1
        log.debug("curve fix at frame %d: shift (%.1f, %.1f) m, RMS %.2f m, runner-up %.2f m, unshifted %.2f m", k,
                  reg.dx_m, reg.dy_m, reg.rms_m, reg.runner_up_rms_m, reg.rms_unshifted_m)
        self.forget()
        self.last_shift_m, self.last_path_k0 = (reg.dx_m, reg.dy_m), int(path[0, 4])
        return self._fixes(path, reg.dx_m, reg.dy_m, t)

    def _fixes(self, path: np.ndarray, dx_m: float, dy_m: float, t: float) -> list[gtsam.NonlinearFactor]:
        """The shift as position factors on up to ``curve_fix_frames`` frames of the path (the current one last)."""
        cfg = self.cfg
        recent = np.flatnonzero(path[:, 5] >= t - 0.5 * cfg.lag_s)
        rows = recent[np.unique(np.round(np.linspace(len(recent) - 1, 0, min(cfg.curve_fix_frames, len(recent)))))
                      .astype(int)]
        sigma = cfg.curve_fix_sigma_m * math.sqrt(len(rows))
        return [factors.gps_factor(cfg.state, int(path[i, 4]), path[i, 1] + dx_m, path[i, 2] + dy_m, None, sigma)
                for i in rows]
