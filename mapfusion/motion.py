"""Wheel speed and a yaw-rate gyro: a second motion source beside the odometry (issue 18).

Every car has both (ESC needs them) and neither cares about rain or darkness. :class:`WheelGyro`
buffers the samples and integrates them into planar steps (distance along the body's x axis from
the wheel's speed, yaw from the gyro's rate less its bias). It keeps two calibrations:

- the **gyro bias**: the gyro's turn beyond the odometry's over frames where the two agree, fitted as
  b·dt + c·ds (its bias per second beside the odometry's own yaw drift per metre), or beyond zero
  while the wheel says the vehicle stands still; least squares with exponential forgetting
  (``gyro_bias_time_constant_s``);
- the **wheel scale** (true metres per wheel metre): a similarity fit of the wheel + gyro
  dead-reckoned track to the GPS fixes of the last ``WHEEL_SCALE_WINDOW_S`` (where the wheels may
  slip, the odometry's distance), with its σ from the fit's residuals; until a fit is more certain
  than ``wheel_scale_sigma`` it stays 1. A calibrated wheel also gives the odometry's scale.

The engine asks for the step between two frame times (:meth:`WheelGyro.step`), checks the
odometry's own step against it (:func:`agrees`) and fuses the two (:func:`fuse_steps`), or uses it
alone where the odometry has no frames or jumped. Nothing here knows the factor graph.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
import math
from collections import deque
from dataclasses import dataclass

import gtsam
import numpy as np

from . import odometry_trust
from .config import FusionConfig
from .errors import InputError
from .geometry import wrap_angle
from .metrics import umeyama
from .track import Alignment, Track

log = logging.getLogger(__name__)

#: With no odometry frame for this long, wheel + gyro make the frames themselves (one per nominal odometry period),
#: so the estimate never stops where the camera fails. Unit: s. Source: issue 18: three frames at 10 Hz; a single
#: dropped frame is bridged by the VO itself.
WHEEL_FRAME_GAP_S = 0.3

#: The wheel scale is fitted (similarity of the wheel + gyro track to the fixes) over the fixes of this last
#: window. Unit: s. Source: issue 18: long enough for 0.1% from 1 Hz fixes of σ 2 m; short enough to follow tyre
#: warm-up.
WHEEL_SCALE_WINDOW_S = 300.0


class MotionInputError(InputError):
    """A wheel-speed or gyro sample the engine cannot take (non-finite, time going backwards)."""


#: Samples older than this (before the newest) are forgotten: a frame never spans more.
HISTORY_S = 120.0
#: A standstill: the wheel reads less than this (m/s) over the whole step.
STANDSTILL_MPS = 0.05
#: A bias sample's σ (the odometry's and the gyro's yaw noise over a frame), and the prior information
#: on (gyro bias rad/s, odometry yaw drift rad/m): wide on the bias, about a real VO's drift on c.
BIAS_SAMPLE_SIGMA_RAD = 2e-4
BIAS_PRIOR_INFO = np.diag([1.0 / 0.05**2, 1.0 / 1e-5**2])
#: Above this |acceleration| (m/s², from the wheel's speed over half a second) a wet road may slip the
#: wheels: the calibration takes the odometry's distance there (the sensor model slips above 1 m/s²).
SLIP_FREE_ACCEL_MPS2 = 0.7
#: The wheel scale fit needs this many fixes spanning this far (m) on the dead-reckoned track.
SCALE_FIT_MIN_FIXES, SCALE_FIT_MIN_EXTENT_M = 20, 100.0


@dataclass(frozen=True)
class PlanarStep:
    """A planar motion in the body frame of its start: forward, left (m), turn (rad), with σ's."""

    dx_m: float
    dy_m: float
    dyaw_rad: float
    sigma_along_m: float
    sigma_lateral_m: float
    sigma_yaw_rad: float

    @property
    def length_m(self) -> float:
        return math.hypot(self.dx_m, self.dy_m)


