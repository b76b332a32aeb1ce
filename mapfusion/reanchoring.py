"""Two parts that re-anchor the estimate: :class:`OutageCarry`, the step over an odometry outage carried along the
road graph (and carried again once the speed after it is known), and :class:`GpsReanchoring`, the restart from
GPS when consistent fixes disagree with the estimate. Each proposes to the :class:`~mapfusion.estimate.Estimate`,
which applies."""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable

import gtsam
import numpy as np

from . import factors
from .config import FusionConfig, OutageStep, StateModel
from .counters import Counters
from .estimate import Estimate
from .factors import OUTAGE_ROT_SIGMA_DEG
from .gps_gate import GpsGate
from .initialisation import Initialiser
from .metrics import umeyama
from .relocalise import RELOC_SEED, SEARCH_PARTICLES, RoadFollower
from .roadmap import RoadMap
from .track import JumpGuard, Track, level, spread_back

log = logging.getLogger(__name__)

#: With outage_step = road: an estimate within its road's width (plus a lane) and heading along it within this is
#: carried on the road itself (its heading becomes the road's); else by the road's own motion from where it is
#: matched, its offset and heading error kept. Unit: deg. Source: issue 17: set60 Helsinki heavy rain s6 (37 m off
#: before a 3 s gap: 17 -> 57 m when snapped).
OUTAGE_ON_ROAD_DEG = 10.0

#: The heading difference A in outage_end_weight_m_per_deg's D is counted up to this: ends further off the guess's
#: heading than this are told apart by their position alone (the odometry's turn over a gap says roughly which way,
#: not which of two roads both far off it). Unit: deg. Source: issue 17: heavy-rain Kotka s2 (a 65° turn inside a 2
#: s gap the VO saw as 4°: uncapped, the end 165° off the truth won over the one 32° off by 4 m of D).
OUTAGE_END_MAX_DEG = 45.0


def placed_on(step: Callable[[int], gtsam.Pose3], k0: int, fixes, sigma: float,
              yaw_sigma: float) -> tuple[gtsam.Pose3, float]:
    """Frame k0's pose that puts the odometry from k0 (``step(k)``: the step into frame k) onto ``fixes`` ((x, y,
    frame), ≥ 2) by a rigid fit, and its positional σ (the fixes' and the heading's lever arm over the distance to
    them)."""
    chain, pose = {k0: gtsam.Pose3()}, gtsam.Pose3()
    for j in range(k0 + 1, max(kf for _, _, kf in fixes) + 1):
        pose = chain[j] = pose.compose(step(j))
    odo = np.array([[chain[kf].x(), chain[kf].y()] for _, _, kf in fixes])
    rot, trans, _ = umeyama(odo, np.array([[x, y] for x, y, _ in fixes]))
    lever_m = float(np.max(np.hypot(odo[:, 0], odo[:, 1])))
    placed = gtsam.Pose3(gtsam.Rot3.Yaw(math.atan2(rot[1, 0], rot[0, 0])), gtsam.Point3(trans[0], trans[1], 0.0))
    return placed, math.hypot(sigma, yaw_sigma * lever_m)


