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
import logging
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from . import factors
from .config import FusionConfig, ScaleFormula, StateModel
from .counters import Counters
from .factors import X
from .metrics import umeyama
from .odometry_trust import SCALE_FIT_MIN_FIXES, SCALE_FIT_OUTLIER_FLOOR_M, SCALE_FIT_OUTLIER_SIGMA
from .track import Alignment, Track

log = logging.getLogger(__name__)

#: Fixes needed before the GPS initialisation may run. Source: a heading needs two displacements.
INIT_MIN_FIXES = 3

#: Scale samples needed for such an early initialisation. Source: robustness (issue 6).
INIT_STALL_MIN_SAMPLES = 5

#: Yaw σ of the prior on the first frame. Unit: deg. Source: by measurement.
INIT_PRIOR_YAW_SIGMA_DEG = 10.0

#: x/y σ of the prior on the first frame. Unit: m. Source: by measurement.
INIT_PRIOR_SIGMA_M = 5.0

#: Roll/pitch σ of the first frame's prior (pose3 state). Unit: deg. Source: by measurement.
INIT_PRIOR_TILT_SIGMA_DEG = 2.0

#: z σ of the first frame's prior (pose3 state). Unit: m. Source: by measurement.
INIT_PRIOR_Z_SIGMA_M = 1.0

#: A fix enters the scale windows only within this many of its σ (plus SCALE_OUTLIER_FLOOR_M) of its neighbours'
#: midpoint. Source: multipath rejection (issue 6).
SCALE_OUTLIER_SIGMA = 4.0

#: Added to that bound: a turn at city speed moves the midpoint by about 2.5 m at 1 Hz; by the square of the three
#: fixes' half-span beyond 1 s (fixes 5 s apart: 25 times). Unit: m. Source: issue 6.
SCALE_OUTLIER_FLOOR_M = 3.0

#: A fit needs the fixes to spread at least this far (RMS about their mean); a shorter stretch says little about
#: scale. Unit: m. Source: by measurement.
SCALE_FIT_MIN_EXTENT_M = 50.0

#: Fixes of this many last seconds enter a refit after initialisation. Unit: s. Source: by measurement.
SCALE_REFIT_WINDOW_S = 300.0


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

    def replace_positions(self, positions: list[np.ndarray]) -> None:
        """Replace the first ``len(positions)`` odometry positions (the frame was levelled)."""
        for i, p in enumerate(positions):
            self._odo_p[i] = p

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
            # a turn or a change of speed moves the midpoint by the square of the fixes' half-span
            floor = SCALE_OUTLIER_FLOOR_M * max(1.0, 0.25 * (t2 - t0) ** 2)
            if math.hypot(x1 - mx, y1 - my) > SCALE_OUTLIER_SIGMA * s1 + floor:
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
        """Median of the samples (of the last ``last`` if given) and its standard error over the samples."""
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


Fix = tuple[float, float, float, float]  # (t, x, y, sigma), ENU metres


