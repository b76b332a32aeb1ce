"""Which road a predicted pose lies on, and whether the map may correct it (paper III.B, DESIGN
items 2, 3 and 7): the match by D = E + w·A, the gates that keep wrong-road priors out, and the map prior's
factor.

A prior is added only when the predicted pose lies farther from its road than the road is wide
(road width = lanes × ``lane_width_m``), and not when the match's angle exceeds
``prior_max_angle_deg``, the match lies on a join inside a junction, another way's best D is
within ``prior_ambiguity_m`` (junctions, parallel roads; a way continuing the match's road on its line, within
``prior_ambiguity_line_m``, is the same road and no rival). Where the prior puts the
vehicle across the road is ``prior_target``: the centre line (the paper), the nearest edge of the
band (the default), or the band combined with the estimate's own lateral σ; at most
one prior per ``prior_spacing_m`` of driving.
"""

from __future__ import annotations

import collections
import math

import gtsam
import numpy as np

from . import factors, relocalise
from .config import FusionConfig, PriorTarget
from .counters import Counters
from .geometry import on_line
from .matcher import Match, lateral_bound_ok, map_pose, match, match_candidates
from .roadmap import RoadMap

#: Half-width of the band the edge and band targets use, as a fraction of the road width (lanes × lane width): 0.5
#: is the road's own half-width, 1 the paper's trigger distance. Source: issue 16; by measurement.
PRIOR_BAND_FRACTION = 1.0

#: No heading prior from a match whose angle A exceeds this: an estimate turning, changing lanes or matched to the
#: crossing road. Unit: deg. Source: a lane change turns a vehicle some 3-6 degrees.
HEADING_PRIOR_MAX_DEG = 10.0


#: Distances within this of SearchParams.gps_fit_m count as covering it (the running sums' rounding decides nothing).
FIT_TIE_M = 1e-6

#: Floor of the band prior's σ across the road: the moment-matched factor of an estimate far
#: outside the band is next to rigid, and GTSAM's linear algebra should not see a σ of micrometres.
BAND_SIGMA_FLOOR_M = 0.1


def _across(pose: gtsam.Pose3, lateral_m: float) -> gtsam.Pose3:
    """The pose moved ``lateral_m`` to its left (its own y axis)."""
    return pose.compose(gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(0.0, lateral_m, 0.0)))


#: A heading prior needs its road straight: way-points (~1 m apart) either side of the match's within this heading.
STRAIGHT_M = 20
STRAIGHT_DEG = 2.0

#: Most a way-point's heading may turn from the match's road's and still continue it (prior_ambiguity_line_m).
_CONTINUES_RAD = math.radians(10.0)


