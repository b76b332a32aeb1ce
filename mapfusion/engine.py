"""The Map-Fusion engine (paper III, DESIGN "The method" items 3–7): a GTSAM factor graph of
odometry, GPS and map priors.

:class:`MapFusion` takes measurements and returns estimates; it owns no files and prints
nothing. One Pose3 per odometry frame (key ``x<k>``); odometry enters as BetweenFactorPose3,
GPS as GPSFactor, the map as a prior on a frame whose predicted pose lies farther from its road
than the road is wide. Until the GPS initialisation has its scale the frames are only buffered
(no estimate exists in the map frame before heading and scale are known); at initialisation they
all enter the graph with the loose pre-initialisation odometry σ.
"""

from __future__ import annotations

import bisect
import logging
import math
from dataclasses import dataclass, field

import gtsam
import numpy as np

from .config import Backend, FusionConfig, RobustKernel, StateModel
from .errors import InputError
from .initialisation import ScaleEstimator, heading_offset
from .matcher import check_pose_args, map_pose, match_candidates
from .prior import prior_sqrt_information
from .roadmap import RoadMap

log = logging.getLogger(__name__)

X = gtsam.symbol_shorthand.X


class EngineError(InputError):
    """A measurement the engine cannot take (wrong shape, time going backwards)."""


@dataclass
class Counters:
    """What the engine did, for metrics and diagnostics."""

    frames: int = 0
    odometry_rejected: int = 0
    gps_used: int = 0
    gps_rejected_gate: int = 0
    gps_rejected_invalid: int = 0
    gps_before_init: int = 0
    map_priors: int = 0
    priors_gated: int = 0
    matches: int = 0
    match_fallbacks: int = 0
    odometry_priors: int = 0
    recoveries: int = 0
    gps_relocalisations: int = 0
    updates: int = 0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def _as_pose3(pose) -> gtsam.Pose3:
    if isinstance(pose, gtsam.Pose3):
        return pose
    m = np.asarray(pose, dtype=float)
    if m.shape != (4, 4):
        raise EngineError(f"relative pose must be a gtsam.Pose3 or a 4×4 array, got shape {m.shape}")
    return gtsam.Pose3(m)


def _finite_pose(p: gtsam.Pose3) -> bool:
    return bool(np.all(np.isfinite(p.matrix())))


def level(p: gtsam.Pose3) -> gtsam.Pose3:
    """The pose with roll and pitch removed and z = 0 (a ground vehicle on the map plane)."""
    yaw = p.rotation().yaw()
    return gtsam.Pose3(gtsam.Rot3.Yaw(yaw), gtsam.Point3(p.x(), p.y(), 0.0))


def planar_step(prev_odo: gtsam.Pose3, cur_odo: gtsam.Pose3) -> gtsam.Pose3:
    """Relative motion projected on the horizontal plane with the odometry's own attitude:
    the world displacement rotated by the previous yaw only; dz, roll and pitch dropped."""
    d = cur_odo.translation() - prev_odo.translation()
    y0 = prev_odo.rotation().yaw()
    y1 = cur_odo.rotation().yaw()
    c, s = math.cos(y0), math.sin(y0)
    return gtsam.Pose3(gtsam.Rot3.Yaw(y1 - y0), gtsam.Point3(c * d[0] + s * d[1], -s * d[0] + c * d[1], 0.0))


class _Smoother:
    """ISAM2 over the whole history, or GTSAM's incremental fixed-lag smoother."""

    def __init__(self, cfg: FusionConfig) -> None:
        params = gtsam.ISAM2Params()
        params.setFactorization(cfg.factorization.value)
        params.setRelinearizeThreshold(0.01)
        params.relinearizeSkip = 1
        self.fixed_lag = cfg.backend is Backend.fixed_lag
        # marginalised factors free their slots: reuse them, or ISAM2's factor list grows forever
        params.findUnusedFactorSlots = self.fixed_lag
        self.s = gtsam.IncrementalFixedLagSmoother(cfg.lag_s, params) if self.fixed_lag else gtsam.ISAM2(params)

    def update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, float]) -> None:
        if self.fixed_lag:
            self.s.update(graph, values, stamps)
        else:
            self.s.update(graph, values)

    def pose(self, key: int) -> gtsam.Pose3:
        return self.s.calculateEstimatePose3(key)

    def covariance(self, key: int) -> np.ndarray:
        return self.s.marginalCovariance(key)

    def keys(self) -> list[int]:
        return list(self.s.calculateEstimate().keys())


@dataclass
class _Pending:
    graph: gtsam.NonlinearFactorGraph = field(default_factory=gtsam.NonlinearFactorGraph)
    values: gtsam.Values = field(default_factory=gtsam.Values)
    stamps: dict = field(default_factory=dict)
    keys: list = field(default_factory=list)
    factor_keys: list = field(default_factory=list)


