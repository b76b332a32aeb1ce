"""GPS initialisation (paper III.C, DESIGN item 4): scale, heading and position of the odometry frame.

Scale: the paper's windows. With md (m), ms (km/h), f_gps and f_vo (Hz),
C_gps = ⌈md·3.6·f_gps/ms⌉ and C_vo = round(C_gps·f_vo/f_gps). A window opens at a fix and closes
at the first later fix at least md away; if it needed more than C_gps fixes (or C_vo odometry
frames) the vehicle was too slow and no sample is taken. A sample is the ratio of speeds
(‖d_gps‖/t_gps)/(‖d_vo‖/t_vo) (default) or the paper's printed S = ‖d_gps‖²/‖d_vo‖²·t_vo/t_gps;
the scale is the median of ``scale_samples`` samples. Windows slide by one fix.

Distances are chords (first to last position of the window), not summed paths: the summed path
of noisy fixes is longer than the true path by about σ²/d per segment (tens of percent for 1 Hz
fixes in town), the bias that made a 30 s window overestimate the scale by 6%.

Multipath outliers would poison many overlapping windows at once, so a fix enters the windows one
fix late, and only if it lies within 4σ + 3 m of the midpoint of its two neighbours (a turn at
city speed moves that midpoint by about 2.5 m at 1 Hz).

Heading: the length-weighted circular mean, over consecutive fixes, of the GPS displacement's
heading minus the odometry displacement's heading over the same times.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from .config import FusionConfig, ScaleFormula


def window_counts(cfg: FusionConfig, f_gps_hz: float, f_vo_hz: float) -> tuple[int, int]:
    """(C_gps, C_vo) of paper Eq. (5)."""
    c_gps = math.ceil(cfg.scale_min_distance_m * 3.6 * f_gps_hz / cfg.scale_min_speed_kmh)
    c_vo = round(c_gps * f_vo_hz / f_gps_hz)
    return max(c_gps, 2), max(c_vo, 2)


def scale_sample(d_gps: float, t_gps: float, d_vo: float, t_vo: float, formula: ScaleFormula) -> float:
    """One scale sample from the GPS and odometry distances and durations of a window."""
    if formula is ScaleFormula.paper:
        return (d_gps * d_gps) / (d_vo * d_vo) * (t_vo / t_gps)
    return (d_gps / t_gps) / (d_vo / t_vo)


@dataclass(frozen=True)
class ScaleEstimate:
    scale: float
    sigma: float  # standard error of the median (from the MAD of the samples)
    samples: int


class ScaleEstimator:
    """Collects scale samples from GPS fixes and raw (unscaled) odometry positions."""

    def __init__(self, cfg: FusionConfig, f_gps_hz: float, f_vo_hz: float) -> None:
        self.cfg = cfg
        self.c_gps, self.c_vo = window_counts(cfg, f_gps_hz, f_vo_hz)
        self._fixes: deque[tuple[float, float, float]] = deque()
        self._recent: deque[tuple[float, float, float, float]] = deque(maxlen=3)  # (t, x, y, sigma)
        self.rejected = 0
        self._odo_t: list[float] = []
        self._odo_p: list[np.ndarray] = []
        self.samples: list[float] = []

    def add_odometry(self, t: float, position_odo: np.ndarray) -> None:
        self._odo_t.append(float(t))
        self._odo_p.append(np.asarray(position_odo, dtype=float))

    def _odo_at(self, t: float) -> tuple[np.ndarray, float, int] | None:
        """Odometry position at the frame nearest to t, that frame's time and index."""
        ts = self._odo_t
        if not ts or t < ts[0] - 1.0 or t > ts[-1] + 1.0:
            return None
        i = min(bisect.bisect_left(ts, t), len(ts) - 1)
        if i > 0 and abs(ts[i - 1] - t) <= abs(ts[i] - t):
            i -= 1
        return self._odo_p[i], ts[i], i

    def add_gps(self, t: float, x: float, y: float, sigma_m: float = 2.0) -> float | None:
        """Add a fix (ENU metres). The fix before it is checked against its neighbours and, if
        consistent, closes windows; returns the newest sample if one was taken."""
        self._recent.append((float(t), float(x), float(y), float(sigma_m)))
        if len(self._recent) == 3:
            (t0, x0, y0, _), (t1, x1, y1, s1), (t2, x2, y2, _) = self._recent
            w = (t1 - t0) / (t2 - t0) if t2 > t0 else 0.5
            mx, my = x0 + w * (x2 - x0), y0 + w * (y2 - y0)
            if math.hypot(x1 - mx, y1 - my) > 4.0 * s1 + 3.0:
                self.rejected += 1
                self._recent.remove((t1, x1, y1, s1))
                return None
            return self._window(t1, x1, y1)
        return None

    def _window(self, t: float, x: float, y: float) -> float | None:
        self._fixes.append((t, x, y))
        new = None
        while len(self._fixes) >= 2:
            t0, x0, y0 = self._fixes[0]
            t1, x1, y1 = self._fixes[-1]
            n_fix = len(self._fixes)
            if n_fix > self.c_gps:
                self._fixes.popleft()  # too slow: the window ran out of fixes before md
                continue
            d_gps = math.hypot(x1 - x0, y1 - y0)
            if d_gps < self.cfg.scale_min_distance_m:
                break
            a, b = self._odo_at(t0), self._odo_at(t1)
            if a is not None and b is not None and (b[2] - a[2]) <= self.c_vo:
                d_vo = float(np.linalg.norm(b[0] - a[0]))
                t_vo = b[1] - a[1]
                if d_vo > 1e-6 and t_vo > 0 and t1 > t0:
                    new = scale_sample(d_gps, t1 - t0, d_vo, t_vo, self.cfg.scale_formula)
                    self.samples.append(new)
            self._fixes.popleft()  # slide the window by one fix
        return new

    @property
    def ready(self) -> bool:
        return len(self.samples) >= self.cfg.scale_samples

    def estimate(self, last: int | None = None) -> ScaleEstimate | None:
        """Median of the samples (of the last ``last`` if given) and its standard error."""
        s = np.asarray(self.samples if last is None else self.samples[-last:])
        if len(s) == 0:
            return None
        med = float(np.median(s))
        mad = float(np.median(np.abs(s - med)))
        sigma = 1.4826 * mad * 1.2533 / math.sqrt(len(s))  # σ of a median ≈ 1.2533 σ/√n
        return ScaleEstimate(med, sigma, len(s))


