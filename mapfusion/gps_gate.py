"""The GPS gate: which fixes the engine takes, and when a run of rejected fixes means the estimate
is lost rather than the GPS (then the engine re-localises on GPS).

A fix is taken when it lies within ``gps_gate_sigma`` of its combined spread (the fix's σ, the
estimate's positional σ and a floor) from the frame's estimate. A run of rejected fixes that agree
with each other — each one's distance from the run's first matches the odometry's over the same
frames, within the gate and a fraction of the distance — means the estimate is lost: after
``relocalise_after_fixes`` such fixes within ``RELOCALISE_WINDOW_S`` the engine re-initialises
from them. So does a longer run, ``relocalise_track_fixes``, that agrees only with itself (each fix
within a vehicle's reach of the one before) while the odometry's distances disagree: the odometry
is what failed then (it stalled, jumped, lost its scale), and a drive of consecutive fixes none of
which the estimate explains is the GPS's word against a sensor that has already shown it is wrong.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import gtsam

from .config import FusionConfig, StateModel
from .track import Track, level

#: Fastest a vehicle moves between two fixes of a track run (relocalise_track_fixes). Unit: m/s. Source: issue 16;
#: 250 km/h.
RELOCALISE_TRACK_SPEED_MPS = 70.0

#: A fix farther than this in time from every odometry frame is rejected. Unit: s. Source: robustness.
GPS_MAX_FRAME_GAP_S = 1.0

#: Gated fixes older than this leave the run that can trigger a GPS re-localisation. Unit: s. Source: issue 6.
RELOCALISE_WINDOW_S = 60.0

#: A re-localisation corrects the heading only when the run's GPS and the estimate each moved at least this far.
#: Unit: m. Source: issue 6.
RELOCALISE_MIN_BASELINE_M = 5.0

#: Added to the re-localised heading's σ (atan of 3σ over the run's length). Unit: deg. Source: issue 6.
RELOCALISE_YAW_SIGMA_FLOOR_DEG = 2.0

#: A run of fixes agrees with the odometry when their distances differ by less than the gate plus this fraction of
#: the distance. Source: issue 6 (scale error and drift).
RELOCALISE_DISTANCE_TOLERANCE = 0.05


#: A fix waiting for its frame: (t, x, y, alt or None, σ), map ENU metres.
Fix = tuple[float, float, float, "float | None", float]


class GpsQueue:
    """Fixes that arrived before the odometry frame nearest to them: each is handed out once that
    frame exists, or counted as rejected for its time (no frame within ``GPS_MAX_FRAME_GAP_S``)."""

    def __init__(self, cfg: FusionConfig) -> None:
        self.cfg = cfg
        self.waiting: list[Fix] = []

    def due(self, track: Track, counters) -> list[tuple[int, Fix]]:
        """(frame, fix) of every waiting fix whose frame now exists, in arrival order."""
        out, keep = [], []
        for fix in self.waiting:
            t = fix[0]
            if t > track.t[-1] + 0.5 * track.frame_period():
                keep.append(fix)
                continue
            k = track.frame_at(t)
            if abs(track.t[k] - t) > GPS_MAX_FRAME_GAP_S:
                counters.gps_rejected_time += 1
                continue
            out.append((k, fix))
        self.waiting = keep
        return out

    def drop(self, counters) -> None:
        """The drive ended: every waiting fix is rejected for its time."""
        counters.gps_rejected_time += len(self.waiting)
        self.waiting = []


class Verdict(enum.Enum):
    """What to do with one fix."""

    accept = "accept"
    reject = "reject"
    relocalise = "relocalise"


@dataclass(frozen=True)
class Relocalisation:
    """Where a GPS re-localisation re-anchors the estimate: frame ``k``, its pose and yaw σ."""

    k: int
    pose: gtsam.Pose3
    yaw_sigma_rad: float
    since_k: int = -1  # after an outage: its first frame, which the correction reaches back to (else -1)
    fixes: tuple[tuple[float, float, int], ...] = ()  # the run's fixes (x, y, frame): added when since_k is set
    taken_k: int = -1  # the frame of the last fix the gate took before the run (-1: none)
    scale_ratio: tuple[float, float] | None = None  # a track run's GPS chord over the estimate's, and its relative σ


class GpsGate:
    """Gates fixes against the estimate and keeps the run of rejected ones."""

    def __init__(self, cfg: FusionConfig) -> None:
        self.cfg = cfg
        self.run: list[tuple[float, float, float, int]] = []  # consecutive gated fixes (t, x, y, frame)
        self.track: list[tuple[float, float, float, int]] = []  # the same, as far as they agree only with each other
        self.open_m = 0.0  # after an odometry outage: how far the estimate may be off (σ, m), until the next fix
        self.open_k = -1  # the outage's first frame (while open)
        self.taken_k = -1  # the frame of the last fix taken (the estimate was right there)
        self.by_track = False  # the run handed to the next re-localisation is a track run (see _scale_ratio)

    def open(self, sigma_m: float, k: int) -> None:
        """The odometry lost track (an outage longer than ``reloc_gap_s``): the estimate may be ``sigma_m``
        off, so the next fix within the widened gate re-anchors it rather than being rejected."""
        self.open_m = max(self.open_m, sigma_m)
        self.open_k = k if self.open_k < 0 else self.open_k
        self.run, self.track = [], []  # fixes from before the outage say nothing of where the odometry resumed

    def check(self, track: Track, k: int, x: float, y: float, sigma: float, pos_sigma: float) -> Verdict:
        """The verdict on a fix at frame k (ENU metres, σ per axis)."""
        cfg = self.cfg
        pred = track.online[k] or track.online[-1]
        assert pred is not None  # fixes are gated only after initialisation
        # after an outage the estimate's own σ is the guess's (large, from a solve far from the truth): only a
        # fix near it is a factor, the rest re-anchor. (A fix from before the outage, handed out late, is not.)
        opened = self.open_m > 0.0 and k >= self.open_k
        spread = math.sqrt(sigma * sigma + (0.0 if opened else pos_sigma) ** 2 + cfg.gps_gate_floor_m**2)
        dist = math.hypot(pred.x() - x, pred.y() - y)
        t = track.t[k]
        if dist <= cfg.gps_gate_sigma * spread:
            self.run.clear()
            self.track.clear()
            self.taken_k = max(self.taken_k, k)
            if opened:
                self.open_m, self.open_k = 0.0, -1
            return Verdict.accept
        if k < self.open_k:
            return Verdict.reject
        if opened and dist <= cfg.gps_gate_sigma * math.hypot(spread, self.open_m):
            # after an outage two fixes that agree place the estimate anew (their chord gives the heading)
            if self._extend(track, t, x, y, k, sigma) >= 2:
                self.open_m = 0.0
                return Verdict.relocalise  # (open_k stays for the relocalisation to read)
            return Verdict.reject
        # the run is broken by any accepted fix; with GPS every 5 s, three fixes span 10 s
        if self._extend(track, t, x, y, k, sigma) >= cfg.relocalise_after_fixes:
            return Verdict.relocalise
        if 0 < cfg.relocalise_track_fixes <= self._follow(track, t, x, y, k, sigma):
            self.run = list(self.track)  # (the re-localisation anchors on the run it is handed)
            self.by_track = True
            return Verdict.relocalise
        return Verdict.reject

    def _follow(self, track: Track, t: float, x: float, y: float, k: int, sigma: float) -> int:
        """Add a gated fix to the track run (fixes each within a vehicle's reach of the one before, within the
        window); a fix out of reach starts it afresh. Returns its length."""
        cfg = self.cfg
        if track.online[k] is None:  # (a re-localisation needs the estimate at both ends of its run)
            return len(self.track)
        self.track = [r for r in self.track if t - r[0] <= RELOCALISE_WINDOW_S]
        if self.track:
            t0, x0, y0, _ = self.track[-1]
            reach = RELOCALISE_TRACK_SPEED_MPS * abs(t - t0) + cfg.gps_gate_sigma * math.sqrt(2.0) * sigma
            if math.hypot(x - x0, y - y0) > reach:
                self.track = []
        self.track.append((t, x, y, k))
        return len(self.track)

    def _scale_ratio(self, gps_m: float, estimate_m: float, sigma: float) -> tuple[float, float] | None:
        """A track run's GPS chord over the estimate's own chord between the same frames (how far the odometry's
        scale is off) and that ratio's relative σ (the fixes' σ at both ends of the chord); None when the chord is
        under ``relocalise_rescale_min_sigmas`` fix σ, or the ratio beyond ``relocalise_rescale_max`` either way
        (an odometry that stopped has no scale to measure)."""
        ratio = gps_m / estimate_m if estimate_m > 0.0 else math.inf
        limit = self.cfg.relocalise_rescale_max
        if gps_m < self.cfg.relocalise_rescale_min_sigmas * sigma or not 1.0 / limit <= ratio <= limit:
            return None
        return ratio, math.sqrt(2.0) * sigma / gps_m

    def _extend(self, track: Track, t: float, x: float, y: float, k: int, sigma: float) -> int:
        """Add a gated fix to the run; the run is then its longest consistent tail within the window (a fix
        that disagrees — one taken in an outage and attached to the frame after it, an outlier — leaves it
        rather than blocking every later run); returns its length."""
        self.run = [r for r in self.run if t - r[0] <= RELOCALISE_WINDOW_S] + [(t, x, y, k)]
        while len(self.run) >= 2 and not self._consistent(track, sigma):
            self.run.pop(0)
        return len(self.run)

    def _consistent(self, track: Track, sigma: float) -> bool:
        """The run's fixes move as far as the odometry says, each from the first fix. Lengths, not
        vectors: an estimate that is lost is often turned too (a bend in a tunnel)."""
        _, x0, y0, k0 = self.run[0]
        p0 = track.online[k0]
        for _, x, y, k in self.run[1:]:
            p = track.online[k]
            if p is None or p0 is None:
                return False
            dg = math.hypot(x - x0, y - y0)
            do = math.hypot(p.x() - p0.x(), p.y() - p0.y())
            if (
                abs(dg - do)
                > self.cfg.gps_gate_sigma * math.sqrt(2.0) * sigma + RELOCALISE_DISTANCE_TOLERANCE * do
            ):
                return False
        return True

    def relocalisation(self, track: Track, sigma: float) -> Relocalisation:
        """The anchor of a re-localisation from the current run (which it clears): the run's last
        fix gives the position, the angle between the run's GPS displacement and the estimate's
        own displacement corrects the heading."""
        cfg = self.cfg
        _, x0, y0, k0 = self.run[0]
        _, xn, yn, kn = self.run[-1]
        p0, pn = track.online[k0], track.online[kn]
        assert p0 is not None and pn is not None  # a consistent run has estimates at both ends
        dg = (xn - x0, yn - y0)
        do = (pn.x() - p0.x(), pn.y() - p0.y())
        length = math.hypot(*dg)
        base = RELOCALISE_MIN_BASELINE_M
        delta = math.atan2(dg[1], dg[0]) - math.atan2(do[1], do[0]) if length > base and math.hypot(*do) > base else 0.0
        yaw = pn.rotation().yaw() + delta
        anchor = gtsam.Pose3(
            gtsam.Rot3.Ypr(yaw, pn.rotation().pitch(), pn.rotation().roll()), gtsam.Point3(xn, yn, pn.z())
        )
        if cfg.state is StateModel.planar:
            anchor = level(anchor)
        # a 3σ error at either end of the run's chord, plus a floor
        yaw_sigma = math.atan2(3.0 * sigma, max(length, 1.0)) + math.radians(RELOCALISE_YAW_SIGMA_FLOOR_DEG)
        since_k, fixes = self.open_k, tuple((x, y, k) for _, x, y, k in self.run)
        self.run, self.track, self.open_k = [], [], -1
        taken_k, self.taken_k = (self.taken_k if self.taken_k < k0 else -1), kn
        ratio = self._scale_ratio(length, math.hypot(*do), sigma) if self.by_track else None
        self.by_track = False
        return Relocalisation(kn, anchor, yaw_sigma, since_k, fixes, taken_k, ratio)