class MapAssociation:
    """The matcher as the engine uses it, with the state matching continuity needs."""

    def __init__(self, road: RoadMap, cfg: FusionConfig, counters: Counters) -> None:
        self.road = road
        self.cfg = cfg
        self.counters = counters
        if cfg.use_map:
            _ = road.cells  # the map's cell index, built with the engine rather than inside its first frame
        self._robust = factors.robust_kernel(cfg)
        self._unexplained_m = 0.0
        self.lost = False  # no road explains the estimate (watched with map_relocalisation: lost_events)
        self.became_lost = False  # set when the estimate becomes lost; cleared by take_became_lost
        self.explained_xy: tuple[float, float] | None = None  # the estimate where a road last explained it
        self._since_prior_m = math.inf  # odometry distance since the last map prior
        self._since_heading_m = math.inf  # odometry distance since the last heading prior
        # the estimate's recent path: (distance, on a road?) per frame over the last SearchParams.gps_fit_m
        self._fit: collections.deque[tuple[float, bool]] = collections.deque()
        self._fit_m = self._fit_on_m = 0.0

    def reset(self) -> None:
        """Forget what was watched (after a re-localisation)."""
        self._unexplained_m, self.lost = 0.0, False

    def take_became_lost(self) -> bool:
        """Whether the estimate became lost since the last call (the flag is cleared)."""
        became, self.became_lost = self.became_lost, False
        return became

    def _watch_lost(self, explained: bool, moved_m: float, pred: gtsam.Pose3) -> None:
        """Lost after ``lost_after_m`` of driving unexplained (no road within ``lost_cost_m`` of D); found again at
        the next explained frame."""
        if explained:
            self._unexplained_m, self.lost = 0.0, False
            self.explained_xy = (pred.x(), pred.y())
            return
        self._unexplained_m += moved_m
        if not self.lost and self._unexplained_m >= self.cfg.lost_after_m:
            self.lost = True
            self.became_lost = True
            self.counters.lost_events += 1

    def _record_fit(self, m: Match | None, moved_m: float) -> None:
        """One frame of the estimate's path: on a road (within its width + ``SearchParams.gps_fit_margin_m`` of the
        centre line, its heading within ``prior_max_angle_deg``) or not, over the last ``SearchParams.gps_fit_m``."""
        sp = relocalise.SEARCH_PARAMS
        cfg = self.cfg
        on = m is not None and m.angle_deg <= cfg.prior_max_angle_deg and \
            m.lateral_m <= m.lanes * cfg.lane_width_m + sp.gps_fit_margin_m
        self._fit.append((moved_m, on))
        self._fit_m += moved_m
        self._fit_on_m += moved_m if on else 0.0
        while len(self._fit) > 1 and self._fit_m - self._fit[0][0] >= sp.gps_fit_m - FIT_TIE_M:
            d, was_on = self._fit.popleft()
            self._fit_m -= d
            self._fit_on_m -= d if was_on else 0.0

    def road_fit(self) -> float | None:
        """The share of the estimate's last ``SearchParams.gps_fit_m`` of driving that lay on a road (None before any
        driving)."""
        if self._fit_m <= 0.0:
            return None
        return min(max(self._fit_on_m / self._fit_m, 0.0), 1.0)

    def kept_to_roads(self) -> bool:
        """At least ``SearchParams.gps_fit_min`` of the estimate's last ``SearchParams.gps_fit_m`` lay on a road (False
        where the share is not measured: before any driving, or with ``map_relocalisation`` or
        ``SearchParams.gps_fit_min`` off)."""
        sp = relocalise.SEARCH_PARAMS
        fit = self.road_fit()
        return sp.gps_fit_min > 0 and fit is not None and fit >= sp.gps_fit_min

    @property
    def unexplained_m(self) -> float:
        """Odometry distance since a road last explained the estimate."""
        return self._unexplained_m

    def match(self, pred: gtsam.Pose3) -> Match | None:
        """The best way-point for a predicted pose (the paper's D = E + w·A)."""
        cfg = self.cfg
        return match(self.road, pred.x(), pred.y(), pred.rotation().yaw(), cfg.search_radius_m,
                     cfg.angle_weight_m_per_deg)

    def ambiguous(self, m: Match, pred: gtsam.Pose3) -> bool:
        """Another way's best D lies within ``prior_ambiguity_m`` of the match's."""
        margin = self.cfg.prior_ambiguity_m
        if margin <= 0:
            return False
        road = self.road
        near = road.query_radius(pred.x(), pred.y(), self.cfg.search_radius_m)
        other = near[road.way_index[near] != road.way_index[m.index]]
        if other.size and self.cfg.prior_ambiguity_line_m > 0:
            other = other[~self._continues(m, other)]
        if other.size == 0:
            return False
        _, _, _, _, d = match_candidates(pred.x(), pred.y(), pred.rotation().yaw(), road.xy_m[other],
                                         road.legal_cos[other], road.legal_sin[other],
                                         self.cfg.angle_weight_m_per_deg, road.two_way_sign[other])
        return d - m.cost < margin

    def _continues(self, m: Match, points: np.ndarray) -> np.ndarray:
        """Which way-points continue the match's road (``prior_ambiguity_line_m``): on its line, heading along it."""
        road = self.road
        return on_line(road.xy_m[m.index], road.yaw_rad.item(m.index), road.xy_m[points], road.yaw_rad[points],
                       self.cfg.prior_ambiguity_line_m, _CONTINUES_RAD)

    def gated(self, m: Match, pred: gtsam.Pose3, lateral_m: float, width_m: float, pos_sigma_m: float) -> bool:
        """A prior from this match would likely come from the wrong road."""
        cfg = self.cfg
        return (m.angle_deg > cfg.prior_max_angle_deg or (m.is_join and not cfg.prior_on_joins)
                or self.ambiguous(m, pred))

    def prior(self, k: int, pred: gtsam.Pose3, step: gtsam.Pose3, dt_s: float, pos_sigma_m: float,
              lat_sigma_m: float = 0.0) -> tuple[Match | None, gtsam.PriorFactorPose3 | None]:
        """The match of frame k's predicted pose and, if the map should correct it, its prior."""
        sp = relocalise.SEARCH_PARAMS
        moved_m = math.hypot(step.x(), step.y())
        m = self.match(pred)
        if self.cfg.map_relocalisation:  # (lost is watched for only where it is acted on)
            self._watch_lost(m is not None and m.cost <= self.cfg.lost_cost_m, moved_m, pred)
        self._since_prior_m += moved_m
        if self.cfg.map_relocalisation and sp.gps_fit_min > 0:
            self._record_fit(m, moved_m)
        if m is None:
            return None, None
        self.counters.matches += 1
        width = m.lanes * self.cfg.lane_width_m
        if self._since_prior_m < self.cfg.prior_spacing_m or lateral_bound_ok(m, pred.matrix(), width):
            return m, None  # (most frames: on the road; R_t is built only when a prior may follow)
        r_pose, lateral = map_pose(m, pred)
        if lateral <= width:
            return m, None
        if self.gated(m, pred, lateral, width, pos_sigma_m):
            self.counters.priors_gated += 1
            return m, None
        if self.cfg.prior_target is PriorTarget.band:
            # the map says the vehicle is on the road, not on its centre line: the band's
            # information given the estimate's own lateral σ (and the map's)
            sigma = max(math.hypot(lat_sigma_m, self.cfg.prior_map_sigma_m), 0.05)
            upd = factors.band_update(m.signed_lateral_m, sigma, PRIOR_BAND_FRACTION * width)
            if upd is None:
                return m, None
            r_pose = _across(r_pose, upd[0])
            noise = factors.band_prior_noise(self.cfg, max(upd[1], BAND_SIGMA_FLOOR_M), self._robust)
        else:
            if self.cfg.prior_target is PriorTarget.edge:
                r_pose = _across(r_pose, math.copysign(PRIOR_BAND_FRACTION * width, m.signed_lateral_m))
            v_lon, v_lat = step.x() / dt_s, step.y() / dt_s
            yaw = pred.rotation().yaw()
            motion_dir = yaw + math.atan2(step.y(), step.x()) if step.translation()[:2].any() else yaw
            noise = factors.map_prior_noise(self.cfg, m.yaw_rad, motion_dir, v_lon, v_lat, self._robust)
        self.counters.map_priors += 1
        self._since_prior_m = 0.0
        return m, factors.pose_prior(k, r_pose, noise)

    def heading_prior(self, k: int, pred: gtsam.Pose3, m: Match | None, moved_m: float,
                      yaw_sigma_rad: float = math.inf, sigma_factor: float = 1.0) -> gtsam.PriorFactorPose3 | None:
        """A prior on frame k's yaw alone (``heading_prior_sigma_deg``): the road's heading, when the estimate lies on a
        straight stretch of its road heading along it and knows its own heading less well than the road does
        (``yaw_sigma_rad``: its marginal σ, unless the learned odometry σ factor ``sigma_factor`` exceeds
        ``heading_prior_open_factor``; see the fields' documentation)."""
        cfg = self.cfg
        self._since_heading_m += moved_m
        sigma = math.radians(cfg.heading_prior_sigma_deg)
        shut = yaw_sigma_rad < cfg.heading_prior_gate * sigma and not 0 < cfg.heading_prior_open_factor < sigma_factor
        if sigma <= 0 or m is None or m.is_join or self._since_heading_m < cfg.heading_prior_spacing_m or \
                m.angle_deg > HEADING_PRIOR_MAX_DEG or shut:
            return None
        if m.lateral_m > m.lanes * cfg.lane_width_m or not self._straight(m):
            return None
        self._since_heading_m = 0.0
        self.counters.heading_priors += 1
        turn = math.remainder(m.yaw_rad - pred.rotation().yaw(), 2.0 * math.pi)
        target = pred.compose(gtsam.Pose3(gtsam.Rot3.Yaw(turn), gtsam.Point3(0.0, 0.0, 0.0)))
        r = np.zeros((6, 6))
        r[2, 2] = 1.0 / sigma
        return factors.pose_prior(k, target, factors.sqrt_information_noise(r, self._robust))

    def _straight(self, m: Match) -> bool:
        """The match's road keeps its heading within STRAIGHT_DEG over STRAIGHT_M either side of the way-point."""
        road, i = self.road, m.index
        e = int(road.edge.item(i))
        a, b = max(int(road.edge_start[e]), i - STRAIGHT_M), min(int(road.edge_end[e]), i + STRAIGHT_M + 1)
        if b - a < STRAIGHT_M:
            return False
        d = np.remainder(road.yaw_rad[a:b] - road.yaw_rad.item(i) + math.pi, 2.0 * math.pi) - math.pi
        return bool(np.max(np.abs(d)) <= math.radians(STRAIGHT_DEG))

    def odometry_prior(self, k: int, pred: gtsam.Pose3, pos_sigma_m: float) -> gtsam.PriorFactorPose3 | None:
        """Paper IV.B: when the estimate's positional σ exceeds the width of the road it is on
        (one lane where there is none, or without the map), its own pose becomes a prior with the
        road width as σ, so uncertainty cannot grow without bound."""
        cfg = self.cfg
        m = self.road.match(pred.x(), pred.y(), pred.rotation().yaw(), cfg.search_radius_m) if cfg.use_map else None
        width = (m.lanes if m else 1) * cfg.lane_width_m
        if pos_sigma_m <= width:
            return None
        sigmas = factors.pose_sigmas(cfg.state, math.radians(cfg.odometry_prior_rot_sigma_deg), width)
        return factors.pose_prior(k, pred, factors.diagonal(sigmas))
