"""Re-anchoring the estimate on the map (issue 17): :class:`MapAnchors`, the path every map re-anchoring takes
(counted, the stretch its search matched mended), and :class:`FixRegistration`: when GPS falls quiet, its last
fixes are registered on the roads (:mod:`~mapfusion.register`): a decisive shift re-anchors the smoother at once,
the odometry placed on the shifted fixes, without a search."""

from __future__ import annotations

import logging
import math

import gtsam
import numpy as np

from . import factors, relocalise
from .association import MapAssociation
from .config import FusionConfig, StateModel
from .counters import Counters
from .estimate import Estimate
from .gps_gate import RELOCALISE_YAW_SIGMA_FLOOR_DEG
from .initialisation import Initialiser
from .reanchoring import placed_on
from .register import register_on_roads
from .relocalise import Region
from .roadmap import RoadMap
from .track import Track, planar_of

log = logging.getLogger(__name__)


class MapAnchors:
    """The map's re-anchorings of the estimate: each one applied through the estimate, counted, its searched
    stretch mended, and the last one remembered (where a later doubt looks again)."""

    def __init__(self, road: RoadMap, cfg: FusionConfig, track: Track, estimate: Estimate, counters: Counters) -> None:
        self.road, self.cfg, self.track, self.counters = road, cfg, track, counters
        self._estimate = estimate
        self.last: tuple[int, Region] | None = None  # the last map re-anchoring: its frame, its search's region
        self.relocalised_at: list[tuple[float, float]] = []  # (time, distance searched) of each

    def found_at_start(self, driven_m: float) -> None:
        """A cold start's search found the vehicle (counted as a map re-localisation)."""
        self.counters.map_relocalisations += 1
        self.relocalised_at.append((self.track.t[-1], driven_m))

    def reanchor(self, k: int, pred: gtsam.Pose3, pose: gtsam.Pose3, sigma_m: float, yaw_sigma_rad: float,
                 k0: int, region: Region, searched_m: float, now: int | None = None,
                 fixes: tuple[list[tuple[float, float, int]], float] | None = None) -> None:
        """The smoother re-anchored at frame k on ``pose`` (σ ``sigma_m`` per axis, ``yaw_sigma_rad``) by the map (at
        frame ``now``, k by default: a re-anchoring may reach back), counted with the distance ``searched_m`` it took;
        the final estimates from frame k0 on are moved with it (``pred``: frame k's estimate before), and ``region`` is
        where a later doubt looks again (``SearchParams.doubt_m``). ``fixes`` ((x, y, frame) in the map frame, and their
        σ in m) enter the graph with it."""
        est = self._estimate
        now = k if now is None else now
        self.last = (now, region)
        sigmas = factors.pose_sigmas(StateModel.planar, yaw_sigma_rad, sigma_m)
        est.restart_from(k, pose, factors.diagonal(sigmas), sigma_m)
        self.mend_searched(k0, k, pred, pose)
        if fixes is not None:
            for x, y, kf in fixes[0]:
                est.add(factors.gps_factor(self.cfg.state, kf, x, y, None, fixes[1]))
        self.counters.map_relocalisations += 1
        self.relocalised_at.append((self.track.t[now], searched_m))
        est.update()

    def mend_searched(self, k0: int, k1: int, was: gtsam.Pose3, now: gtsam.Pose3) -> None:
        """A map re-anchoring moved frame k1 from ``was`` to ``now``; its search matched the odometry's path from
        frame k0 on to the roads, so that path lies where the re-anchoring puts its end: the final estimates of
        frames k0 … k1-1 are moved rigidly by the same correction (about z) — unless the moved path would keep to the
        roads less than ``SearchParams.mend_keep_ratio`` as well as the path as it was (an estimate the map's priors had
        kept on its roads is not swung off them about its end by the answer's heading). The online estimates stay as
        they were (causal)."""
        sp = relocalise.SEARCH_PARAMS
        sm, track = self._estimate.sm, self.track
        k0 = max(k0, track.first)
        dyaw = math.remainder(now.rotation().yaw() - was.rotation().yaw(), 2.0 * math.pi)
        c, s = math.cos(dyaw), math.sin(dyaw)
        turn = gtsam.Rot3.Yaw(dyaw)
        moves: dict[int, gtsam.Pose3] = {}
        for j in range(k0, k1):
            p = sm.smoothed.get(j)
            if p is None:
                continue
            dx, dy = p.x() - was.x(), p.y() - was.y()
            moves[j] = gtsam.Pose3(turn.compose(p.rotation()),
                                   gtsam.Point3(now.x() + c * dx - s * dy, now.y() + s * dx + c * dy, p.z()))
        if sp.mend_keep_ratio > 0 and moves:
            keys = list(moves)[::5]  # (a sample: the share of a path on its roads, not each frame's)
            before = self._on_roads([p for j in keys if (p := sm.smoothed.get(j)) is not None])
            after = self._on_roads([moves[j] for j in keys])
            if after < sp.mend_keep_ratio * before:
                log.info("t=%.1f s: the map's correction would take the %d frames its search matched off the roads "
                         "(%.0f%% on them, %.0f%% as they are): left as they are", track.t[k1], len(moves),
                         100 * after, 100 * before)
                return
        self._estimate.move_final(moves)
        log.info("t=%.1f s: the map's correction moved the %d frames its search matched", track.t[k1], len(moves))

    def _on_roads(self, poses: list[gtsam.Pose3]) -> float:
        """The share of ``poses`` on a road: matched within half its width plus a lane of its centre line, heading
        within ``prior_max_angle_deg`` of it."""
        cfg, on = self.cfg, 0
        for p in poses:
            m = self.road.match(p.x(), p.y(), p.rotation().yaw(), cfg.search_radius_m, cfg.angle_weight_m_per_deg)
            on += m is not None and m.lateral_m <= (0.5 * m.lanes + 1.0) * cfg.lane_width_m \
                and m.angle_deg <= cfg.prior_max_angle_deg
        return on / max(len(poses), 1)

    def replay_start(self, k: int, distance_m: float) -> int:
        """The frame ``distance_m`` of driving before frame k (metres at the engine's scale), or the earliest one
        after which every frame has an online estimate, no odometry gap (longer than ``reloc_gap_s``) intervenes and
        no map re-anchoring moved the estimate (the online estimates before it are where the engine then thought)."""
        track, a = self.track, self._estimate.alignment
        if distance_m <= 0 or a is None:
            return k
        scale, driven = a.scale, 0.0
        floor = max(track.first, self.last[0] if self.last is not None else 0)
        x1, y1, _ = planar_of(track.raw[k])
        j = k
        while j - 1 >= floor and track.online[j - 1] is not None \
                and track.t[j] - track.t[j - 1] <= self.cfg.reloc_gap_s:
            x0, y0, _ = planar_of(track.raw[j - 1])
            driven += math.hypot(x1 - x0, y1 - y0) * scale
            x1, y1 = x0, y0
            j -= 1
            if driven >= distance_m:
                break
        return j


