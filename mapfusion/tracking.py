"""Road fixes (``road_fixes``, issues 16 and 17): while GPS is silent, the re-localisation's road-network
particles follow the vehicle from where the estimate is, and their confident answer enters the graph as
a position fix.

The factor graph follows one road association at a time; a wrong one, or an odometry whose scale
wanders (a monocular VO: tens of percent), takes it off the network, and the map's priors then come
from wrong roads. The particles keep many places and scales at once, each weighed by how well the
odometry's shape since the start fits the roads it would have driven (:class:`~mapfusion.relocalise.
RoadParticles`): their answer does not depend on the estimate, so it can pull a lost estimate back.
They start on the roads within ``RoadFixParams.radius_m`` (at least 3 σ) of the estimate when no GPS fix
was used for ``RoadFixParams.after_gps_s``, their scales log-uniform within the estimate's scale ×/÷
``RoadFixParams.scale_factor`` and walking (``ParticleParams.scale_walk``) — the map observes the scale as it
observes the place. Every ``RoadFixParams.every_m`` of driving, when one disc of ``RoadFixParams.cluster_m``
holds ``RoadFixParams.min_mass`` of the posterior, its pose is a fix: σ its spread (at least
``RoadFixParams.sigma_m``; Gaussian: under the map priors' robust kernel a fix far from a lost estimate
would be too weak to pull it back, and the posterior's mass already weighed the roads), and not added
unless it moved as the estimate did since the last one (``RoadFixParams.gate_sigma``, ``RoadFixParams.drift``), and
not while the estimate lies on a road within ``RoadFixParams.agree_m`` of it (a right estimate is not pulled
to the particles' own errors), nor, farther, while the particles still hold ``RoadFixParams.rival_mass`` of their
posterior near it (they preferred another place without ruling its own out). A new answer (after a start,
or a step without one) must first hold, confident and continuous, over ``RoadFixParams.hold_m``. Particles that
give no confident answer over ``RoadFixParams.restart_m`` start again around the estimate: a posterior spread
for long gathers again on look-alike roads far away. A used GPS fix stops them. Their number adapts to
how settled the posterior is (``RoadFixParams.kld_epsilon``: KLD-sampling), and a start spreads at most
``RoadFixParams.particles`` (per scale band) however large its region.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from . import factors
from .config import FusionConfig
from .counters import Counters
from .estimate import Estimate
from .relocalise import (
    RELOC_SEED,
    ROAD_FIX_UTURN_PROBABILITY,
    SEARCH_PARTICLES,
    Guess,
    Located,
    ParticleParams,
    Region,
    RoadParticles,
)
from .roadmap import RoadMap
from .track import planar_of

log = logging.getLogger(__name__)

__all__ = ["RoadFixes", "particle_config"]


@dataclass(frozen=True)
class RoadFixParams:
    """The road fixes' own settings (:data:`ROAD_FIX_PARAMS`): fixed values of the engine, each chosen by the
    measurement its comment names, not settings of :class:`~mapfusion.config.FusionConfig`; tests and benchmarks
    build :class:`RoadFixes` with others."""

    #: reloc_particles for the road fixes' particles: the most a start spreads over its region's roads (before the
    #: scale bands multiply it); a region grown by a long stretch without a fix is covered more thinly instead of
    #: costing more. Source: issue 21: 60-run sets, 60000 / 20000 / 8000: seeds 1-10 7.35 / 7.21 / 8.10 m, fusion
    #: 132 / 122 / 116 s; held-out 11-20 6.32 / 6.32 m, 135 / 122 s.
    particles: int = 20000

    #: Radius of the region around the estimate the particles start in (at least 3 × the estimate's positional σ).
    #: Unit: m. Source: issue 16; by measurement.
    radius_m: float = 50.0

    #: Largest region the particles start in, however long the drive went without a fix: wider, particles cover it
    #: too thinly to converge, and their cost keeps growing as they spread over the map (finding a vehicle that far
    #: off is map_relocalisation's search). Unit: m. Source: issue 21: a one-hour drive whose fixes never came
    #: (mapfusion bench).
    radius_max_m: float = 2000.0

    #: The particles' scales start within the estimate's scale ×/÷ this (a monocular VO's scale wanders by tens of
    #: percent). Source: issue 16 item 3; real TrianFlow scale 25-31 on KITTI 00.
    scale_factor: float = 1.3

    #: Driving between two fixes. Unit: m. Source: issue 16; by measurement.
    every_m: float = 5.0

    #: Posterior mass within cluster_m a fix needs. Source: issue 16; as reloc_converge_mass.
    min_mass: float = 0.8

    #: Particles that gave no confident answer over this much driving start again around the estimate (a posterior
    #: spread for long gathers again on look-alike roads far away). Unit: m. Source: issue 16; real TrianFlow on
    #: KITTI 01.
    restart_m: float = 300.0

    #: No fix while the estimate lies on a road (within agree_widths of its centre line, its heading within
    #: prior_max_angle_deg) this close to the particles' answer: a right estimate is not pulled to the particles'
    #: own errors (0: a fix whenever confident). Unit: m. Source: issue 16: KITTI's ground truth as odometry bent
    #: 0.37 -> 3.43 m without it.
    agree_m: float = 20.0

    #: How far from a road's centre line the estimate still lies on it, for agree_m, in road widths (lanes ×
    #: lane_width_m): OSM's centre line of an untagged two-way street is one 3 m lane, and a tracked estimate
    #: strays 3-5 m from it. Source: issue 16: simulated VO on KITTI 00/02/05 (1 width: 2.9 -> 4.0 m, 5.3 -> 7.1 m;
    #: 2.5: unchanged) and 60 runs seeds 1-10 (10.8 m; any distance: 11.7 m).
    agree_widths: float = 2.5

    #: No fix farther than agree_m from the estimate while the particles hold at least this share of their
    #: posterior within half that distance of the estimate (outside the answer's cluster_m): they have not
    #: ruled its place out, only preferred another (a parallel road, a wrong scale) (0: no such test). Source:
    #: issue 16: Helsinki VIO clear-full s3, fixes 43 m off with 15% of the posterior at the estimate; by
    #: measurement.
    rival_mass: float = 0.05

    #: Smallest σ of a fix (per axis; the cluster's spread when larger). Unit: m. Source: issue 16; by measurement.
    sigma_m: float = 3.0

    #: Largest heading innovation the road fixes' particles' offsets follow in one step: a slow drift is followed,
    #: a turn the road did not make (the vehicle turned where a particle went straight) is not absorbed. Unit: deg.
    #: Source: issue 16: Helsinki seed 5 (90° absorbed in five steps).
    offset_max_deg: float = 5.0

    #: Each road fix moves the engine's odometry scale this fraction of the way (in log) to the fix's cluster's
    #: scale: the map keeps observing the scale after GPS ends (0: the scale GPS measured stays). Source: issue 16
    #: item 3.
    scale_gain: float = 0.02

    #: What the odometry may drift, as a fraction of the distance driven: the gate's allowance since its last
    #: answer, and a restart's radius (× 3) since the last fix (GPS's or a road fix). Source: issue 16; real
    #: TrianFlow drifts 10-12% (KITTI t_err).
    drift: float = 0.1

    #: The particles start weighted by the estimate's heading: a Gaussian of this σ (or 3 × the smoother's marginal
    #: yaw σ, when larger) in the angle between each particle's heading (its road's, in its direction) and the
    #: estimate's, above heading_floor. Without it a start spreads both ways along every road of its region, and on
    #: a regular grid the mirrored and turned copies of the path fit the odometry as well as the true one for ever;
    #: 0: off. Unit: deg. Source: issue 21: the bench's grid city.
    heading_sigma_deg: float = 0.0

    #: With heading_sigma_deg: the share of a start's weight a particle keeps however far its heading lies from the
    #: estimate's (an estimate's heading may be wrong). Source: issue 21.
    heading_floor: float = 0.01

    #: The particles start when no GPS fix was used for this long; a used fix stops them. Unit: s. Source: GPS places
    #: the estimate better while it comes.
    after_gps_s: float = 2.0

    #: A new answer (after a start, or after a step without one) is a fix only once it has been confident and
    #: continuous over this much driving. Unit: m. Source: issue 16: Helsinki rain seed 2 (one answer 190 m off after a
    #: restart).
    hold_m: float = 50.0

    #: An answer that moved, since the last one, farther from where the estimate moved than this × the combined σ (the
    #: answer's spread, the drift) is not a fix (0: no gate). Source: issue 16: never make a drive worse.
    gate_sigma: float = 5.0

    #: Radius of the disc whose mass decides a fix. Unit: m. Source: as ParticleParams.converge_radius_m.
    cluster_m: float = 25.0

    #: ParticleParams.kld_epsilon for the road fixes' particles: once they agree on one place they need far fewer
    #: than it took to find it. Source: issue 21; by measurement.
    kld_epsilon: float = 0.05


#: The engine's road fixes.
ROAD_FIX_PARAMS = RoadFixParams()


def particle_config(params: RoadFixParams) -> ParticleParams:
    """The road fixes' particles' own view of the configuration: no distance before an answer (they start
    where the vehicle is), the fix's disc and mass, their offsets and turns back, their adaptive count and
    the start's cap."""
    return dataclasses.replace(SEARCH_PARTICLES, min_distance_m=0.0, converge_radius_m=params.cluster_m,
                               converge_mass=params.min_mass, offset_max_deg=params.offset_max_deg,
                               uturn_probability=ROAD_FIX_UTURN_PROBABILITY, uturn_at_vertex=0.0,
                               kld_epsilon=params.kld_epsilon, particles=params.particles)


