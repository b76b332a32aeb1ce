"""Which road a predicted pose lies on, and whether the map may correct it (paper III.B, DESIGN
items 2, 3 and 7): the match by D = E + w·A (optionally preferring the roads the graph joins to
the last one), the gates that keep wrong-road priors out, and the map prior's factor.

A prior is added only when the predicted pose lies farther from its road than the road is wide
(road width = lanes × ``lane_width_m``), and not when the match's angle exceeds
``prior_max_angle_deg``, the match lies on a join inside a junction, another way's best D is
within ``prior_ambiguity_m`` (junctions, parallel roads), or — with ``prior_gate_sigma`` — the
correction is implausibly large for the estimate's own uncertainty.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from . import factors
from .config import FusionConfig
from .counters import Counters
from .matcher import Match, map_pose, match, match_candidates
from .roadmap import RoadMap


class MapAssociation:
    """The matcher as the engine uses it, with the state matching continuity needs."""

    def __init__(self, road: RoadMap, cfg: FusionConfig, counters: Counters) -> None:
        self.road = road
        self.cfg = cfg
        self.counters = counters
        self.edge = -1  # the road edge the vehicle was last matched to
        self._mask = np.zeros(len(road), dtype=bool)
        self._robust = factors.robust_kernel(cfg)

    def reset(self) -> None:
        """Forget the last road (after a re-localisation)."""
        self.edge = -1

    def match(self, pred: gtsam.Pose3) -> Match | None:
        """The best way-point for a predicted pose (with continuity: among the roads joined to the
        last one, unless an unrestricted match is better by more than ``continuity_slack_m``)."""
        cfg, road = self.cfg, self.road
        x, y, yaw = pred.x(), pred.y(), pred.rotation().yaw()
        near = road.query_radius(x, y, cfg.search_radius_m)
        best = match(road, x, y, yaw, cfg.search_radius_m, cfg.angle_weight_m_per_deg, candidates=near)
        if best is None:
            return None
        if cfg.match_continuity and self.edge >= 0:
            neigh = road.neighbourhood(self.edge)
            self._mask[neigh] = True  # a scratch mask: O(|neighbourhood| + |near|), no sorting
            allowed = near[self._mask[near]]
            self._mask[neigh] = False
            m = match(road, x, y, yaw, cfg.search_radius_m, cfg.angle_weight_m_per_deg, candidates=allowed) \
                if allowed.size else None
            if m is not None and m.cost <= best.cost + cfg.continuity_slack_m:
                best = m
            else:
                self.counters.match_fallbacks += 1
        if best.edge >= 0:
            self.edge = best.edge
        return best

    def ambiguous(self, m: Match, pred: gtsam.Pose3) -> bool:
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
                                         road.yaw_cos[other], road.yaw_sin[other],
                                         self.cfg.angle_weight_m_per_deg)
        return d - m.cost < margin

    def gated(self, m: Match, pred: gtsam.Pose3, lateral_m: float, width_m: float, pos_sigma_m: float) -> bool:
        """A prior from this match would likely come from the wrong road."""
        cfg = self.cfg
        gate = cfg.prior_gate_sigma
        return (m.angle_deg > cfg.prior_max_angle_deg or (m.is_join and not cfg.prior_on_joins)
                or (gate > 0 and lateral_m > gate * math.hypot(pos_sigma_m, 0.5 * width_m))
                or self.ambiguous(m, pred))

    def prior(self, k: int, pred: gtsam.Pose3, step: gtsam.Pose3, dt_s: float, pos_sigma_m: float
              ) -> tuple[Match | None, gtsam.PriorFactorPose3 | None]:
        """The match of frame k's predicted pose and, if the map should correct it, its prior."""
        m = self.match(pred)
        if m is None:
            return None, None
        self.counters.matches += 1
        width = m.lanes * self.cfg.lane_width_m
        r_pose, lateral = map_pose(m, pred)
        if lateral <= width:
            return m, None
        if self.gated(m, pred, lateral, width, pos_sigma_m):
            self.counters.priors_gated += 1
            return m, None
        v_lon, v_lat = step.x() / dt_s, step.y() / dt_s
        yaw = pred.rotation().yaw()
        motion_dir = yaw + math.atan2(step.y(), step.x()) if step.translation()[:2].any() else yaw
        noise = factors.map_prior_noise(self.cfg, m.yaw_rad, motion_dir, v_lon, v_lat, self._robust)
        self.counters.map_priors += 1
        return m, factors.pose_prior(k, r_pose, noise)

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