class OutageCarry:
    """The step into the frame after an odometry outage (``outage_step = road``): carried along the road graph,
    the GPS gate opened for fixes that place it anew, and the gap carried again ``outage_speed_after_s`` later."""

    def __init__(self, road: RoadMap, cfg: FusionConfig, track: Track, estimate: Estimate, gate: GpsGate,
                 jumps: JumpGuard) -> None:
        self.road, self.cfg, self.track = road, cfg, track
        self._estimate, self._gate, self._jumps = estimate, gate, jumps
        self._follower: RoadFollower | None = None
        self._gap_pending: tuple[int, gtsam.Pose3, float] | None = None  # the last gap carried: frame, pose before, m

    def carried_sigma_m(self, length_m: float) -> float:
        """σ (m) of a step carried ``length_m`` along the road over an odometry gap: ``ParticleParams.sigma_m`` +
        ``outage_step_fraction`` of its length (the road follower's spread, and the gap's search's guess)."""
        return SEARCH_PARTICLES.sigma_m + self.cfg.outage_step_fraction * length_m

    def step_into(self, k: int, prev: gtsam.Pose3, length_m: float | None = None) -> gtsam.Pose3:
        """The step into frame k. After an odometry outage longer than ``reloc_gap_s`` with ``outage_step =
        road`` and the map: as far as the odometry's guess (the last velocity straight on) goes, but along the
        road graph from the road ``prev`` is matched to (a tunnel's curve, the road beyond a junction nearest
        the guess), proposed to the estimate as frame k's step (a restart re-adds it). ``length_m``: carried this
        far instead of the odometry's guess (``outage_speed_after_s``)."""
        step = self.track.step(k, self._estimate.aligned.scale)
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
            self._follower = RoadFollower(self.road, dataclasses.replace(SEARCH_PARTICLES, uturn_at_vertex=0.0),
                                          RELOC_SEED)
        tr = step.translation()
        guessed_m = math.sqrt(tr.dot(tr))
        if length_m is None:
            length_m = guessed_m
            self._gap_pending = (k, prev, guessed_m)
        road_step = self._along(m, prev, length_m)
        self._estimate.carry_step(k, road_step)
        log.info("t=%.1f s: the odometry resumed after %.1f s: carried %.0f m along the road", t[k], t[k] - t[k - 1],
                 length_m)
        return road_step

    def _along(self, m, prev: gtsam.Pose3, length_m: float) -> gtsam.Pose3:
        """The step of ``length_m`` along the road from ``prev`` (matched to ``m``), turning at a junction as the
        odometry did over the gap (a constant turn)."""
        cfg, follower = self.cfg, self._follower
        assert follower is not None
        half = 0.5 * self._jumps.gap_yaw_rad
        chord = length_m * (math.sin(half) / half if abs(half) > 1e-9 else 1.0)
        # an estimate on its road (within its width, along it) is carried on the road itself; one off it or
        # turned against it by the road's own motion from where it is matched (its offset kept: the map's
        # priors judge that)
        place = (m.edge, -1 if m.reversed else 1, m.along_m)
        if m.lateral_m <= (0.5 * m.lanes + 1.0) * cfg.lane_width_m and m.angle_deg <= OUTAGE_ON_ROAD_DEG:
            start = level(prev)
        else:
            x0, y0, yaw0 = follower.road_pose(*place)
            start = gtsam.Pose3(gtsam.Rot3.Yaw(yaw0), gtsam.Point3(x0, y0, 0.0))
        guess = start.compose(gtsam.Pose3(gtsam.Rot3(), gtsam.Point3(chord * math.cos(half), chord * math.sin(half),
                                                                      0.0)))
        x, y, yaw = follower.follow(*place, length_m, (guess.x(), guess.y()), self.carried_sigma_m(length_m),
                                    target_yaw_rad=start.rotation().yaw() + 2.0 * half,
                                    weight_m_per_deg=cfg.outage_end_weight_m_per_deg, max_deg=OUTAGE_END_MAX_DEG)
        return start.between(gtsam.Pose3(gtsam.Rot3.Yaw(yaw), gtsam.Point3(x, y, start.z())))

    def note_outage(self, k: int, step: gtsam.Pose3) -> None:
        """An odometry outage longer than ``reloc_gap_s`` into frame k: where the odometry resumed is a guess,
        so the GPS gate opens for fixes that place it anew (:meth:`GpsGate.open`)."""
        gap_s = self.track.t[k] - self.track.t[k - 1]
        if gap_s > self.cfg.reloc_gap_s:
            self._gate.open(factors.outage_sigma_m(self.cfg, step, gap_s), k)

    def note_outage_in_batch(self) -> None:
        """The initialisation's frames hold an outage: the batch gated the fixes after it against the
        odometry's guess, so the gate opens as after an outage (the next fix near the estimate closes it)."""
        t = self.track.t
        for k in range(len(self.track) - 1, max(self.track.first, 0), -1):
            if t[k] - t[k - 1] > self.cfg.reloc_gap_s:
                self.note_outage(k, self._estimate.step(k))
                return

    def recarry_gap(self, k: int) -> None:
        """``outage_speed_after_s`` after the odometry resumed from the last gap carried along the road (frame k,
        the last): that gap's step carried again at the mean of the speeds before it and since (a vehicle that
        sped up or slowed down unseen is placed by both), and, when the lengths differ by more than 5% and 10 m,
        the estimate moved by the difference and the smoother restarted there."""
        if self._gap_pending is None:
            return
        kg, prev, guessed_m = self._gap_pending
        t, raw, est = self.track.t, self.track.raw, self._estimate
        if t[k] - t[kg] < self.cfg.outage_speed_after_s:
            return
        self._gap_pending = None
        was_road, now = est.road_steps.get(kg), self.track.online[k]
        if self.cfg.outage_speed_after_s <= 0 or was_road is None or now is None or est.smoother is None:
            return
        moved = raw[k].translation() - raw[kg].translation()
        v_after = math.sqrt(moved.dot(moved)) * est.aligned.scale / max(t[k] - t[kg], 1e-3)
        length_m = 0.5 * (guessed_m + v_after * (t[kg] - t[kg - 1]))
        if abs(length_m - guessed_m) <= max(10.0, 0.05 * guessed_m):  # (not worth a restart)
            return
        log.info("t=%.1f s: the gap into t=%.1f s carried again at the speeds on both sides: %.0f m, not %.0f m",
                 t[k], t[kg], length_m, guessed_m)
        moved_by = prev.compose(self.step_into(kg, prev, length_m)).compose(prev.compose(was_road).inverse())
        pose = level(moved_by.compose(now))
        sigma = max(est.pos_sigma_m, SEARCH_PARTICLES.sigma_m)
        noise = factors.diagonal(factors.pose_sigmas(StateModel.planar, math.radians(OUTAGE_ROT_SIGMA_DEG),
                                                     sigma))
        est.restart_from(k, pose, noise, sigma)
        est.update()


