"""Global re-localisation on the road network from the odometry's shape alone (issue 17; after
Brubaker, Geiger and Urtasun, "Lost! Leveraging the Crowd for Probabilistic Visual
Self-Localization", CVPR 2013): no GPS, only the roads and the odometry.

A particle is a position on the road graph — an edge, a direction of travel, a distance along the
edge — and a heading offset (the map's heading minus the odometry's, the rotation that takes the
odometry frame into the map). Particles start spread uniformly over the roads of a region (every
road in each direction it may be driven), each with the offset that makes the vehicle drive along
its road. Every ``ParticleParams.step_m`` of odometry each particle drives the same distance along the graph
(at a vertex it takes a random legal exit: the particles that turned wrong die at the next steps)
and is weighted by how well its own displacement on the road agrees with the odometry's
displacement turned by its offset: a Gaussian in the 2-D difference, σ = ``ParticleParams.sigma_m`` +
``ParticleParams.sigma_per_m`` × distance. Turns at junctions, curvature and the lengths between turns are
what separates the right place from the others; a straight road is the same everywhere and the
posterior stays spread until the path turns. The offset follows the odometry's slow heading drift
(a small gain on each step's heading innovation).

Each particle also carries the odometry's scale (map metres per odometry unit). It is 1 for a metric
odometry taken as given; a search told the scale is unknown (``--scale-unknown``: ``reloc_scale_min``
to ``reloc_scale_max``) draws it log-uniformly over that range, and the lengths between turns decide it
as they decide the place: a particle with the wrong scale reaches the next junction too early or too
late. Its logarithm walks by ``ParticleParams.scale_walk`` a step (a monocular VO's scale wanders).

The posterior has *converged* when one disc of ``ParticleParams.converge_radius_m`` holds at least
``ParticleParams.converge_mass`` of it after at least ``ParticleParams.min_distance_m`` of driving; the answer is that
cluster's pose (on its road, heading from its offsets) and its spread.

:class:`RoadParticles` is the filter (arrays only, no GTSAM); :class:`Relocaliser` feeds it from an
odometry stream (planar poses in the odometry's frame) and is what the engine holds.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np

from .config import FusionConfig
from .geometry import fast_clip, point_segment_distance, wrap_angle
from .roadmap import RoadMap

log = logging.getLogger(__name__)

__all__ = ["Region", "Located", "RoadParticles", "Relocaliser", "enclosing_disc", "kld_count"]

#: Seed of the re-localisation's random numbers (runs are reproducible); with the frame a search begins at, it
#: seeds that search, whose draws then do not depend on the searches before it. Source: reproducibility.
RELOC_SEED = 0

#: Probability that a road fix particle on a two-way road turns back in one step: vehicles turn back (SUMO's routes
#: at dead ends and junctions), and particles that cannot are all wrong after it. Source: issue 16: Helsinki seed 5
#: turns back at 253 s.
ROAD_FIX_UTURN_PROBABILITY = 0.02

#: Vertices a particle may pass in one step (a step longer than this many short edges stops at the last).
MAX_HOPS = 16

#: A search for the scale spreads as many particles per factor SCALE_BAND of its range as a search at a
#: known scale has in all (0.5-2: four times as many; 8 Helsinki drives found at 1.4, 3 wrong with once as many).
SCALE_BAND = math.sqrt(2.0)


@dataclass(frozen=True)
class Region:
    """Where the vehicle is known to be: a disc in the map frame (m)."""

    x_m: float
    y_m: float
    radius_m: float


@dataclass(frozen=True)
class Guess:
    """The engine's own guess of the pose as a search begins (after an odometry gap: the step carried along the
    road): a soft prior on the search's first particles, ``floor`` + (1 − floor) × a Gaussian in position (σ m)
    and heading (σ rad), so that places the guess rules out keep ``floor`` of its weight. With ``from_xy_m`` the
    position is anywhere on the segment from there to (``x_m``, ``y_m``): the Gaussian is in the distance to it."""

    x_m: float
    y_m: float
    sigma_m: float
    yaw_rad: float
    yaw_sigma_rad: float
    floor: float
    from_xy_m: tuple[float, float] | None = None


@dataclass(frozen=True)
class Located:
    """A converged posterior: the pose of its main cluster and how sure it is."""

    x_m: float
    y_m: float
    yaw_rad: float  # the vehicle's heading in the map frame (the odometry's, turned by the offset)
    offset_rad: float  # map heading minus odometry heading (the alignment's rotation)
    edge: int
    direction: int
    along_m: float
    mass: float  # posterior mass within ParticleParams.converge_radius_m of the pose
    spread_m: float  # RMS distance of that mass from the pose
    yaw_spread_rad: float  # circular σ of its offsets
    driven_m: float  # odometry distance since the filter started (m, at the posterior's scale)
    scale: float = 1.0  # the cluster's odometry scale (map metres per odometry unit; its weighted geometric mean)
    scale_spread: float = 0.0  # relative σ of that scale within the cluster


@dataclass(frozen=True)
class ParticleParams:
    """The road particles' own settings. The defaults are the search's (:data:`SEARCH_PARTICLES`); the road
    fixes take their own view of them (:func:`mapfusion.tracking.particle_config`). Fixed values of the engine,
    each chosen by the measurement its comment names, not settings of :class:`~mapfusion.config.FusionConfig`."""

    #: Particles of the global re-localisation, spread over the region's roads. Source: issue 17; speed (10 Hz on
    #: one core, 2 km radius).
    particles: int = 60000

    #: Particles per metre of road (both directions) in the search region, up to particles. Unit: 1/m. Source:
    #: issue 17; by measurement: kidnapped seeds 1-10 / held-out 11-20, 4 → 10 per m: Map-Fusion ATE 78.2 → 60.6 /
    #: 104.0 → 84.6 m.
    particles_per_m: float = 10.0

    #: Fewest particles an adaptive count keeps. Source: issue 21.
    particles_min: int = 500

    #: Adaptive particle count (KLD-sampling, Fox 2003): at each resampling as many particles as bound the
    #: posterior's error by this (Kullback-Leibler divergence, 99% confidence) over the bins it occupies, at most
    #: the count the filter started with (0: the count stays). Source: issue 21; Fox, 'Adapting the sample size in
    #: particle filters through KLD-sampling', IJRR 2003.
    kld_epsilon: float = 0.0

    #: Bin size b of that count: position cells of b metres, each direction, heading offsets per 2·b degrees,
    #: scales per b percent. Unit: m. Source: issue 21; by measurement.
    kld_bin_m: float = 5.0

    #: Odometry distance between two re-localisation steps. Unit: m. Source: issue 17.
    step_m: float = 5.0

    #: σ of a step's displacement mismatch (road against odometry), constant part. Unit: m. Source: issue 17; by
    #: measurement.
    sigma_m: float = 1.5

    #: σ of a step's displacement mismatch, per metre of the step (heading and scale error). Unit: m/m. Source:
    #: issue 17; by measurement.
    sigma_per_m: float = 0.15

    #: Relative σ of each particle's distance per step (the odometry's scale error). Source: issue 22's fitted VO:
    #: 2.5% scale.
    scale_sigma: float = 0.03

    #: σ of the random walk of a particle's log-scale per step, when the scale is searched for (a monocular VO's
    #: scale wanders). Source: issue 22: real mono VO's scale random walk 0.004 per √m, 5 m steps → 0.009; by
    #: measurement.
    scale_walk: float = 0.005

    #: σ added to each particle's distance per step (diffusion along the road). Unit: m. Source: issue 17; by
    #: measurement.
    along_sigma_m: float = 0.5

    #: Gain with which a particle's heading offset follows each step's heading innovation (the odometry's yaw
    #: drift). Source: issue 17; by measurement.
    offset_gain: float = 0.2

    #: σ of the random walk of a particle's heading offset per step. Unit: deg. Source: issue 22's fitted VO yaw
    #: drift.
    offset_sigma_deg: float = 0.3

    #: Largest heading innovation a particle's offset follows in one step (180: any; the road fixes' particles take
    #: RoadFixParams.offset_max_deg). Unit: deg. Source: issue 16.
    offset_max_deg: float = 180.0

    #: Probability that a particle on a two-way road turns back in one step (0: only at a dead end; the road fixes'
    #: particles take ROAD_FIX_UTURN_PROBABILITY). Source: issue 16.
    uturn_probability: float = 0.0

    #: A search's particle reaching a vertex of a two-way road may also turn back there: one more exit, of this
    #: prior weight against 1 for each legal exit (0: only at a dead end). The road fixes' particles turn back by
    #: ROAD_FIX_UTURN_PROBABILITY instead. Source: issue 17: SUMO's vehicles turn back at junctions; kidnapped runs
    #: re-anchored wrong 13 -> 7 of 120 (seeds 1-30).
    uturn_at_vertex: float = 0.1

    #: Radius of the disc whose posterior mass decides convergence. Unit: m. Source: issue 17; by measurement.
    converge_radius_m: float = 25.0

    #: Posterior mass one disc must hold to call the position found. Source: issue 17; by measurement.
    converge_mass: float = 0.8

    #: Driving before a re-localisation may converge. Unit: m. Source: issue 17; by measurement.
    min_distance_m: float = 100.0


#: The search's particles.
SEARCH_PARTICLES = ParticleParams()


@dataclass(frozen=True)
class SearchParams:
    """The map search's own settings (with ``map_relocalisation``, and a cold start): fixed values of the engine,
    each chosen by the measurement its comment names, not settings of :class:`~mapfusion.config.FusionConfig`.
    The engine's parts read :data:`SEARCH_PARAMS` when they decide."""

    #: A re-localisation within this distance of the current estimate only confirms it (no re-anchoring); farther,
    #: the estimate is re-anchored on it (the search's answer is a cluster of a few metres' spread, placed by the
    #: path's turns). Unit: m. Source: issue 17: never move an estimate that was not lost; 5 m against 15 m:
    #: kidnapped seeds 1-10 within 500 m 36 against 34 of 40, seeds 11-20 after-error 7.27 against 7.43 m, none
    #: wrong.
    confirm_m: float = 5.0

    #: With map_relocalisation: this long after the last GPS fix a search around the estimate checks where GPS left
    #: it; while fixes come more often, GPS places the estimate and no search runs (0: searches regardless of GPS).
    #: Unit: s. Source: issue 17: a biased fix window leaves the estimate off.
    after_gps_s: float = 10.0

    #: With map_relocalisation: the search begun when GPS falls silent (after_gps_s; only where GPS left the
    #: estimate off the roads, gps_fit_min) starts this much driving back, around the estimate there, and is fed
    #: the odometry since at once (from GPS's first fix at the earliest, never across an odometry gap): a fix
    #: window that shared one bias is judged on the path driven under it, not only on the path after it (0: the
    #: search starts at the silence). Unit: m. Source: issue 17: with gps_fit_min, kidnapped seeds 1-30, 0 / 250 /
    #: 500 m: within 500 m 77 / 84 / 85 of 120, runs re-anchored wrong 10 / 9 / 9, ATE 51.9 / 52.6 / 53.1 m
    #: (without the fit test 250 m moved a good estimate 237 m on a drive whose VO scale changes by 20% after GPS).
    gps_replay_m: float = 500.0

    #: With map_relocalisation: when GPS falls silent (after_gps_s), the second opinion's search begins only if
    #: less than this share of the estimate's last gps_fit_m of driving lay on a road (within its width +
    #: gps_fit_margin_m of the centre line, heading within prior_max_angle_deg): a path GPS placed on the roads is
    #: trusted, one it placed off them is searched for (0: always search). Source: issue 17: the last 300 m before
    #: the silence on 36 runs of the 60-run sets (GPS unbiased) 0.84-1.00 on a road, on 20 kidnapped runs with
    #: biased fixes 0.00-0.41 and one 0.67.
    gps_fit_min: float = 0.75

    #: Driving over which gps_fit_min measures the estimate's path. Unit: m. Source: issue 17: as reloc_radius_m.
    gps_fit_m: float = 300.0

    #: How far beyond a road's width (lanes × lane_width_m) from its centre line the estimate still lies on it, for
    #: gps_fit_min. Unit: m. Source: issue 17: a tracked estimate strays a lane from OSM's centre line.
    gps_fit_margin_m: float = 3.0

    #: With map_relocalisation: when GPS falls quiet (register_after_s) where it left the estimate off the roads
    #: (gps_fit_min, or lost beside GPS; anywhere with reloc_register_on_roads), its fixes of the last
    #: reloc_register_m are first registered on the roads (mapfusion.register: the shift within reloc_radius_m that
    #: puts them nearest the way-points); the estimate is moved by that shift, without a search, when the best
    #: shift farther than register_separation_m from it fits this many times worse (RMS), the shift itself fits
    #: within register_rms_m and it is longer than register_separation_m (0: off; a search as before). Source:
    #: issue 17: the fix windows of the kidnapped seeds 1-10 (offline, mapfusion.register): the 19 of 20 biased
    #: windows found within 3.4 m of their bias had ratios 1.35-3.38, the one found 246 m off 1.04.
    register_ratio: float = 1.25

    #: The fixes are registered (register_ratio) this long after the last one, once per last fix: soon, for the
    #: odometry carries the estimate from the last fix to the re-anchoring (a VO's heading wanders a few degrees in
    #: 10 s: 26 m off at 25 m/s when measured). Unit: s. Source: issue 17: kidnapped GPS bias Kotka s7.
    register_after_s: float = 2.0

    #: A decisive registration places the odometry on the last fixes, shifted, by a rigid fit (as a GPS re-
    #: localisation does): those back from the last one to the first that lies this far from it in a straight line
    #: (a longer stretch bends with the VO's heading wander; a shorter one, or a standstill, leaves the heading
    #: undetermined). Unit: m. Source: issue 17: kidnapped GPS bias Kotka s7 (25 m/s), 2 s after the last fix 7.1 m
    #: off with 10 s of fixes, 10.7 m with 60 s; Helsinki s9, 10 s of fixes at a standstill turned the estimate
    #: 138°.
    register_place_m: float = 150.0

    #: Largest RMS distance (each capped at 10 m) of the shifted fixes to the roads' way-points for the
    #: registration to act. Unit: m. Source: issue 17: 2.1-3.0 m on the kidnapped seeds 1-10's windows (GPS σ 2 m,
    #: vehicles 1.6 m right of the centre line).
    register_rms_m: float = 4.0

    #: How far another shift must lie from the best to count as its runner-up (register_ratio): nearer shifts are
    #: the same place. Unit: m. Source: issue 17: a few lane widths, under a block's length.
    register_separation_m: float = 30.0

    #: With reloc_mend_back: the searched path is not moved when the moved path's share of frames on a road (every
    #: fifth frame matched within half its road's width plus a lane, heading within prior_max_angle_deg) would fall
    #: below this fraction of its share as it is: an estimate the map's priors kept on its roads is not swung off
    #: them about its end by the answer's heading (0: always moved, as before). Source: issue 17: kidnapped VO jump
    #: Kotka s11, a re-anchoring turned 1,353 m of path from 68% on the roads to 13% and its smoothed RMSE 18.7 ->
    #: 104.5 m; good mends measured 35-64% against 57-83% (refused at ratio 1, docs/method.md).
    mend_keep_ratio: float = 0.5

    #: A search begun when the estimate is lost within this much driving after a map re-anchoring also covers the
    #: region the re-anchoring's search ran in, grown by the distance since: the re-anchoring may have been wrong
    #: (0: the lost region only). Unit: m. Source: issue 17: kidnapped seeds 1-10 / held-out 11-20, 0 / 1000 / 2000
    #: m: ATE 60.4 / 58.7 / 58.7 and 82.6 / 80.5 / 80.4 m.
    doubt_m: float = 1000.0

    #: A search that re-anchored the estimate goes on over this much more driving, its posterior kept whole (its
    #: particles may now turn back, as the road fixes' do): should its mass gather at another place (a look-alike
    #: path that the road since has ruled out) more than watch_apart_m from the estimate, it re-anchors there (0: a
    #: search ends when it converges). Unit: m. Source: issue 17: a wrong convergence stayed until the next lost
    #: event; kidnapped seeds 1-10 / 11-20, 0 / 500 m: ATE 53.2 / 49.3 and 56.2 / 55.9 m, wrong for 1,386 / 1,381
    #: and 1,603 / 1,603 m at most, 4 runs better, none worse.
    watch_m: float = 500.0

    #: How far from the estimate the watched posterior's answer must be to re-anchor again (nearer: the same place,
    #: the tracking's own along-road error). Unit: m. Source: issue 17: twice reloc_converge_radius_m.
    watch_apart_m: float = 50.0

    #: No map re-anchoring while the search's posterior still holds at least this share of its mass within 2 ×
    #: reloc_converge_radius_m of the estimate: it has not ruled the estimate's place out, only preferred another
    #: (a look-alike path) (0: no such test). Source: issue 17: as road_fix_rival_mass; kidnapped seeds 1-10 /
    #: held-out 11-20, 0 / 0.02 / 0.05 / 0.1: ATE 53.8 / 53.2 / 53.2 / 53.2 and 70.9 / 56.2 / 56.2 / 57.7 m, runs
    #: re-anchored wrong 4 / 3 / 3 / 3 and 8 / 5 / 5 / 6.
    rival_mass: float = 0.05

    #: Speed assumed through such a gap: the search region's radius is reloc_gap_margin_m + this × the gap, and the
    #: opened GPS gate's σ at least this × the gap. Unit: m/s. Source: issue 17: city speeds.
    gap_speed_mps: float = 15.0

    #: The search region after an odometry gap also reaches the step carried over it (outage_step) plus this many
    #: of that step's σ (reloc_sigma_m + outage_step_fraction × its length): a vehicle may speed up in the gap, and
    #: the carried step assumes the speeds at its ends; 0: the carried step's length alone. Source: issue 17: rain-
    #: tunnel Andorra vo s2 drove 27 m/s in a 106 s tunnel gap carried at 19-25 m/s; its search's 2,612 m region
    #: ended 300 m short of the vehicle and converged on a look-alike 860 m off.
    gap_reach_sigmas: float = 1.0

    #: Largest search region. Unit: m. Source: issue 17: 2 km in a city at 10 Hz on one core.
    max_radius_m: float = 2000.0

    #: A search not converged after this much driving starts again around the estimate with twice the radius. Unit: m.
    #: Source: issue 17.
    give_up_m: float = 1500.0

    #: Radius of the search region around the estimate where a road last explained it, when lost (and around the
    #: estimate when GPS falls silent). Unit: m. Source: issue 17.
    radius_m: float = 300.0

    #: Growth of that radius per metre driven since a road last explained the estimate. Unit: m/m. Source: issue 17:
    #: the vehicle is at most that far from there.
    radius_per_m: float = 1.0

    #: Length of the fixes' path registered on the roads (SearchParams.register_ratio), back from the last fix. Unit: m.
    #: Source: issue 17: the kidnapped family's fix windows (120 s, 250-900 m).
    register_m: float = 1000.0

    #: Radius of the search after an odometry gap beyond the distance the vehicle may have driven through it (the
    #: estimate before the gap was good to about this). Unit: m. Source: issue 17: a smaller region holds fewer look-
    #: alike paths.
    gap_margin_m: float = 100.0

    #: The search begun after an odometry gap starts from the engine's own guess (the step carried along the road,
    #: outage_step): its particles weighted floor + (1 − floor) × a Gaussian around that pose (σ of the carried step:
    #: ParticleParams.sigma_m + outage_step_fraction × its length, and OUTAGE_ROT_SIGMA_DEG), so that places the guess
    #: rules out keep this share of the weight; 1: uniform over the region. Source: issue 17 (kidnapped VO jumps:
    #: carried steps 2–50 m off in most runs, while a uniform search took 600–1,000 m of Kotka's long roads to
    #: converge).
    gap_guess_floor: float = 0.05


