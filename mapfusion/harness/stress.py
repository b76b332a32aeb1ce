"""Intersection stress test of the matcher (``mapfusion maps stress``).

Poses are placed on the approaches and exits of every junction (degree ≥ 3) of a road map,
pushed across the road by up to the road width plus a margin and turned by a heading error,
then matched. The score is the fraction matched to the way each pose was generated from,
overall and by junction kind.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from enum import Enum

import numpy as np

from mapfusion.errors import ConfigError
from mapfusion.roadmap import RoadMap, can_drive


class JunctionKind(str, Enum):
    """How a junction is classified (first that applies, in this order)."""

    roundabout = "roundabout"  # an incident way is part of a roundabout
    parallel = "parallel road"  # a way not meeting the junction runs parallel within parallel_gap_m
    y_split = "y-split"  # three roads, two of them leaving within y_split_max_deg of each other
    T = "T"  # three roads
    X = "X"  # four roads
    other = "other"  # five or more


@dataclass(frozen=True)
class StressConfig:
    """Parameters of the stress test. Lengths in metres, angles in degrees."""

    offset_extra_m: float = 3.0
    """Across-road offsets reach ± (road width + this) from the centreline (issue 3: width + 3 m)."""
    heading_error_deg: float = 20.0
    """Heading errors are uniform in ± this."""
    distances_m: tuple[float, ...] = (5.0, 10.0, 20.0, 35.0, 50.0)
    """Stations along every approach and exit, measured from the junction."""
    poses_per_station: int = 4
    """Random poses per station and direction of travel."""
    radius_m: float = 20.0
    """Matcher search radius (paper: 20 m)."""
    angle_weight_m_per_deg: float = 1.0
    """Matcher weight w in D = E + w·A (paper: 1 m per degree)."""
    parallel_gap_m: float = 15.0
    """A non-incident parallel way this close to an approach makes the junction a 'parallel road' one."""
    y_split_max_deg: float = 40.0
    """Two roads of a three-way junction leaving within this angle make it a y-split."""
    seed: int = 0
    """Seed of the offsets and heading errors."""
    lane_width_m: float = 3.0
    """Lane width: road width = lanes × this (the engine's FusionConfig.lane_width_m default)."""

    def __post_init__(self) -> None:
        if not (self.offset_extra_m >= 0 and self.heading_error_deg >= 0):
            raise ConfigError("stress: offset_extra_m and heading_error_deg must be >= 0")
        if self.poses_per_station < 1 or not self.distances_m or min(self.distances_m) <= 0:
            raise ConfigError("stress: need at least one pose per station and positive station distances")
        if not self.radius_m > 0:
            raise ConfigError(f"stress: radius_m must be > 0, got {self.radius_m}")
        if not 0.5 <= self.lane_width_m <= 10.0:
            raise ConfigError(f"stress: lane_width_m must be within 0.5–10 m, got {self.lane_width_m}")


@dataclass(frozen=True)
class KindResult:
    kind: str
    junctions: int
    poses: int
    matched: int

    @property
    def rate(self) -> float:
        return self.matched / self.poses if self.poses else float("nan")


@dataclass(frozen=True)
class StressResult:
    map: str
    config: StressConfig
    junctions: int
    poses: int
    matched: int
    unmatched_none: int
    by_kind: tuple[KindResult, ...]

    @property
    def rate(self) -> float:
        return self.matched / self.poses if self.poses else float("nan")

    def to_dict(self) -> dict:
        return {
            "map": self.map,
            "config": dataclasses.asdict(self.config),
            "junctions": self.junctions,
            "poses": self.poses,
            "matched": self.matched,
            "no_match": self.unmatched_none,
            "match_rate": self.rate,
            "by_kind": {
                k.kind: {"junctions": k.junctions, "poses": k.poses, "matched": k.matched, "match_rate": k.rate}
                for k in self.by_kind
            },
        }


def _edge_ends(road: RoadMap) -> dict[int, list[tuple[int, bool]]]:
    """Vertex → [(edge, edge starts at the vertex)]."""
    ends: dict[int, list[tuple[int, bool]]] = {}
    for e in range(len(road.edge_u)):
        ends.setdefault(int(road.edge_u[e]), []).append((e, True))
        ends.setdefault(int(road.edge_v[e]), []).append((e, False))
    return ends


def _far_end(road: RoadMap, e: int, v: int) -> int:
    """The end of edge e that is not vertex v."""
    return int(road.edge_u[e]) if int(road.edge_v[e]) == v else int(road.edge_v[e])


def _station(road: RoadMap, e: int, from_start: bool, dist: float) -> int | None:
    """Index of the way-point of edge e nearest to ``dist`` from the given end, or None if too short."""
    a, b = int(road.edge_start[e]), int(road.edge_end[e])
    length = float(road.edge_length_m[e])
    if b - a < 2 or dist > length - 1.0:
        return None
    s = road.s_m[a:b]
    target = dist if from_start else length - dist
    return a + int(np.argmin(np.abs(s - target)))


def classify_junctions(road: RoadMap, cfg: StressConfig = StressConfig()) -> dict[int, JunctionKind]:
    """Kind of every junction (vertex of degree ≥ 3) of the map."""
    ends = _edge_ends(road)
    roundabout_way = np.array([w.roundabout for w in road.ways], dtype=bool)
    out: dict[int, JunctionKind] = {}
    sin_parallel = math.sin(math.radians(20.0))
    for v, inc in ends.items():
        if road.vertex_degree[v] < 3:
            continue
        inc_ways = {int(road.edge_way_index[e]) for e, _ in inc}
        if any(roundabout_way[w] for w in inc_ways):
            out[v] = JunctionKind.roundabout
            continue
        # directions of the incident roads 15 m out, and parallel neighbours 20–50 m out
        dirs = []
        parallel = False
        vx, vy = road.vertex_xy_m[v]
        for e, from_start in inc:
            i = _station(road, e, from_start, 15.0) or _station(road, e, from_start, 3.0)
            if i is not None:
                dirs.append(math.atan2(road.xy_m[i, 1] - vy, road.xy_m[i, 0] - vx))
            for dist in (20.0, 35.0, 50.0):
                j = _station(road, e, from_start, dist)
                if j is None:
                    continue
                near = road.query_radius(road.xy_m[j, 0], road.xy_m[j, 1], cfg.parallel_gap_m)
                near = near[~np.isin(road.way_index[near], list(inc_ways)) & ~road.is_join[near]]
                if near.size:
                    sin_d = np.abs(np.sin(road.yaw_rad[near] - road.yaw_rad[j]))
                    if np.any(sin_d < sin_parallel):
                        parallel = True
                        break
        if parallel:
            out[v] = JunctionKind.parallel
            continue
        deg = int(road.vertex_degree[v])
        if deg == 3 and len(dirs) == 3:
            gaps = [abs(math.degrees(math.atan2(math.sin(a - b), math.cos(a - b)))) for i, a in enumerate(dirs) for b in dirs[i + 1:]]
            if min(gaps) < cfg.y_split_max_deg:
                out[v] = JunctionKind.y_split
                continue
        out[v] = JunctionKind.T if deg == 3 else JunctionKind.X if deg == 4 else JunctionKind.other
    return out


@dataclass(frozen=True)
class StressPoses:
    """Generated poses (arrays of equal length) and the junction kinds they were drawn around."""

    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    way_id: np.ndarray  # the way each pose was generated from
    vertex: np.ndarray  # its junction
    station: np.ndarray  # the way-point it was generated at
    heading_rad: np.ndarray  # the direction of travel it was generated for (before the error)
    kinds: dict

    def __len__(self) -> int:
        return len(self.x_m)


def stress_poses(road: RoadMap, cfg: StressConfig = StressConfig()) -> StressPoses:
    """Poses on the approaches and exits of every junction, offset across the road and turned."""
    rng = np.random.default_rng(cfg.seed)
    kinds = classify_junctions(road, cfg)
    ends = _edge_ends(road)
    rows: list[tuple[int, int, int]] = []  # (way-point index, direction sign, vertex)
    for v in sorted(kinds):
        for e, from_start in ends[v]:
            for dist in cfg.distances_m:
                i = _station(road, e, from_start, dist)
                if i is None:
                    continue
                # exit (away from the junction) and approach (towards it), each where the road may be
                # driven that way (a vehicle keeps to a one-way road's direction)
                away = 1 if from_start else -1
                if can_drive(road, e, _far_end(road, e, v)):
                    rows.append((i, away, v))
                if can_drive(road, e, v):
                    rows.append((i, -away, v))
    if not rows:
        f, i = np.zeros(0), np.zeros(0, dtype=np.int64)
        return StressPoses(f, f, f, i, i, i, f, kinds)
    idx = np.repeat(np.array([r[0] for r in rows]), cfg.poses_per_station)
    sign = np.repeat(np.array([r[1] for r in rows], dtype=float), cfg.poses_per_station)
    vertex = np.repeat(np.array([r[2] for r in rows]), cfg.poses_per_station)
    n = len(idx)
    heading = road.yaw_rad[idx] + np.where(sign < 0, np.pi, 0.0)
    max_off = road.width_m(cfg.lane_width_m)[idx] + cfg.offset_extra_m
    offset = rng.uniform(-1.0, 1.0, n) * max_off
    err = np.radians(rng.uniform(-cfg.heading_error_deg, cfg.heading_error_deg, n))
    x = road.xy_m[idx, 0] - np.sin(heading) * offset
    y = road.xy_m[idx, 1] + np.cos(heading) * offset
    return StressPoses(x, y, heading + err, road.way_id[idx], vertex, idx, heading, kinds)


def run_stress(road: RoadMap, cfg: StressConfig = StressConfig()) -> StressResult:
    """Match the stress poses of a map and score them by junction kind."""
    poses = stress_poses(road, cfg)
    x, vertex, kinds = poses.x_m, poses.vertex, poses.kinds
    if len(x):
        res = road.match_many(poses.x_m, poses.y_m, poses.yaw_rad, cfg.radius_m, cfg.angle_weight_m_per_deg)
        ok = res["way_id"] == poses.way_id
        none = int(np.sum(res["index"] < 0))
    else:
        ok = np.zeros(0, dtype=bool)
        none = 0
    kind_of_pose = np.array([kinds[int(v)].value for v in vertex]) if len(vertex) else np.zeros(0, dtype=str)
    by_kind = []
    for k in JunctionKind:
        sel = kind_of_pose == k.value
        nj = sum(1 for kk in kinds.values() if kk is k)
        if nj:
            by_kind.append(KindResult(k.value, nj, int(sel.sum()), int(ok[sel].sum())))
    return StressResult(
        map=road.source,
        config=cfg,
        junctions=len(kinds),
        poses=len(x),
        matched=int(ok.sum()),
        unmatched_none=none,
        by_kind=tuple(by_kind),
    )


# ----------------------------------------------------------------------------- sequences (--sequence)
@dataclass(frozen=True)
class SequenceConfig:
    """Drives through junctions for the sequence stress test. Lengths in metres, angles in degrees."""

    approach_m: float = 40.0
    """Length driven on the entering road before the junction, and on the leaving road after it."""
    sample_m: float = 2.0
    """Distance between two matched poses of a drive."""
    correlation_m: float = 30.0
    """Correlation length of the offset and heading errors along a drive (a drifting odometry's errors
    change slowly)."""
    skip_near_vertex_m: float = 5.0
    """Poses closer than this to the junction are not scored (inside it the way is a matter of definition)."""
    warm_up_m: float = 10.0
    """Poses in the first metres of a drive are not scored."""


@dataclass(frozen=True)
class SequenceKindResult:
    kind: str
    junctions: int
    drives: int
    poses: int
    matched: int
    matched_single: int

    @property
    def rate(self) -> float:
        return self.matched / self.poses if self.poses else float("nan")

    @property
    def rate_single(self) -> float:
        return self.matched_single / self.poses if self.poses else float("nan")


@dataclass(frozen=True)
class SequenceResult:
    map: str
    by_kind: tuple[SequenceKindResult, ...]

    @property
    def poses(self) -> int:
        return sum(k.poses for k in self.by_kind)

    @property
    def rate(self) -> float:
        n = self.poses
        return sum(k.matched for k in self.by_kind) / n if n else float("nan")

    @property
    def rate_single(self) -> float:
        n = self.poses
        return sum(k.matched_single for k in self.by_kind) / n if n else float("nan")

    def to_dict(self) -> dict:
        return {"map": self.map, "match_rate": self.rate, "match_rate_single": self.rate_single, "poses": self.poses,
                "by_kind": {k.kind: {"junctions": k.junctions, "drives": k.drives, "poses": k.poses,
                                     "match_rate": k.rate, "match_rate_single": k.rate_single} for k in self.by_kind}}


def _towards(road: RoadMap, e: int, v: int, length_m: float) -> np.ndarray:
    """Way-point indices of edge e within ``length_m`` of its end at vertex v, ordered towards v."""
    a, b = int(road.edge_start[e]), int(road.edge_end[e])
    idx = np.arange(a, b)
    s = road.s_m[a:b].astype(float)
    to_v = (float(road.edge_length_m[e]) - s) if int(road.edge_v[e]) == v else s
    keep = to_v <= length_m
    idx, to_v = idx[keep], to_v[keep]
    return idx[np.argsort(-to_v)]


def _correlated(rng: np.random.Generator, n: int, rho: float, sigma: float, bound: float) -> np.ndarray:
    """AR(1) samples with stationary σ, clipped to ±bound."""
    out = np.empty(n)
    x = rng.normal(0.0, sigma)
    for i in range(n):
        out[i] = x
        x = rho * x + math.sqrt(1.0 - rho * rho) * rng.normal(0.0, sigma)
    return np.clip(out, -bound, bound)


def run_sequence_stress(road: RoadMap, cfg: StressConfig = StressConfig(), seq: SequenceConfig = SequenceConfig(),
                        ) -> SequenceResult:
    """Drive through every junction from every entering road to every other road, with offset and
    heading errors correlated along the drive; match each drive as a sequence with the road
    hypotheses (started on the entering road: the vehicle arrives localised) and pose by pose with
    the single-frame matcher, and score both by junction kind."""
    from mapfusion.hypotheses import RoadHypotheses, candidates

    rng = np.random.default_rng(cfg.seed)
    kinds = classify_junctions(road, cfg)
    ends = _edge_ends(road)
    width = road.width_m(cfg.lane_width_m)
    rho = math.exp(-seq.sample_m / seq.correlation_m)
    tally: dict[str, list[int]] = {k.value: [0, 0, 0, 0] for k in JunctionKind}  # drives, poses, seq, single
    hyp = RoadHypotheses(road)
    for v in sorted(kinds):
        inc = [e for e, _ in ends[v]]
        for e_in in inc:
            for e_out in inc:
                if e_out == e_in or not (can_drive(road, e_in, v) and can_drive(road, e_out, _far_end(road, e_out, v))):
                    continue  # (a vehicle enters and leaves along each road's legal direction)
                path = np.concatenate([_towards(road, e_in, v, seq.approach_m),
                                       _towards(road, e_out, v, seq.approach_m)[::-1]])
                true_edge = road.edge[path]
                # resample at sample_m along the path
                step = np.hypot(*np.diff(road.xy_m[path], axis=0).T)
                s = np.concatenate([[0.0], np.cumsum(step)])
                if s[-1] < 2 * seq.warm_up_m:
                    continue
                pick = np.searchsorted(s, np.arange(0.0, s[-1], seq.sample_m))
                pick = np.minimum(pick, len(path) - 2)
                p, nxt = path[pick], path[pick + 1]
                heading = np.arctan2(road.xy_m[nxt, 1] - road.xy_m[p, 1], road.xy_m[nxt, 0] - road.xy_m[p, 0])
                n = len(p)
                off = _correlated(rng, n, rho, 0.5 * (width[p].max() + cfg.offset_extra_m),
                                  float(width[p].max() + cfg.offset_extra_m))
                err = np.radians(_correlated(rng, n, rho, 0.5 * cfg.heading_error_deg, cfg.heading_error_deg))
                x = road.xy_m[p, 0] - np.sin(heading) * off
                y = road.xy_m[p, 1] + np.cos(heading) * off
                yaw = heading + err
                single = road.match_many(x, y, yaw, cfg.radius_m, cfg.angle_weight_m_per_deg)
                dist_v = np.hypot(road.xy_m[p, 0] - road.vertex_xy_m[v, 0], road.xy_m[p, 1] - road.vertex_xy_m[v, 1])
                true_way = road.way_ids[road.edge_way_index[true_edge[pick]]]
                # the drive arrives localised: the filter starts on the entering road, as a tracker
                # that followed the vehicle there would; what is tested is the way out of the junction
                d_in = 1 if int(road.edge_v[e_in]) == v else -1
                hyp.start_on(e_in, d_in, float(road.s_m[p[0]]))
                t = tally[kinds[v].value]
                t[0] += 1
                for i in range(n):
                    near = road.query_radius(float(x[i]), float(y[i]), cfg.radius_m)
                    st = hyp.step(candidates(road, near, float(x[i]), float(y[i]), float(yaw[i]),
                                             cfg.angle_weight_m_per_deg), seq.sample_m if i else 0.0)
                    if i * seq.sample_m < seq.warm_up_m or dist_v[i] < seq.skip_near_vertex_m:
                        continue
                    t[1] += 1
                    got = -1 if st.best is None else int(road.way_ids[road.edge_way_index[st.best.edge]])
                    t[2] += int(got == true_way[i])
                    t[3] += int(single["way_id"][i] == true_way[i])
    by_kind = []
    for k in JunctionKind:
        nj = sum(1 for kk in kinds.values() if kk is k)
        if nj:
            d, n_poses, ok, ok1 = tally[k.value]
            by_kind.append(SequenceKindResult(k.value, nj, d, n_poses, ok, ok1))
    return SequenceResult(road.source, tuple(by_kind))