class GpsReanchoring:
    """From GPS, as at the start: when the gate's run of consistent fixes disagrees with the estimate, a fresh
    smoother at the gate's pose, reaching back over an outage, and the odometry re-scaled when a track run
    showed its scale off."""

    def __init__(self, cfg: FusionConfig, track: Track, estimate: Estimate, gate: GpsGate, initialiser: Initialiser,
                 counters: Counters) -> None:
        self.cfg, self.track, self.counters = cfg, track, counters
        self._estimate, self._gate, self._initialiser = estimate, gate, initialiser

    def relocalise(self, sigma: float) -> None:
        """A fresh smoother at the gate's pose. After an odometry outage the correction reaches back to the outage:
        the odometry since is placed on the run's fixes (a rigid fit) and those fixes are added, so the estimate
        between the outage and the re-anchoring is mended too."""
        est = self._estimate
        r = self._gate.relocalisation(self.track, sigma)
        k, pose, yaw_sigma = r.k, r.pose, r.yaw_sigma_rad
        if r.scale_ratio is not None:
            self._rescale(*r.scale_ratio)
        if 0 <= r.since_k < r.k and len(r.fixes) >= 2:
            k, pose, sigma = r.since_k, *placed_on(est.step, r.since_k, r.fixes, sigma, yaw_sigma)
        noise = factors.diagonal(factors.pose_sigmas(StateModel.planar, yaw_sigma, sigma))
        was = self.track.online[k]
        est.restart_from(k, pose, noise, sigma)
        if k == r.k and was is not None:
            self._spread_back(r.taken_k, k, was, pose)
        for x, y, kf in r.fixes if k == r.since_k else ():
            est.add(factors.gps_factor(self.cfg.state, kf, x, y, None, sigma))
        est.update()

    def _rescale(self, ratio: float, relative_sigma: float) -> None:
        """A track run showed the odometry's scale off by ``ratio`` (known to ``relative_sigma``): the frames from
        now on use the new scale, and later refits are judged against it, not against the initialisation's."""
        a = self._estimate.aligned
        scale = a.scale * ratio
        sigma = scale * math.hypot(a.relative_sigma, relative_sigma)
        log.info("the GPS track run re-scales the odometry: %.4f → %.4f (± %.4f)", a.scale, scale, sigma)
        self._estimate.set_scale(scale, sigma)
        self._initialiser.rescaled(scale, sigma, self.track.t[-1])
        self.counters.gps_rescales += 1

    def _spread_back(self, k0: int, k1: int, was: gtsam.Pose3, now: gtsam.Pose3) -> None:
        """A GPS re-localisation moved frame k1 from ``was`` to ``now``; the estimate was right at frame k0 (the
        last fix taken). The final estimates between are mended by :func:`~mapfusion.track.spread_back`, so the
        stretch the fixes could not see — a tunnel, a GPS-denied zone — is corrected, not only its end (the
        online estimates stay as they were: causal)."""
        sm, track = self._estimate.sm, self.track
        if k0 < track.first or k0 >= k1 - 1 or sm.smoothed.get(k0) is None:
            return
        frames = [k for k in range(k0 + 1, k1) if sm.smoothed.get(k) is not None]
        path = [p for p in [sm.smoothed[k0]] + [sm.smoothed[k] for k in frames] if p is not None]
        self._estimate.move_final(dict(zip(frames, spread_back(path, was, now))))
        log.info("t=%.1f s: the GPS correction (%.0f m) spread back over %d frames", track.t[k1],
                 math.hypot(now.x() - was.x(), now.y() - was.y()), len(frames))
