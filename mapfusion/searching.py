"""The search of the road network (issue 17): a cold start in a region (no GPS), and, with ``map_relocalisation``,
a search once the estimate is lost — begun after an odometry gap,
when the association calls the estimate lost or when GPS falls silent, run beside GPS when the estimate is
lost while fixes still come, its answer re-anchoring the smoother (unless the posterior has not ruled the
estimate's own place out), and the re-anchoring search watched on for a while after it acts. When GPS falls
silent, its last fixes are first registered on the roads (:mod:`~mapfusion.registering`): a decisive shift
re-anchors the estimate at once, without a search."""

from __future__ import annotations

import logging
import math

import gtsam
import numpy as np

from . import relocalise
from .association import MapAssociation
from .config import FusionConfig, OutageStep
from .estimate import Estimate
from .factors import OUTAGE_ROT_SIGMA_DEG
from .geometry import cumulative_length
from .initialisation import Initialiser
from .reanchoring import OutageCarry
from .registering import FixRegistration, MapAnchors
from .relocalise import SEARCH_PARTICLES, Guess, Located, Region, Relocaliser, Search, enclosing_disc
from .roadmap import RoadMap
from .track import Track, planar_of

log = logging.getLogger(__name__)


class MapSearch:
    """The search of the road network, begun by a cold start or when the estimate is lost; its answers proposed
    to the estimate through :class:`~mapfusion.registering.MapAnchors`."""

    def __init__(self, road: RoadMap, cfg: FusionConfig, track: Track, estimate: Estimate, initialiser: Initialiser,
                 association: MapAssociation, anchors: MapAnchors, registration: FixRegistration,
                 carry: OutageCarry) -> None:
        self.road, self.cfg, self.track = road, cfg, track
        self._estimate, self._initialiser, self._association = estimate, initialiser, association
        self._anchors, self._registration, self._carry = anchors, registration, carry
        self.search = Search(road, cfg)
        self._checked_fix_t = math.nan  # the last fix whose silence started a search
        self._watch_last: Located | None = None  # the watched search's last answer (SearchParams.watch_m)
        self._beside_gps = False  # the running search began while GPS came (it has not acted yet)

    @property
    def running(self) -> bool:
        """A search is running (not only watched)."""
        return self.search.active is not None

    def start_in_region(self, x_m: float, y_m: float, radius_m: float) -> None:
        """Cold start without GPS: the vehicle starts somewhere on the roads within ``radius_m`` of (x, y) (the map's
        ENU frame); the odometry's shape finds it (scale in ``reloc_scale_min`` … ``reloc_scale_max``). The caller
        checks the region (:meth:`MapFusion.start_in_region`)."""
        self.search.begin(Region(float(x_m), float(y_m), float(radius_m)),
                          (self.cfg.reloc_scale_min, self.cfg.reloc_scale_max))

    def feed_cold(self, raw: gtsam.Pose3) -> Located | None:
        """A cold start's search fed the odometry's latest pose (its own units: the search finds the scale); the
        answer once found."""
        return self.search.feed(*planar_of(raw))

    def stop(self) -> None:
        """End any running or watched search (the estimate was re-anchored from outside)."""
        self.search.end()

    def when_lost(self, k: int, pred: gtsam.Pose3) -> None:
        """From the moment the estimate is lost, a search on the road network; once it converges away from
        the estimate, the smoother is re-anchored there (issue 17; near the estimate it only confirms it)."""
        sp = relocalise.SEARCH_PARAMS
        if not self.cfg.use_map:  # (the baseline: no map, so no search on it)
            return
        assoc, search = self._association, self.search
        fixes = self._initialiser.fixes
        reg = self._registration
        if reg.due(k) and reg.register(k, pred):  # the fixes' own shape placed on the roads
            search.end()
            self._beside_gps = False
            return
        if fixes and self.track.t[k] - fixes[-1][0] < sp.after_gps_s:
            search.stop_watching()  # (GPS is back: it places the estimate)
            self._search_beside_gps(k, pred)  # GPS is here: it places the estimate, not a search of the map
            return
        if self._beside_gps:  # GPS fell silent with a search running beside it: that search is the silence's
            self._beside_gps = False
            self._gps_went_silent(k)
        gap_s = self.track.t[k] - self.track.t[k - 1]
        if gap_s > self.cfg.reloc_gap_s:  # the odometry lost track: where it resumed is not to be trusted
            # the vehicle went at most as far as the speed assumed through the gap takes it, or as its last velocity
            # did (the engine's own guess across the gap; the odometry's own step may have jumped: not that one)
            prev = self.track.online[k - 1] or pred
            reach = gap_s * sp.gap_speed_mps
            if self.cfg.outage_step is not OutageStep.odometry:  # (the carried step, and its σ: the speed in the gap)
                carried = math.hypot(pred.x() - prev.x(), pred.y() - prev.y())
                reach = max(reach, carried + sp.gap_reach_sigmas * self._carry.carried_sigma_m(carried))
            region = Region(prev.x(), prev.y(), sp.gap_margin_m + reach)
            search.begin(self._still_open(region, reach), frame=k, guess=self._gap_guess(prev, pred))
            return
        if assoc.take_became_lost():
            if search.active is None:  # (a running search goes on: its particles know more than a new one's)
                x, y = assoc.explained_xy or (pred.x(), pred.y())
                search.begin(self._doubting(k, search.lost_region(x, y, assoc.unexplained_m)), frame=k)
        elif search.active is None and self._gps_went_silent(k) and reg.registered_fix_t != fixes[-1][0] \
                and self._gps_left_it_off_the_roads(k):
            self._search_since_gps(k, pred)  # a second opinion on where GPS left it (the fixes not placed already)
        search.widen_if_stuck(pred.x(), pred.y(), k)
        if search.active is None:
            if search.watching is not None:
                self._watch_reanchoring(k, pred)
            return
        active = search.active
        loc = search.feed(*self._search_pose(k, active), k)
        if loc is None:
            return
        if math.hypot(loc.x_m - pred.x(), loc.y_m - pred.y()) <= sp.confirm_m:
            log.info("t=%.1f s: the search's answer, %.0f m from the estimate, confirms it", self.track.t[k],
                     math.hypot(loc.x_m - pred.x(), loc.y_m - pred.y()))
            return
        if self._rival_at_estimate(k, pred, loc, active):
            return  # (the search ends with its answer held back)
        self._map_reanchor(k, pred, loc, active)

    def _gap_guess(self, prev: gtsam.Pose3, pred: gtsam.Pose3) -> Guess | None:
        """The engine's own guess across an odometry gap (the step carried along the road from ``prev`` to
        ``pred``) as the gap's search's prior (``SearchParams.gap_guess_floor``; none at 1): σ as the carried step's
        (``ParticleParams.sigma_m`` + ``outage_step_fraction`` of its length) and ``OUTAGE_ROT_SIGMA_DEG``. Uniform over
        the region, a search on long straight roads holds the right place with every other stretch of road in
        the region for hundreds of metres, while the estimate it should correct strays at the next junction."""
        floor = relocalise.SEARCH_PARAMS.gap_guess_floor
        if floor >= 1.0:
            return None
        length_m = math.hypot(pred.x() - prev.x(), pred.y() - prev.y())
        return Guess(pred.x(), pred.y(), self._carry.carried_sigma_m(length_m),
                     pred.rotation().yaw(), math.radians(OUTAGE_ROT_SIGMA_DEG), floor, (prev.x(), prev.y()))

    def _still_open(self, region: Region, reach_m: float) -> Region:
        """The region of a search begun after an odometry gap (``region``: around the estimate before it) while another
        search still runs unconverged: the smallest disc that also holds the running
        search's region grown by the distance driven since it began and by the gap's ``reach_m`` (the vehicle may be
        anywhere that search had not ruled out, the estimate it left being no better than its guess), at most
        ``SearchParams.max_radius_m``."""
        sp = relocalise.SEARCH_PARAMS
        running = self.search.active
        if running is None:
            return region
        old = running.region
        both = enclosing_disc(region, Region(old.x_m, old.y_m, old.radius_m + running.particles.driven_m + reach_m))
        log.info("an odometry gap while a search runs: the new search covers the running one's region too, %.0f m "
                 "around (%.0f, %.0f)", min(both.radius_m, sp.max_radius_m), both.x_m, both.y_m)
        return Region(both.x_m, both.y_m, min(both.radius_m, sp.max_radius_m))

    def _gps_left_it_off_the_roads(self, k: int) -> bool:
        """GPS has fallen silent: does where it left the estimate need a second opinion? Only when less than
        ``SearchParams.gps_fit_min`` of the estimate's last ``SearchParams.gps_fit_m`` lay on a road: fixes that share
        one bias place the path off the roads most of the way, good ones on them (a search around a good estimate can
        only confirm it, or, converging on a look-alike path, move it away)."""
        sp = relocalise.SEARCH_PARAMS
        assoc = self._association
        if not assoc.kept_to_roads():
            return True
        log.info("t=%.1f s: GPS silent, %.0f%% of the estimate's last %.0f m on a road: no search", self.track.t[k],
                 100 * (assoc.road_fit() or 0.0), sp.gps_fit_m)
        return False

    def _search_since_gps(self, k: int, pred: gtsam.Pose3) -> None:
        """GPS has fallen silent: a search around where it left the estimate, begun ``SearchParams.gps_replay_m`` of
        driving back (around the estimate there) and fed the frames since at once, so that the path driven under
        the fixes already counts (all the fixes of a window may share one bias that only the roads can show)."""
        sp = relocalise.SEARCH_PARAMS
        k0 = self._anchors.replay_start(k, sp.gps_replay_m)
        centre = self.track.online[k0] if k0 < k else pred  # (every frame it steps back over has an estimate)
        assert centre is not None
        search = self.search
        search.begin(Region(centre.x(), centre.y(), sp.radius_m), frame=k)
        active = search.active
        assert active is not None
        for j in range(k0, k):
            active.add(*self._search_pose(j, active), j)

    def _search_pose(self, k: int, search: Relocaliser) -> tuple[float, float, float]:
        """Frame k's planar odometry pose for ``search`` (x and y in metres, yaw), at the scale the search was first
        fed with: the engine's scale moves while a search runs (GPS refits beside GPS, road fixes while it is
        watched), and a new scale times positions kilometres from the odometry's origin would jump its steps."""
        scale = search.fed_at(self._estimate.aligned.scale)
        x, y, yaw = planar_of(self.track.raw[k])
        return x * scale, y * scale, yaw

    def _watch_reanchoring(self, k: int, pred: gtsam.Pose3) -> None:
        """The search that re-anchored the estimate goes on (``SearchParams.watch_m``). If its posterior's mass moves to
        another place (its answer jumps, beyond where the vehicle drove, by more than ``SearchParams.watch_apart_m``)
        farther than that from the estimate, the path since has ruled the first answer out, and the estimate is
        re-anchored again, there — at the first step at which the posterior no longer holds ``SearchParams.rival_mass``
        at the estimate (until then the jump is weighed again at each step). If instead its one cluster drifts away from
        the estimate (a manoeuvre its particles could not follow), the watched posterior no longer means anything:
        watching ends."""
        sp = relocalise.SEARCH_PARAMS
        search = self.search
        watched = search.watching
        assert watched is not None
        loc = search.watched(*self._search_pose(k, watched), k)
        if loc is None:
            return
        last = self._watch_last
        apart = sp.watch_apart_m
        off = math.hypot(loc.x_m - pred.x(), loc.y_m - pred.y())
        if off <= apart:
            self._watch_last = loc
            return
        jumped = last is None or \
            math.hypot(loc.x_m - last.x_m, loc.y_m - last.y_m) - (loc.driven_m - last.driven_m) > apart
        if not jumped:
            log.info("t=%.1f s: the watched search's cluster drifted %.0f m from the estimate: watching ends",
                     self.track.t[k], off)
            search.stop_watching()
            return
        if self._rival_at_estimate(k, pred, loc, watched):
            # (the answer that jumped is not the last one yet: at the next step it has still jumped, and the rival
            # mass left at the estimate is weighed again; counted as the last, it would be taken for a drift)
            return
        log.info("t=%.1f s: the search that re-anchored the estimate now holds %.0f%% of its posterior %.0f m away",
                 self.track.t[k], 100 * loc.mass, off)
        self._map_reanchor(k, pred, loc, watched)

    def _rival_at_estimate(self, k: int, pred: gtsam.Pose3, loc: Located, search: Relocaliser) -> bool:
        """True (and logged) when ``search``, whose answer ``loc`` is away from the estimate, still holds at least
        ``SearchParams.rival_mass`` of its posterior within 2 × ``ParticleParams.converge_radius_m`` of the estimate
        (outside the answer's own disc: an answer near the estimate is not its own rival): it has not ruled the
        estimate's place out, only preferred another, and a good estimate is not moved on that."""
        sp = relocalise.SEARCH_PARAMS
        if sp.rival_mass <= 0:
            return False
        r = SEARCH_PARTICLES.converge_radius_m
        mass = search.particles.mass_within(pred.x(), pred.y(), 2.0 * r,
                                            (loc.x_m, loc.y_m, r))
        if mass < sp.rival_mass:
            return False
        log.info("t=%.1f s: the search prefers a place %.0f m away but still holds %.0f%% of its posterior at the "
                 "estimate: no re-anchoring", self.track.t[k], math.hypot(loc.x_m - pred.x(), loc.y_m - pred.y()),
                 100 * mass)
        return True

    def _map_reanchor(self, k: int, pred: gtsam.Pose3, loc: Located, active: Relocaliser) -> None:
        """Re-anchor the smoother at frame k on a search's answer (counted, logged, the searched path mended), and
        watch that search on from there (``SearchParams.watch_m``)."""
        pose = gtsam.Pose3(gtsam.Rot3.Yaw(loc.yaw_rad), gtsam.Point3(loc.x_m, loc.y_m, pred.z()))
        log.info("t=%.1f s: lost, found again on the road network %.0f m from the estimate", self.track.t[k],
                 math.hypot(loc.x_m - pred.x(), loc.y_m - pred.y()))
        self._anchors.reanchor(k, pred, pose, max(loc.spread_m, 2.0), max(loc.yaw_spread_rad, math.radians(2.0)),
                               active.k0 if active.k0 is not None else k, active.region, loc.driven_m)
        self.search.watch(active)
        self._watch_last = loc

    def _search_beside_gps(self, k: int, pred: gtsam.Pose3) -> None:
        """While GPS comes: no search unless the estimate is lost; then one runs, fed but
        never acted on, so that when GPS falls silent its particles already know where the odometry's path fits
        the roads (a fix window sharing one bias keeps the estimate off the roads long before GPS ends)."""
        sp = relocalise.SEARCH_PARAMS
        assoc, search = self._association, self.search
        if self._estimate.alignment is None or not (assoc.lost or self._beside_gps):
            search.stop()
            self._beside_gps = False
            return
        if search.active is None or not self._beside_gps:
            assoc.take_became_lost()
            x, y = assoc.explained_xy or (pred.x(), pred.y())
            search.begin(search.lost_region(x, y, assoc.unexplained_m), frame=k)
            self._beside_gps = True
        assert search.active is not None
        if search.active.answer is None:  # (a converged search follows the vehicle however far it drives)
            search.widen_if_stuck(pred.x(), pred.y(), k)
        loc = search.active.add(*self._search_pose(k, search.active), k)  # (not feed: a converged search goes on)
        if loc is not None and math.hypot(loc.x_m - pred.x(), loc.y_m - pred.y()) <= sp.confirm_m:
            search.stop()  # the map confirms GPS: a search that found the estimate ends
            self._beside_gps = False

    def _doubting(self, k: int, region: Region) -> Region:
        """The region of a search begun when the estimate is lost within ``SearchParams.doubt_m`` of driving after a map
        re-anchoring: that re-anchoring may have been the wrong turn, so the region also covers the one the
        re-anchoring's search ran in, grown by the distance driven since (the smallest disc holding both, at most
        ``SearchParams.max_radius_m``)."""
        sp = relocalise.SEARCH_PARAMS
        a = self._estimate.alignment
        if self._anchors.last is None or sp.doubt_m <= 0 or a is None:
            return region
        k0, old = self._anchors.last
        track = self.track
        if k0 < track.first:
            return region
        pts = np.array([planar_of(track.raw[j])[:2] for j in range(k0, k + 1)])
        driven = float(cumulative_length(pts)[-1]) * a.scale
        if driven > sp.doubt_m:
            return region
        grown = Region(old.x_m, old.y_m, old.radius_m + driven)
        both = enclosing_disc(region, grown)
        return Region(both.x_m, both.y_m, min(both.radius_m, sp.max_radius_m))

    def _gps_went_silent(self, k: int) -> bool:
        """True once per GPS outage: the last fix is ``SearchParams.after_gps_s`` old (the estimate is where GPS left
        it — a biased fix window leaves it in the wrong place, and nothing but the map can tell)."""
        sp = relocalise.SEARCH_PARAMS
        fixes = self._initialiser.fixes
        if not fixes or sp.after_gps_s <= 0:
            return False
        last = fixes[-1][0]
        if last == self._checked_fix_t or self.track.t[k] - last < sp.after_gps_s:
            return False
        self._checked_fix_t = last
        return True