class RoadFixes:
    """The particles that follow the vehicle while GPS is silent, and the fixes they give."""

    def __init__(self, road: RoadMap, cfg: FusionConfig, counters: Counters,
                 params: RoadFixParams = ROAD_FIX_PARAMS) -> None:
        self.road, self.cfg, self.counters = road, cfg, counters  # (counts road_fixes and road_fixes_gated)
        self.params = params
        self.enabled = cfg.road_fixes and cfg.use_map
        self.particles: RoadParticles | None = None  # the filter while it runs
        self._filter: RoadParticles | None = None
        self.last_gps_t = -math.inf
        self.starts = 0
        self.last: Located | None = None  # the particles' answer at the last fix's turn (None: not confident)
        self._anchor = (0.0, 0.0)  # odometry position (its own units) at the last particle step
        self._last_xy = (0.0, 0.0)
        self._moved = 0.0  # odometry distance since that step, its own units
        self._since_fix_m = 0.0
        self._unsure_m = 0.0  # driving since the particles last gave a confident answer (or started)
        self._unfixed_m = 0.0  # driving since the last fix (GPS's or a road fix)
        self._since_ref_m = 0.0  # driving since the reference below
        self._held_m = 0.0  # driving over which the answer has been confident and continuous
        self._ref = (0.0, 0.0, 0.0, 0.0)  # the last fix added and the estimate then, or the start's estimate twice
        self._ref_pending = False  # the reference's estimate is taken at the next frame (after the fix's update)
        self._after_reanchoring = False  # the next start follows a re-anchoring: it waits for a steady heading
        self._pending: tuple[float, float, float] | None = None  # odometry pose a start's steadiness is measured from
        self._near_only = False  # this frame: no fix far from the estimate (an estimate kept to the roads)
        self._ref_slack_m = 0.0  # how far from the reference an answer may lie besides drift (the start's radius)

    def gps_used(self, t: float) -> None:
        """A GPS fix entered the graph: it places the estimate, the particles stop."""
        self.last_gps_t = t
        self.drop()
        self._unfixed_m = 0.0

    def reanchored(self) -> None:
        """The smoother was re-anchored (by GPS or the map): the particles start again around the new estimate,
        whose σ is the re-anchoring's — the drift since the last fix no longer widens their region — once the
        heading is steady (:meth:`_steady`)."""
        self.drop()
        self._unfixed_m = 0.0
        self._after_reanchoring = True

    def drop(self) -> None:
        """Stop the particles: they start afresh (around the estimate then) at a later frame."""
        self.particles = None
        self._pending = None

    def fix(self, k: int, t: float, raw: gtsam.Pose3, pred: gtsam.Pose3, estimate: Estimate,
            searching: bool, kept_to_roads: Callable[[], bool]) -> gtsam.NonlinearFactor | None:
        """The particles' fix on frame k (``raw``: its odometry pose) while GPS is silent (None: none), proposed with
        a scale: each fix moves the estimate's odometry scale ``scale_gain`` of the way (in log) to the
        fix's (the map observes the scale). ``searching``: a map search runs (the particles stop, to start afresh
        around the estimate it leaves); ``kept_to_roads()``: the estimate's recent path kept to the roads."""
        if not self.enabled:
            return None
        cfg = self.cfg
        if searching:
            self.drop()
            return None
        a = estimate.aligned
        near_only = cfg.map_relocalisation and kept_to_roads()
        fix = self.step(k, t, planar_of(raw), a.scale, pred, estimate.pos_sigma_m, near_only=near_only,
                        yaw_sigma_rad=estimate.yaw_sigma_rad)
        if fix is None:
            return None
        loc, gain = self.last, self.params.scale_gain
        if loc is not None and gain > 0:
            estimate.set_scale(math.exp((1.0 - gain) * math.log(a.scale) + gain * math.log(loc.scale)))
        return fix

    def step(self, k: int, t: float, raw_xy_yaw: tuple[float, float, float], scale: float, pred: gtsam.Pose3,
             sigma_m: float, near_only: bool = False, yaw_sigma_rad: float = math.inf) -> gtsam.NonlinearFactor | None:
        """Frame k at time t: the odometry's raw planar pose (its own units and frame), the estimate's scale
        (metres per odometry unit), the predicted pose and its positional σ (m); ``near_only``: no fix farther
        than ``agree_m`` from the estimate (with ``map_relocalisation``, while the estimate kept to the roads);
        ``yaw_sigma_rad``: the estimate's marginal yaw σ (for ``heading_sigma_deg``). Returns a fix on
        frame k, or None."""
        self._near_only = near_only
        silent = t - self.last_gps_t >= self.params.after_gps_s
        if not (self.enabled and silent and math.isfinite(scale) and scale > 0):
            return None
        x, y, yaw = raw_xy_yaw
        if self._ref_pending:  # the estimate the last fix moved: this frame's prediction starts from it
            self._ref, self._ref_pending = (self._ref[0], self._ref[1], pred.x(), pred.y()), False
        if self.particles is None:
            if self._steady(x, y, yaw, scale):
                self._start(x, y, yaw, scale, pred, sigma_m, yaw_sigma_rad)
            return None
        if len(self.particles) == 0:  # no road in the region: start again from the next frame's estimate
            self.drop()
            return None
        self._moved += math.hypot(x - self._last_xy[0], y - self._last_xy[1])
        self._last_xy = (x, y)
        if self._moved * scale < SEARCH_PARTICLES.step_m:
            return None
        moved, chord = self._moved, np.array([x - self._anchor[0], y - self._anchor[1]])
        self._anchor, self._moved = (x, y), 0.0
        self.particles.step(moved, chord)
        self._since_fix_m += moved * scale
        self._unfixed_m += moved * scale
        self._since_ref_m += moved * scale
        if self._since_fix_m < self.params.every_m:
            return None
        loc = self.particles.located(yaw)
        self.last = loc
        return self._answer(k, loc, pred)

    def _answer(self, k: int, loc: Located | None, pred: gtsam.Pose3) -> gtsam.NonlinearFactor | None:
        """The particles' answer at a fix's turn (None: not confident): the fix, or None with the guards' state
        moved on."""
        cfg = self.cfg
        sigma = max(loc.spread_m, self.params.sigma_m) if loc is not None else math.inf
        # continuity: since the last fix that entered the graph (or the particles' start, whose region the answer
        # may lie anywhere in), the answer has moved as the estimate has, within what the odometry may have
        # drifted — a posterior that jumps to another road, or runs off where the vehicle turned, is not a fix
        gated = False
        if loc is not None and self.params.gate_sigma > 0:
            fx, fy, px, py = self._ref
            ex, ey = loc.x_m - (fx + pred.x() - px), loc.y_m - (fy + pred.y() - py)
            tolerance = self._ref_slack_m + self.params.gate_sigma * math.hypot(sigma, self.params.drift *
                                                                                 self._since_ref_m)
            gated = math.hypot(ex, ey) > tolerance
        if loc is None or gated:
            self.counters.road_fixes_gated += gated
            self._unsure_m += self._since_fix_m
            self._since_fix_m = self._held_m = 0.0
            if self._unsure_m >= self.params.restart_m:  # no fix for too long: start again around the estimate
                self.drop()
            return None
        held, self._held_m = self._held_m, self._held_m + self._since_fix_m
        self._since_fix_m = self._unsure_m = self._since_ref_m = self._ref_slack_m = 0.0
        if held < self.params.hold_m:  # a new answer holds, moving as the estimate does, before it is a fix
            self._ref, self._ref_pending = (loc.x_m, loc.y_m, pred.x(), pred.y()), False
            return None
        self._unfixed_m = 0.0
        agree = self._agrees(loc, pred)
        self._ref, self._ref_pending = (loc.x_m, loc.y_m, pred.x(), pred.y()), not agree
        if agree:
            return None
        self.counters.road_fixes += 1
        return factors.gps_factor(cfg.state, k, loc.x_m, loc.y_m, None, sigma)  # (z free: the map has no height)

    def _agrees(self, loc: Located, pred: gtsam.Pose3) -> bool:
        """The estimate is on a road (within ``agree_widths`` road widths of its centre line, at most
        prior_max_angle_deg off its heading) within ``agree_m`` of the answer: a fix would only pull a
        right estimate to the particles' own errors (their place on the centre line, their spread along the
        road). Or, farther, the particles still hold ``rival_mass`` of their posterior near the
        estimate: they preferred another place without ruling its own out."""
        cfg = self.cfg
        if math.hypot(loc.x_m - pred.x(), loc.y_m - pred.y()) > self.params.agree_m:
            if self._near_only:  # (far answers are the search's, or the path kept to the roads: not moved far)
                return True
            return self._rival_mass(loc, pred) >= self.params.rival_mass > 0  # (far: unless they still hold it)
        m = self.road.match(pred.x(), pred.y(), pred.rotation().yaw(), cfg.search_radius_m, cfg.angle_weight_m_per_deg)
        return (m is not None and m.lateral_m <= self.params.agree_widths * m.lanes * cfg.lane_width_m
                and m.angle_deg <= cfg.prior_max_angle_deg)

    def _rival_mass(self, loc: Located, pred: gtsam.Pose3) -> float:
        """The particles' posterior mass within agree_m / 2 of the estimate, outside the answer's own
        disc (``RoadFixParams.cluster_m``)."""
        p = self.particles
        if p is None or len(p) == 0:
            return 0.0
        xy = p.positions()
        near = (np.hypot(xy[:, 0] - pred.x(), xy[:, 1] - pred.y()) <= 0.5 * self.params.agree_m) & \
            (np.hypot(xy[:, 0] - loc.x_m, xy[:, 1] - loc.y_m) > self.params.cluster_m)
        return float(np.exp(p.logw[near]).sum())

    def _steady(self, x: float, y: float, yaw: float, scale: float) -> bool:
        """May the particles start: the odometry's heading turned by at most ``offset_max_deg`` over its
        last ``ParticleParams.step_m`` — the first start after a re-anchoring. The
        particles start heading along their roads, which is where the vehicle heads only when it is not turning:
        started mid-turn at a junction, those on the road it turns into carry the turn still to come in their
        offsets, more than they may absorb, and die. A search converges where the path turns, so the re-anchoring
        it makes (and the start after it) falls at a junction."""
        if not self._after_reanchoring:
            return True
        if self._pending is None:
            self._pending = (x, y, yaw)
            return False
        px, py, pyaw = self._pending
        if math.hypot(x - px, y - py) * scale < SEARCH_PARTICLES.step_m:
            return False
        self._pending = (x, y, yaw)
        return abs(math.remainder(yaw - pyaw, 2.0 * math.pi)) <= math.radians(self.params.offset_max_deg)

    def _start(self, x: float, y: float, yaw: float, scale: float, pred: gtsam.Pose3, sigma_m: float,
               yaw_sigma_rad: float = math.inf) -> None:
        if self._filter is None:  # (one filter, started afresh each time: its exits table is built once)
            self._filter = RoadParticles(self.road, particle_config(self.params), RELOC_SEED)
        self.particles, self._after_reanchoring = self._filter, False
        f = self.params.scale_factor
        # around the estimate, as far as it may be off: its marginal's 3 σ, or 3 × what the odometry may have
        # drifted since the last fix (a restart after a long stretch without one)
        radius = min(max(self.params.radius_m, 3.0 * sigma_m, 3.0 * self.params.drift * self._unfixed_m),
                     max(self.params.radius_max_m, self.params.radius_m))
        guess = None
        if self.params.heading_sigma_deg > 0:  # (the place anywhere in the region: only the heading is weighed)
            guess = Guess(pred.x(), pred.y(), math.inf, pred.rotation().yaw(),
                          max(math.radians(self.params.heading_sigma_deg), 3.0 * yaw_sigma_rad),
                          self.params.heading_floor)
        self.particles.start(Region(pred.x(), pred.y(), radius), yaw, scale_range=(scale / f, scale * f), guess=guess)
        self.starts += 1
        self._anchor = self._last_xy = (x, y)
        self._moved = self._since_fix_m = self._unsure_m = self._since_ref_m = self._held_m = 0.0
        self._ref, self._ref_slack_m, self._ref_pending = (pred.x(), pred.y(), pred.x(), pred.y()), radius, False
        log.info("GPS silent: road particles follow the vehicle from (%.0f, %.0f), %.0f m around, %d particles",
                 pred.x(), pred.y(), radius, len(self.particles))
