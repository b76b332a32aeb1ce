"""The Map-Fusion engine (paper III, DESIGN "The method" items 3–7): a GTSAM factor graph of
odometry, GPS and map priors.

:class:`MapFusion` takes measurements and returns estimates; it owns no files and prints
nothing. It coordinates parts, each holding its own state: the frames (:mod:`.track`), the GPS
initialisation and scale (:mod:`.initialisation`), the estimate's one owner (:mod:`.estimate`: the
alignment, the smoother, its restarts), the road association and map prior (:mod:`.association`), the
GPS gate (:mod:`.gps_gate`), the wheel and gyro (:mod:`.motion`), the outage carry and GPS's re-anchoring
(:mod:`.reanchoring`), the map's re-anchorings (:mod:`.registering`), the search of the road network
(:mod:`.searching`) and the road fixes (:mod:`.tracking`). The parts propose; the estimate applies.

One Pose3 per odometry frame (key ``x<k>``); odometry enters as BetweenFactorPose3, GPS as
GPSFactor, the map as a prior on a frame whose predicted pose lies farther from its road than
the road is wide. Until the GPS initialisation has its scale the frames are only buffered (no
estimate exists in the map frame before heading and scale are known); at initialisation they
are solved as one batch and the smoother starts from the last of them.
"""

from __future__ import annotations

import logging
import math

import gtsam
import numpy as np

from . import factors
from .association import MapAssociation
from .config import FusionConfig, StateModel
from .counters import Counters
from .errors import EngineError
from .estimate import Estimate
from .gps_gate import GpsGate, GpsQueue, Verdict
from .initialisation import Initialiser
from .motion import MotionFusion
from .reanchoring import GpsReanchoring, OutageCarry
from .registering import FixRegistration, MapAnchors
from .relocalise import SEARCH_PARTICLES, Located
from .roadmap import RoadMap
from .searching import MapSearch
from .stream import OnFinal, Release
from .track import Alignment, JumpGuard, track_for
from .tracking import RoadFixes

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