class _Series:
    """Time-ordered samples of one sensor, forgetting those older than HISTORY_S."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.t: list[float] = []
        self.v: list[float] = []

    def add(self, t: float, v: float) -> None:
        if not (math.isfinite(t) and math.isfinite(v)):
            raise MotionInputError(f"{self.name}: sample at t = {t} is not finite ({v})")
        if self.t and t <= self.t[-1]:
            raise MotionInputError(f"{self.name}: time {t} does not increase (previous {self.t[-1]})")
        self.t.append(t)
        self.v.append(v)
        if t - self.t[0] > 2 * HISTORY_S:  # drop in blocks: amortised O(1) per sample
            i = bisect.bisect_left(self.t, t - HISTORY_S)
            del self.t[:i], self.v[:i]

    def covers(self, t0: float, t1: float, tol_s: float) -> bool:
        return bool(self.t) and self.t[0] <= t0 + tol_s and self.t[-1] >= t1 - tol_s

    @property
    def last_t(self) -> float:
        return self.t[-1] if self.t else -math.inf

    def at(self, times: np.ndarray) -> np.ndarray:
        """Linear interpolation (held flat beyond the ends)."""
        lo = max(bisect.bisect_left(self.t, float(times[0])) - 1, 0)
        hi = bisect.bisect_right(self.t, float(times[-1])) + 1
        return np.interp(times, self.t[lo:hi], self.v[lo:hi])


class WheelGyro:
    """Wheel speed (m/s) and yaw rate (rad/s) samples, their calibrations, and planar steps."""

    def __init__(self, cfg: FusionConfig) -> None:
        self.cfg = cfg
        self.wheel = _Series("wheel speed")
        self.gyro = _Series("yaw rate")
        self.scale = 1.0
        self.scale_sigma = cfg.wheel_scale_sigma
        self.bias_radps = 0.0
        self._bias_weight = 0.0  # seconds of samples (with forgetting)
        self._bias_info, self._bias_vec = np.zeros((2, 2)), np.zeros(2)
        self._dr_t: deque[float] = deque()  # the dead-reckoned track (wheel metres, bias removed)
        self._dr_xy: deque[tuple[float, float]] = deque()
        self._dr_pose = (0.0, 0.0, 0.0)
        self._fixes: deque[tuple[float, float, float]] = deque()

    # ------------------------------------------------------------------ samples
    def add_wheel(self, t: float, speed_mps: float) -> None:
        self.wheel.add(float(t), float(speed_mps))

    def add_yaw_rate(self, t: float, yaw_rate_radps: float) -> None:
        self.gyro.add(float(t), float(yaw_rate_radps))

    @property
    def covered_until(self) -> float:
        """The latest time both sensors have reached."""
        return min(self.wheel.last_t, self.gyro.last_t)

    def covers(self, t0: float, t1: float) -> bool:
        tol = 0.05
        return self.wheel.covers(t0, t1, tol) and self.gyro.covers(t0, t1, tol)

    # ------------------------------------------------------------------ integration
    def _grid(self, t0: float, t1: float) -> np.ndarray:
        """t0, the gyro's sample times strictly between, and t1: where the rates are integrated."""
        gt = self.gyro.t
        return np.array([t0, *gt[bisect.bisect_right(gt, t0):bisect.bisect_left(gt, t1)], t1])

    def _integrate(self, t0: float, t1: float, scale: float) -> tuple[float, float, float]:
        """(forward, left, turn) from t0 to t1 in the body frame at t0: the wheel's distance turned by
        the gyro's yaw, midpoint rule on the union of the gyro's sample times."""
        grid = self._grid(t0, t1)
        w = self.gyro.at(grid) - self.bias_radps
        v = self.wheel.at(grid) * scale
        dt = np.diff(grid)
        dyaw = 0.5 * (w[1:] + w[:-1]) * dt
        yaw_end = np.cumsum(dyaw)
        yaw_mid = yaw_end - 0.5 * dyaw
        ds = 0.5 * (v[1:] + v[:-1]) * dt
        return float(np.sum(ds * np.cos(yaw_mid))), float(np.sum(ds * np.sin(yaw_mid))), float(yaw_end[-1])

    def step(self, t0: float, t1: float) -> PlanarStep:
        """The wheel + gyro step from t0 to t1 (the caller checks :meth:`covers`), with its σ's."""
        dx, dy, dyaw = self._integrate(t0, t1, self.scale)
        cfg, d = self.cfg, math.hypot(dx, dy)
        along = d * math.hypot(cfg.wheel_sigma_per_m, self.scale_sigma)
        return PlanarStep(dx, dy, dyaw, max(along, 1e-4), max(d * cfg.wheel_lateral_sigma_per_m, 1e-4),
                          max(cfg.gyro_sigma_radps * (t1 - t0), 1e-6))

    def accel_mps2(self, t: float) -> float:
        """|Acceleration| from the wheel's speed over the half second up to t."""
        v = self.wheel.at(np.array([t - 0.5, t]))
        return abs(float(v[1] - v[0])) / 0.5

    def raw_yaw_change(self, t0: float, t1: float) -> float:
        """The gyro's integrated yaw (bias not removed) from t0 to t1."""
        times = self._grid(t0, t1)
        w = self.gyro.at(times)
        return float(np.sum(0.5 * (w[1:] + w[:-1]) * np.diff(times)))

    # ------------------------------------------------------------------ calibration
    def observe_yaw(self, t0: float, t1: float, reference_dyaw_rad: float | None, distance_m: float = 0.0) -> None:
        """A bias sample: the gyro's yaw change over [t0, t1] beyond a trusted one (the odometry's, which
        drives ``distance_m``), or beyond zero at a standstill (``reference_dyaw_rad`` None: used only if
        the wheel stands).

        The excess is b·dt + c·ds: the gyro's bias b per second and the odometry's own yaw drift c per
        metre (which a bias learnt from it alone would inherit: at 28 m/s a VO drifting 8e-6 rad/m looks
        like a gyro bias of 2e-4 rad/s). Both are fitted by least squares with exponential forgetting;
        a weak prior on c keeps b determined at constant speed (then the two cannot be told apart)."""
        dt = t1 - t0
        if dt <= 0:
            return
        if reference_dyaw_rad is None:
            if float(np.max(np.abs(self.wheel.at(np.array([t0, 0.5 * (t0 + t1), t1]))))) >= STANDSTILL_MPS:
                return
            reference_dyaw_rad, distance_m = 0.0, 0.0
        excess = wrap_angle(self.raw_yaw_change(t0, t1) - reference_dyaw_rad)
        forget = math.exp(-dt / self.cfg.gyro_bias_time_constant_s)
        row = np.array([dt, distance_m])
        self._bias_info = self._bias_info * forget + np.outer(row, row) / BIAS_SAMPLE_SIGMA_RAD**2
        self._bias_vec = self._bias_vec * forget + row * excess / BIAS_SAMPLE_SIGMA_RAD**2
        self._bias_weight = self._bias_weight * forget + dt
        if self._bias_weight >= 1.0:
            self.bias_radps = float(np.linalg.solve(self._bias_info + BIAS_PRIOR_INFO, self._bias_vec)[0])

    def advance(self, t0: float, t1: float, step: PlanarStep, dyaw_rad: float | None = None,
                distance_m: float | None = None) -> None:
        """Extend the dead-reckoned track (unit wheel scale) by a frame's wheel step, for the scale fit;
        ``dyaw_rad``: a better turn than the gyro's (the step fused with the odometry); ``distance_m``: a
        better distance in uncalibrated wheel metres (the odometry's, where the wheels may slip)."""
        d = step.length_m / self.scale if distance_m is None else distance_m
        turn = step.dyaw_rad if dyaw_rad is None else dyaw_rad
        x, y, yaw = self._dr_pose
        mid = yaw + 0.5 * turn
        self._dr_pose = (x + d * math.cos(mid), y + d * math.sin(mid), yaw + turn)
        if not self._dr_t or t0 != self._dr_t[-1]:
            self._dr_t.clear()  # a break in the frames: the fit starts again
            self._dr_xy.clear()
            self._fixes.clear()
            self._dr_t.append(t0)
            self._dr_xy.append((x, y))
        self._dr_t.append(t1)
        self._dr_xy.append(self._dr_pose[:2])
        while self._dr_t[0] < t1 - WHEEL_SCALE_WINDOW_S - 10.0:
            self._dr_t.popleft()
            self._dr_xy.popleft()

    def add_fix(self, t: float, x_m: float, y_m: float) -> None:
        """A GPS fix (map ENU): refit the wheel scale over the window's fixes."""
        self._fixes.append((t, x_m, y_m))
        while self._fixes[0][0] < t - WHEEL_SCALE_WINDOW_S:
            self._fixes.popleft()
        self._fit_scale()

    def _fit_scale(self) -> None:
        if len(self._fixes) < SCALE_FIT_MIN_FIXES or not self._dr_t:
            return
        f = np.array(self._fixes)
        dr_t = np.fromiter(self._dr_t, float)
        f = f[(f[:, 0] >= dr_t[0]) & (f[:, 0] <= dr_t[-1])]  # fixes on the dead-reckoned track
        if len(f) < SCALE_FIT_MIN_FIXES:
            return
        xy = np.array(self._dr_xy)
        src = np.column_stack([np.interp(f[:, 0], dr_t, xy[:, 0]), np.interp(f[:, 0], dr_t, xy[:, 1])])
        if np.ptp(src, axis=0).max() < SCALE_FIT_MIN_EXTENT_M:
            return
        dst = f[:, 1:]
        for _ in range(2):  # a second pass without the multipath outliers the first one shows
            r, t, s = umeyama(src, dst, with_scale=True)
            res = np.linalg.norm(dst - (s * src @ r.T + t), axis=1)
            keep = res <= 3.0 * 1.4826 * float(np.median(res)) + 1.0
            if keep.all() or keep.sum() < SCALE_FIT_MIN_FIXES:
                break
            src, dst = src[keep], dst[keep]
        centred = src - src.mean(axis=0)
        spread = math.sqrt(float(np.mean(np.sum(centred * centred, axis=1))))
        sigma_res = math.sqrt(float(np.mean(res * res)) / 2.0)
        sigma = sigma_res / (spread * math.sqrt(len(src)))  # var(s) = σ²/Σ|a|² for the fit's s = Σ b·Ra/Σ|a|²
        if sigma < self.cfg.wheel_scale_sigma:  # the window's latest fit, never held against an older one
            self.scale, self.scale_sigma = s, sigma


