"""The Map-Fusion engine (paper III, DESIGN "The method" items 3–7): a GTSAM factor graph of
odometry, GPS and map priors.

:class:`MapFusion` takes measurements and returns estimates; it owns no files and prints
nothing. It coordinates the parts, each in its own module: the frames (:mod:`.track`), the GPS
initialisation and scale (:mod:`.initialisation`), the road association and map prior
(:mod:`.association`), the GPS gate (:mod:`.gps_gate`), every factor and noise model
(:mod:`.factors`) and the smoother with its re-anchoring (:mod:`.smoother`).

One Pose3 per odometry frame (key ``x<k>``); odometry enters as BetweenFactorPose3, GPS as
GPSFactor, the map as a prior on a frame whose predicted pose lies farther from its road than
the road is wide. Until the GPS initialisation has its scale the frames are only buffered (no
estimate exists in the map frame before heading and scale are known); at initialisation they
are solved as one batch and the smoother starts from the last of them.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import gtsam
import numpy as np

from . import factors, odometry_trust
from .association import MapAssociation
from .config import FusionConfig
from .counters import Counters
from .errors import EngineError
from .gps_gate import GpsGate, GpsQueue, Verdict
from .motion import MotionFusion
from .initialisation import Initialiser, solve_initial_batch
from .roadmap import RoadMap
from .smoother import Smoother
from .stream import OnFinal, Release
from .searching import MapSearching
from .track import Alignment, JumpGuard, planar_of, track_for
from .tracking import RoadFixes, RoadFixing

log = logging.getLogger(__name__)

__all__ = ["MapFusion", "EngineError"]


def _as_pose3(pose) -> tuple[gtsam.Pose3, bool]:
    """The pose as a gtsam.Pose3, and whether it is finite (checked on the array when one is given)."""
    if isinstance(pose, gtsam.Pose3):
        return pose, _finite_pose(pose)
    m = np.asarray(pose, dtype=float)
    if m.shape != (4, 4):
        raise EngineError(f"relative pose must be a gtsam.Pose3 or a 4×4 array, got shape {m.shape}")
    return gtsam.Pose3(m), math.isfinite(sum(m[:3].ravel().tolist()))  # (a NaN or an infinity makes the sum one)


def _gps_sigma(sigma_m: float | None, default_m: float) -> float:
    """A fix's σ: its own, or the configured one for None or NaN; never a σ ≤ 0 silently replaced."""
    if sigma_m is None or math.isnan(sigma_m):
        return default_m
    if not 0.0 < sigma_m < math.inf:
        raise EngineError(f"GPS sigma_m must be > 0 and finite (None or NaN: the configured σ), got {sigma_m}")
    return float(sigma_m)


def _finite_pose(p: gtsam.Pose3) -> bool:
    return bool(np.all(np.isfinite(p.matrix())))


class _Readings:
    """The engine's read-only figures (scale, σ, calibrations): kept apart from the engine's logic."""

    alignment: Alignment | None
    initialiser: Initialiser
    _motion: MotionFusion
    _pos_sigma: float

    @property
    def initialised(self) -> bool:
        return self.alignment is not None

    @property
    def scale(self) -> float | None:
        """The odometry's scale (map metres per odometry unit), None before initialisation."""
        return None if self.alignment is None else self.alignment.scale

    scale_sigma = property(lambda self: None if self.alignment is None else self.alignment.scale_sigma)
    wheel_scale = property(lambda self: self._motion.wg.scale, doc="True metres per wheel metre (1 until calibrated).")
    gyro_bias_radps = property(lambda self: self._motion.wg.bias_radps, doc="The gyro's estimated yaw-rate bias.")
    position_sigma_m = property(lambda self: self._pos_sigma, doc="The latest marginal's largest positional σ (m).")
    odometry_sigma_factor = property(lambda self: self._motion.sigma_factor,
                                     doc="The factor on the configured odometry σ (odometry_sigma_learned; else 1).")

    scale_windows = property(lambda self: None if self.initialiser.windows is None else self.initialiser.windows.scale,
                             doc="The paper's median-of-windows scale at initialisation.")

    @property
    def scale_samples(self) -> int:
        """Scale samples the windows gave so far."""
        return len(self.initialiser.scale_estimator.samples)


