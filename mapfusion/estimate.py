"""The one owner of the estimate: the alignment (heading, offset and the odometry's scale), the smoother and its
restarts, the steps that replace the odometry's (an outage carried along the road), the final poses and the
estimate's own σ. The road components (:mod:`.reanchoring`, :mod:`.registering`, :mod:`.searching`,
:mod:`.tracking`) propose — a factor, a re-anchoring, a re-scaling, a mended stretch — and :class:`Estimate`
applies; nothing else writes these.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable

import gtsam

from . import factors
from .config import FusionConfig
from .counters import Counters
from .initialisation import Initialiser, solve_initial_batch
from .motion import MotionFusion
from .smoother import Smoother
from .track import Alignment, Track

log = logging.getLogger(__name__)

#: How often the marginal σ is checked for odometry priors. Unit: s.
ODOMETRY_PRIOR_EVERY_S = 1.0

#: Frames between two smoother updates; the online estimate composes odometry on the last update in between.
#: Source: speed (mapfusion bench).
UPDATE_EVERY = 5

#: The map's odometry prior on frame k at a positional σ: (k, predicted pose, σ m) → a factor, or None.
OdometryPrior = Callable[[int, gtsam.Pose3, float], "gtsam.NonlinearFactor | None"]


class Estimate:
    """The estimate and its only writer (see the module docstring). ``on_restart`` callbacks run at every
    re-anchoring, in their order (the road fixes and the road association forget what they followed)."""

    def __init__(self, cfg: FusionConfig, track: Track, counters: Counters, motion: MotionFusion,
                 initialiser: Initialiser, on_restart: tuple[Callable[[], None], ...] = ()) -> None:
        self.cfg, self.track, self.counters = cfg, track, counters
        self._motion = motion  # (read: the odometry σ's factor, the wheel's calibration of the scale)
        self._initialiser = initialiser
        self.alignment: Alignment | None = None
        self.initialised_at: float | None = None
        self.smoother: Smoother | None = None
        self.road_steps: dict[int, gtsam.Pose3] = {}  # steps carried along the road over an odometry outage, by frame
        self.pos_sigma_m = self.lat_sigma_m = 0.0  # the estimate's positional σ: largest, across the vehicle
        self.yaw_sigma_rad = math.inf  # and its yaw σ (unknown until the first check)
        self._on_restart = on_restart
        self._since_update = 0
        self._last_cov_check_t = -math.inf

    # ------------------------------------------------------------------ reading
    @property
    def sm(self) -> Smoother:
        """The smoother (it exists from initialisation on)."""
        assert self.smoother is not None
        return self.smoother

    @property
    def aligned(self) -> Alignment:
        assert self.alignment is not None
        return self.alignment

    def step(self, k: int) -> gtsam.Pose3:
        """The step into frame k: carried along the road, or the odometry's at the estimate's scale."""
        return self.road_steps[k] if k in self.road_steps else self.track.step(k, self.aligned.scale)

    def between(self, k: int, before_init: bool = False, step: gtsam.Pose3 | None = None) -> gtsam.BetweenFactorPose3:
        """The odometry factor into frame k."""
        step = self.step(k) if step is None else step
        noise = factors.odometry_noise(self.cfg, step, self.track.gap_frames(k), self.track.nominal_period_s,
                                       before_init=before_init, scale_sigma=self.aligned.relative_sigma,
                                       sigma_factor=self._motion.sigma_factor)
        return factors.between(k, step, noise)

    def to_map(self, raw: gtsam.Pose3) -> gtsam.Pose3:
        return self.track.to_map(raw, self.aligned)

    # ------------------------------------------------------------------ the scale
    def set_scale(self, scale: float, scale_sigma: float | None = None) -> None:
        """The odometry's scale from now on (a GPS refit, a track run, a search's or the road fixes' answer)."""
        a = self.aligned
        self.alignment = dataclasses.replace(a, scale=scale, scale_sigma=a.scale_sigma if scale_sigma is None
                                             else scale_sigma)

    def refit(self, t: float, x: float, y: float, sigma: float) -> None:
        """``refine_scale``: a GPS fix refits the scale; a calibrated wheel knows it better."""
        fit = self._initialiser.refit_with_fix(self.track, t, x, y, sigma)
        if fit is not None:
            self.set_scale(fit.scale, fit.scale_sigma)
        self.alignment = self._motion.rescale(self.aligned)

    # ------------------------------------------------------------------ beginning
    def begin(self, a: Alignment, anchor: int = 0) -> None:
        """Initialised (by GPS, or a cold start's search at frame ``anchor``): the buffered frames solved as one
        batch; the smoother then starts from the last of them, with the batch's marginal covariance as its prior
        (so the estimates inside the initialisation window use its later fixes too)."""
        self.alignment, self.initialised_at = a, self.track.t[-1]
        self.smoother = Smoother(self.cfg, self.track, self.counters, self.between,
                                 lambda: self.to_map(self.track.raw[0]))
        init = self._initialiser
        if self.cfg.refine_scale:
            fit = init.fit(self.track)
            if fit is not None:
                log.info("scale refined by the initialisation fit: %.4f → %.4f (± %.4f)", self.aligned.scale,
                         fit.scale, fit.scale_sigma)
                self.alignment = self._motion.rescale(fit)
        self._motion.learn_sigma(self.track, self.aligned, init.fixes)
        batch = solve_initial_batch(self.cfg, self.track, self.aligned, init.fixes,
                                    lambda k: self.between(k, before_init=True), self.counters, anchor)
        sm, last = self.sm, len(self.track) - 1
        for k, pose in enumerate(batch.poses):
            self.track.online[k] = pose
        sm.seed(batch.poses[:last])
        sm.add(factors.pose_prior(last, batch.poses[last], batch.last_noise))
        sm.insert(last, batch.poses[last])
        self.update()

    # ------------------------------------------------------------------ frames
    def carry_step(self, k: int, step: gtsam.Pose3) -> None:
        """Frame k's step is ``step`` (carried along the road), not the odometry's, also when a restart re-adds it."""
        self.road_steps[k] = step

    def frame(self, k: int, pred: gtsam.Pose3, prior_added: bool, odometry_prior: OdometryPrior) -> None:
        """Frame k is in the graph with its factors: the σs checked (:meth:`check_sigmas`), and its causal estimate
        (after an update when a map prior came or ``UPDATE_EVERY`` frames have passed: the causal estimate of
        frame k includes its own prior)."""
        self.track.online[k] = pred
        self._since_update += 1
        self.check_sigmas(k, pred, odometry_prior)
        if prior_added or self._since_update >= UPDATE_EVERY:
            sm = self.sm
            self.update()
            if sm.last_updated_key == k:
                self.track.online[k] = sm.last_updated_pose

    def add(self, factor: gtsam.NonlinearFactor) -> None:
        self.sm.add(factor)

    def update(self) -> None:
        if self.sm.update():
            self._since_update = 0

    def check_sigmas(self, k: int, pred: gtsam.Pose3, odometry_prior: OdometryPrior) -> None:
        """Every ``ODOMETRY_PRIOR_EVERY_S``: the marginal σs; paper IV.B: when the positional σ exceeds the road
        width, the odometry estimate becomes a prior (``odometry_prior(k, pred, σ)``: the road width as its σ, or
        None), so uncertainty cannot grow without bound."""
        cfg, sm = self.cfg, self.smoother
        if not cfg.odometry_priors or sm is None or sm.last_updated_key < 0:
            return
        if self.track.t[k] - self._last_cov_check_t < ODOMETRY_PRIOR_EVERY_S:
            return
        self._last_cov_check_t = self.track.t[k]
        sigmas = sm.position_sigmas()
        if sigmas is None:
            return
        self.pos_sigma_m, self.lat_sigma_m, self.yaw_sigma_rad = sigmas
        prior = odometry_prior(k, pred, self.pos_sigma_m)
        if prior is not None:
            sm.add(prior)
            self.counters.odometry_priors += 1

    # ------------------------------------------------------------------ re-anchoring
    def restart_from(self, k: int, pose: gtsam.Pose3, noise, sigma_m: float) -> None:
        """The smoother afresh at frame k (a prior on ``pose``), the estimate's σ set, the parts that follow a
        road told (``on_restart``): the path every re-anchoring takes (GPS's and the map's)."""
        self.sm.restart_from(k, pose, noise, self.step)
        for told in self._on_restart:
            told()
        self.pos_sigma_m = self.lat_sigma_m = sigma_m

    def move_final(self, moves: dict[int, gtsam.Pose3]) -> None:
        """Final poses replaced (a correction spread back over a stretch the fixes or the map could not see)."""
        self.sm.smoothed.update(moves)