class FixRegistration:
    """GPS's last fixes registered on the roads once GPS falls silent, and a decisive shift taken as a map
    re-anchoring (``SearchParams.register_ratio``)."""

    def __init__(self, road: RoadMap, cfg: FusionConfig, track: Track, estimate: Estimate, initialiser: Initialiser,
                 association: MapAssociation, anchors: MapAnchors) -> None:
        self.road, self.cfg, self.track = road, cfg, track
        self._estimate, self._initialiser, self._association, self._anchors = estimate, initialiser, association, \
            anchors
        self._checked_t = math.nan  # the last fix whose window was examined
        self.registered_fix_t = math.nan  # the last fix whose window the registration placed the estimate on

    def due(self, k: int) -> bool:
        """Are GPS's fixes to be registered on the roads now: ``SearchParams.register_after_s`` after the last one (once
        per last fix), wherever the estimate is (a window biased along its streets, or onto parallel ones, leaves it on
        roads too)?"""
        sp = relocalise.SEARCH_PARAMS
        fixes = self._initialiser.fixes
        if sp.register_ratio <= 0 or not fixes or fixes[-1][0] == self._checked_t \
                or self.track.t[k] - fixes[-1][0] < sp.register_after_s:
            return False
        self._checked_t = fixes[-1][0]
        return True

    def _window(self) -> tuple[list[tuple[float, float, float]], float]:
        """The fixes (t, x, y) of the last ``SearchParams.register_m`` of GPS's path, and that path's length."""
        fixes: list[tuple[float, float, float]] = []
        length_m, most_m = 0.0, relocalise.SEARCH_PARAMS.register_m
        for t, x, y, _ in reversed(self._initialiser.fixes):
            if fixes:
                length_m += math.hypot(x - fixes[-1][1], y - fixes[-1][2])
                if length_m > most_m:
                    break
            fixes.append((t, x, y))
        fixes.reverse()
        return fixes, length_m

    def register(self, k: int, pred: gtsam.Pose3) -> bool:
        """GPS has fallen silent: its fixes of the last ``SearchParams.register_m`` registered on the roads
        (:func:`~mapfusion.register.register_on_roads`, ``SearchParams.register_ratio``). When the shift is decisive,
        the odometry of the last ``SearchParams.register_place_m`` of fixes is placed on them, shifted, by a rigid fit
        (as a GPS re-localisation places it; not the estimate moved: after a biased window its heading may be off too),
        the smoother re-anchored there (a map re-anchoring), and True; otherwise False."""
        sp = relocalise.SEARCH_PARAMS
        fixes, length_m = self._window()
        sep = sp.register_separation_m
        reg = register_on_roads(self.road, np.array([f[1:] for f in fixes]).reshape(-1, 2), sp.radius_m,
                                separation_m=sep)
        if reg is None or not reg.decisive(sp.register_ratio, sp.register_rms_m, sep):
            if reg is not None:
                log.info("t=%.1f s: the last fixes registered on the roads %.0f m away, RMS %.1f m, runner-up %.1f m: "
                         "not taken", self.track.t[k], reg.shift_m, reg.rms_m, reg.runner_up_rms_m)
            return False
        _, lx, ly = fixes[-1]
        far = [i for i, (_, x, y) in enumerate(fixes) if math.hypot(x - lx, y - ly) >= sp.register_place_m]
        placed = self._fixes_on_frames([(t, x + reg.dx_m, y + reg.dy_m) for t, x, y in fixes[far[-1]:]], k) \
            if far else []
        if len(placed) < 2 or math.hypot(placed[0][0] - placed[-1][0], placed[0][1] - placed[-1][1]) \
                < sp.register_place_m:  # (too short a stretch has frames to be placed on: the heading is not)
            return False
        log.info("t=%.1f s: the last %d fixes fit the roads %.0f m away (RMS %.1f m, runner-up %.1f m)",
                 self.track.t[k], reg.points, reg.shift_m, reg.rms_m, reg.runner_up_rms_m)
        self.registered_fix_t = fixes[-1][0]
        k0 = placed[0][2]
        yaw_sigma = math.radians(RELOCALISE_YAW_SIGMA_FLOOR_DEG)
        sigma_m = max(reg.rms_m, 2.0)
        pose, placed_sigma_m = placed_on(self._estimate.step, k0, placed, sigma_m, yaw_sigma)
        was = self.track.online[k0]
        assert was is not None
        self._anchors.reanchor(k0, was, pose, placed_sigma_m, yaw_sigma, self._anchors.replay_start(k, length_m),
                               Region(pred.x(), pred.y(), sp.radius_m), 0.0, k, (placed, sigma_m))
        return True

    def _fixes_on_frames(self, fixes: list[tuple[float, float, float]], k: int) -> list[tuple[float, float, int]]:
        """Fixes (t, x, y) as (x, y, frame): each on the last frame at or before its time, among the frames back from
        k that every one has an online estimate and no odometry gap or map re-anchoring intervenes (as
        :meth:`MapAnchors.replay_start` steps back)."""
        floor, t = self._anchors.replay_start(k, math.inf), self.track.t
        out: list[tuple[float, float, int]] = []
        j = k
        for ft, x, y in reversed(fixes):
            while j > floor and t[j] > ft:
                j -= 1
            if t[j] > ft:
                break
            out.append((x, y, j))
        return out[::-1]