class MapFusion:
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
        cfg = self.cfg = config or FusionConfig()
        counters = self.counters = Counters()
        track = self.track = track_for(cfg, odometry_rate_hz)
        init = self.initialiser = Initialiser(cfg, gps_rate_hz, odometry_rate_hz)
        self.map_prior_frames: list[int] = []
        self.lost_s = 0.0  # time the association held the estimate lost (map_relocalisation)
        self.matched_way: list[int] = []  # OSM way the matcher chose at each frame (-1: none)
        assoc = self._association = MapAssociation(road, cfg, counters)
        gate = self._gate = GpsGate(cfg)
        jumps = self._jumps = JumpGuard.for_config(cfg)
        self._motion = MotionFusion(cfg, counters)  # wheel speed and gyro, when fed (issue 18)
        self._release = Release(cfg, on_final)  # streaming: final frames handed out, then forgotten
        self._gps = GpsQueue(cfg)
        self._road_fixes = RoadFixes(road, cfg, counters)  # (inert unless road_fixes and use_map)
        est = self._estimate = Estimate(cfg, track, counters, self._motion, init,
                                        on_restart=(self._road_fixes.reanchored, assoc.reset))
        self._carry = OutageCarry(road, cfg, track, est, gate, jumps)
        self._gps_reanchoring = GpsReanchoring(cfg, track, est, gate, init, counters)
        anchors = self._anchors = MapAnchors(road, cfg, track, est, counters)
        self._map_search = MapSearch(road, cfg, track, est, init, assoc, anchors,
                                     FixRegistration(road, cfg, track, est, init, assoc, anchors), self._carry)

    # ------------------------------------------------------------------ readings
    alignment = property(lambda self: self._estimate.alignment, doc="Heading, offset and scale; None before "
                         "initialisation.")
    initialised_at = property(lambda self: self._estimate.initialised_at, doc="Time of initialisation, or None.")
    initialised = property(lambda self: self._estimate.alignment is not None)
    smoother = property(lambda self: self._estimate.smoother, doc="The smoother (None before initialisation).")
    relocalised_at = property(lambda self: self._anchors.relocalised_at,
                              doc="(time, distance searched) of each map re-localisation.")
    scale = property(lambda self: None if self.alignment is None else self.alignment.scale,
                     doc="The odometry's scale (map metres per odometry unit), None before initialisation.")
    scale_sigma = property(lambda self: None if self.alignment is None else self.alignment.scale_sigma)
    wheel_scale = property(lambda self: self._motion.wg.scale, doc="True metres per wheel metre (1 until calibrated).")
    gyro_bias_radps = property(lambda self: self._motion.wg.bias_radps, doc="The gyro's estimated yaw-rate bias.")
    position_sigma_m = property(lambda self: self._estimate.pos_sigma_m,
                                doc="The latest marginal's largest positional σ (m).")
    odometry_sigma_factor = property(lambda self: self._motion.sigma_factor,
                                     doc="The factor on the configured odometry σ (odometry_sigma_learned; else 1).")
    scale_windows = property(lambda self: None if self.initialiser.windows is None else self.initialiser.windows.scale,
                             doc="The paper's median-of-windows scale at initialisation.")
    scale_samples = property(lambda self: len(self.initialiser.scale_estimator.samples),
                             doc="Scale samples the windows gave so far.")
    searching_from_region = property(lambda self: self.alignment is None and self._map_search.running,
                                     doc="A cold start's search is running (no estimate yet).")

    def map_prior_times(self) -> list[float]:
        """Times of the frames that received a map prior."""
        return [self.track.t[k] for k in self.map_prior_frames if k >= self.track.first]

    # ------------------------------------------------------------------ input
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
        motion.odometry_seen(t)

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
            self._estimate.refit(t, x, y, sigma)
        self._gps.waiting.append((t, x, y, None if alt is None else float(alt), sigma))
        self._flush_gps()

    # ------------------------------------------------------------------ output
    def estimate(self) -> gtsam.Pose3 | None:
        """The current causal estimate of the latest frame, or None before initialisation."""
        return self.track.online[-1] if self.initialised and len(self.track.online) else None

    def online_estimates(self) -> tuple[np.ndarray, list[gtsam.Pose3 | None]]:
        """Every frame's causal estimate as it was made (None before initialisation)."""
        return np.array([t for _, t in self.track.t.held()]), [p for _, p in self.track.online.held()]

    def trajectory(self) -> dict[float, gtsam.Pose3]:
        """Smoothed poses of every frame so far, by time (flushes pending factors first)."""
        sm = self.smoother
        if sm is None:
            return {}
        self._estimate.update()
        out = sm.poses()
        for k, p in self.track.online.held():  # frames the smoother never held (a failed update)
            if k not in out and p is not None:
                out[k] = p
        return {self.track.t[k]: pose for k, pose in sorted(out.items()) if pose is not None}

    def finish(self) -> None:
        """Add what is pending (call once at the end); later fixes count as rejected for their time."""
        if self.initialised:
            self._gps.drop(self.counters)
            self._estimate.update()
        self._release.finish(self)

    # ------------------------------------------------------------------ re-anchoring from outside
    def start_in_region(self, lat: float, lon: float, radius_m: float) -> None:
        """Cold start without GPS (issue 17): the vehicle starts somewhere on the roads within ``radius_m`` of
        (lat, lon); the odometry's shape finds it, and the estimate begins once found. The odometry's scale is
        taken as 1 (a metric VO or VIO) unless ``reloc_scale_min`` < ``reloc_scale_max``: then the search finds
        the scale in that range with the position (``fuse --scale-unknown``)."""
        if self.alignment is not None or self.track.t:
            raise EngineError("start_in_region must be called before the first odometry frame")
        if not (math.isfinite(lat) and math.isfinite(lon) and math.isfinite(radius_m) and radius_m > 0):
            raise EngineError(f"start region needs a finite latitude, longitude and radius > 0, got {lat}, {lon}, "
                              f"{radius_m}")
        x, y = self.road.projection.to_enu(lat, lon)
        self._map_search.start_in_region(float(x), float(y), float(radius_m))

    def reanchor_at(self, x_m: float, y_m: float, yaw_rad: float, sigma_m: float = 0.5,
                    yaw_sigma_rad: float = 0.01) -> None:
        """Re-anchor the estimate on a pose known from elsewhere (the map's ENU frame, m; yaw from east, rad): the
        smoother restarts at the last frame with that pose as its prior (σ ``sigma_m`` a horizontal axis,
        ``yaw_sigma_rad``), as the engine's own re-localisations do, and any running search ends. For a pose from
        outside (an operator, another localiser), and to measure what a perfect re-localisation would give
        (``mapfusion.harness.bounds``)."""
        if self.alignment is None or self.smoother is None or not self.track.t:
            raise EngineError("reanchor_at needs an estimate to re-anchor: the engine is not initialised yet")
        values = (x_m, y_m, yaw_rad, sigma_m, yaw_sigma_rad)
        if not all(math.isfinite(v) for v in values) or sigma_m <= 0 or yaw_sigma_rad <= 0:
            raise EngineError(f"reanchor_at needs finite x, y, yaw and σs > 0, got {values}")
        k = len(self.track) - 1
        was = self.track.online[k]
        z = was.z() if was is not None else 0.0
        pose = gtsam.Pose3(gtsam.Rot3.Yaw(yaw_rad), gtsam.Point3(x_m, y_m, z))
        self._map_search.stop()
        noise = factors.diagonal(factors.pose_sigmas(StateModel.planar, yaw_sigma_rad, sigma_m))
        self._estimate.restart_from(k, pose, noise, sigma_m)
        self._estimate.update()

    # ------------------------------------------------------------------ frames
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
            if not (self.initialised or self.initialiser.fixes) and (loc := self._map_search.feed_cold(
                    self.track.raw[-1])):
                self._initialise_at(loc)
        else:
            self._add_frame(len(self.track) - 1)
        self._flush_gps()
        self._release.step(self)

    def _try_initialise(self) -> None:
        self._motion.restate(self.track, self.initialiser.scale_estimator)  # frames made before the wheel calibrated
        a = self.initialiser.try_align(self.track)
        if a is not None:
            self._begin(self._motion.rescale(a))

    def _begin(self, a: Alignment, anchor: int = 0) -> None:
        self._estimate.begin(a, anchor)
        self._carry.note_outage_in_batch()

    def _initialise_at(self, loc: Located) -> None:
        """A cold start's search has found the vehicle: the odometry's frame aligned so that its last pose
        is the found one (at the search's scale), the frames so far solved as at a GPS initialisation."""
        if self.cfg.state is StateModel.planar and self.track.level_rot is None:
            self.track.level_frame()
        raw = self.track.raw[-1]
        rot = loc.yaw_rad - raw.rotation().yaw()
        c, s, (px, py, _) = math.cos(rot), math.sin(rot), raw.translation()
        scale, c, s = loc.scale, c * loc.scale, s * loc.scale
        sigma = max(SEARCH_PARTICLES.scale_sigma, loc.scale_spread) * scale
        self._motion.cold_start()  # (no window measured this odometry's drift)
        self._begin(Alignment(scale, sigma, rot, np.array([loc.x_m - (c * px - s * py), loc.y_m - (s * px + c * py)])),
                    anchor=len(self.track) - 1)
        self._anchors.found_at_start(loc.driven_m)

    def _add_frame(self, k: int) -> None:
        track, est = self.track, self._estimate
        prev = track.online[k - 1]
        if prev is None:
            prev = est.to_map(track.raw[k - 1])
        step = self._carry.step_into(k, prev)
        est.add(est.between(k, step=step))
        pred = prev.compose(step)
        self._carry.note_outage(k, step)
        est.sm.insert(k, pred)
        prior_added = self._map_prior(k, pred, step) if self.cfg.use_map else False
        fix = self._road_fixes.fix(k, track.t[k], track.raw[k], pred, est, self._map_search.running,
                                   self._association.kept_to_roads)
        if fix is not None:
            est.add(fix)
        est.frame(k, pred, fix is not None or prior_added, self._association.odometry_prior)
        if self.cfg.map_relocalisation:
            self._map_search.when_lost(k, pred)
        self._carry.recarry_gap(k)

    def _map_prior(self, k: int, pred: gtsam.Pose3, step: gtsam.Pose3) -> bool:
        """Add the map prior on frame k if its predicted pose is off its road, else the heading prior if one is due
        (``heading_prior_sigma_deg``); True if either was added."""
        dt, est = self.track.t[k] - self.track.t[k - 1], self._estimate
        m, prior = self._association.prior(k, pred, step, dt, est.pos_sigma_m, est.lat_sigma_m)
        if self._association.lost:
            self.lost_s += dt
        self.matched_way[k] = m.way_id if m is not None else -1
        if prior is None:  # (on its road: perhaps a prior on the heading alone)
            prior = self._association.heading_prior(k, pred, m, math.hypot(step.x(), step.y()), est.yaw_sigma_rad,
                                                    self._motion.sigma_factor)
            if prior is None:
                return False
        else:
            self.map_prior_frames.append(k)
        est.add(prior)
        return True

    # ------------------------------------------------------------------ GPS
    def _flush_gps(self) -> None:
        """Attach waiting fixes to the frame nearest in time, once that frame exists."""
        if self.initialised and self.track.t:
            for k, fix in self._gps.due(self.track, self.counters):
                self._gate_and_add(k, *fix[1:])

    def _gate_and_add(self, k: int, x: float, y: float, alt: float | None, sigma: float) -> None:
        verdict = self._gate.check(self.track, k, x, y, sigma, self._estimate.pos_sigma_m)
        if verdict is Verdict.accept:
            self._estimate.add(factors.gps_factor(self.cfg.state, k, x, y, alt, sigma))
            self.counters.gps_used += 1
            self._road_fixes.gps_used(self.track.t[k])
            return
        self.counters.gps_rejected_gate += 1
        if verdict is Verdict.relocalise:
            self.counters.gps_relocalisations += 1
            log.info("t=%.1f s: %d consistent GPS fixes disagree with the estimate: re-localising on GPS",
                     self.track.t[k], len(self._gate.run))
            self._gps_reanchoring.relocalise(sigma)