class Initialiser:
    """The GPS initialisation and the scale's later refits: from fixes and the raw odometry to an
    :class:`~mapfusion.track.Alignment` of the odometry frame in the map frame.

    The windows' median (:class:`ScaleEstimator`) gives the scale; the heading is
    :func:`heading_offset`, the shift the median residual. A least-squares similarity fit over the
    fixes may then refine it (:meth:`fit`), but only where it agrees with the median within
    ``scale_fit_max_disagreement_sigma`` combined σ: drift inside the window can bend the
    odometry so that the fit absorbs it as scale.
    """

    def __init__(self, cfg: FusionConfig, gps_rate_hz: float, odometry_rate_hz: float) -> None:
        self.cfg = cfg
        self.scale_estimator = ScaleEstimator(cfg, gps_rate_hz, odometry_rate_hz)
        self.fixes: list[Fix] = []
        self.windows: ScaleEstimate | None = None  # the windows' median at initialisation
        self._fixes_since_fit = 0
        self._refit_from_t = -math.inf  # refits fit no fix before this (a re-scaling's time)

    def add_fix(self, t: float, x: float, y: float, sigma: float) -> None:
        """A fix before initialisation."""
        self.fixes.append((t, x, y, sigma))
        self.scale_estimator.add_gps(t, x, y, sigma)

    def try_align(self, track: Track) -> Alignment | None:
        """The alignment once the windows have enough samples (or GPS stalled with a few, or with too few but
        fixes spread far enough for a similarity fit: :meth:`_align_by_fit`), or None."""
        cfg = self.cfg
        if len(self.fixes) < INIT_MIN_FIXES or not track.t:
            return None
        est = self.scale_estimator.estimate()
        stalled = track.t[-1] - self.fixes[-1][0] > cfg.init_stall_s
        if est is None or not (self.scale_estimator.ready or stalled and est.samples >= INIT_STALL_MIN_SAMPLES):
            return self._align_by_fit(track, est) if stalled and cfg.init_fit_min_extent_m > 0 else None
        self._level(track)
        g = np.array([(t, x, y) for t, x, y, _ in self.fixes])
        g = g[g[:, 0] <= track.t[-1] + 1e-9]
        g = g[g[:, 0] >= track.t[0] - 1e-9]
        if len(g) < INIT_MIN_FIXES:
            return None
        odo_xyz = np.array([track.raw_at(t).translation() for t in g[:, 0]])
        rot = heading_offset(g[:, 1:3], odo_xyz[:, :2])
        if rot is None:
            return None
        s = est.scale
        c, sn = math.cos(rot), math.sin(rot)
        rxy = odo_xyz[:, :2] @ np.array([[c, sn], [-sn, c]]) * s
        trans = np.median(g[:, 1:3] - rxy, axis=0)
        self.windows = est
        log.info("initialised at t=%.1f s: scale %.4f ± %.4f from %d samples, heading offset %.2f°",
                 track.t[-1], s, est.sigma, est.samples, math.degrees(rot))
        return Alignment(s, est.sigma, rot, trans)

    def _level(self, track: Track) -> None:
        """The planar model's odometry frame levelled with every frame of the initialisation window (once)."""
        if self.cfg.state is StateModel.planar and track.level_rot is None:
            angle = track.level_frame()
            if angle is not None and angle > 0.0:
                self.scale_estimator.replace_positions([p.translation() for p in track.raw])
                log.info("odometry frame levelled by %.2f°", math.degrees(angle))

    def _align_by_fit(self, track: Track, est: ScaleEstimate | None) -> Alignment | None:
        """GPS stalled before the windows took ``INIT_STALL_MIN_SAMPLES`` samples — a drive whose fixes never
        spanned a chord of ``scale_min_distance_m`` (one that circled a block): the alignment is the least-squares
        similarity fit to the fixes (:meth:`fit`) when they spread ``init_fit_min_extent_m`` about their mean, or
        None (the engine waits for more fixes)."""
        self._level(track)
        a = self.fit(track, min_extent_m=self.cfg.init_fit_min_extent_m)
        if a is None:
            return None
        self.windows = ScaleEstimate(a.scale, a.scale_sigma, est.samples if est is not None else 0)
        log.info("initialised at t=%.1f s by a similarity fit to %d fixes (%d scale samples): scale %.4f ± %.4f, "
                 "heading offset %.2f°", track.t[-1], len(self.fixes), self.windows.samples, a.scale, a.scale_sigma,
                 math.degrees(a.rot_rad))
        return a

    def fit(self, track: Track, since_t: float = -math.inf, min_extent_m: float | None = None) -> Alignment | None:
        """Least-squares similarity between the raw odometry and the fixes after ``since_t``
        (outliers beyond the fit's bound of a first fit dropped), or None when there are too few
        fixes, too little motion (their RMS spread below ``min_extent_m``, by default
        ``SCALE_FIT_MIN_EXTENT_M``), or the fit disagrees with the windows' median."""
        cfg = self.cfg
        lo, hi = max(since_t, track.t[track.first] - 0.5), track.t[-1] + 0.5
        g = np.array([f for f in self.fixes if lo <= f[0] <= hi]).reshape(-1, 4)
        if len(g) < SCALE_FIT_MIN_FIXES:
            return None
        o = np.array([track.raw_at(t).translation()[:2] for t in g[:, 0]])
        keep = np.ones(len(g), dtype=bool)
        for _ in range(2):
            r, tr, sc = umeyama(o[keep], g[keep, 1:3], with_scale=True)
            resid = np.hypot(*(g[:, 1:3] - (sc * o @ r.T + tr)).T)
            keep = resid <= SCALE_FIT_OUTLIER_SIGMA * np.median(g[:, 3]) + SCALE_FIT_OUTLIER_FLOOR_M
            if keep.sum() < SCALE_FIT_MIN_FIXES:
                return None
        spread = float(np.sqrt(np.mean(np.sum((o[keep] - o[keep].mean(0)) ** 2, axis=1))))
        if spread * sc < (SCALE_FIT_MIN_EXTENT_M if min_extent_m is None else min_extent_m):
            return None
        sigma = float(np.median(g[keep, 3])) / (spread * math.sqrt(keep.sum()))
        limit = cfg.scale_fit_max_disagreement_sigma
        w = self.windows
        if limit > 0 and w is not None and abs(sc - w.scale) > limit * math.hypot(sigma, w.sigma):
            log.info("scale fit %.4f ± %.4f disagrees with the windows' median %.4f ± %.4f: kept the median",
                     sc, sigma, w.scale, w.sigma)
            return None
        return Alignment(float(sc), sigma, math.atan2(r[1, 0], r[0, 0]), tr)

    def rescaled(self, scale: float, sigma: float, t: float) -> None:
        """The odometry's scale was re-measured at time t (a GPS track run): later refits are judged against
        it and fit only the fixes from then on (the earlier ones measured the scale that broke)."""
        n = self.windows.samples if self.windows is not None else 1
        self.windows = ScaleEstimate(scale, sigma, n)
        self._refit_from_t = t

    def refit_with_fix(self, track: Track, t: float, x: float, y: float, sigma: float) -> Alignment | None:
        """A fix after initialisation: every ``scale_samples`` fixes, a refit over the last
        ``SCALE_REFIT_WINDOW_S`` (its scale and σ replace the current ones), else None."""
        self.fixes.append((t, x, y, sigma))
        self._fixes_since_fit += 1
        if self._fixes_since_fit < self.cfg.scale_samples:
            return None
        self._fixes_since_fit = 0
        return self.fit(track, max(t - SCALE_REFIT_WINDOW_S, self._refit_from_t))