def agrees(cfg: FusionConfig, odo: PlanarStep, wheel: PlanarStep) -> bool:
    """Whether the odometry's step (metric, planar) lies inside the wheel + gyro step's gate."""
    gate = cfg.wheel_gate_m + cfg.wheel_gate_fraction * wheel.length_m
    off = math.hypot(odo.dx_m - wheel.dx_m, odo.dy_m - wheel.dy_m)
    return off <= gate and abs(wrap_angle(odo.dyaw_rad - wheel.dyaw_rad)) <= math.radians(cfg.wheel_gate_deg)


def fuse_steps(odo: PlanarStep, wheel: PlanarStep) -> PlanarStep:
    """Inverse-variance mean of two planar steps, axis by axis (forward, left, turn)."""

    def mean(a: float, sa: float, b: float, sb: float) -> tuple[float, float]:
        wa, wb = 1.0 / (sa * sa), 1.0 / (sb * sb)
        return (wa * a + wb * b) / (wa + wb), math.sqrt(1.0 / (wa + wb))

    dx, sx = mean(odo.dx_m, odo.sigma_along_m, wheel.dx_m, wheel.sigma_along_m)
    dy, sy = mean(odo.dy_m, odo.sigma_lateral_m, wheel.dy_m, wheel.sigma_lateral_m)
    dyaw, syaw = mean(odo.dyaw_rad, odo.sigma_yaw_rad,
                      odo.dyaw_rad + wrap_angle(wheel.dyaw_rad - odo.dyaw_rad), wheel.sigma_yaw_rad)
    return PlanarStep(dx, dy, dyaw, sx, sy, syaw)


