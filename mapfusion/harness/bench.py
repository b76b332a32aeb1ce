"""Throughput and scaling measurements (``mapfusion bench`` and ``benchmarks/``).

Speed goals are measured here as throughputs and medians, never as timed unit tests.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from mapfusion.errors import MapContentError
from mapfusion.maps import resolve_map
from mapfusion.matcher import DEFAULT_RADIUS_M
from mapfusion.roadmap import RoadMap
from sim.drive import run_drive
from sim.network import build_network
from sim.scenario import scenario_from_dict


@dataclass(frozen=True)
class RoadMapBench:
    """Build and radius-query figures of one map."""

    map: str
    waypoints: int
    build_s: float
    query_radius_m: float
    query_median_us: float
    query_p90_us: float
    mean_hits: float

    def to_dict(self) -> dict:
        return asdict(self)


def bench_roadmap(path: str | Path, n_queries: int = 20000, radius_m: float = 20.0, seed: int = 0) -> RoadMapBench:
    """Build ``path`` without the cache, then time single radius queries near random way-points."""
    road = RoadMap.from_osm(path, cache=False)
    _ = road.cells  # the query's index, built on first use: not timed as a query
    rng = np.random.default_rng(seed)
    centres = road.xy_m[rng.integers(0, len(road), n_queries)] + rng.normal(0.0, 3.0, (n_queries, 2))
    times = np.empty(n_queries)
    hits = 0
    clock = time.perf_counter_ns
    for i, (x, y) in enumerate(centres):
        t0 = clock()
        found = road.query_radius(x, y, radius_m)
        times[i] = clock() - t0
        hits += len(found)
    return RoadMapBench(
        map=str(path),
        waypoints=len(road),
        build_s=road.build_s,
        query_radius_m=radius_m,
        query_median_us=float(np.median(times) / 1e3),
        query_p90_us=float(np.percentile(times, 90) / 1e3),
        mean_hits=hits / n_queries,
    )


@dataclass(frozen=True)
class MatchBench:
    """Matcher throughput on one map, one core."""

    map: str
    poses: int
    batch_matches_per_s: float
    single_matches_per_s: float
    first_pass_settled: float  # fraction of poses the batch path's first k-nearest pass settles
    kdtree_queries_per_s: float = 0.0
    """The anchor: k-d tree ball queries (20 m) on the same poses, timed in turns with the single matches."""

    def to_dict(self) -> dict:
        return asdict(self)


def bench_match(road: RoadMap, n_poses: int = 50000, n_single: int = 5000, seed: int = 0,
                chunk: int = 250) -> MatchBench:
    """Matches per second for poses near random way-points (3 m position and 0.2 rad heading noise):
    through the batch API (``RoadMap.match_many``) and one call at a time (``RoadMap.match``), and the
    anchor, a k-d tree ball query of the default 20 m radius per pose, timed in turns with the single
    matches, ``chunk`` poses at a time (a shared machine's speed drifts within seconds: both see the same)."""
    rng = np.random.default_rng(seed)
    i = rng.integers(0, len(road), n_poses)
    x = road.xy_m[i, 0] + rng.normal(0.0, 3.0, n_poses)
    y = road.xy_m[i, 1] + rng.normal(0.0, 3.0, n_poses)
    yaw = road.yaw_rad[i] + rng.normal(0.0, 0.2, n_poses)
    road.match_many(x[:1000], y[:1000], yaw[:1000])  # warm-up: first-touch allocations
    best = float("inf")
    for _ in range(3):  # best of three: the least disturbed by other work on the machine
        t0 = time.perf_counter()
        road.match_many(x, y, yaw)
        best = min(best, time.perf_counter() - t0)
    batch = n_poses / best
    road.match(float(x[0]), float(y[0]), float(yaw[0]))  # warm-up: the first single call builds the cell index
    xs, ys, yaws = x[:n_single].tolist(), y[:n_single].tolist(), yaw[:n_single].tolist()
    points, tree = np.column_stack([x, y])[:n_single], road.tree
    single_s = kd_s = 0.0
    for a in range(0, n_single, chunk):
        t0 = time.perf_counter()
        for j in range(a, min(a + chunk, n_single)):
            road.match(xs[j], ys[j], yaws[j])
        t1 = time.perf_counter()
        for p in points[a:a + chunk]:
            tree.query_ball_point(p, DEFAULT_RADIUS_M)
        kd_s += time.perf_counter() - t1
        single_s += t1 - t0
    from mapfusion.matcher import first_pass_settled

    return MatchBench(map=road.source, poses=n_poses, batch_matches_per_s=batch,
                      single_matches_per_s=n_single / single_s, first_pass_settled=first_pass_settled(road, x, y, yaw),
                      kdtree_queries_per_s=n_single / kd_s)


def big_city_map(directory: Path | None = None) -> Path:
    """Generate the 10 km × 15 km synthetic city used for performance work."""
    from mapfusion import synthetic

    d = Path(directory) if directory else Path(tempfile.mkdtemp(prefix="mapfusion-bench-"))
    return synthetic.write("city", d / "city-10x15km.osm", width_km=10.0, height_km=15.0)


@dataclass(frozen=True)
class EngineBench:
    """Engine throughput on a long drive (one core)."""

    map: str
    frames: int
    duration_s: float
    map_priors: int
    frames_per_s: float
    first_10pct_us: float
    last_10pct_us: float
    # the same over the frames after the GPS (from 10 s after its last fix): the drive's two parts do different
    # work, so `growth` over the whole drive also measures the switch from one to the other (nan: too short)
    after_gps_first_10pct_us: float = float("nan")
    after_gps_last_10pct_us: float = float("nan")
    # of a frame's time, on average over the drive: GTSAM's updates (the backend's update calls) and the road
    # fixes' particles (their step and answer): what no Python-side work in the engine can remove
    gtsam_update_us_per_frame: float = float("nan")
    road_fixes_us_per_frame: float = float("nan")

    @property
    def growth(self) -> float:
        return self.last_10pct_us / self.first_10pct_us

    @property
    def growth_after_gps(self) -> float:
        return self.after_gps_last_10pct_us / self.after_gps_first_10pct_us

    def to_dict(self) -> dict:
        return asdict(self) | {"growth_last_over_first": self.growth, "growth_after_gps": self.growth_after_gps}


def route_walk(road: RoadMap, length_m: float, seed: int = 0) -> np.ndarray:
    """A legal drive along the road graph (:func:`route_states`), its edges' way-points chained: (N, 2) positions."""
    pts: list[np.ndarray] = []
    for state in route_states(road, length_m, seed):
        e, backward = divmod(state, 2)
        seg = road.xy_m[road.edge_start[e]:road.edge_end[e]]
        pts.append((seg[::-1] if backward else seg)[1 if pts else 0:])
    return np.concatenate(pts)


def route_states(road: RoadMap, length_m: float, seed: int = 0) -> list[int]:
    """The edges of a random legal drive of at least ``length_m``, as states 2·edge + (driven against its
    drawing): from a random edge, a random onward edge at every junction that may be driven away from it (one-way
    streets only along their direction; no U-turn where another road leaves, back along a two-way dead end), kept
    to the largest set of roads from which every other is reachable (a one-way street out of the map is never
    entered). On a map of two-way roads it is the walk of any random exit, as before one-way streets were kept to
    (the engine benchmark's city has the same drive)."""
    rng = np.random.default_rng(seed)
    options = _legal_options(road)
    keep = _strongly_connected(options)
    if not keep.any():
        raise MapContentError(f"{road.source}: no road may be driven round and back (the benchmark's drive)")
    while True:  # (an edge outside that set: another draw)
        e = int(rng.integers(len(road.edge_u)))
        state = 2 * e if keep[2 * e] else 2 * e + 1
        if keep[state]:
            break
    states = []
    total = 0.0
    while total < length_m:
        states.append(state)
        total += float(road.edge_length_m[state // 2])
        onward = [x for x in options[state] if keep[x]]
        state = onward[int(rng.integers(len(onward)))]
    return states


def _legal_options(road: RoadMap) -> list[list[int]]:
    """For each state 2·edge + (driven against its drawing): the states a vehicle may go on to at the vertex it
    reaches (the road particles' own legal exits; the edge itself back only when there is none and it is
    two-way); none for a state its edge's one-way tag forbids."""
    from mapfusion.relocalise import _edge_travel, _exits

    exits, travel = _exits(road), _edge_travel(road)
    out: list[list[int]] = []
    for state in range(2 * len(travel)):
        e, backward = divmod(state, 2)
        if travel[e] == (1 if backward else -1):  # (a one-way edge driven against its tag)
            out.append([])
            continue
        rows = slice(exits.start[state], exits.start[state + 1])
        onward = (2 * exits.edge[rows] + (exits.direction[rows] < 0)).tolist()
        out.append(onward or ([state ^ 1] if travel[e] == 0 else []))
    return out


def _strongly_connected(options: list[list[int]]) -> np.ndarray:
    """Which states lie in the largest strongly connected set of the graph ``options`` spans."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(options)
    rows = np.repeat(np.arange(n), [len(o) for o in options])
    cols = np.array([x for o in options for x in o], dtype=np.int64)
    graph = csr_matrix((np.ones(len(cols)), (rows, cols)), shape=(n, n))
    _, label = connected_components(graph, directed=True, connection="strong")
    live = np.array([bool(o) for o in options])
    if not live.any():
        return live
    return label == np.bincount(label[live]).argmax()


#: The engine benchmark's drive has GPS (1 Hz) for this long, then odometry alone.
GPS_S = 120.0


@contextmanager
def _timed(cls: type, method: str, spent_s: list[float]) -> Iterator[None]:
    """While open, every call of ``cls.method`` adds its wall time to ``spent_s[0]`` (about 0.3 µs a call)."""
    original = getattr(cls, method)

    def timed(self, *args, **kwargs):
        t0 = time.perf_counter()
        try:
            return original(self, *args, **kwargs)
        finally:
            spent_s[0] += time.perf_counter() - t0

    setattr(cls, method, timed)
    try:
        yield
    finally:
        setattr(cls, method, original)


def bench_engine(road: RoadMap, duration_s: float = 3600.0, speed_mps: float = 10.0, rate_hz: float = 10.0,
                 lateral_drift_m_per_m: float = 0.01, seed: int = 0, config=None) -> EngineBench:
    """The engine with map priors and the fixed-lag backend on a synthetic drive of ``duration_s``
    along the map's roads: GPS for the first 120 s, then odometry with a lateral drift so priors fire.
    ``config``: a FusionConfig (default: the defaults)."""
    import gtsam

    from mapfusion.config import FusionConfig
    from mapfusion.engine import MapFusion
    from mapfusion.geometry import resample
    from mapfusion.smoother import _Backend
    from mapfusion.tracking import RoadFixes

    path = route_walk(road, duration_s * speed_mps + 100.0, seed)
    pts, _ = resample(path, speed_mps / rate_hz)
    n = min(len(pts), int(duration_s * rate_hz))
    pts = pts[:n]
    yaw = np.arctan2(np.diff(pts[:, 1]), np.diff(pts[:, 0]))
    yaw = np.concatenate([yaw, yaw[-1:]])
    t = np.arange(n) / rate_hz
    rng = np.random.default_rng(seed)
    eng = MapFusion(road, config or FusionConfig(), gps_rate_hz=1.0, odometry_rate_hz=rate_hz)
    lat, lon = road.projection.to_geo(pts[:, 0], pts[:, 1])
    times = np.empty(n)
    prev = gtsam.Pose3(gtsam.Rot3.Yaw(yaw[0]), gtsam.Point3(pts[0, 0], pts[0, 1], 0.0))
    clock = time.perf_counter
    update_s, particles_s = [0.0], [0.0]
    with _timed(_Backend, "update", update_s), _timed(RoadFixes, "step", particles_s):
        for k in range(n):
            cur = gtsam.Pose3(gtsam.Rot3.Yaw(yaw[k]), gtsam.Point3(pts[k, 0], pts[k, 1], 0.0))
            rel = prev.between(cur).matrix()
            if t[k] > GPS_S:  # after the GPS: a drift from the start is taken for a heading offset
                rel[1, 3] += lateral_drift_m_per_m * rel[0, 3]
            prev = cur
            t0 = clock()
            if k % int(rate_hz) == 0 and t[k] <= GPS_S:
                eng.add_gps(float(t[k]), float(lat[k]) + rng.normal(0, 1e-5), float(lon[k]) + rng.normal(0, 2e-5),
                            None, 2.0)
            eng.add_odometry(float(t[k]), rel)
            times[k] = clock() - t0
    eng.finish()
    start = int(np.searchsorted(t, (eng.initialised_at or 0.0) + 1.0))
    run = times[start:]
    tenth = max(1, len(run) // 10)
    after = times[t > GPS_S + 10.0]
    tenth_after = len(after) // 10
    first_after, last_after = (float(after[:tenth_after].mean() * 1e6), float(after[-tenth_after:].mean() * 1e6)) \
        if tenth_after else (float("nan"), float("nan"))
    return EngineBench(map=road.source, frames=n, duration_s=float(t[-1]), map_priors=eng.counters.map_priors,
                       frames_per_s=float(n / times.sum()), first_10pct_us=float(run[:tenth].mean() * 1e6),
                       last_10pct_us=float(run[-tenth:].mean() * 1e6), after_gps_first_10pct_us=first_after,
                       after_gps_last_10pct_us=last_after, gtsam_update_us_per_frame=update_s[0] / n * 1e6,
                       road_fixes_us_per_frame=particles_s[0] / n * 1e6)

@dataclass(frozen=True)
class SimBench:
    map: str
    vehicles: int
    fleet: bool
    sim_s: float
    wall_s: float
    realtime_factor: float

    def to_dict(self) -> dict:
        return asdict(self)


def bench_sim(background_vehicles: int, fleet: bool = False, duration_s: float = 600.0, seed: int = 1,
              map_name: str = "helsinki") -> SimBench:
    """One drive of ``duration_s`` with ``background_vehicles`` others (network build excluded)."""
    path = resolve_map(map_name)
    road = RoadMap.from_osm(path)
    net = build_network(path)
    sc = scenario_from_dict({"name": "bench", "map": str(path), "seed": seed, "duration_s": duration_s,
                             "min_route_m": 100000.0, "route": {"max_trips": 200},
                             "traffic": {"background_vehicles": background_vehicles, "fleet": fleet}}, "bench")
    d = run_drive(sc, road, net)
    return SimBench(map=str(path), vehicles=d.vehicles, fleet=fleet, sim_s=d.sim_s, wall_s=d.wall_s,
                    realtime_factor=d.realtime_factor)


def bench_bare_chain(road: RoadMap, duration_s: float = 3600.0, speed_mps: float = 10.0, rate_hz: float = 10.0,
                     seed: int = 0) -> float:
    """The anchor of the engine benchmark: frames per second of a bare GTSAM Pose3 chain on the same
    drive (BetweenFactorPose3 per frame, a prior every 50 frames, IncrementalFixedLagSmoother with
    a 10 s lag, QR, one update per frame) — what any GTSAM odometry fusion pays at least."""
    import gtsam

    from mapfusion.geometry import resample

    path = route_walk(road, duration_s * speed_mps + 100.0, seed)
    pts, _ = resample(path, speed_mps / rate_hz)
    n = min(len(pts), int(duration_s * rate_hz))
    yaw = np.arctan2(np.diff(pts[:n, 1]), np.diff(pts[:n, 0]))
    yaw = np.concatenate([yaw, yaw[-1:]])
    poses = [gtsam.Pose3(gtsam.Rot3.Yaw(float(yaw[k])), gtsam.Point3(float(pts[k, 0]), float(pts[k, 1]), 0.0))
             for k in range(n)]
    params = gtsam.ISAM2Params()
    params.setFactorization("QR")
    params.findUnusedFactorSlots = True
    smoother = gtsam.IncrementalFixedLagSmoother(10.0, params)
    odo = gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-3, 1e-3, 0.01, 0.05, 0.05, 1e-3]))
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-3, 1e-3, 0.1, 2.0, 2.0, 1e-3]))
    x = gtsam.symbol_shorthand.X
    t0 = time.perf_counter()
    for k in range(n):
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k % 50 == 0:
            g.add(gtsam.PriorFactorPose3(x(k), poses[k], prior))
        if k > 0:
            g.add(gtsam.BetweenFactorPose3(x(k - 1), x(k), poses[k - 1].between(poses[k]), odo))
        v.insert(x(k), poses[k])
        smoother.update(g, v, {x(k): k / rate_hz})
    return n / (time.perf_counter() - t0)


def bench_relocalise(road: RoadMap, radius_m: float = 2000.0, length_m: float = 2000.0, speed_mps: float = 10.0,
                     rate_hz: float = 10.0, seed: int = 0) -> dict:
    """The road-network search (issue 17) fed a 10 Hz drive along the map's roads from a region of ``radius_m``
    around its start: its cost against the drive's own duration (``realtime_factor`` > 1: it keeps up, on
    one core)."""
    from mapfusion.geometry import resample
    from mapfusion.relocalise import SEARCH_PARTICLES, Region, Relocaliser

    pts, _ = resample(route_walk(road, length_m, seed), speed_mps / rate_hz)  # (as bench_engine's drive)
    x, y = pts[:, 0], pts[:, 1]
    yaw = np.arctan2(np.gradient(y), np.gradient(x))
    reloc = Relocaliser(road, SEARCH_PARTICLES, Region(float(x[0]), float(y[0]), radius_m), seed)
    t0 = time.perf_counter()
    for k in range(len(x)):
        reloc.add(float(x[k]), float(y[k]), float(yaw[k]))
    spent = time.perf_counter() - t0
    drive_s = len(x) / rate_hz
    return {"benchmark": "relocalise", "region_radius_m": radius_m, "particles": len(reloc.particles),
            "way_points_in_region": reloc.way_points_in_region, "frames": len(x), "drive_s": drive_s,
            "compute_s": spent, "realtime_factor": drive_s / spent}


def _floor(rounds: list, which: int) -> tuple[dict, dict]:
    """The engine line's floor: the time a frame spends in GTSAM's updates and in the road fixes' particles,
    and the most ``ratio_to_bare`` could be were every other part of the frame free (the bare chain's time a
    frame over those two): (per round, their medians)."""
    upd = [r[which].gtsam_update_us_per_frame for r in rounds]
    par = [r[which].road_fixes_us_per_frame for r in rounds]
    bound = [1e6 / r[0] / (u + p) for r, u, p in zip(rounds, upd, par)]
    per_round = {"gtsam_update_us_per_frame": upd, "road_fixes_us_per_frame": par, "ratio_to_bare_at_most": bound}
    return per_round, {k: float(np.median(v)) for k, v in per_round.items()}


def run_benchmarks(duration_s: float = 3600.0, city_km: tuple[float, float] = (10.0, 15.0), repeats: int = 3,
                   config=None, map_path: str | Path | None = None):
    """``mapfusion bench``: one dict per benchmark (``benchmark`` names it), each with the anchor
    measured in the same run and the ratio to it. The engine and its anchor run ``repeats`` times,
    interleaved (a shared machine's load drifts between runs; neighbours see the same load): the
    figures are medians, each ratio the median of the rounds' ratios. ``config``: the engine's
    FusionConfig (default: the defaults).
    ``map_path``: a map (a built-in name or an OSM file) every line measures in place of the synthetic city
    of ``city_km``; each line names its map. Raises MapFileError (missing, not OSM) or MapContentError (nothing
    drivable) for a map that is not one."""
    from mapfusion import synthetic

    if map_path is not None:
        path = resolve_map(map_path)
        t0 = time.perf_counter()
        road = RoadMap.from_osm(path, cache=False)
        build_s = time.perf_counter() - t0
        name = str(map_path)
    else:  # (the city's OSM file is needed only for the build: it is not left behind in the temporary directory)
        with tempfile.TemporaryDirectory(prefix="mapfusion-bench-") as d:
            city = synthetic.write("city", Path(d) / "city.osm", width_km=city_km[0], height_km=city_km[1])
            t0 = time.perf_counter()
            road = RoadMap.from_osm(city, cache=False)
            build_s = time.perf_counter() - t0
        name = f"synthetic city {city_km[0]:g} × {city_km[1]:g} km"
    yield {"benchmark": "roadmap_build", "map": name, "waypoints": len(road), "build_s": build_s}
    for row in _timed_lines(road, duration_s, repeats, config):
        yield {"benchmark": row.pop("benchmark"), "map": name, **row}


def _timed_lines(road: RoadMap, duration_s: float, repeats: int, config):
    """The engine, search and matcher lines of :func:`run_benchmarks` on one map."""
    from mapfusion.config import FusionConfig

    cfg = config or FusionConfig()
    rounds = []
    for _ in range(max(1, repeats)):
        bare = bench_bare_chain(road, duration_s=duration_s)
        eng = bench_engine(road, duration_s=duration_s, config=cfg)
        rounds.append((bare, eng))
    med = lambda xs: float(np.median(xs))  # noqa: E731
    bare_fps = [b for b, _ in rounds]
    eng_fps = [e.frames_per_s for _, e in rounds]
    eng_ratio = [e / b for e, b in zip(eng_fps, bare_fps)]
    eng = rounds[0][1]
    eng_floor, eng_floor_med = _floor(rounds, 1)
    yield {"benchmark": "engine", "frames": eng.frames, "map_priors": eng.map_priors, "frames_per_s": med(eng_fps),
           "growth": med([e.growth for _, e in rounds]),
           "growth_after_gps": med([e.growth_after_gps for _, e in rounds]),
           "bare_chain_frames_per_s": med(bare_fps),
           "ratio_to_bare": med(eng_ratio), **eng_floor_med,
           "rounds": {"frames_per_s": eng_fps, "bare_chain_frames_per_s": bare_fps, "ratio_to_bare": eng_ratio,
                      **eng_floor}}
    yield bench_relocalise(road)
    singles, batches, kds, settled = [], [], [], 0.0
    for _ in range(max(1, repeats)):
        m = bench_match(road)
        singles.append(m.single_matches_per_s)
        batches.append(m.batch_matches_per_s)
        kds.append(m.kdtree_queries_per_s)
        settled = m.first_pass_settled  # (the same poses every round)
    yield {"benchmark": "matcher", "single_matches_per_s": med(singles), "batch_matches_per_s": med(batches),
           "kdtree_queries_per_s": med(kds), "single_ratio_to_kdtree": med([s / k for s, k in zip(singles, kds)]),
           "batch_ratio_to_kdtree": med([b / k for b, k in zip(batches, kds)]), "batch_first_pass_settled": settled,
           "rounds": {"single_matches_per_s": singles, "batch_matches_per_s": batches, "kdtree_queries_per_s": kds}}