@dataclass(frozen=True)
class Batch:
    """The frames buffered until initialisation, solved together."""

    poses: list[gtsam.Pose3]
    last_noise: gtsam.noiseModel.Base  # the last frame's marginal: the smoother's starting prior


def solve_initial_batch(cfg: FusionConfig, track: Track, alignment: Alignment, fixes: list[Fix],
                        between_for: Callable[[int], gtsam.NonlinearFactor], counters: Counters,
                        anchor: int = 0) -> Batch:
    """The buffered frames as one graph, solved by Levenberg–Marquardt: a prior on frame ``anchor`` (the
    first; the last after a cold start, where the alignment is known at the end), odometry between them
    (``between_for``), the window's fixes gated against the initial guess."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    guesses = [track.to_map(raw, alignment) for raw in track.raw]
    sig = factors.pose_sigmas(cfg.state, math.radians(INIT_PRIOR_YAW_SIGMA_DEG), INIT_PRIOR_SIGMA_M,
                              tilt_rad=math.radians(INIT_PRIOR_TILT_SIGMA_DEG), z_m=INIT_PRIOR_Z_SIGMA_M)
    graph.add(factors.pose_prior(anchor, guesses[anchor], factors.diagonal(sig)))
    values.insert(X(0), guesses[0])
    for k in range(1, len(track)):
        graph.add(between_for(k))
        values.insert(X(k), guesses[k])
    for t, x, y, sigma in fixes:
        if t < track.t[0] - 0.5 or t > track.t[-1] + 0.5:
            counters.gps_rejected_time += 1  # before the first frame, or ahead of the odometry
            continue
        g = guesses[track.frame_at(t)]
        # the guess itself is uncertain by about twice a fix's σ (it was fitted on them)
        if math.hypot(g.x() - x, g.y() - y) > cfg.gps_gate_sigma * math.hypot(sigma, 2.0 * sigma):
            counters.gps_rejected_gate += 1
            continue
        graph.add(factors.gps_factor(cfg.state, track.frame_at(t), x, y, None, sigma))
        counters.gps_used += 1
    params = gtsam.LevenbergMarquardtParams()
    params.setLinearSolverType("MULTIFRONTAL_QR" if cfg.factorization.value == "QR" else "MULTIFRONTAL_CHOLESKY")
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    last = len(track) - 1
    noise: gtsam.noiseModel.Base
    try:
        cov = gtsam.Marginals(graph, result).marginalCovariance(X(last))
        noise = gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T) + 1e-9 * np.eye(6))
    except RuntimeError:
        noise = factors.diagonal(sig)
    return Batch([result.atPose3(X(k)) for k in range(len(track))], noise)
