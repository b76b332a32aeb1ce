"""The engine's re-anchoring paths (a part of :class:`~mapfusion.engine.MapFusion`, kept apart to keep
it small): from GPS, when consistent fixes disagree with the estimate, and from the road network without
GPS (issue 17) — a cold start in a region, or a search once the estimate is lost."""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable

import gtsam
import numpy as np

from . import factors
from .association import MapAssociation
from .config import FusionConfig, OutageStep, StateModel
from .counters import Counters
from .errors import EngineError
from .gps_gate import GpsGate
from .initialisation import Initialiser
from .metrics import umeyama
from .motion import MotionFusion
from .relocalise import Located, Region, RoadFollower, Search
from .roadmap import RoadMap
from .smoother import Smoother
from .track import Alignment, JumpGuard, Track, level, spread_back
from .tracking import RoadFixes

log = logging.getLogger(__name__)


class Reanchoring:
    """Re-anchoring the smoother: mixed into MapFusion, whose state it reads."""

    road: RoadMap
    cfg: FusionConfig
    track: Track
    counters: Counters
    alignment: Alignment | None
    _smoother: Smoother | None
    relocalised_at: list[tuple[float, float]]
    _association: MapAssociation
    _gate: GpsGate
    _search: Search
    _motion: MotionFusion
    _road_fixes: RoadFixes
    _jumps: JumpGuard
    _checked_fix_t: float
    _register_checked_t: float
    _registered_fix_t: float
    initialiser: Initialiser
    _pos_sigma: float
    _lat_sigma: float
    _step: Callable[[int], gtsam.Pose3]
    _update: Callable[[], None]
    _begin: Callable[..., None]

    def _init_reanchoring(self) -> None:
        self._search = Search(self.road, self.cfg)  # re-localisation on the road network (issue 17)
        self._road_steps: dict[int, gtsam.Pose3] = {}  # outages' steps along the road graph, by frame
        self._follower: RoadFollower | None = None
        self._gap_pending: tuple[int, gtsam.Pose3, float] | None = None  # the last gap carried: frame, pose before, m
        self.relocalised_at = []  # (time, distance searched) of each map re-localisation
        self._checked_fix_t = math.nan  # the last fix whose silence started a search
        self._map_anchor: tuple[int, Region] | None = None  # the last map re-anchoring: its frame, its search's region
        self._watch_last: Located | None = None  # the watched search's last answer (reloc_watch_m)
        self._beside_gps = False  # the running search began while GPS came (it has not acted yet)
        self._register_checked_t = math.nan  # the last fix whose window was examined for registration on the roads
        self._registered_fix_t = math.nan  # the last fix whose window the registration placed the estimate on

    def _restart_from(self, k: int, pose: gtsam.Pose3, noise, sigma_m: float) -> None:
        """The smoother afresh at frame k (a prior on ``pose``), the estimate's σ set, the road association
        forgotten: the path every re-anchoring takes (GPS's and the map's)."""
        assert self._smoother is not None
        self._smoother.restart_from(k, pose, noise, self._step)
        self._road_fixes.reanchored()
        self._pos_sigma = self._lat_sigma = sigma_m
        self._association.reset()

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
        self._search.begin(Region(float(x), float(y), float(radius_m)),
                           (self.cfg.reloc_scale_min, self.cfg.reloc_scale_max))

    def reanchor_at(self, x_m: float, y_m: float, yaw_rad: float, sigma_m: float = 0.5,
                    yaw_sigma_rad: float = 0.01) -> None:
        """Re-anchor the estimate on a pose known from elsewhere (the map's ENU frame, m; yaw from east, rad): the
        smoother restarts at the last frame with that pose as its prior (σ ``sigma_m`` a horizontal axis,
        ``yaw_sigma_rad``), as the engine's own re-localisations do, and any running search ends. For a pose from
        outside (an operator, another localiser), and to measure what a perfect re-localisation would give
        (``mapfusion.harness.bounds``)."""
        if self.alignment is None or self._smoother is None or not self.track.t:
            raise EngineError("reanchor_at needs an estimate to re-anchor: the engine is not initialised yet")
        values = (x_m, y_m, yaw_rad, sigma_m, yaw_sigma_rad)
        if not all(math.isfinite(v) for v in values) or sigma_m <= 0 or yaw_sigma_rad <= 0:
            raise EngineError(f"reanchor_at needs finite x, y, yaw and σs > 0, got {values}")
        k = len(self.track) - 1
        was = self.track.online[k]
        z = was.z() if was is not None else 0.0
        pose = gtsam.Pose3(gtsam.Rot3.Yaw(yaw_rad), gtsam.Point3(x_m, y_m, z))
        self._search.active = self._search.watching = None
        self._restart_from(k, pose, factors.diagonal(factors.pose_sigmas(StateModel.planar, yaw_sigma_rad, sigma_m)),
                           sigma_m)
        self._update()

    @property
    def searching_from_region(self) -> bool:
        """A cold start's search is running (no estimate yet)."""
        return self.alignment is None and self._search.active is not None

    def _gps_went_silent(self, k: int) -> bool:
        """True once per GPS outage: the last fix is ``reloc_after_gps_s`` old (the estimate is where GPS left
        it — a biased fix window leaves it in the wrong place, and nothing but the map can tell)."""
        fixes = self.initialiser.fixes
        if not fixes or self.cfg.reloc_after_gps_s <= 0:
            return False
        last = fixes[-1][0]
        if last == self._checked_fix_t or self.track.t[k] - last < self.cfg.reloc_after_gps_s:
            return False
        self._checked_fix_t = last
        return True

    def _initialise_at(self, loc: Located) -> None:
        """A cold start's search has found the vehicle: the odometry's frame aligned so that its last pose
        is the found one (at the search's scale), the frames so far solved as at a GPS initialisation."""
        if self.cfg.state is StateModel.planar and self.track.level_rot is None:
            self.track.level_frame()
        raw = self.track.raw[-1]
        rot = loc.yaw_rad - raw.rotation().yaw()
        c, s, (px, py, _) = math.cos(rot), math.sin(rot), raw.translation()
        scale, c, s = loc.scale, c * loc.scale, s * loc.scale
        sigma = max(self.cfg.reloc_scale_sigma, loc.scale_spread) * scale
        if self.cfg.odometry_sigma_learned:  # no window measured this odometry's drift
            self._motion.sigma_factor = self.cfg.odometry_sigma_cold_factor
        self._begin(Alignment(scale, sigma, rot, np.array([loc.x_m - (c * px - s * py), loc.y_m - (s * px + c * py)])),
                    anchor=len(self.track) - 1)
        self.counters.map_relocalisations += 1
        self.relocalised_at.append((self.track.t[-1], loc.driven_m))

    def _carried_sigma_m(self, length_m: float) -> float:
        """σ (m) of a step carried ``length_m`` along the road over an odometry gap: ``reloc_sigma_m`` +
        ``outage_step_fraction`` of its length (the road follower's spread, and the gap's search's guess)."""
        return self.cfg.reloc_sigma_m + self.cfg.outage_step_fraction * length_m

    def _along_road(self, k: int, prev: gtsam.Pose3, length_m: float | None = None) -> gtsam.Pose3:
        """The step into frame k. After an odometry outage longer than ``reloc_gap_s`` with ``outage_step =
        road`` and the map: as far as the odometry's guess (the last velocity straight on) goes, but along the
        road graph from the road ``prev`` is matched to (a tunnel's curve, the road beyond a junction nearest
        the guess), held for re-use (a restart re-adds it). ``length_m``: carried this far instead of the
        odometry's guess (``outage_speed_after_s``)."""
        assert self.alignment is not None
        step = self.track.step(k, self.alignment.scale)
        cfg, t = self.cfg, self.track.t
        if (cfg.outage_step is not OutageStep.road or not cfg.use_map or cfg.state is not StateModel.planar
                or t[k] - t[k - 1] <= cfg.reloc_gap_s):
            return step
        m = self.road.match(prev.x(), prev.y(), prev.rotation().yaw(), cfg.search_radius_m,
                            cfg.angle_weight_m_per_deg)
        if m is None or m.is_join:
            return step
        if self._follower is None:
            # (it follows the road the estimate is on: turning back at a vertex is a search's hypothesis, not a guess)
            self._follower = RoadFollower(self.road, dataclasses.replace(cfg, reloc_uturn_at_vertex=0.0),
                                          cfg.reloc_seed)
        tr = step.translation()
        guessed_m = math.sqrt(tr.dot(tr))
        if length_m is None:
            length_m = guessed_m
            self._gap_pending = (k, prev, guessed_m)
        # which way at a junction: the guess turns by the odometry's own turn over the gap, as a constant turn
        half = 0.5 * self._jumps.gap_yaw_rad if cfg.outage_turn else 0.0
        chord = length_m * (math.sin(half) / half if abs(half) > 1e-9 else 1.0)
        # an estimate on its road (within its width, along it) is carried on the road itself; one off it or
        # turned against it by the road's own motion from where it is matched (its offset kept: the map's
        # priors judge that)
        place = (m.edge, -1 if m.reversed else 1, m.along_m)
        if m.lateral_m <= (0.5 * m.lanes + 1.0) * cfg.lane_width_m and m.angle_deg <= cfg.outage_on_road_deg:
            start = level(prev)
        else:
            x0, y0, yaw0 = self._follower.road_pose(*place)
            start = gtsam.Pose3(gtsam.Rot3.Yaw(yaw0), gtsam.Point3(x0, y0, 0.0))
        guess = start.compose(gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(chord * math.cos(half), chord * math.sin(half),
                                                                      0.0)))
        x, y, yaw = self._follower.follow(*place, length_m, (guess.x(), guess.y()),
                                          self._carried_sigma_m(length_m),
                                          target_yaw_rad=start.rotation().yaw() + 2.0 * half,
                                          weight_m_per_deg=cfg.outage_end_weight_m_per_deg,
                                          max_deg=cfg.outage_end_max_deg)
        road_step = start.between(gtsam.Pose3(gtsam.Rot3.Yaw(yaw), gtsam.Point3(x, y, start.z())))
        self._road_steps[k] = road_step
        log.info("t=%.1f s: the odometry resumed after %.1f s: carried %.0f m along the road", t[k], t[k] - t[k - 1],
                 length_m)
        return road_step

    def _note_outage(self, k: int, step: gtsam.Pose3) -> None:
        """An odometry outage longer than ``reloc_gap_s`` into frame k: where the odometry resumed is a guess,
        so the GPS gate opens for fixes that place it anew (:meth:`GpsGate.open`)."""
        gap_s = self.track.t[k] - self.track.t[k - 1]
        if gap_s > self.cfg.reloc_gap_s:
            self._gate.open(factors.outage_sigma_m(self.cfg, step, gap_s), k)

    def _recarry_gap(self, k: int) -> None:
        """``outage_speed_after_s`` after the odometry resumed from the last gap carried along the road (frame k,
        the last): that gap's step carried again at the mean of the speeds before it and since (a vehicle that
        sped up or slowed down unseen is placed by both), and, when the lengths differ by more than 5% and 10 m,
        the estimate moved by the difference and the smoother restarted there."""
        assert self._gap_pending is not None
        kg, prev, guessed_m = self._gap_pending
        t, raw = self.track.t, self.track.raw
        if t[k] - t[kg] < self.cfg.outage_speed_after_s:
            return
        self._gap_pending = None
        was_road, now = self._road_steps.get(kg), self.track.online[k]
        if self.cfg.outage_speed_after_s <= 0 or was_road is None or now is None or self._smoother is None:
            return
        moved = raw[k].translation() - raw[kg].translation()
        assert self.alignment is not None
        v_after = math.sqrt(moved.dot(moved)) * self.alignment.scale / max(t[k] - t[kg], 1e-3)
        length_m = 0.5 * (guessed_m + v_after * (t[kg] - t[kg - 1]))
        if abs(length_m - guessed_m) <= max(10.0, 0.05 * guessed_m):  # (not worth a restart)
            return
        log.info("t=%.1f s: the gap into t=%.1f s carried again at the speeds on both sides: %.0f m, not %.0f m",
                 t[k], t[kg], length_m, guessed_m)
        moved_by = prev.compose(self._along_road(kg, prev, length_m)).compose(prev.compose(was_road).inverse())
        pose = level(moved_by.compose(now))
        sigma = max(self._pos_sigma, self.cfg.reloc_sigma_m)
        noise = factors.diagonal(factors.pose_sigmas(StateModel.planar, math.radians(self.cfg.outage_rot_sigma_deg),
                                                     sigma))
        self._restart_from(k, pose, noise, sigma)
        self._update()

    def _note_outage_in_batch(self) -> None:
        """The initialisation's frames hold an outage: the batch gated the fixes after it against the
        odometry's guess, so the gate opens as after an outage (the next fix near the estimate closes it)."""
        t = self.track.t
        for k in range(len(self.track) - 1, max(self.track.first, 0), -1):
            if t[k] - t[k - 1] > self.cfg.reloc_gap_s:
                self._note_outage(k, self._step(k))
                return

    def _relocalise(self, sigma: float) -> None:
        """From GPS, as at the start: a fresh smoother at the gate's pose. After an odometry outage the
        correction reaches back to the outage: the odometry since is placed on the run's fixes (a rigid fit)
        and those fixes are added, so the estimate between the outage and the re-anchoring is mended too."""
        r = self._gate.relocalisation(self.track, sigma)
        k, pose, yaw_sigma = r.k, r.pose, r.yaw_sigma_rad
        if r.scale_ratio is not None:
            self._rescale(*r.scale_ratio)
        if 0 <= r.since_k < r.k and len(r.fixes) >= 2:
            k, pose, sigma = r.since_k, *self._placed_on(r.since_k, r.fixes, sigma, yaw_sigma)
        noise = factors.diagonal(factors.pose_sigmas(StateModel.planar, yaw_sigma, sigma))
        was = self.track.online[k]
        self._restart_from(k, pose, noise, sigma)
        if self.cfg.gps_reach_back and k == r.k and was is not None:
            self._spread_back(r.taken_k, k, was, pose)
        assert self._smoother is not None
        for x, y, kf in r.fixes if k == r.since_k else ():
            self._smoother.add(factors.gps_factor(self.cfg.state, kf, x, y, None, sigma))
        self._update()

    def _rescale(self, ratio: float, relative_sigma: float) -> None:
        """A track run showed the odometry's scale off by ``ratio`` (known to ``relative_sigma``): the frames from
        now on use the new scale, and later refits are judged against it, not against the initialisation's."""
        a = self.alignment
        assert a is not None
        scale = a.scale * ratio
        sigma = scale * math.hypot(a.relative_sigma, relative_sigma)
        log.info("the GPS track run re-scales the odometry: %.4f → %.4f (± %.4f)", a.scale, scale, sigma)
        self.alignment = dataclasses.replace(a, scale=scale, scale_sigma=sigma)
        self.initialiser.rescaled(scale, sigma, self.track.t[-1])
        self.counters.gps_rescales += 1

    def _spread_back(self, k0: int, k1: int, was: gtsam.Pose3, now: gtsam.Pose3) -> None:
        """A GPS re-localisation moved frame k1 from ``was`` to ``now``; the estimate was right at frame k0 (the
        last fix taken). The final estimates between are mended by :func:`~mapfusion.track.spread_back`, so the
        stretch the fixes could not see — a tunnel, a GPS-denied zone — is corrected, not only its end (the
        online estimates stay as they were: causal)."""
        sm, track = self._smoother, self.track
        assert sm is not None
        if k0 < track.first or k0 >= k1 - 1 or sm.smoothed.get(k0) is None:
            return
        frames = [k for k in range(k0 + 1, k1) if sm.smoothed.get(k) is not None]
        path = [p for p in [sm.smoothed[k0]] + [sm.smoothed[k] for k in frames] if p is not None]
        for k, pose in zip(frames, spread_back(path, was, now)):
            sm.smoothed[k] = pose
        log.info("t=%.1f s: the GPS correction (%.0f m) spread back over %d frames", track.t[k1],
                 math.hypot(now.x() - was.x(), now.y() - was.y()), len(frames))

    def _placed_on(self, k0: int, fixes, sigma: float, yaw_sigma: float) -> tuple[gtsam.Pose3, float]:
        """Frame k0's pose that puts the odometry from k0 onto ``fixes`` ((x, y, frame), ≥ 2) by a rigid fit,
        and its positional σ (the fixes' and the heading's lever arm over the distance to them)."""
        chain, pose = {k0: gtsam.Pose3()}, gtsam.Pose3()
        for j in range(k0 + 1, max(kf for _, _, kf in fixes) + 1):
            pose = chain[j] = pose.compose(self._step(j))
        odo = np.array([[chain[kf].x(), chain[kf].y()] for _, _, kf in fixes])
        rot, trans, _ = umeyama(odo, np.array([[x, y] for x, y, _ in fixes]))
        lever_m = float(np.max(np.hypot(odo[:, 0], odo[:, 1])))
        placed = gtsam.Pose3(gtsam.Rot3.Yaw(math.atan2(rot[1, 0], rot[0, 0])), gtsam.Point3(trans[0], trans[1], 0.0))
        return placed, math.hypot(sigma, yaw_sigma * lever_m)