def _odometry_sigmas(cfg: FusionConfig, length_m: float, factor: float = 1.0) -> tuple[float, float]:
    """The odometry step's translation σ per axis and yaw σ, as its factor states them (``factor``: the learned
    odometry σ's)."""
    return (factor * math.hypot(cfg.odometry_sigma_after_init_m, cfg.odometry_sigma_per_m * length_m),
            factor * math.radians(math.hypot(cfg.odometry_rot_sigma_deg, cfg.odometry_rot_sigma_deg_per_m * length_m)))


def _as_raw(step: PlanarStep, metres_per_unit: float, like: gtsam.Pose3 | None) -> gtsam.Pose3:
    """A metric planar step as a raw odometry step (the odometry's units; its roll, pitch and height
    change kept from ``like``)."""
    rot = gtsam.Rot3.Yaw(step.dyaw_rad)
    dz = 0.0
    if like is not None:
        r = like.rotation()
        rot = gtsam.Rot3.Ypr(step.dyaw_rad, r.pitch(), r.roll())
        dz = like.z()
    return gtsam.Pose3(rot, gtsam.Point3(step.dx_m / metres_per_unit, step.dy_m / metres_per_unit, dz))


class MotionFusion:
    """Which step goes into a frame when wheel speed and gyro are fed: the odometry's fused with
    theirs where the two agree, theirs alone where the odometry jumped or has no frame, and when
    the engine must make a frame itself (no odometry frame for ``WHEEL_FRAME_GAP_S``)."""

    MIN_RATIO_STEP_M, MIN_RATIOS = 0.2, 5
    #: The odometry's scale against the calibrated wheel: over agreeing steps, forgetting with this
    #: time constant (s), once they cover MIN_SCALE_DISTANCE_M.
    SCALE_TIME_CONSTANT_S, MIN_SCALE_DISTANCE_M = 120.0, 100.0

    def __init__(self, cfg: FusionConfig, counters) -> None:
        self.cfg = cfg
        self.counters = counters
        self.wg = WheelGyro(cfg)
        self.last_odometry_t: float | None = None  # the odometry's own latest frame
        self._first_sample_t: float | None = None
        self._ratios: deque[float] = deque(maxlen=51)  # wheel metres per odometry unit, step by step
        self._before_init: dict[float, tuple[float, gtsam.Pose3]] = {}  # t → (units per wheel metre, step made)
        self._restated: tuple[float, float] | None = None
        self._wheel_m = self._odometry_units = 0.0  # over agreeing steps, with forgetting (uncalibrated metres)
        self.sigma_factor = 1.0  # the learned odometry σ's factor (set at initialisation)

    def learn_sigma(self, track: Track, alignment: Alignment, fixes: list) -> None:
        """``odometry_sigma_learned``: the initialisation window's fixes set the factor on the odometry's σ
        (:mod:`.odometry_trust`)."""
        if self.cfg.odometry_sigma_learned and fixes:
            trust = odometry_trust.from_window(self.cfg, track, alignment, fixes)
            if trust is not None:
                self.sigma_factor = trust.factor
                log.info("odometry σ × %.3f: the window's drift %.2f-%.2f m against %.2f m at the configured σ "
                         "(%d fixes)", trust.factor, trust.drift_low_m, trust.drift_m, trust.model_m, trust.fixes)

    def cold_start(self) -> None:
        """A cold start on the map: no window measured the odometry's drift (``odometry_sigma_cold_factor``)."""
        if self.cfg.odometry_sigma_learned:
            self.sigma_factor = self.cfg.odometry_sigma_cold_factor

    def odometry_seen(self, t: float) -> None:
        """The odometry's own frame at t has been taken."""
        self.last_odometry_t = t

    @property
    def active(self) -> bool:
        return bool(self.wg.wheel.t) and bool(self.wg.gyro.t)

    def add_wheel(self, t: float, speed_mps: float) -> None:
        self.wg.add_wheel(t, speed_mps)
        self._first_sample_t = t if self._first_sample_t is None else self._first_sample_t

    def add_yaw_rate(self, t: float, yaw_rate_radps: float) -> None:
        self.wg.add_yaw_rate(t, yaw_rate_radps)
        self._first_sample_t = t if self._first_sample_t is None else self._first_sample_t

    def same_frame_s(self, t_last_frame: float) -> float:
        """How far (s) an odometry frame may lie behind or just after the engine's last frame and be that
        frame: 1 µs when wheel and gyro made it (their frame times are sums of periods), else 0."""
        made = self.active and (self.last_odometry_t is None or self.last_odometry_t < t_last_frame - 1e-9)
        return 1e-6 if made else 0.0

    def rejoin(self, t_last_frame: float) -> bool:
        """An odometry frame at (or within :meth:`same_frame_s` of) the engine's last frame: True, and the
        odometry's next step counts from there, when wheel and gyro made that frame; else False."""
        if not self.same_frame_s(t_last_frame):
            return False
        self.last_odometry_t = t_last_frame
        return True

    def metres_per_unit(self, scale: float | None) -> float | None:
        """The odometry's scale: the engine's once initialised, else the wheel's median ratio."""
        if scale:
            return scale
        return float(np.median(self._ratios)) if len(self._ratios) >= self.MIN_RATIOS else None

    def odometry_scale(self) -> tuple[float, float] | None:
        """Metres per odometry unit from the calibrated wheel (and its σ), or None until the wheel's scale
        is known to a quarter of its prior σ over enough distance."""
        wg = self.wg
        if wg.scale_sigma > 0.25 * self.cfg.wheel_scale_sigma or self._wheel_m < self.MIN_SCALE_DISTANCE_M:
            return None
        scale = wg.scale * self._wheel_m / self._odometry_units
        return scale, scale * wg.scale_sigma

    def rescale(self, a: Alignment) -> Alignment:
        """The alignment with the wheel's odometry scale where it has one (see :meth:`odometry_scale`)."""
        s = self.odometry_scale() if self.active else None
        return a if s is None else dataclasses.replace(a, scale=s[0], scale_sigma=s[1])

    def odometry_step(self, t_prev: float, t: float, rel: gtsam.Pose3, scale: float | None) -> gtsam.Pose3 | None:
        """The raw step into the odometry's frame at ``t`` (the engine's previous frame at ``t_prev``), or
        None where wheel and gyro cannot judge it (the caller's jump guard then does)."""
        joined = self.last_odometry_t == t_prev  # the odometry's step spans the engine's
        self.last_odometry_t = t
        if not self.wg.covers(t_prev, t):
            return None
        wheel = self.wg.step(t_prev, t)
        raw_len = math.hypot(rel.x(), rel.y())
        if joined and wheel.length_m >= self.MIN_RATIO_STEP_M and raw_len > 0:
            self._ratios.append(wheel.length_m / raw_len)
        u = self.metres_per_unit(scale)
        if u is None:
            self.wg.advance(t_prev, t, wheel)
            return None
        if joined:
            s_xy, s_yaw = _odometry_sigmas(self.cfg, raw_len * u, self.sigma_factor)
            odo = PlanarStep(rel.x() * u, rel.y() * u, rel.rotation().yaw(), s_xy, s_xy, s_yaw)
            if agrees(self.cfg, odo, wheel):
                self.wg.observe_yaw(t_prev, t, odo.dyaw_rad, wheel.length_m)
                fused = fuse_steps(odo, wheel)
                self.wg.advance(t_prev, t, wheel, fused.dyaw_rad, self._slip_free(t_prev, t, wheel, raw_len))
                return _as_raw(fused, u, rel)
            self.counters.odometry_vetoed += 1
            log.info("t = %.2f s: the odometry's step disagrees with wheel + gyro by %.2f m: replaced",
                     t, math.hypot(odo.dx_m - wheel.dx_m, odo.dy_m - wheel.dy_m))
        self.wg.advance(t_prev, t, wheel)
        return self._made(t, wheel, u, scale)

    def _slip_free(self, t_prev: float, t: float, wheel: PlanarStep, raw_len: float) -> float | None:
        """At a steady speed the step's wheel and odometry distances enter their ratio (the odometry's
        scale against the wheel); under hard acceleration or braking, where a wet road slips the wheels,
        the odometry's distance times that ratio is the step's wheel distance for the calibration fit
        (returned; None: the wheel's own)."""
        if wheel.length_m < self.MIN_RATIO_STEP_M:  # slow: the odometry's noise is most of its step
            return None
        if self.wg.accel_mps2(t) < SLIP_FREE_ACCEL_MPS2:
            forget = math.exp(-(t - t_prev) / self.SCALE_TIME_CONSTANT_S)
            self._wheel_m = self._wheel_m * forget + wheel.length_m / self.wg.scale
            self._odometry_units = self._odometry_units * forget + raw_len
            return None
        return raw_len * self._wheel_m / self._odometry_units if self._odometry_units > 0 else None

    def frame_due(self, t_last: float | None, period_s: float) -> float | None:
        """The time of a frame wheel and gyro should make now (the odometry silent), or None."""
        if not self.active:
            return None
        until = self.wg.covered_until
        since = self.last_odometry_t if self.last_odometry_t is not None else self._first_sample_t
        if since is None or until - since <= WHEEL_FRAME_GAP_S:
            return None
        if t_last is None:
            return until
        t = t_last + period_s
        return t if t <= until + 1e-9 else None

    def wheel_step(self, t_prev: float, t: float, scale: float | None) -> gtsam.Pose3:
        """The raw step of a frame wheel and gyro make alone."""
        wheel = self.wg.step(t_prev, t)
        self.wg.observe_yaw(t_prev, t, None)
        self.wg.advance(t_prev, t, wheel)
        self.counters.wheel_frames += 1
        return self._made(t, wheel, self.metres_per_unit(scale) or 1.0, scale)

    def _made(self, t: float, wheel: PlanarStep, u: float, scale: float | None) -> gtsam.Pose3:
        """A raw step from wheel and gyro alone; one made before initialisation is remembered, so that
        the wheel's later calibration can restate it (:meth:`restate`)."""
        rel = _as_raw(wheel, u, None)
        if scale is None:
            self._before_init[t] = (u / self.wg.scale, rel)
        return rel

    def restate(self, track: Track, scale_estimator) -> None:
        """Before initialisation, the frames wheel and gyro made restated with the wheel's latest
        calibration and the odometry's latest scale (a drive that starts in a tunnel makes its first
        frames before either is known: 2% of a kilometre is 20 m); the scale windows' positions with them."""
        wg = self.wg
        if not self._before_init or wg.scale_sigma > 0.25 * self.cfg.wheel_scale_sigma:
            return
        s, ratio = self.odometry_scale(), self.metres_per_unit(None)  # (the latter in uncalibrated wheel metres)
        m_now = s[0] if s is not None else (ratio or 1.0) * wg.scale
        if (wg.scale, m_now) == self._restated:
            return
        self._restated = (wg.scale, m_now)
        steps = {}
        for k, t in track.t.held():
            made = self._before_init.get(t)
            if made is not None:
                f = made[0] * wg.scale / m_now
                r = made[1]
                steps[k] = gtsam.Pose3(r.rotation(), gtsam.Point3(r.x() * f, r.y() * f, r.z()))
        positions = track.restate_steps(steps)
        if positions is not None:
            scale_estimator.replace_positions(positions)