#: The engine's map search (read as ``relocalise.SEARCH_PARAMS`` where it decides).
SEARCH_PARAMS = SearchParams()


class RoadParticles:
    """The particle filter over positions on the road graph (see the module docstring)."""

    def __init__(self, road: RoadMap, params: ParticleParams, seed: int | list[int] = 0) -> None:
        self.road, self.params = road, params
        self.rng = np.random.default_rng(seed)
        n_pts = int(np.count_nonzero(~road.is_join))  # edges' way-points come first, join curves after
        self._n_pts = n_pts
        lengths = road.edge_length_m
        self._base = np.concatenate(([0.0], np.cumsum(lengths + 1.0)))[:-1]  # (a 1 m gap keeps edges apart)
        self._glob = road.s_m[:n_pts].astype(np.float64) + self._base[road.edge[:n_pts]]
        self._index = _ArcIndex(self._glob)
        self._exits = _exits(road)
        self._two_way = _edge_travel(road) == 0
        self.edge = np.zeros(0, dtype=np.int64)
        self.direction = np.zeros(0, dtype=np.int64)
        self.along = np.zeros(0)
        self.offset = np.zeros(0)
        self.log_scale = np.zeros(0)
        self._log_range = (0.0, 0.0)  # the logs of the scales searched over (equal: the scale is known)
        self.logw = np.zeros(0)
        self.driven_m = 0.0
        self._xy: np.ndarray | None = None  # the particles' positions while (edge, along) are unchanged
        self._n_max = 0  # the count the filter started with (an adaptive count stays at or under it)

    def __len__(self) -> int:
        return len(self.edge)

    @property
    def scale_free(self) -> bool:
        """The scale is a state of the search (a range was given)."""
        return self._log_range[1] > self._log_range[0]

    def start(self, region: Region, odometry_yaw_rad: float, n: int | None = None,
              scale_range: tuple[float, float] = (1.0, 1.0), guess: Guess | None = None) -> int:
        """Spread ``n`` particles (``ParticleParams.particles``) uniformly over the road length inside the region,
        in each legal direction, heading along their roads, their scales log-uniform over ``scale_range``;
        weighted by ``guess`` when one is given (else equal weights); returns how many way-points lay inside."""
        road = self.road
        near = road.query_radius(region.x_m, region.y_m, region.radius_m)
        near = near[near < self._n_pts]
        if near.size == 0:
            self.edge = np.zeros(0, dtype=np.int64)
            return 0
        lo, hi = math.log(scale_range[0]), math.log(scale_range[1])
        if n is None:  # by the road length in the region (way-points ~1 m apart), both directions
            # and, when the scale is searched too, by its range: one band of particles per factor √2
            bands = max(1.0, (hi - lo) / math.log(SCALE_BAND))
            n = int(bands * min(self.params.particles, max(1000, self.params.particles_per_m * near.size)))
        pick = near[self.rng.integers(0, near.size, n)]
        travel = road.travel[pick]
        d = np.where(self.rng.random(n) < 0.5, 1, -1)
        d = np.where(travel != 0, travel, d).astype(np.int64)
        self.edge = road.edge[pick].astype(np.int64)
        self.direction = d
        self.along = road.s_m[pick].astype(np.float64)
        yaw = self._heading(self.edge, self.along, d)
        self.offset = wrap_angle(yaw - odometry_yaw_rad + self.rng.normal(0.0, math.radians(2.0), n))
        self._log_range = (lo, hi)
        self.log_scale = self.rng.uniform(lo, hi, n) if self.scale_free else np.full(n, lo)
        self.logw = np.full(n, -math.log(n))
        self.driven_m = 0.0
        self._xy = None
        self._n_max = n
        if guess is not None:
            self.logw = guess_log_weights(guess, self.positions(), yaw)
        return int(near.size)

    def road_pose(self, edge: int, direction: int, along_m: float) -> tuple[float, float, float]:
        """(x, y, heading in the direction of travel) of a place on the graph."""
        e, a, d = np.array([edge]), np.array([float(along_m)]), np.array([direction])
        xy = self.positions(e, a)[0]
        return float(xy[0]), float(xy[1]), math.remainder(float(self._heading(e, a, d)[0]), 2.0 * math.pi)

    # ---------------------------------------------------------------- geometry on the graph
    def positions(self, edge: np.ndarray | None = None, along: np.ndarray | None = None) -> np.ndarray:
        """(n, 2) map positions of (edge, along) pairs (the particles' own by default)."""
        if edge is None and along is None:  # (the particles' own: kept from the step that moved them)
            if self._xy is None or len(self._xy) != len(self.edge):
                self._xy = self._positions(self.edge, self.along)
                self._xy.flags.writeable = False  # (shared with every caller until the particles move)
            return self._xy
        return self._positions(self.edge if edge is None else edge, self.along if along is None else along)

    def _positions(self, edge: np.ndarray, along: np.ndarray) -> np.ndarray:
        road = self.road
        g, i = self._waypoint(edge, along)
        j = np.minimum(i + 1, road.edge_end[edge] - 1)
        span = self._glob[j] - self._glob[i]
        f = np.where(span > 0, (g - self._glob[i]) / np.where(span > 0, span, 1.0), 0.0)[:, None]
        return np.take(road.xy_m, i, axis=0) * (1.0 - f) + np.take(road.xy_m, j, axis=0) * f  # (take: a faster gather)

    def _waypoint(self, edge: np.ndarray, along: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The global arc length of (edge, along) pairs and the way-point at or before each, on its own edge."""
        road = self.road
        g = self._base[edge] + along
        i = fast_clip(self._index.last_at_or_before(g), road.edge_start[edge], road.edge_end[edge] - 1)
        return g, i

    def _heading(self, edge: np.ndarray, along: np.ndarray, direction: np.ndarray) -> np.ndarray:
        _, i = self._waypoint(edge, along)
        return self.road.yaw_rad[i] + np.where(direction < 0, math.pi, 0.0)

    def drive_from(self, edge: int, direction: int, along_m: float, distance_m: float,
                   target_xy: tuple[float, float], sigma_m: float, n: int) -> None:
        """The particles replaced by ``n`` at one place (edge, direction, along), driven ``distance_m`` along the
        graph, each taking at a vertex an exit drawn as near as it leads to ``target_xy`` (:meth:`_drive`)."""
        self.edge, self.direction = np.full(n, edge, dtype=np.int64), np.full(n, direction, dtype=np.int64)
        self.along = np.full(n, float(along_m))
        self.offset, self.logw, self.driven_m = np.zeros(n), np.full(n, -math.log(n)), 0.0
        self.log_scale, self._log_range = np.zeros(n), (0.0, 0.0)
        self._drive(np.full(n, float(distance_m)), np.tile(np.asarray(target_xy, dtype=float), (n, 1)), sigma_m)

    def headings(self) -> np.ndarray:
        """Each particle's heading: its road's at its place, in its direction."""
        return self._heading(self.edge, self.along, self.direction)

    def allow_uturns(self, probability: float) -> None:
        """Let the particles turn back with at least ``probability`` per step (``ParticleParams.uturn_probability``)."""
        if self.params.uturn_probability < probability:
            self.params = dataclasses.replace(self.params, uturn_probability=probability)

    def _drive(self, distance: np.ndarray, target: np.ndarray, sigma_m: float) -> None:
        """Each particle drives its own distance along the graph. At a vertex it takes a legal exit drawn
        in proportion to how near the exit leads it to ``target`` (its expected end position, (n, 2)):
        the odometry's own turn picks the exit, so the particles at the right place follow the right
        road; the importance weight (mean over the exits / the chosen exit's likelihood) keeps the
        posterior that of a uniform choice. No U-turn, except at a dead end or, with
        ``ParticleParams.uturn_at_vertex``, back along a two-way road as one more exit of that prior weight."""
        road, exits = self.road, self._exits
        uturn = self.params.uturn_at_vertex
        self._xy = None  # (the particles move)
        along = self.along + self.direction * distance
        length = road.edge_length_m[self.edge]
        for hop in range(MAX_HOPS):
            over = np.flatnonzero((along > length) | (along < 0.0))
            if over.size == 0:
                break
            e, d = self.edge[over], self.direction[over]
            rest = np.where(d > 0, along[over] - length[over], -along[over])  # beyond the vertex
            key = 2 * e + (d < 0)
            lo, count = exits.start[key], exits.start[key + 1] - exits.start[key]
            width = max(int(count.max()), 1) + (uturn > 0)
            j = np.arange(width)
            valid = j[None, :] < count[:, None]
            pick = np.where(valid, lo[:, None] + j[None, :], 0)
            dead = count == 0
            ce = np.where(valid, exits.edge[pick], e[:, None]) if exits.edge.size else np.repeat(e[:, None], width, 1)
            cd = np.where(valid, exits.direction[pick], -d[:, None]) if exits.edge.size else \
                np.repeat(-d[:, None], width, 1)
            cl = road.edge_length_m[ce]
            ca = fast_clip(np.where(cd > 0, rest[:, None], cl - rest[:, None]), 0.0, cl)
            end = self.positions(ce.ravel(), ca.ravel()).reshape(len(over), width, 2)
            err2 = np.sum((end - target[over][:, None, :]) ** 2, axis=2)
            logl = np.where(valid | dead[:, None], -0.5 * err2 / (sigma_m * sigma_m), -np.inf)
            logl[dead, 1:] = -np.inf
            prior = np.ones_like(logl)
            if uturn > 0:  # turning back on a two-way road: one more exit (the column after the legal ones)
                back = (j[None, :] == count[:, None]) & ~dead[:, None] & self._two_way[e][:, None]
                logl, prior = np.where(back, -0.5 * err2 / (sigma_m * sigma_m), logl), np.where(back, uturn, 1.0)
            top = np.max(logl, axis=1, keepdims=True)
            lik = np.exp(logl - top) * prior
            total = lik.sum(axis=1)
            choice = np.minimum((np.cumsum(lik, axis=1) < (self.rng.random(len(over)) * total)[:, None]).sum(axis=1),
                                width - 1)
            rows = np.arange(len(over))
            if hop == 0:  # (later hops, on very short edges, are rare: their choice is left unweighted)
                # the weight: the chosen exit's prior share over its share of the proposal
                held = np.where(np.isfinite(logl), prior, 0.0).sum(axis=1)
                self.logw[over] += np.log(total / held) - np.log(lik[rows, choice]) + np.log(prior[rows, choice])
            ne, nd = ce[rows, choice], cd[rows, choice]
            self.edge[over], self.direction[over], length[over] = ne, nd, road.edge_length_m[ne]
            along[over] = np.where(nd > 0, rest, length[over] - rest)
        self.along = fast_clip(along, 0.0, length)

    # ---------------------------------------------------------------- the filter
    def step(self, moved_m: float, chord_odo_xy: np.ndarray) -> None:
        """One filter step: the odometry drove ``moved_m`` (path length, m) and its displacement was
        ``chord_odo_xy`` (2,) in the odometry frame (m)."""
        if len(self) == 0 or moved_m <= 0.0:
            return
        prm, rng, n = self.params, self.rng, len(self)
        before = self.positions()
        scale = np.exp(self.log_scale) if self.scale_free else 1.0  # (a known scale: the odometry's metres)
        c, s = np.cos(self.offset) * scale, np.sin(self.offset) * scale
        ox, oy = chord_odo_xy
        expected = np.column_stack([c * ox - s * oy, s * ox + c * oy])  # the odometry's displacement, per particle
        metres = moved_m * scale
        sigma = prm.sigma_m + prm.sigma_per_m * metres
        if prm.uturn_probability > 0:  # (the vehicle turned back where it may: a two-way road)
            back = (rng.random(n) < prm.uturn_probability) & self._two_way[self.edge]
            self.direction = np.where(back, -self.direction, self.direction)
        noise = 1.0 + rng.normal(0.0, prm.scale_sigma, n)
        self._drive(np.maximum(metres * noise + rng.normal(0.0, prm.along_sigma_m, n), 0.0), before + expected,
                    _median(sigma))
        moved = self.positions() - before  # each particle's displacement on the road
        ex = moved[:, 0] - expected[:, 0]
        ey = moved[:, 1] - expected[:, 1]
        if self.scale_free:
            # compared at one reference scale: a particle whose scale is small makes small errors in metres,
            # and σ's constant part would otherwise favour it whatever the path's shape says
            ref = math.exp(0.5 * sum(self._log_range))
            sigma_ref = prm.sigma_m + prm.sigma_per_m * moved_m * ref
            loglik = -0.5 * (ex * ex + ey * ey) * (ref * ref) / (scale * scale * sigma_ref * sigma_ref)
        else:
            loglik = -0.5 * (ex * ex + ey * ey) / (sigma * sigma)
        self.logw += loglik
        chord = math.hypot(ox, oy)
        if chord > 1.0:  # the offset follows the odometry's heading drift
            road_dir = np.arctan2(moved[:, 1], moved[:, 0])
            innov = wrap_angle(road_dir - math.atan2(oy, ox) - self.offset)
            if prm.offset_max_deg < 180.0:  # a turn the road did not make is a mismatch, not a drift
                lim = math.radians(prm.offset_max_deg)
                innov = fast_clip(innov, -lim, lim)
            moved_on_road = np.hypot(moved[:, 0], moved[:, 1]) > 0.5 * chord * scale
            self.offset = wrap_angle(self.offset + np.where(moved_on_road, prm.offset_gain * innov, 0.0))
        self.offset = wrap_angle(self.offset + rng.normal(0.0, math.radians(prm.offset_sigma_deg), n))
        if self.scale_free and prm.scale_walk > 0:
            self.log_scale = fast_clip(self.log_scale + rng.normal(0.0, prm.scale_walk, n), *self._log_range)
        self.logw -= _logsumexp(self.logw)
        self.driven_m += moved_m * (math.exp(float(np.sum(np.exp(self.logw) * self.log_scale))) if self.scale_free
                                    else 1.0)
        if 1.0 / float(np.sum(np.exp(2.0 * self.logw))) < 0.5 * n:
            self._resample()

    def _resample(self) -> None:
        n = len(self)
        w = np.exp(self.logw)
        cum = np.cumsum(w)
        cum[-1] = 1.0
        idx = np.searchsorted(cum, (self.rng.random() + np.arange(n)) / n)
        if self.params.kld_epsilon > 0:  # as many as the occupied bins need (KLD-sampling), drawn afresh
            m = min(max(kld_count(_occupied_bins(self, idx), self.params.kld_epsilon), self.params.particles_min),
                    max(self._n_max, n))
            if m != n:
                n = m
                idx = np.searchsorted(cum, (self.rng.random() + np.arange(n)) / n)
        self.edge, self.direction = self.edge[idx], self.direction[idx]
        self.along, self.offset, self.log_scale = self.along[idx], self.offset[idx], self.log_scale[idx]
        if self._xy is not None:
            self._xy = self._xy[idx]
            self._xy.flags.writeable = False
        self.logw = np.full(n, -math.log(n))

    def mass_within(self, x_m: float, y_m: float, radius_m: float,
                    outside: tuple[float, float, float] | None = None) -> float:
        """The posterior mass within ``radius_m`` of (x, y) (0 with no particles); with ``outside`` (x, y,
        radius), only the mass that is not also within that disc."""
        if len(self) == 0:
            return 0.0
        xy = self.positions()
        near = np.hypot(xy[:, 0] - x_m, xy[:, 1] - y_m) <= radius_m
        if outside is not None:
            near &= np.hypot(xy[:, 0] - outside[0], xy[:, 1] - outside[1]) > outside[2]
        return float(np.exp(self.logw[near]).sum())

    def located(self, odometry_yaw_rad: float) -> Located | None:
        """The main cluster's pose when the posterior has converged (see the module docstring), else None;
        its heading is the odometry's current heading turned by the cluster's mean offset."""
        prm = self.params
        if len(self) == 0 or self.driven_m < prm.min_distance_m:
            return None
        xy, w = self.positions(), np.exp(self.logw)
        r = prm.converge_radius_m
        cx, cy = np.floor(xy[:, 0] / r).astype(np.int64), np.floor(xy[:, 1] / r).astype(np.int64)
        inv = _cell_ids(cx, cy)
        best = int(np.argmax(np.bincount(inv, weights=w)))
        in_best = inv == best
        centre = _weighted_mean_xy(xy[in_best], w[in_best] + 1e-300)
        # the two discs below, around points of the best cell, reach at most its neighbours two cells away:
        # only the particles within three are measured (the same particles in the same order as all of them)
        bx, by = cx[in_best][0], cy[in_best][0]
        near = np.flatnonzero((np.abs(cx - bx) <= 3) & (np.abs(cy - by) <= 3))
        xs, ws = xy[near], w[near]
        for _ in range(2):  # the cell's mass, re-centred on the disc around it
            inside = np.hypot(xs[:, 0] - centre[0], xs[:, 1] - centre[1]) <= r
            if not inside.any():  # (a centre farther than r from every particle: no mass to speak of)
                return None
            centre = _weighted_mean_xy(xs[inside], ws[inside] + 1e-300)
        mass = float(ws[inside].sum())
        if mass < prm.converge_mass:
            return None
        wi = ws[inside] / ws[inside].sum()
        d2 = np.sum((xs[inside] - centre) ** 2, axis=1)
        inside = near[inside]
        k = int(inside[np.argmin(d2)])  # the particle nearest the centre gives the road
        sin_m, cos_m = float(np.sum(wi * np.sin(self.offset[inside]))), float(np.sum(wi * np.cos(self.offset[inside])))
        off, resultant = math.atan2(sin_m, cos_m), math.hypot(sin_m, cos_m)
        yaw_spread = math.sqrt(max(-2.0 * math.log(max(resultant, 1e-12)), 0.0))
        heading = math.remainder(odometry_yaw_rad + off, 2.0 * math.pi)
        ls = self.log_scale[inside]
        ls_mean = float(np.sum(wi * ls))
        ls_sd = math.sqrt(max(float(np.sum(wi * (ls - ls_mean) ** 2)), 0.0))
        return Located(float(xy[k, 0]), float(xy[k, 1]), heading, off, int(self.edge[k]), int(self.direction[k]),
                       float(self.along[k]), mass, float(math.sqrt(np.sum(wi * d2))), yaw_spread, self.driven_m,
                       math.exp(ls_mean), ls_sd)


def _occupied_bins(p: RoadParticles, idx: np.ndarray) -> int:
    """How many bins of ``p``'s state its particles ``idx`` occupy: cells of ``ParticleParams.kld_bin_m`` = b, each
    direction, heading offsets per 2·b degrees, scales per b percent (each about b metres of position
    after some 30-100 m of driving)."""
    b = p.params.kld_bin_m
    xy = p.positions()[idx]
    key = np.floor(xy[:, 0] / b).astype(np.int64) * 2_000_003 + np.floor(xy[:, 1] / b).astype(np.int64)
    key = key * 2 + (p.direction[idx] > 0)
    key = key * 1024 + np.floor(p.offset[idx] / math.radians(2.0 * b)).astype(np.int64)
    key = key * 2048 + np.floor(p.log_scale[idx] / (0.01 * b)).astype(np.int64)
    return int(np.unique(key).size)


class RoadFollower:
    """The outage step's road follower: a few drives along the graph from one place towards a guess."""

    def __init__(self, road: RoadMap, params: ParticleParams, seed: int | list[int] = 0) -> None:
        self.particles = RoadParticles(road, params, seed)

    def road_pose(self, edge: int, direction: int, along_m: float) -> tuple[float, float, float]:
        return self.particles.road_pose(edge, direction, along_m)

    def follow(self, edge: int, direction: int, along_m: float, distance_m: float, target_xy: tuple[float, float],
               sigma_m: float, n: int = 32, target_yaw_rad: float | None = None,
               weight_m_per_deg: float = 0.0, max_deg: float = 180.0) -> tuple[float, float, float]:
        """Drive ``distance_m`` along the graph from (edge, direction, along): ``n`` drives, each taking at a
        vertex an exit drawn in proportion to how near it leads to ``target_xy`` (see
        :meth:`RoadParticles.drive_from`); the end nearest the target is the answer, as (x, y, heading of its road
        in its direction). With ``target_yaw_rad``, nearest by D = E + w·A (metres from the target plus
        ``weight_m_per_deg`` × degrees from its heading, counted up to ``max_deg``): a drive that has just turned
        into a side street can end nearer the target's position than the one that went on, with its heading 90°
        off."""
        p = self.particles
        p.drive_from(edge, direction, along_m, distance_m, target_xy, sigma_m, n)
        xy = p.positions()
        cost = np.hypot(xy[:, 0] - target_xy[0], xy[:, 1] - target_xy[1])
        if target_yaw_rad is not None and weight_m_per_deg > 0:
            off = np.abs(wrap_angle(p.headings() - target_yaw_rad))
            cost = cost + weight_m_per_deg * np.minimum(np.degrees(off), max_deg)
        i = int(np.argmin(cost))
        return p.road_pose(int(p.edge[i]), int(p.direction[i]), float(p.along[i]))


def guess_log_weights(guess: Guess, xy_m: np.ndarray, heading_rad: np.ndarray) -> np.ndarray:
    """Normalised log-weights of particles at ``xy_m`` (n × 2, m) heading ``heading_rad`` (their roads' headings
    in their directions) under ``guess``: log(floor + (1 − floor) × exp(−½ (d²/σ² + a²/σ_yaw²))), normalised."""
    end = np.array([[guess.x_m, guess.y_m]])
    start = np.array([guess.from_xy_m]) if guess.from_xy_m is not None else end
    d2 = (point_segment_distance(xy_m, start, end) / guess.sigma_m) ** 2
    a2 = (wrap_angle(heading_rad - guess.yaw_rad) / guess.yaw_sigma_rad) ** 2
    with np.errstate(divide="ignore"):  # (a floor of 0 or 1: one of the two terms is log 0)
        logw = np.logaddexp(math.log(guess.floor) if guess.floor > 0 else -np.inf,
                            (math.log1p(-guess.floor) if guess.floor < 1 else -np.inf) - 0.5 * (d2 + a2))
    top = float(logw.max())  # (in logs: with no floor, a guess far from every particle would underflow)
    return logw - (top + math.log(float(np.exp(logw - top).sum())))


@dataclass(frozen=True)
class _Exits:
    """For each (edge, direction) key = 2·edge + (direction < 0): the legal (edge, direction) pairs
    leaving its exit vertex, as rows ``start[key]:start[key + 1]`` of ``edge``/``direction``."""

    start: np.ndarray
    edge: np.ndarray
    direction: np.ndarray


def _edge_travel(road: RoadMap) -> np.ndarray:
    """Each edge's legal travel along its drawing: 1 forward only, -1 backward only, 0 both ways."""
    if not len(road.edge_u):
        return np.zeros(0, dtype=np.int64)
    return np.array([road.ways[int(w)].travel for w in road.edge_way_index], dtype=np.int64)


def _exits(road: RoadMap) -> _Exits:
    """The successors of every (edge, direction): the other edges at its exit vertex that may be
    driven away from it (no U-turn onto the same edge unless it is a dead end, handled by the caller)."""
    travel = _edge_travel(road)
    leaving: dict[int, list[tuple[int, int]]] = {}
    for e, (u, v) in enumerate(zip(road.edge_u.tolist(), road.edge_v.tolist())):
        if travel[e] >= 0:
            leaving.setdefault(u, []).append((e, 1))
        if travel[e] <= 0:
            leaving.setdefault(v, []).append((e, -1))
    rows: list[list[tuple[int, int]]] = []
    for e, (u, v) in enumerate(zip(road.edge_u.tolist(), road.edge_v.tolist())):
        for vertex in (v, u):  # the exit vertex along the drawing (key 2e), then against it (2e + 1)
            rows.append([x for x in leaving.get(vertex, []) if x[0] != e])
    counts = np.array([len(r) for r in rows], dtype=np.int64)
    flat = [x for r in rows for x in r]
    return _Exits(np.concatenate(([0], np.cumsum(counts))).astype(np.int64),
                  np.array([x[0] for x in flat], dtype=np.int64), np.array([x[1] for x in flat], dtype=np.int64))


class _ArcIndex:
    """``searchsorted(values, g, side="right") - 1`` for a sorted array of arc lengths (m, ≥ 0) in a few
    gathers: a table of the answer at every whole metre, then a step forward over the few values between
    (the way-points lie about a metre apart; a binary search over a city's millions is the particles' main
    cost otherwise). The answers are the same to the index."""

    def __init__(self, values: np.ndarray) -> None:
        self._values = np.concatenate((values, [np.inf]))
        top = int(math.ceil(float(values[-1]))) + 2 if len(values) else 1
        self._first = np.searchsorted(values, np.arange(top, dtype=np.float64), side="right") - 1

    def last_at_or_before(self, g: np.ndarray) -> np.ndarray:
        """The index of the last value ≤ each of ``g`` (-1 where none is)."""
        finite = np.isfinite(g)
        if not finite.all() or len(self._values) == 1:
            return np.searchsorted(self._values[:-1], g, side="right") - 1
        first = self._first
        # (truncation is the floor for g ≥ 0, and a g < 0 is clipped to 0 and answered -1 either way)
        i = first[fast_clip(g.astype(np.int64), 0, len(first) - 1)]
        i = np.where(g < 0.0, -1, i)
        active = np.flatnonzero(self._values[i + 1] <= g)
        while active.size:  # (i + 1 stays within the array: its last value is +inf)
            i[active] += 1
            active = active[self._values[i[active] + 1] <= g[active]]
        return i


def _cell_ids(cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
    """Ids of integer grid cells (x and y indices) that order them row by row (x, then y), as ``np.unique``
    of the pairs would: dense over the cells' bounding box when it is small, else unique's own."""
    x0, y0 = int(cx.min()), int(cy.min())
    nx, ny = int(cx.max()) - x0 + 1, int(cy.max()) - y0 + 1
    if nx * ny <= 4 * len(cx) + 1024:
        return (cx - x0) * ny + (cy - y0)
    return np.unique(cx * 1_000_003 + cy, return_inverse=True)[1]


def enclosing_disc(a: Region, b: Region) -> Region:
    """The smallest disc holding both discs."""
    d = math.hypot(b.x_m - a.x_m, b.y_m - a.y_m)
    if d + a.radius_m <= b.radius_m:
        return b
    if d + b.radius_m <= a.radius_m:
        return a
    radius = 0.5 * (d + a.radius_m + b.radius_m)
    f = (radius - a.radius_m) / d  # (from a's centre towards b's: d > 0 here, or one disc would hold the other)
    return Region(a.x_m + f * (b.x_m - a.x_m), a.y_m + f * (b.y_m - a.y_m), radius)


def kld_count(bins: int, epsilon: float, z: float = 2.326) -> int:
    """Particles that bound the Kullback-Leibler divergence between the sample-based and the true posterior
    by ``epsilon`` with probability Φ(z) (99%) when the posterior occupies ``bins`` bins (Fox 2003, from the
    Wilson-Hilferty approximation of the χ² quantile)."""
    if bins <= 1:
        return 1
    k = bins - 1
    a = 2.0 / (9.0 * k)
    return int(math.ceil(k / (2.0 * epsilon) * (1.0 - a + math.sqrt(a) * z) ** 3))


def _weighted_mean_xy(xy: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``np.average(xy, axis=0, weights=w)`` of (n, 2) points, n ≥ 1, to the bit and a third of its cost at a few
    hundred particles: numpy sums a column of an (n, 2) array in order, as cumsum does, and the weights pairwise."""
    total = w.sum()
    return np.array((np.cumsum(xy[:, 0] * w)[-1] / total, np.cumsum(xy[:, 1] * w)[-1] / total))


def _median(v: np.ndarray | float) -> float:
    """``float(np.median(v))`` of finite values (an array or one number), to the bit without np.median's own
    overhead (a fifth of its cost at a few hundred particles)."""
    if not isinstance(v, np.ndarray):
        return float(v)
    n = v.size
    h = n // 2
    if n % 2:
        return float(np.partition(v, h)[h])
    part = np.partition(v, (h - 1, h))
    return float((part[h - 1] + part[h]) / 2.0)


def _logsumexp(v: np.ndarray) -> float:
    m = float(np.max(v))
    return m if m == -math.inf else m + math.log(float(np.sum(np.exp(v - m))))


class Relocaliser:
    """Feeds :class:`RoadParticles` from an odometry stream of planar poses (x, y, yaw in the odometry's
    frame, metres after the odometry's scale) and says where the vehicle is once it has converged."""

    def __init__(self, road: RoadMap, params: ParticleParams, region: Region, seed: int | list[int] = 0,
                 scale_range: tuple[float, float] = (1.0, 1.0), guess: Guess | None = None) -> None:
        self.particles = RoadParticles(road, params, seed)
        self.region = region
        self.guess = guess
        self.scale_range = scale_range
        self._anchor: tuple[float, float] | None = None  # odometry position at the last filter step
        self._last: tuple[float, float] | None = None
        self._moved = 0.0
        self.way_points_in_region = 0
        self.answer: Located | None = None  # the converged answer at the last step (None: not converged)
        self.k0: int | None = None  # the caller's frame number of the first pose, when it gives one
        self.feed_scale: float | None = None  # the engine's odometry scale when it first fed this search

    def fed_at(self, scale: float) -> float:
        """The engine's odometry scale this search is fed at: ``scale`` at its first call, that one from then on."""
        if self.feed_scale is None:
            self.feed_scale = scale
        return self.feed_scale

    def add(self, x: float, y: float, yaw: float, frame: int | None = None) -> Located | None:
        """One odometry pose (``frame``: the caller's number for it, kept for the first); the converged answer,
        or None (not yet, or nothing in the region)."""
        if self._anchor is None:
            self._anchor = self._last = (x, y)
            self.k0 = frame
            self.way_points_in_region = self.particles.start(self.region, yaw, scale_range=self.scale_range,
                                                             guess=self.guess)
            log.info("re-localising in a %.0f m region around (%.0f, %.0f): %d particles on %d way-points",
                     self.region.radius_m, self.region.x_m, self.region.y_m, len(self.particles),
                     self.way_points_in_region)
            return None
        assert self._last is not None
        self._moved += math.hypot(x - self._last[0], y - self._last[1])
        self._last = (x, y)
        if self._moved < self.particles.params.step_m:
            return None
        chord = np.array([x - self._anchor[0], y - self._anchor[1]])
        moved, self._anchor, self._moved = self._moved, (x, y), 0.0
        self.particles.step(moved, chord)
        self.answer = self.particles.located(yaw)
        return self.answer


class Search:
    """When the engine searches the road network (issue 17), and the running search: a cold start in a
    region given by the caller or, with ``map_relocalisation``, a search the engine begins (after an
    odometry gap, when the estimate is lost, when GPS falls silent). It feeds the odometry's planar poses
    (in metres) to a :class:`Relocaliser`."""

    def __init__(self, road: RoadMap, cfg: FusionConfig) -> None:
        self.road, self.cfg = road, cfg
        self.active: Relocaliser | None = None
        self.searches = 0
        self.watching: Relocaliser | None = None  # a search that re-anchored, still fed (SearchParams.watch_m)
        self._watch_until_m = 0.0

    def begin(self, region: Region, scale_range: tuple[float, float] = (1.0, 1.0), frame: int | None = None,
              guess: Guess | None = None) -> None:
        """Start a search in ``region`` (a new one replaces any running, and ends any watched); its particles'
        scales spread over ``scale_range`` (map metres per odometry unit), their first weights from ``guess``
        if given. ``frame``: the engine's frame it begins at, which seeds it (with ``RELOC_SEED``), so that a
        search's draws do not depend on how many searches came before it (without: the count so far does)."""
        seed: int | list[int] = RELOC_SEED + self.searches if frame is None else [RELOC_SEED, frame]
        self.active = Relocaliser(self.road, SEARCH_PARTICLES, region, seed, scale_range, guess)
        self.watching = None
        self.searches += 1

    def stop(self) -> None:
        """End the running search."""
        self.active = None

    def stop_watching(self) -> None:
        """End the watched search."""
        self.watching = None

    def end(self) -> None:
        """End the running and the watched search."""
        self.active = self.watching = None

    def watch(self, search: Relocaliser) -> None:
        """Keep feeding ``search``, which has just re-anchored the estimate, over ``SearchParams.watch_m`` more driving
        (nothing when that is 0): its posterior is kept whole, so that a look-alike path it converged on can
        still lose its mass to the right place (see :meth:`watched`)."""
        if SEARCH_PARAMS.watch_m > 0:
            self.watching = search
            self._watch_until_m = search.particles.driven_m + SEARCH_PARAMS.watch_m
            # a search's particles never turn back (over its few hundred metres the vehicle rarely does); followed
            # for longer, a vehicle that turns back kills the right cluster: watched, they may, as the road fixes' do
            search.particles.allow_uturns(ROAD_FIX_UTURN_PROBABILITY)

    def watched(self, x_m: float, y_m: float, yaw_rad: float, frame: int | None = None) -> Located | None:
        """One odometry pose (as :meth:`feed`) for the watched search; its converged answer, or None. Watching
        ends after ``SearchParams.watch_m``."""
        w = self.watching
        if w is None:
            return None
        loc = w.add(x_m, y_m, yaw_rad, frame)
        if w.particles.driven_m >= self._watch_until_m:
            self.watching = None
        return loc

    def widen_if_stuck(self, x_m: float, y_m: float, frame: int | None = None) -> None:
        """A search that has not converged over ``SearchParams.give_up_m`` starts again around (x, y) with twice
        its radius (up to ``SearchParams.max_radius_m``): the vehicle may have left the region."""
        a = self.active
        if a is not None and a.particles.driven_m >= SEARCH_PARAMS.give_up_m:
            self.begin(Region(x_m, y_m, min(2.0 * a.region.radius_m, SEARCH_PARAMS.max_radius_m)), a.scale_range,
                       frame)

    def lost_region(self, x_m: float, y_m: float, unexplained_m: float) -> Region:
        """Where to look when lost: around the estimate where a road last explained it (``x_m``, ``y_m``), the
        radius grown with the distance driven since (the vehicle is at most that far from there)."""
        return Region(x_m, y_m, min(SEARCH_PARAMS.radius_m + SEARCH_PARAMS.radius_per_m * unexplained_m,
                                    SEARCH_PARAMS.max_radius_m))

    def feed(self, x_m: float, y_m: float, yaw_rad: float, frame: int | None = None) -> Located | None:
        """One odometry pose (metres, the odometry's frame; ``frame``: the caller's number for it); the answer
        once converged (the search then ends)."""
        if self.active is None:
            return None
        loc = self.active.add(x_m, y_m, yaw_rad, frame)
        if loc is not None:
            self.active = None
            log.info("re-localised on the road network after %.0f m: (%.1f, %.1f), %.0f%% of the posterior "
                     "within %.0f m (spread %.1f m), scale %.4f ± %.1f%%", loc.driven_m, loc.x_m, loc.y_m,
                     100 * loc.mass, SEARCH_PARTICLES.converge_radius_m, loc.spread_m, loc.scale,
                     100 * loc.scale_spread)
        return loc