class MapFusion(_Readings, MapSearching, RoadFixing):
    """The engine: feed it odometry and GPS in time order, read estimates back.

    ``add_odometry(t, relative_pose)``: the motion since the previous frame, body frame (x
    forward, y left, z up), as a gtsam.Pose3 or a 4×4 array, in the odometry's own (unscaled)
    units. The first call only sets the start frame's time. ``add_gps(t, lat, lon, alt, sigma_m)``.
    ``estimate()`` the current (causal) pose, or None before initialisation;
    ``trajectory()`` the smoothed poses so far as {t: Pose3}.
    """

    def __init__(self, road: RoadMap, config: FusionConfig | None = None, *, gps_rate_hz: float = 1.0,
                 odometry_rate_hz: float = 10.0, on_final: OnFinal | None = None) -> None:
        self.road = road
        self.cfg = config or FusionConfig()
        self.counters = Counters()
        self.track = track_for(self.cfg, odometry_rate_hz)
        self.initialiser = Initialiser(self.cfg, gps_rate_hz, odometry_rate_hz)
        self.alignment: Alignment | None = None
        self.initialised_at: float | None = None
        self.map_prior_frames: list[int] = []
        self.lost_s = 0.0  # time the association held the estimate lost (map_relocalisation)
        self.matched_way: list[int] = []  # OSM way the matcher chose at each frame (-1: none)
        self._association = MapAssociation(road, self.cfg, self.counters)
        self._gate = GpsGate(self.cfg)
        self._jumps = JumpGuard.for_config(self.cfg)
        self._motion = MotionFusion(self.cfg, self.counters)  # wheel speed and gyro, when fed (issue 18)
        self._release = Release(self.cfg, on_final)  # streaming: final frames handed out, then forgotten
        self._smoother: Smoother | None = None
        self._gps = GpsQueue(self.cfg)
        self._since_update = 0
        self._last_cov_check_t = -math.inf
        self._pos_sigma = self._lat_sigma = 0.0  # the estimate's positional σ: largest, across the vehicle
        self._yaw_sigma = math.inf  # and its yaw σ (rad; unknown until the first check)
        self._init_reanchoring()
        self._road_fixes = RoadFixes(road, self.cfg, self.counters)  # (inert unless road_fixes and use_map)

    # ------------------------------------------------------------------ public API (and the readings of _Readings)
    def map_prior_times(self) -> list[float]:
        """Times of the frames that received a map prior."""
        return [self.track.t[k] for k in self.map_prior_frames if k >= self.track.first]

    def add_odometry(self, t: float, relative_pose) -> None:
        """One odometry frame: the motion since the previous frame (see the class docstring)."""
        (rel, finite), t = _as_pose3(relative_pose), float(t)
        if not (math.isfinite(t) and finite):
            self.counters.odometry_rejected += 1
            return
        track, motion = self.track, self._motion
        if track.t and t <= track.t[-1] + motion.same_frame_s(track.t[-1]):
            if not motion.rejoin(track.t[-1]):  # (True: wheel + gyro made this frame; the odometry is back)
                raise EngineError(f"odometry time {t} does not increase (previous {track.t[-1]})")
            return
        step = motion.odometry_step(track.t[-1], t, rel, self.scale) if track.t and motion.active else None
        self._append(t, self._jumps.bridge(t, rel, self.scale, self.counters) if step is None else step)
        motion.last_odometry_t = t

    def add_wheel_speed(self, t: float, speed_mps: float) -> None:
        """One wheel-speed sample (m/s, forward); with a yaw rate it is a second motion source (issue 18)."""
        self._motion.add_wheel(t, speed_mps)
        self._wheel_frames()

    def add_yaw_rate(self, t: float, yaw_rate_radps: float) -> None:
        """One gyro yaw-rate sample (rad/s about the vehicle's up axis, counter-clockwise positive)."""
        self._motion.add_yaw_rate(t, yaw_rate_radps)
        self._wheel_frames()

    def add_imu(self, t: float, gyro_radps, accel_mps2=None) -> None:
        """One IMU sample (body frame: x forward, y left, z up): the planar engine takes gyro z."""
        self.add_yaw_rate(t, float(np.asarray(gyro_radps, dtype=float)[2]))

    def _wheel_frames(self) -> None:  # frames wheel and gyro make alone while the odometry is silent
        track, motion = self.track, self._motion
        while (t := motion.frame_due(track.t[-1] if track.t else None, track.nominal_period_s)) is not None:
            self._append(t, motion.wheel_step(track.t[-1], t, self.scale) if track.t else gtsam.Pose3())

    def _append(self, t: float, rel: gtsam.Pose3) -> None:
        position = self.track.append(t, rel)
        self.counters.frames += 1
        self.matched_way.append(-1)
        if not self.initialised:
            self.initialiser.scale_estimator.add_odometry(t, position)  # read only until initialised
            self._try_initialise()
            if not (self.initialised or self.initialiser.fixes) and (loc := self._search.feed(*planar_of(
                    self.track.raw[-1]))):
                self._initialise_at(loc)
        else:
            self._add_frame(len(self.track) - 1)
        self._flush_gps()
        self._release.step(self)

    def add_gps(self, t: float, lat: float, lon: float, alt: float | None = None, sigma_m: float | None = None) -> None:
        """One GPS fix (WGS84 degrees; ``sigma_m`` per axis, or the configured gps_sigma_m)."""
        vals = [t, lat, lon]
        if not all(v is not None and math.isfinite(v) for v in vals) or not (-90 <= lat <= 90 and -180 <= lon <= 180):
            self.counters.gps_rejected_invalid += 1
            return
        sigma = _gps_sigma(sigma_m, self.cfg.gps_sigma_m)
        x, y = self.road.projection.to_enu(lat, lon)
        t, x, y = float(t), float(x), float(y)
        if self._motion.active:
            self._motion.wg.add_fix(t, x, y)
        if not self.initialised:
            self.counters.gps_before_init += 1
            self.initialiser.add_fix(t, x, y, sigma)
            self._try_initialise()
            return
        if self.cfg.refine_scale:
            fit = self.initialiser.refit_with_fix(self.track, t, x, y, sigma)
            if fit is not None:
                self.alignment = dataclasses.replace(self._aligned, scale=fit.scale, scale_sigma=fit.scale_sigma)
            self.alignment = self._motion.rescale(self._aligned)  # a calibrated wheel knows the scale better
        self._gps.waiting.append((t, x, y, None if alt is None else float(alt), sigma))
        self._flush_gps()

    def estimate(self) -> gtsam.Pose3 | None:
        """The current causal estimate of the latest frame, or None before initialisation."""
        return self.track.online[-1] if self.initialised and len(self.track.online) else None

    def online_estimates(self) -> tuple[np.ndarray, list[gtsam.Pose3 | None]]:
        """Every frame's causal estimate as it was made (None before initialisation)."""
        return np.array([t for _, t in self.track.t.held()]), [p for _, p in self.track.online.held()]

    def trajectory(self) -> dict[float, gtsam.Pose3]:
        """Smoothed poses of every frame so far, by time (flushes pending factors first)."""
        if self._smoother is None:
            return {}
        self._update()
        out = self._sm.poses()
        for k, p in self.track.online.held():  # frames the smoother never held (a failed update)
            if k not in out and p is not None:
                out[k] = p
        return {self.track.t[k]: pose for k, pose in sorted(out.items()) if pose is not None}

    def finish(self) -> None:
        """Add what is pending (call once at the end); later fixes count as rejected for their time."""
        if self.initialised:
            self._gps.drop(self.counters)
            self._update()
        self._release.finish(self)

    @property
    def _sm(self) -> Smoother:
        """The smoother (it exists from initialisation on)."""
        assert self._smoother is not None
        return self._smoother

    @property
    def _aligned(self) -> Alignment:
        assert self.alignment is not None
        return self.alignment

    # ------------------------------------------------------------------ initialisation
    def _try_initialise(self) -> None:
        self._motion.restate(self.track, self.initialiser.scale_estimator)  # frames made before the wheel calibrated
        a = self.initialiser.try_align(self.track)
        if a is not None:
            self._begin(self._motion.rescale(a))

    def _begin(self, a: Alignment, anchor: int = 0) -> None:
        self.alignment, self.initialised_at = a, self.track.t[-1]
        self._smoother = Smoother(self.cfg, self.track, self.counters, self._between,
                                  lambda: self._to_map(self.track.raw[0]))
        self._start_graph(anchor)
        self._note_outage_in_batch()

    def _learn_odometry_sigma(self) -> None:
        """``odometry_sigma_learned``: the window's fixes set the factor on the odometry's σ (odometry_trust.py)."""
        if self.cfg.odometry_sigma_learned and self.initialiser.fixes:
            trust = odometry_trust.from_window(self.cfg, self.track, self._aligned, self.initialiser.fixes)
            if trust is not None:
                self._motion.sigma_factor = trust.factor
                log.info("odometry σ × %.3f: the window's drift %.2f-%.2f m against %.2f m at the configured σ "
                         "(%d fixes)", trust.factor, trust.drift_low_m, trust.drift_m, trust.model_m, trust.fixes)

    def _to_map(self, raw: gtsam.Pose3) -> gtsam.Pose3:
        return self.track.to_map(raw, self._aligned)

    def _start_graph(self, anchor: int = 0) -> None:
        """All buffered frames, solved as one batch; the smoother then starts from the last
        buffered frame, with the batch's marginal covariance as its prior. (So the estimates inside
        the initialisation window use its later fixes too.)"""
        if self.cfg.refine_scale:
            fit = self.initialiser.fit(self.track)
            if fit is not None:
                log.info("scale refined by the initialisation fit: %.4f → %.4f (± %.4f)", self.scale, fit.scale,
                         fit.scale_sigma)
                self.alignment = self._motion.rescale(fit)
        self._learn_odometry_sigma()
        batch = solve_initial_batch(self.cfg, self.track, self._aligned, self.initialiser.fixes,
                                    lambda k: self._between(k, before_init=True), self.counters, anchor)
        sm, last = self._sm, len(self.track) - 1
        for k, pose in enumerate(batch.poses):
            self.track.online[k] = pose
            if k < last:
                sm.smoothed[k] = pose
        sm.smoothed_upto = last - 1
        sm.add(factors.pose_prior(last, batch.poses[last], batch.last_noise))
        sm.insert(last, batch.poses[last])
        self._update()

    # ------------------------------------------------------------------ frames
    def _step(self, k: int) -> gtsam.Pose3:
        return self._road_steps[k] if k in self._road_steps else self.track.step(k, self._aligned.scale)

    def _between(self, k: int, before_init: bool = False, step: gtsam.Pose3 | None = None) -> gtsam.BetweenFactorPose3:
        """The odometry factor into frame k."""
        step = self._step(k) if step is None else step
        noise = factors.odometry_noise(self.cfg, step, self.track.gap_frames(k), self.track.nominal_period_s,
                                       before_init=before_init, scale_sigma=self._aligned.relative_sigma,
                                       sigma_factor=self._motion.sigma_factor)
        return factors.between(k, step, noise)

    def _add_frame(self, k: int) -> None:
        track, sm = self.track, self._sm
        prev = track.online[k - 1]
        if prev is None:
            prev = self._to_map(track.raw[k - 1])
        step = self._along_road(k, prev)
        sm.add(self._between(k, step=step))
        pred = prev.compose(step)
        self._note_outage(k, step)
        sm.insert(k, pred)
        prior_added = self._map_prior(k, pred, step) if self.cfg.use_map else False
        prior_added = self._road_fix(k, pred) or prior_added
        track.online[k] = pred
        self._since_update += 1
        self._maybe_odometry_prior(k, pred)
        # a map prior updates at once: the causal estimate of frame k includes its own prior
        if prior_added or self._since_update >= self.cfg.update_every:
            self._update()
            if sm.last_updated_key == k:
                track.online[k] = sm.last_updated_pose
        if self.cfg.map_relocalisation:
            self._search_when_lost(k, pred)
        if self._gap_pending is not None:
            self._recarry_gap(k)

    def _map_prior(self, k: int, pred: gtsam.Pose3, step: gtsam.Pose3) -> bool:
        """Add the map prior on frame k if its predicted pose is off its road, else the heading prior if one is due
        (``heading_prior_sigma_deg``); True if either was added."""
        dt = self.track.t[k] - self.track.t[k - 1]
        m, prior = self._association.prior(k, pred, step, dt, self._pos_sigma, self._lat_sigma)
        if self._association.lost:
            self.lost_s += dt
        self.matched_way[k] = m.way_id if m is not None else -1
        if prior is None:  # (on its road: perhaps a prior on the heading alone)
            prior = self._association.heading_prior(k, pred, m, math.hypot(step.x(), step.y()), self._yaw_sigma,
                                                    self._motion.sigma_factor)
            if prior is None:
                return False
        else:
            self.map_prior_frames.append(k)
        self._sm.add(prior)
        return True

    def _maybe_odometry_prior(self, k: int, pred: gtsam.Pose3) -> None:
        """Paper IV.B: when the marginal positional σ exceeds the road width, the odometry estimate
        becomes a prior (with σ = the road width), so uncertainty cannot grow without bound."""
        cfg, sm = self.cfg, self._smoother
        if not cfg.odometry_priors or sm is None or sm.last_updated_key < 0:
            return
        if self.track.t[k] - self._last_cov_check_t < cfg.odometry_prior_every_s:
            return
        self._last_cov_check_t = self.track.t[k]
        sigmas = sm.position_sigmas()
        if sigmas is None:
            return
        self._pos_sigma, self._lat_sigma, self._yaw_sigma = sigmas
        prior = self._association.odometry_prior(k, pred, self._pos_sigma)
        if prior is not None:
            sm.add(prior)
            self.counters.odometry_priors += 1

    # ------------------------------------------------------------------ GPS
    def _flush_gps(self) -> None:
        """Attach waiting fixes to the frame nearest in time, once that frame exists."""
        if self.initialised and self.track.t:
            for k, fix in self._gps.due(self.track, self.counters):
                self._gate_and_add(k, *fix[1:])

    def _gate_and_add(self, k: int, x: float, y: float, alt: float | None, sigma: float) -> None:
        verdict = self._gate.check(self.track, k, x, y, sigma, self._pos_sigma)
        if verdict is Verdict.accept:
            self._sm.add(factors.gps_factor(self.cfg.state, k, x, y, alt, sigma))
            self.counters.gps_used += 1
            self._road_fixes.gps_used(self.track.t[k])
            return
        self.counters.gps_rejected_gate += 1
        if verdict is Verdict.relocalise:
            self.counters.gps_relocalisations += 1
            log.info("t=%.1f s: %d consistent GPS fixes disagree with the estimate: re-localising on GPS",
                     self.track.t[k], len(self._gate.run))
            self._relocalise(sigma)

    def _update(self) -> None:
        if self._sm.update():
            self._since_update = 0