def heading_offset(gps_xy: np.ndarray, odo_xy: np.ndarray, min_step_m: float = 1.0) -> float | None:
    """Rotation (rad) taking odometry headings to ENU: the length-weighted circular mean, over
    successive fixes at least ``min_step_m`` apart, of the GPS displacement heading minus the
    odometry displacement heading over the same times. Fixes closer than that to the last kept one
    are skipped, so 10 Hz fixes at walking pace still give headings (from their longer chords)."""
    g = np.asarray(gps_xy, dtype=float)
    o = np.asarray(odo_xy, dtype=float)
    if len(g) < 2:
        return None
    keep = [0]
    for i in range(1, len(g)):
        if math.hypot(g[i, 0] - g[keep[-1], 0], g[i, 1] - g[keep[-1], 1]) > min_step_m:
            keep.append(i)
    g, o = np.diff(g[keep], axis=0), np.diff(o[keep], axis=0)
    lg, lo = np.hypot(*g.T), np.hypot(*o.T)
    ok = lo > 1e-6
    if not ok.any():
        return None
    d = np.arctan2(g[ok, 1], g[ok, 0]) - np.arctan2(o[ok, 1], o[ok, 0])
    w = lg[ok]
    return float(math.atan2(np.sum(w * np.sin(d)), np.sum(w * np.cos(d))))