class MapFusion:
    """The engine: feed it odometry and GPS in time order, read estimates back.

    ``add_odometry(t, relative_pose)``: the motion since the previous frame, body frame (x
    forward, y left, z up), as a gtsam.Pose3 or a 4×4 array, in the odometry's own (unscaled)
    units. The first call only sets the start frame's time. ``add_gps(t, lat, lon, alt, sigma_m)``.
    ``estimate()`` the current (causal) pose, or None before initialisation;
    ``trajectory()`` the smoothed poses so far as {t: Pose3}.
    """

    def __init__(self, road: RoadMap, config: FusionConfig | None = None, *,
                 gps_rate_hz: float = 1.0, odometry_rate_hz: float = 10.0) -> None:
        self.road = road
        self.cfg = config or FusionConfig()
        self.counters = Counters()
        self._scale_est = ScaleEstimator(self.cfg, gps_rate_hz, odometry_rate_hz)
        self._nominal_period = 1.0 / odometry_rate_hz
        self._level: gtsam.Pose3 | None = None  # rotation levelling the odometry frame (planar state)
        self._rejected_run: list[tuple[float, float, float, int]] = []  # consecutive gated fixes (t, x, y, frame)
        self.scale: float | None = None
        self.scale_sigma: float | None = None
        self.scale_windows: float | None = None  # the paper's median-of-windows estimate at initialisation
        self._windows_sigma = math.inf
        self._n_init_samples = 0
        self._fixes_since_fit = 0
        self._rot = 0.0  # odometry frame → ENU yaw offset
        self._trans = np.zeros(2)
        # raw odometry, accumulated in its own frame (for initialisation and scale samples)
        self._odo_abs = gtsam.Pose3()
        self._t: list[float] = []
        self._raw: list[gtsam.Pose3] = []  # raw absolute odometry poses per frame
        self._rel: list[gtsam.Pose3] = []  # raw relative motion into each frame (identity for the first)
        self._gps_pre: list[tuple[float, float, float, float]] = []  # (t, x, y, sigma) before initialisation
        self._gps_wait: list[tuple[float, float, float, float | None, float]] = []
        self.initialised = False
        self.initialised_at: float | None = None
        self._smoother: _Smoother | None = None
        self._pending = _Pending()
        self._online: list[gtsam.Pose3 | None] = []
        self._last_key = -1
        self._last_updated_key = -1
        self._last_updated_pose: gtsam.Pose3 | None = None
        self._smoothed: dict[int, gtsam.Pose3] = {}
        self._smoothed_upto = -1  # every frame up to this one has its final smoothed estimate
        self._since_update = 0
        self._last_cov_check_t = -math.inf
        self._pos_sigma = 0.0
        self._edge = -1  # the road edge the vehicle was last matched to
        self.map_prior_frames: list[int] = []
        self.matched_way: list[int] = []  # OSM way the matcher chose at each frame (-1: none)
        self._yaw_sigma = math.radians(self.cfg.yaw_sigma_deg)
        self._mask = np.zeros(len(road), dtype=bool)
        self._robust = self._make_robust()

    # ------------------------------------------------------------------ public API
    def add_odometry(self, t: float, relative_pose) -> None:
        """One odometry frame: the motion since the previous frame (see the class docstring)."""
        t = float(t)
        rel = _as_pose3(relative_pose)
        if not (math.isfinite(t) and _finite_pose(rel)):
            self.counters.odometry_rejected += 1
            return
        if self._t and t <= self._t[-1]:
            raise EngineError(f"odometry time {t} does not increase (previous {self._t[-1]})")
        first = not self._t
        self._odo_abs = self._odo_abs if first else self._odo_abs.compose(rel)
        self._t.append(t)
        self._raw.append(self._level.compose(self._odo_abs) if self._level is not None else self._odo_abs)
        self._rel.append(gtsam.Pose3() if first else rel)
        self.counters.frames += 1
        self._scale_est.add_odometry(t, self._odo_abs.translation())
        self._online.append(None)
        self.matched_way.append(-1)
        if not self.initialised:
            self._try_initialise()
            self._flush_gps()
            return
        self._add_frame(len(self._t) - 1)
        self._flush_gps()

    def add_gps(self, t: float, lat: float, lon: float, alt: float | None = None, sigma_m: float | None = None) -> None:
        """One GPS fix (WGS84 degrees; ``sigma_m`` per axis, or the configured gps_sigma_m)."""
        vals = [t, lat, lon]
        if not all(v is not None and math.isfinite(v) for v in vals) or not (-90 <= lat <= 90 and -180 <= lon <= 180):
            self.counters.gps_rejected_invalid += 1
            return
        sigma = self.cfg.gps_sigma_m if sigma_m is None or not math.isfinite(sigma_m) or sigma_m <= 0 else float(sigma_m)
        x, y = self.road.projection.to_enu(lat, lon)
        if not self.initialised:
            self.counters.gps_before_init += 1
            self._gps_pre.append((float(t), float(x), float(y), sigma))
            self._scale_est.add_gps(t, x, y, sigma)
            self._try_initialise()
            return
        if self.cfg.refine_scale:
            self._refine_with_fix(t, x, y, sigma)
        self._gps_wait.append((float(t), float(x), float(y), None if alt is None else float(alt), sigma))
        self._flush_gps()

    def estimate(self) -> gtsam.Pose3 | None:
        """The current causal estimate of the latest frame, or None before initialisation."""
        if not self.initialised or not self._online:
            return None
        return self._online[-1]

    def online_estimates(self) -> tuple[np.ndarray, list[gtsam.Pose3 | None]]:
        """Every frame's causal estimate as it was made (None before initialisation)."""
        return np.asarray(self._t), list(self._online)

    def trajectory(self) -> dict[float, gtsam.Pose3]:
        """Smoothed poses of every frame so far, by time (flushes pending factors first)."""
        if not self.initialised:
            return {}
        self._update()
        out = dict(self._smoothed)
        if self._smoother is not None:
            for key in self._smoother.keys():
                out[gtsam.Symbol(key).index()] = self._smoother.pose(key)
        for k, p in enumerate(self._online):  # frames the smoother never held (a failed update)
            if k not in out and p is not None:
                out[k] = p
        return {self._t[k]: out[k] for k in sorted(out)}

    def finish(self) -> None:
        """Add what is still pending (call once after the last measurement)."""
        if self.initialised:
            self._update()

    # ------------------------------------------------------------------ initialisation
    def _try_initialise(self) -> None:
        est = self._scale_est.estimate()
        if est is None or len(self._gps_pre) < 3 or not self._t:
            return
        enough = self._scale_est.ready
        stalled = (self._t[-1] - self._gps_pre[-1][0] > 5.0) and est.samples >= 5
        if not (enough or stalled):
            return
        if self.cfg.state is StateModel.planar and self._level is None:
            self._level_odometry_frame()  # with every frame of the initialisation window
        g = np.array([(t, x, y) for t, x, y, _ in self._gps_pre])
        g = g[g[:, 0] <= self._t[-1] + 1e-9]
        g = g[g[:, 0] >= self._t[0] - 1e-9]
        if len(g) < 3:
            return
        odo_xyz = np.array([self._raw_at(t).translation() for t in g[:, 0]])
        rot = heading_offset(g[:, 1:3], odo_xyz[:, :2])
        if rot is None:
            return
        s = est.scale
        c, sn = math.cos(rot), math.sin(rot)
        rxy = odo_xyz[:, :2] @ np.array([[c, sn], [-sn, c]]) * s
        resid = g[:, 1:3] - rxy
        trans = np.median(resid, axis=0)
        self.scale, self.scale_sigma = s, est.sigma
        self.scale_windows = s
        self._windows_sigma = est.sigma
        self._n_init_samples = est.samples
        self._rot, self._trans = rot, trans
        self.initialised = True
        self.initialised_at = self._t[-1]
        log.info("initialised at t=%.1f s: scale %.4f ± %.4f from %d samples, heading offset %.2f°",
                 self._t[-1], s, est.sigma, est.samples, math.degrees(rot))
        self._smoother = _Smoother(self.cfg)
        self._start_graph()

    def _fit_scale(self, since_t: float = -math.inf):
        """Least-squares similarity between the raw odometry and the fixes after ``since_t``
        (outliers beyond 3σ of a first fit dropped): (scale, σ, rotation, translation) or None
        when there are too few fixes or too little motion."""
        from .metrics import umeyama

        g = np.array([(t, x, y, s) for t, x, y, s in self._gps_pre
                      if max(since_t, self._t[0] - 0.5) <= t <= self._t[-1] + 0.5]).reshape(-1, 4)
        if len(g) < 10:
            return None
        o = np.array([self._raw_at(t).translation()[:2] for t in g[:, 0]])
        keep = np.ones(len(g), dtype=bool)
        for _ in range(2):
            r, tr, sc = umeyama(o[keep], g[keep, 1:3], with_scale=True)
            resid = np.hypot(*(g[:, 1:3] - (sc * o @ r.T + tr)).T)
            keep = resid <= 3.0 * np.median(g[:, 3]) + 1.0
            if keep.sum() < 10:
                return None
        spread = float(np.sqrt(np.mean(np.sum((o[keep] - o[keep].mean(0)) ** 2, axis=1))))
        if spread * sc < 50.0:
            return None
        sigma = float(np.median(g[keep, 3])) / (spread * math.sqrt(keep.sum()))
        limit = self.cfg.scale_fit_max_disagreement_sigma
        if limit > 0 and self.scale_windows is not None:
            if abs(sc - self.scale_windows) > limit * math.hypot(sigma, self._windows_sigma):
                log.info("scale fit %.4f ± %.4f disagrees with the windows' median %.4f ± %.4f: kept the median",
                         sc, sigma, self.scale_windows, self._windows_sigma)
                return None
        return float(sc), sigma, math.atan2(r[1, 0], r[0, 0]), tr

    def _refine_scale_ls(self) -> None:
        """At initialisation, refine the windows' median by the least-squares fit over the whole
        window: the median uses each fix a few times over short chords, the fit all at once."""
        fit = self._fit_scale()
        if fit is None:
            return
        log.info("scale refined by the initialisation fit: %.4f → %.4f (± %.4f)", self.scale, fit[0], fit[1])
        self.scale, self.scale_sigma, self._rot, self._trans = fit

    def _level_odometry_frame(self) -> None:
        """A VO's frame is its first camera frame, often pitched a degree or two: projecting its
        motion on that frame's "horizontal" shortens distances by 1 − cos(tilt), which the scale
        then absorbs wrongly. Roads are level on average, so the mean of the body's up axis over the
        frames so far is up: rotate the frame so it is."""
        ups = np.array([p.rotation().matrix()[:, 2] for p in self._raw])
        up = ups.mean(axis=0)
        norm = np.linalg.norm(up)
        if norm < 0.5:
            return
        up /= norm
        axis = np.cross(up, [0.0, 0.0, 1.0])
        angle = math.asin(min(1.0, float(np.linalg.norm(axis))))
        if angle < 1e-6:
            self._level = gtsam.Pose3()
            return
        lvl = gtsam.Pose3(gtsam.Rot3.Rodrigues(axis / np.linalg.norm(axis) * angle), gtsam.Point3(0, 0, 0))
        self._level = lvl
        self._raw = [lvl.compose(p) for p in self._raw]
        for i in range(len(self._raw)):
            self._scale_est._odo_p[i] = self._raw[i].translation()
        log.info("odometry frame levelled by %.2f°", math.degrees(angle))

    def _refine_with_fix(self, t: float, x: float, y: float, sigma: float) -> None:
        """While fixes keep coming after initialisation, refit the scale on the fixes of the last
        300 s every ``scale_samples`` fixes (the least-squares fit of :meth:`_fit_scale`)."""
        self._gps_pre.append((t, x, y, sigma))
        self._fixes_since_fit += 1
        if self._fixes_since_fit >= self.cfg.scale_samples:
            self._fixes_since_fit = 0
            fit = self._fit_scale(t - 300.0)
            if fit is not None:
                self.scale, self.scale_sigma = fit[0], fit[1]

    def _raw_at(self, t: float) -> gtsam.Pose3:
        return self._raw[self._frame_at(t)]

    def _to_map(self, raw: gtsam.Pose3) -> gtsam.Pose3:
        """A raw odometry pose in the map frame by the initialisation's scale, heading and shift."""
        p = raw.translation() * self.scale
        c, s = math.cos(self._rot), math.sin(self._rot)
        xy = np.array([c * p[0] - s * p[1], s * p[0] + c * p[1]]) + self._trans
        rot = gtsam.Rot3.Yaw(self._rot).compose(raw.rotation())
        pose = gtsam.Pose3(rot, gtsam.Point3(xy[0], xy[1], p[2]))
        return level(pose) if self.cfg.state is StateModel.planar else pose

    def _start_graph(self) -> None:
        """All buffered frames, solved as one batch: a prior on the first, loose odometry between
        them, and the initialisation window's fixes (gated against the initialisation fit). The
        smoother then starts from the last buffered frame, with the batch's marginal covariance as
        its prior. (So the estimates inside the initialisation window use its later fixes too.)"""
        if self.cfg.refine_scale:
            self._refine_scale_ls()
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        first = self._to_map(self._raw[0])
        if self.cfg.state is StateModel.planar:
            sig = np.array([1e-3, 1e-3, math.radians(10.0), 5.0, 5.0, 1e-3])
        else:
            sig = np.array([math.radians(2.0), math.radians(2.0), math.radians(10.0), 5.0, 5.0, 1.0])
        graph.add(gtsam.PriorFactorPose3(X(0), first, gtsam.noiseModel.Diagonal.Sigmas(sig)))
        values.insert(X(0), first)
        pred = first
        guesses = [first]
        for k in range(1, len(self._t)):
            step = self._step(k)
            graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), step, self._odometry_noise(True, step, self._gap_frames(k))))
            pred = self._to_map(self._raw[k])
            values.insert(X(k), pred)
            guesses.append(pred)
        for t, x, y, sigma in self._gps_pre:
            if t < self._t[0] - 0.5 or t > self._t[-1] + 0.5:
                continue
            k = self._frame_at(t)
            g = guesses[k]
            if math.hypot(g.x() - x, g.y() - y) > self.cfg.gps_gate_sigma * math.hypot(sigma, 2.0 * sigma):
                self.counters.gps_rejected_gate += 1
                continue
            graph.add(self._gps_factor(k, x, y, None, sigma))
            self.counters.gps_used += 1
        params = gtsam.LevenbergMarquardtParams()
        params.setLinearSolverType("MULTIFRONTAL_QR" if self.cfg.factorization.value == "QR" else "MULTIFRONTAL_CHOLESKY")
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        last = len(self._t) - 1
        for k in range(len(self._t)):
            pose = result.atPose3(X(k))
            self._online[k] = pose
            if k < last:
                self._smoothed[k] = pose
        self._smoothed_upto = last - 1
        try:
            cov = gtsam.Marginals(graph, result).marginalCovariance(X(last))
            noise = gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T) + 1e-9 * np.eye(6))
        except RuntimeError:
            noise = gtsam.noiseModel.Diagonal.Sigmas(sig)
        anchor = result.atPose3(X(last))
        self._pending.graph.add(gtsam.PriorFactorPose3(X(last), anchor, noise))
        self._insert_value(last, anchor)
        self._update()

    # ------------------------------------------------------------------ frames
    def _frame_at(self, t: float) -> int:
        """Index of the frame nearest in time (bisect: the frame list only grows)."""
        i = min(bisect.bisect_left(self._t, t), len(self._t) - 1)
        if i > 0 and abs(self._t[i - 1] - t) <= abs(self._t[i] - t):
            i -= 1
        return i

    def _insert_value(self, k: int, pose: gtsam.Pose3) -> None:
        self._pending.values.insert(X(k), pose)
        self._pending.stamps[X(k)] = self._t[k]
        self._pending.keys.append(k)
        self._last_key = k

    def _step(self, k: int) -> gtsam.Pose3:
        """The scaled relative motion into frame k in the engine's state model."""
        if self.cfg.state is StateModel.planar:
            rel = planar_step(self._raw[k - 1], self._raw[k])
        else:
            rel = self._rel[k]
        t = rel.translation() * self.scale
        return gtsam.Pose3(rel.rotation(), gtsam.Point3(*t))

    def _odometry_noise(self, before_init: bool, step: gtsam.Pose3, gap_frames: float = 1.0) -> gtsam.noiseModel.Base:
        """σ of one odometry step. A step across dropped frames is looser in proportion to the
        frames it spans, and one across an outage (over 1 s) is at least 30% of its length: a
        re-initialised odometry guesses the motion it did not see."""
        n = max(1.0, gap_frames)
        st = self.cfg.odometry_sigma_after_init_m * n
        sr = math.radians(self.cfg.odometry_rot_sigma_deg) * n
        if n * self._nominal_period > 1.0:
            st = max(st, 0.3 * float(np.linalg.norm(step.translation())))
            sr = max(sr, math.radians(20.0))
        if before_init and self.cfg.loose_before_init:
            st, sr = self.cfg.odometry_sigma_before_init_m, 10.0 * sr
        elif before_init:
            # the batch is solved once the scale is known: its uncertainty scales the step's length
            st = math.hypot(st, (self.scale_sigma or 0.0) * float(np.linalg.norm(step.translation())))
        if self.cfg.state is StateModel.planar:
            sig = [1e-3, 1e-3, sr, st, st, 1e-3]
        else:
            sig = [sr, sr, sr, st, st, st]
        return gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sig))

    def _gap_frames(self, k: int) -> float:
        return (self._t[k] - self._t[k - 1]) / self._nominal_period

    def _add_frame(self, k: int, before_init: bool = False) -> None:
        step = self._step(k)
        noise = self._odometry_noise(before_init, step, self._gap_frames(k))
        self._pending.graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), step, noise))
        prev = self._online[k - 1]
        if prev is None:
            prev = self._to_map(self._raw[k - 1])
        pred = prev.compose(step)
        self._insert_value(k, pred)
        prior_added = False
        if self.cfg.use_map and not before_init:
            prior_added = self._map_prior(k, pred, step)
        self._online[k] = pred
        self._since_update += 1
        if not before_init:
            self._maybe_odometry_prior(k, pred)
            # a map prior updates at once: the causal estimate of frame k includes its own prior
            if prior_added or self._since_update >= self.cfg.update_every:
                self._update()
                self._online[k] = self._last_updated_pose if self._last_updated_key == k else self._online[k]

    # ------------------------------------------------------------------ map prior
    def _make_robust(self):
        kind = self.cfg.robust_kernel
        if kind is RobustKernel.huber:
            return gtsam.noiseModel.mEstimator.Huber.Create(self.cfg.robust_k)
        if kind is RobustKernel.cauchy:
            return gtsam.noiseModel.mEstimator.Cauchy.Create(self.cfg.robust_k)
        return None

    def _match(self, pred: gtsam.Pose3):
        cfg = self.cfg
        x, y, yaw = pred.x(), pred.y(), pred.rotation().yaw()
        check_pose_args(x, y, yaw, cfg.search_radius_m)
        road = self.road
        near = road.query_radius(x, y, cfg.search_radius_m)
        if near.size == 0:
            return None
        k_all, rev_all, e_all, a_all, d_all = match_candidates(x, y, yaw, road.xy_m[near], road.yaw_cos[near],
                                                               road.yaw_sin[near], cfg.angle_weight_m_per_deg)
        best = (int(near[k_all]), rev_all, d_all)
        if cfg.match_continuity and self._edge >= 0:
            neigh = road.neighbourhood(self._edge)
            self._mask[neigh] = True  # a scratch mask: O(|neighbourhood| + |near|), no sorting
            allowed = near[self._mask[near]]
            self._mask[neigh] = False
            if allowed.size:
                k, rev, e, a, d = match_candidates(x, y, yaw, road.xy_m[allowed], road.yaw_cos[allowed],
                                                   road.yaw_sin[allowed], cfg.angle_weight_m_per_deg)
                if d <= d_all + cfg.continuity_slack_m:
                    best = (int(allowed[k]), rev, d)
                else:
                    self.counters.match_fallbacks += 1
            else:
                self.counters.match_fallbacks += 1
        i, rev, _ = best
        from .matcher import _make_match  # local: the dataclass builder shared with RoadMap.match

        e = float(math.hypot(road.xy_m[i, 0] - x, road.xy_m[i, 1] - y))
        a = float(np.degrees(np.arccos(min(1.0, abs(math.cos(road.yaw_rad[i] - yaw))))))
        m = _make_match(road, i, rev, x, y, e, a, best[2])
        if road.edge[i] >= 0:
            self._edge = int(road.edge[i])
        elif self._edge < 0:
            self._edge = -1
        return m

    def _ambiguous(self, m, pred: gtsam.Pose3) -> bool:
        """Another way's best D lies within ``prior_ambiguity_m`` of the match's."""
        margin = self.cfg.prior_ambiguity_m
        if margin <= 0:
            return False
        road = self.road
        near = road.query_radius(pred.x(), pred.y(), self.cfg.search_radius_m)
        other = near[road.way_index[near] != road.way_index[m.index]]
        if other.size == 0:
            return False
        _, _, _, _, d = match_candidates(pred.x(), pred.y(), pred.rotation().yaw(), road.xy_m[other],
                                         road.yaw_cos[other], road.yaw_sin[other], self.cfg.angle_weight_m_per_deg)
        return d - m.cost < margin

    def _map_prior(self, k: int, pred: gtsam.Pose3, step: gtsam.Pose3) -> bool:
        """Add the map prior on frame k if its predicted pose is off its road; True if added."""
        m = self._match(pred)
        if m is None:
            return False
        self.counters.matches += 1
        self.matched_way[k] = m.way_id
        width = m.lanes * self.cfg.lane_width_m
        r_pose, lateral = map_pose(m, pred)
        if lateral <= width:
            return False
        gate = self.cfg.prior_gate_sigma
        if m.angle_deg > self.cfg.prior_max_angle_deg or (m.is_join and not self.cfg.prior_on_joins) \
                or (gate > 0 and lateral > gate * math.hypot(self._pos_sigma, 0.5 * width)) \
                or self._ambiguous(m, pred):
            self.counters.priors_gated += 1
            return False
        dt = self._t[k] - self._t[k - 1]
        v_lon, v_lat = step.x() / dt, step.y() / dt
        motion_dir = pred.rotation().yaw() + math.atan2(step.y(), step.x()) if step.translation()[:2].any() else pred.rotation().yaw()
        r = prior_sqrt_information(m.yaw_rad, motion_dir, v_lon, v_lat, self._yaw_sigma,
                                   self.cfg.prior_lambda_floor_m2, self.cfg.prior_mode)
        noise = gtsam.noiseModel.Gaussian.SqrtInformation(r, False)
        if self._robust is not None:
            noise = gtsam.noiseModel.Robust.Create(self._robust, noise)
        self._pending.graph.add(gtsam.PriorFactorPose3(X(k), r_pose, noise))
        self.counters.map_priors += 1
        self.map_prior_frames.append(k)
        return True

    def _maybe_odometry_prior(self, k: int, pred: gtsam.Pose3) -> None:
        """Paper IV.B: when the marginal positional σ exceeds the road width, the odometry estimate
        becomes a prior (with σ = the road width), so uncertainty cannot grow without bound."""
        if not self.cfg.odometry_priors or self._smoother is None:
            return
        if self._t[k] - self._last_cov_check_t < self.cfg.odometry_prior_every_s or self._last_updated_key < 0:
            return
        self._last_cov_check_t = self._t[k]
        try:
            cov = self._smoother.covariance(X(self._last_updated_key))
        except (RuntimeError, IndexError):
            # no marginal for that key (e.g. ISAM2 re-anchored after a failed Cholesky update and
            # the key is not in the new Bayes tree): skip this check, the next one will have one
            return
        sig = math.sqrt(max(np.linalg.eigvalsh(cov[3:5, 3:5]).max(), 0.0))
        self._pos_sigma = sig
        m = self.road.match(pred.x(), pred.y(), pred.rotation().yaw(), self.cfg.search_radius_m) if self.cfg.use_map else None
        width = (m.lanes if m else 1) * self.cfg.lane_width_m
        if sig <= width:
            return
        if self.cfg.state is StateModel.planar:
            sigmas = [1e-3, 1e-3, self._yaw_sigma, width, width, 1e-3]
        else:
            sigmas = [self._yaw_sigma, self._yaw_sigma, self._yaw_sigma, width, width, width]
        self._pending.graph.add(gtsam.PriorFactorPose3(X(k), pred, gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas))))
        self.counters.odometry_priors += 1

    # ------------------------------------------------------------------ GPS
    def _flush_gps(self) -> None:
        """Attach waiting fixes to the frame nearest in time, once that frame exists."""
        if not self.initialised or not self._t:
            return
        keep = []
        for fix in self._gps_wait:
            t = fix[0]
            if t > self._t[-1] + 0.5 * self._frame_period():
                keep.append(fix)
                continue
            k = self._frame_at(t)
            if abs(self._t[k] - t) > 1.0:
                self.counters.gps_rejected_invalid += 1
                continue
            self._gate_and_add(k, *fix[1:])
        self._gps_wait = keep

    def _frame_period(self) -> float:
        return (self._t[-1] - self._t[-2]) if len(self._t) >= 2 else 0.1

    def _gate_and_add(self, k: int, x: float, y: float, alt: float | None, sigma: float) -> None:
        """Mahalanobis gate. A run of rejected fixes that agree with each other means the estimate
        is lost, not the GPS: after ``relocalise_after_fixes`` in a row (within 60 s) whose distances
        from the first match the odometry's within the gate, the estimate is re-initialised from
        them (counted)."""
        pred = self._online[k] or self._online[-1]
        spread = math.sqrt(sigma * sigma + self._pos_sigma * self._pos_sigma + 1.0)
        if math.hypot(pred.x() - x, pred.y() - y) <= self.cfg.gps_gate_sigma * spread:
            self._rejected_run.clear()
            self._add_gps_factor(k, x, y, alt, sigma)
            return
        self.counters.gps_rejected_gate += 1
        t = self._t[k]
        # the run is broken by any accepted fix; with GPS every 5 s, three fixes span 10 s
        self._rejected_run = [r for r in self._rejected_run if t - r[0] <= 60.0] + [(t, x, y, k)]
        if len(self._rejected_run) >= self.cfg.relocalise_after_fixes and self._run_consistent(sigma):
            self.counters.gps_relocalisations += 1
            log.info("t=%.1f s: %d consistent GPS fixes disagree with the estimate: re-localising on GPS",
                     t, len(self._rejected_run))
            self._relocalise(sigma)

    def _relocalise(self, sigma: float) -> None:
        """Re-initialise from GPS, as at the start: the run's last fix gives the position, the angle
        between the run's GPS displacement and the estimate's own displacement corrects the heading.
        A fresh smoother is anchored there and the frames since are re-added on top."""
        run = self._rejected_run
        _, x0, y0, k0 = run[0]
        _, xn, yn, kn = run[-1]
        p0, pn = self._online[k0], self._online[kn]
        dg = (xn - x0, yn - y0)
        do = (pn.x() - p0.x(), pn.y() - p0.y())
        length = math.hypot(*dg)
        delta = math.atan2(dg[1], dg[0]) - math.atan2(do[1], do[0]) if length > 5.0 and math.hypot(*do) > 5.0 else 0.0
        yaw = pn.rotation().yaw() + delta
        anchor = gtsam.Pose3(gtsam.Rot3.Ypr(yaw, pn.rotation().pitch(), pn.rotation().roll()),
                             gtsam.Point3(xn, yn, pn.z()))
        if self.cfg.state is StateModel.planar:
            anchor = level(anchor)
        yaw_sigma = math.atan2(3.0 * sigma, max(length, 1.0)) + math.radians(2.0)
        for k in range(self._smoothed_upto + 1, kn):
            if self._online[k] is not None:
                self._smoothed.setdefault(k, self._online[k])
        self._smoothed_upto = max(self._smoothed_upto, kn - 1)
        self._smoother = _Smoother(self.cfg)
        self._pending = _Pending()
        self._pending.graph.add(gtsam.PriorFactorPose3(X(kn), anchor, gtsam.noiseModel.Diagonal.Sigmas(
            np.array([1e-3, 1e-3, yaw_sigma, sigma, sigma, 1e-3]))))
        self._insert_value(kn, anchor)
        self._online[kn] = anchor
        pose = anchor
        for k in range(kn + 1, len(self._t)):
            step = self._step(k)
            self._pending.graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), step,
                                                             self._odometry_noise(False, step, self._gap_frames(k))))
            pose = pose.compose(step)
            self._insert_value(k, pose)
            self._online[k] = pose
        self._last_updated_key, self._last_updated_pose = -1, None
        self._rejected_run = []
        self._pos_sigma = sigma
        self._edge = -1
        self._update()

    def _run_consistent(self, sigma: float) -> bool:
        """The run's fixes move as far as the odometry says, each from the first fix. Lengths, not
        vectors: an estimate that is lost is often turned too (a bend in a tunnel)."""
        _, x0, y0, k0 = self._rejected_run[0]
        p0 = self._online[k0]
        for _, x, y, k in self._rejected_run[1:]:
            p = self._online[k]
            if p is None or p0 is None:
                return False
            dg = math.hypot(x - x0, y - y0)
            do = math.hypot(p.x() - p0.x(), p.y() - p0.y())
            if abs(dg - do) > self.cfg.gps_gate_sigma * math.sqrt(2.0) * sigma + 0.05 * do:
                return False
        return True

    def _gps_factor(self, k: int, x: float, y: float, alt: float | None, sigma: float) -> gtsam.GPSFactor:
        planar = self.cfg.state is StateModel.planar or alt is None
        z = 0.0 if planar else alt
        prec_z = 0.0 if planar else 1.0 / (4.0 * sigma * sigma)
        noise = gtsam.noiseModel.Diagonal.Precisions(np.array([1.0 / sigma**2, 1.0 / sigma**2, prec_z]))
        return gtsam.GPSFactor(X(k), gtsam.Point3(x, y, z), noise)

    def _add_gps_factor(self, k: int, x: float, y: float, alt: float | None, sigma: float) -> None:
        self._pending.graph.add(self._gps_factor(k, x, y, alt, sigma))
        self.counters.gps_used += 1

    # ------------------------------------------------------------------ the smoother
    def _update(self) -> None:
        p = self._pending
        if p.graph.size() == 0 and p.values.size() == 0:
            return
        sm = self._smoother
        try:
            if sm.fixed_lag and self._last_updated_key >= 0:
                self._keep_leaving(p)
            sm.update(p.graph, p.values, p.stamps)
            # a second pass lets ISAM2 relinearise around the new solution
            sm.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), {})
            latest = self._last_key
            pose = sm.pose(X(latest))
            self._last_updated_key, self._last_updated_pose = latest, pose
            self._online[latest] = pose
        except (RuntimeError, IndexError) as exc:  # IndeterminantLinearSystem, std::out_of_range and the like
            self.counters.recoveries += 1
            log.warning("GTSAM failed (%s): re-anchoring at the last good estimate", (str(exc).strip().splitlines() or [type(exc).__name__])[0])
            self._reanchor(p)
        self.counters.updates += 1
        self._pending = _Pending()
        self._since_update = 0

    def _keep_leaving(self, p: _Pending) -> None:
        """Store the final estimate of the frames the fixed-lag window is about to marginalise."""
        t_new = max(p.stamps.values()) if p.stamps else self._t[self._last_key]
        horizon = t_new - self.cfg.lag_s
        for k in range(self._smoothed_upto + 1, self._last_updated_key + 1):
            if self._t[k] >= horizon:
                break
            try:
                self._smoothed[k] = self._smoother.pose(X(k))
            except (RuntimeError, IndexError):  # already marginalised
                self._smoothed[k] = self._online[k]
            self._smoothed_upto = k

    def _reanchor(self, failed: _Pending) -> None:
        """A fresh smoother: a tight prior at the last good estimate, then the failed frames on it."""
        anchor_k = self._last_updated_key
        anchor = self._last_updated_pose
        if anchor is None:
            anchor_k = min(failed.keys) - 1 if failed.keys else self._last_key
            anchor = self._online[anchor_k] if anchor_k >= 0 else self._to_map(self._raw[0])
        for k in range(self._smoothed_upto + 1, anchor_k + 1):
            self._smoothed.setdefault(k, self._online[k])
        self._smoothed_upto = max(self._smoothed_upto, anchor_k)
        self._smoother = _Smoother(self.cfg)
        g = gtsam.NonlinearFactorGraph()
        v = gtsam.Values()
        stamps = {}
        g.add(gtsam.PriorFactorPose3(X(anchor_k), anchor, gtsam.noiseModel.Diagonal.Sigmas(
            np.array([1e-3, 1e-3, math.radians(2.0), 0.5, 0.5, 1e-3]))))
        v.insert(X(anchor_k), anchor)
        stamps[X(anchor_k)] = self._t[anchor_k]
        for k in failed.keys:
            if k <= anchor_k:
                continue
            step = self._step(k)
            g.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), step, self._odometry_noise(False, step, self._gap_frames(k))))
            v.insert(X(k), self._online[k] if self._online[k] is not None else anchor)
            stamps[X(k)] = self._t[k]
        try:
            self._smoother.update(g, v, stamps)
            latest = max([anchor_k] + [k for k in failed.keys if k > anchor_k])
            self._last_updated_key, self._last_updated_pose = latest, self._smoother.pose(X(latest))
        except (RuntimeError, IndexError):
            log.error("re-anchoring failed too; continuing from the odometry")
