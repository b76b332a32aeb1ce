"""The processed road map (paper III.A, DESIGN "The method" item 1).

Drivable OSM ways are split at junctions into edges of a graph whose vertices are the
junctions; every edge is interpolated into way-points about ``spacing_m`` apart, smoothed by a
rolling average, and the joins between edges are rounded with short curves. Every way-point
carries a heading (towards the next way-point; the last takes the previous one's), its OSM way
and that way's lanes, width, oneway, tunnel, bridge and layer flags. A k-d tree answers radius
queries. The processed map is cached on disk, keyed by the file's hash and the parameters.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from .errors import ConfigError, MapFileError, MapMismatchError
from . import matcher as _matcher
from . import polylines
from .geometry import as_complex, wrap_angle
from .osm import DRIVABLE_HIGHWAYS, OsmWay, check_osm_path, read_drivable_ways
from .projection import LocalProjection
from .spatial import CellIndex

log = logging.getLogger(__name__)

#: Bumped whenever the processed arrays change meaning, so stale caches are never read.
CACHE_FORMAT = 6


#: The way-point spacing's range (RoadMapConfig.spacing_m).
MIN_SPACING_M, MAX_SPACING_M = 0.05, 50.0


@dataclass(frozen=True)
class RoadMapConfig:
    """How an OSM file becomes a road map. Every field has a default; all lengths in metres."""

    spacing_m: float = 1.0
    """Way-point spacing after interpolation (paper III.A: "linearly interpolated"; 1 m, DESIGN item 1).
    0.05–50 m: finer spacing multiplies a city's way-points past memory (1e-6 m would never finish),
    coarser leaves junctions without a way-point."""
    smoothing_window_m: float = 5.0
    """Length of the rolling-average window. 5 m keeps every smoothed point within 1.2 m of the
    raw polyline (half a 3 m lane) while rounding OSM's sharp vertices."""
    join_radius_m: float = 6.0
    """How far back from a junction the rounded join between two edges starts (and ends)."""
    join_min_turn_deg: float = 10.0
    """Joins turning less than this are already smooth enough and get no extra curve."""
    join_max_turn_deg: float = 150.0
    """Joins turning more than this (near U-turns) get no curve: a car does not drive them."""
    lane_overrides: tuple[tuple[int, int], ...] = ()
    """(OSM way id, lanes) pairs that replace a way's lane count, like the paper's one fixed road."""
    drivable_highways: tuple[str, ...] = DRIVABLE_HIGHWAYS
    """OSM highway classes kept (see :data:`mapfusion.osm.DRIVABLE_HIGHWAYS`)."""
    origin_lat_deg: float | None = None
    """ENU origin latitude; None centres the projection on the map's bounding box."""
    origin_lon_deg: float | None = None
    """ENU origin longitude; None centres the projection on the map's bounding box."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.spacing_m) and MIN_SPACING_M <= self.spacing_m <= MAX_SPACING_M):
            raise ConfigError(f"spacing_m must be within {MIN_SPACING_M:g}–{MAX_SPACING_M:g} m, got {self.spacing_m!r}")
        for name in ("smoothing_window_m", "join_radius_m"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"RoadMapConfig.{name} must be >= 0 metres, got {v!r}")
        if (self.origin_lat_deg is None) != (self.origin_lon_deg is None):
            raise ConfigError("RoadMapConfig: give both origin_lat_deg and origin_lon_deg, or neither")
        for way_id, lanes in self.lane_overrides:
            if int(lanes) < 1:
                raise ConfigError(f"RoadMapConfig.lane_overrides: way {way_id} needs at least 1 lane, got {lanes}")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["lane_overrides"] = [list(p) for p in self.lane_overrides]
        d["drivable_highways"] = list(self.drivable_highways)
        return d


@dataclass(frozen=True)
class WayInfo:
    """Metadata of one OSM way as the road map keeps it."""

    way_id: int
    name: str
    highway: str
    lanes: int
    lanes_tagged: bool
    oneway: bool
    tunnel: bool
    bridge: bool
    layer: int
    roundabout: bool
    travel: int = 0
    """Legal direction of travel: +1 only along the drawing direction, -1 only against it, 0 both."""


@dataclass(frozen=True)
class MapStats:
    """Summary of a processed road map (``mapfusion maps build``)."""

    source: str
    ways: int
    edges: int
    junctions: int
    vertices: int
    waypoints: int
    road_km: float
    tunnel_km: float
    mean_spacing_m: float
    build_s: float
    from_cache: bool

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def default_cache_dir() -> Path:
    """``$MAPFUSION_CACHE`` or ``~/.cache/mapfusion``."""
    env = os.environ.get("MAPFUSION_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "mapfusion"


class RoadMap:
    """A processed road map in a local ENU frame (metres). See the module docstring.

    Way-point arrays (length N): ``xy_m`` (N, 2), ``yaw_rad`` (heading towards the next
    way-point), ``s_m`` (arc length along its edge or join curve), ``way_index`` (into
    :attr:`ways`), ``edge`` (edge index, or -1 on a join curve), ``is_join``.
    Graph arrays: ``vertex_xy_m`` (V, 2), ``vertex_node_id`` (V,), ``vertex_degree`` (V,);
    ``edge_u``, ``edge_v``, ``edge_way_index``, ``edge_length_m``, ``edge_start``, ``edge_end``
    (E,): edge e's way-points are ``edge_start[e]:edge_end[e]``.
    """

    def __init__(self, arrays: dict[str, np.ndarray], ways: list[WayInfo], meta: dict) -> None:
        self.config = RoadMapConfig(
            **{
                **meta["config"],
                "lane_overrides": tuple(tuple(p) for p in meta["config"]["lane_overrides"]),
                "drivable_highways": tuple(meta["config"]["drivable_highways"]),
            }
        )
        self.source = meta["source"]
        self.build_s = float(meta["build_s"])
        self.from_cache = bool(meta.get("from_cache", False))
        self.projection = LocalProjection(meta["origin_lat_deg"], meta["origin_lon_deg"])
        self.ways = ways
        self.way_ids = np.array([w.way_id for w in ways], dtype=np.int64)
        self._way_row = {int(w): i for i, w in enumerate(self.way_ids)}
        self.way_lanes = np.array([w.lanes for w in ways], dtype=np.int16)

        self.xy_m = np.ascontiguousarray(arrays["xy_m"], dtype=np.float64)
        #: the way-points' positions as complex numbers x + iy (a view of ``xy_m``: the matcher's distances)
        self.xy_complex = as_complex(self.xy_m)
        self.yaw_rad = arrays["yaw_rad"]
        self.s_m = arrays["s_m"]
        self.way_index = arrays["way_index"]
        self.edge = arrays["edge"]
        self.join_vertex = arrays["join_vertex"]
        self.is_join = self.edge < 0
        self.vertex_xy_m = arrays["vertex_xy_m"]
        self.vertex_node_id = arrays["vertex_node_id"]
        self.vertex_degree = arrays["vertex_degree"]
        self.edge_u = arrays["edge_u"]
        self.edge_v = arrays["edge_v"]
        self.edge_way_index = arrays["edge_way_index"]
        self.edge_length_m = arrays["edge_length_m"]
        self.edge_start = arrays["edge_start"]
        self.edge_end = arrays["edge_end"]
        self.yaw_cos = np.cos(self.yaw_rad)
        self.yaw_sin = np.sin(self.yaw_rad)
        self.travel, self.against_drawing, self.legal_cos, self.legal_sin, self.two_way_sign = legal_travel(self)
        self._tree: cKDTree | None = None
        self._cells: CellIndex | None = None
        self._continuations: dict[int, set[int]] | None = None

    # ----------------------------------------------------------------- construction
    @classmethod
    def from_osm(
        cls,
        path: str | Path,
        config: RoadMapConfig | None = None,
        *,
        cache: bool = True,
        cache_dir: Path | None = None,
    ) -> RoadMap:
        """Read, process and (by default) cache the road map of an OSM file.

        Raises :class:`~mapfusion.errors.MapFileError` / :class:`~mapfusion.errors.MapContentError`
        for unusable files.
        """
        cfg = config or RoadMapConfig()
        p = check_osm_path(path)
        cache_path = None
        if cache:
            key_src = json.dumps(
                {"sha": file_sha256(p), "cfg": cfg.to_dict(), "fmt": CACHE_FORMAT}, sort_keys=True
            )
            key = hashlib.sha256(key_src.encode()).hexdigest()[:24]
            cache_path = (cache_dir or default_cache_dir()) / f"roadmap-{key}.npz"
            if cache_path.exists():
                try:
                    road = cls._load(cache_path, str(p))
                    log.debug("road map of %s read from cache %s", p, cache_path)
                    return road
                except Exception as exc:  # a corrupt cache is rebuilt, never trusted
                    log.warning("ignoring unreadable road-map cache %s: %s", cache_path, exc)
        road = cls._build(p, cfg)
        if cache_path is not None:
            try:
                road._save(cache_path)
            except OSError as exc:
                log.warning("could not write road-map cache %s: %s", cache_path, exc)
        return road

    @classmethod
    def _build(cls, path: Path, cfg: RoadMapConfig) -> RoadMap:
        t0 = time.perf_counter()
        osm_ways = read_drivable_ways(path, cfg.drivable_highways)
        overrides = {int(w): int(n) for w, n in cfg.lane_overrides}
        ways = [
            WayInfo(
                way_id=w.way_id,
                name=w.name,
                highway=w.highway,
                lanes=overrides.get(w.way_id, w.lanes or 1),
                lanes_tagged=w.lanes is not None,
                oneway=w.oneway,
                tunnel=w.tunnel,
                bridge=w.bridge,
                layer=w.layer,
                roundabout=w.roundabout,
                travel=w.travel,
            )
            for w in osm_ways
        ]
        lat = np.concatenate([w.lat_deg for w in osm_ways])
        lon = np.concatenate([w.lon_deg for w in osm_ways])
        if cfg.origin_lat_deg is None:
            origin = (0.5 * (lat.min() + lat.max()), 0.5 * (lon.min() + lon.max()))
        else:
            origin = (cfg.origin_lat_deg, cfg.origin_lon_deg)
        proj = LocalProjection(*origin)
        x, y = proj.to_enu(lat, lon)
        xy_all = np.column_stack([x, y])

        arrays = _build_graph_and_points(osm_ways, xy_all, cfg)
        meta = {
            "config": cfg.to_dict(),
            "source": str(path),
            "origin_lat_deg": float(origin[0]),
            "origin_lon_deg": float(origin[1]),
            "build_s": time.perf_counter() - t0,
        }
        road = cls(arrays, ways, meta)
        log.info("built road map of %s: %d way-points in %.2f s", path, len(road), road.build_s)
        return road

    def _save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = {
            "config": self.config.to_dict(),
            "source": self.source,
            "origin_lat_deg": self.projection.origin_lat_deg,
            "origin_lon_deg": self.projection.origin_lon_deg,
            "build_s": self.build_s,
            "ways": [dataclasses.asdict(w) for w in self.ways],
        }
        arrays = {k: getattr(self, k) for k in _ARRAY_NAMES}
        tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
        np.savez(tmp, meta=np.array(json.dumps(meta)), **arrays)
        os.replace(tmp, path)  # atomic: parallel builders never see half a file

    @classmethod
    def _load(cls, path: Path, source: str) -> RoadMap:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            arrays = {k: z[k] for k in _ARRAY_NAMES}
        ways = [WayInfo(**w) for w in meta.pop("ways")]
        meta["source"] = source
        meta["from_cache"] = True
        return cls(arrays, ways, meta)

    # ----------------------------------------------------------------- queries
    def __len__(self) -> int:
        return len(self.xy_m)

    @property
    def way_id(self) -> np.ndarray:
        """OSM way id of every way-point (N,)."""
        return self.way_ids[self.way_index]

    @property
    def lanes(self) -> np.ndarray:
        """Lane count of every way-point's way (N,)."""
        return self.way_lanes[self.way_index]

    def check_covers(self, xy_m: np.ndarray, what: str, margin_m: float = 500.0, min_fraction: float = 0.5) -> None:
        """Raise :class:`MapMismatchError` naming ``what`` unless at least ``min_fraction`` of the
        positions (ENU, metres) lie within ``margin_m`` of the map's extent: a drive must be on its map."""
        xy = np.asarray(xy_m, dtype=float).reshape(-1, 2)
        xy = xy[np.all(np.isfinite(xy), axis=1)]
        if not len(xy) or not len(self.xy_m):
            return
        lo, hi = self.xy_m.min(0) - margin_m, self.xy_m.max(0) + margin_m
        inside = np.all((xy >= lo) & (xy <= hi), axis=1)
        if inside.mean() < min_fraction:
            far = np.max(np.maximum(lo - xy, xy - hi), axis=1)
            raise MapMismatchError(
                f"{what}: {100 * (1 - inside.mean()):.0f}% of the positions lie off the map (median "
                f"{np.median(far) / 1000:,.1f} km beyond its extent): of another place, latitude and longitude "
                "swapped, or the map of another city?")

    def width_m(self, lane_width_m: float) -> np.ndarray:
        """Road width at every way-point: lanes × ``lane_width_m`` (N,). The map stores lanes only;
        the lane width is the engine's (``FusionConfig.lane_width_m``), applied at match time."""
        return self.lanes * lane_width_m

    def way_flags(self, flag: str) -> np.ndarray:
        """Per-way-point boolean flag of its way: 'oneway', 'tunnel', 'bridge' or 'roundabout'."""
        per_way = np.array([getattr(w, flag) for w in self.ways], dtype=bool)
        return per_way[self.way_index]

    def way(self, way_id: int) -> WayInfo:
        """Metadata of an OSM way; KeyError if the map does not hold it."""
        return self.ways[self._way_row[int(way_id)]]

    def has_way(self, way_id: int) -> bool:
        return int(way_id) in self._way_row

    def ways_named(self, name: str) -> list[WayInfo]:
        """Every way whose OSM name equals ``name``."""
        return [w for w in self.ways if w.name == name]

    def waypoints_of_way(self, way_id: int) -> np.ndarray:
        """Indices of the way-points on a way's edges (join curves excluded)."""
        row = self._way_row[int(way_id)]
        return np.flatnonzero((self.way_index == row) & ~self.is_join)

    def continuations(self) -> dict[int, set[int]]:
        """Way id → the ways continuing it through a vertex of degree 2 (where OSM merely splits
        one road into two ways; junctions are the vertices of degree 3 or more)."""
        if self._continuations is None:
            at: dict[int, set[int]] = {}
            for e in range(len(self.edge_u)):
                w = int(self.way_ids[self.edge_way_index[e]])
                for v in (int(self.edge_u[e]), int(self.edge_v[e])):
                    if self.vertex_degree[v] == 2:
                        at.setdefault(v, set()).add(w)
            cont: dict[int, set[int]] = {}
            for ways in at.values():
                for w in ways:
                    cont.setdefault(w, set()).update(ways - {w})
            self._continuations = cont
        return self._continuations

    @property
    def tree(self) -> cKDTree:
        """A k-d tree of the way-points (built on first use: the batch matcher's k-nearest queries)."""
        if self._tree is None:
            self._tree = cKDTree(self.xy_m, balanced_tree=False, compact_nodes=False)
        return self._tree

    @property
    def cells(self) -> CellIndex:
        """The cell index of the way-points (built on first use: single radius queries and matches)."""
        if self._cells is None:
            self._cells = CellIndex(self.xy_m, self.legal_cos, self.legal_sin, self.two_way_sign)
        return self._cells

    def query_radius(self, x_m: float, y_m: float, radius_m: float) -> np.ndarray:
        """Indices of way-points within ``radius_m`` of (x, y), in no particular order (ValueError for a
        non-finite x, y or a NaN radius; an infinite radius holds every way-point)."""
        if not (math.isfinite(x_m) and math.isfinite(y_m)) or math.isnan(radius_m):
            raise ValueError(f"query_radius: x, y and the radius must be numbers, got {x_m!r}, {y_m!r}, {radius_m!r}")
        if radius_m == math.inf:
            return np.arange(len(self), dtype=np.intp)
        return self.cells.query(x_m, y_m, radius_m)

    def match(self, x: float, y: float, yaw: float, radius: float = 20.0, angle_weight_m_per_deg: float = 1.0,
              candidates: np.ndarray | None = None):
        """The closest map pose by D = E + w·A within ``radius`` metres, or None.

        See :func:`mapfusion.matcher.match`; ``yaw`` in radians (ENU, 0 = east, CCW).
        """
        return _matcher.match(self, x, y, yaw, radius, angle_weight_m_per_deg, candidates)

    def match_many(self, x, y, yaw, radius: float = 20.0, angle_weight_m_per_deg: float = 1.0) -> dict:
        """Vectorised :meth:`match` over arrays of poses (see :func:`mapfusion.matcher.match_many`)."""
        return _matcher.match_many(self, x, y, yaw, radius, angle_weight_m_per_deg)

    def stats(self) -> MapStats:
        """Counts and lengths of the processed map."""
        return map_stats(self)


def legal_travel(road: RoadMap) -> tuple[np.ndarray, ...]:
    """Per way-point: ``travel`` (+1 only along the drawing, -1 only against it, 0 both ways),
    ``against_drawing`` (the legal direction is against the drawing), the heading of travel a vehicle
    may drive there (``legal_cos``, ``legal_sin``: the drawing direction, turned round on a way one may
    drive only against it) and ``two_way_sign`` (-1.0 where both directions are legal, +1.0 on a
    one-way road: the matcher's sign). Join curves inside junctions are taken as two-way: which turns a
    junction allows is not in the map."""
    per_way = np.array([w.travel for w in road.ways], dtype=np.int8)
    travel = np.where(road.is_join, 0, per_way[road.way_index] if len(per_way) else 0).astype(np.int8)
    against = travel < 0
    flip = np.where(against, -1.0, 1.0)
    return travel, against, road.yaw_cos * flip, road.yaw_sin * flip, np.where(travel == 0, -1.0, 1.0)


def can_drive(road: RoadMap, edge: int, to_vertex: int) -> bool:
    """Whether a vehicle may drive ``edge`` towards ``to_vertex`` (one of its two ends), by its way's
    legal direction of travel."""
    travel = road.ways[int(road.edge_way_index[edge])].travel
    along_drawing = int(road.edge_v[edge]) == to_vertex
    return travel == 0 or (travel > 0) == along_drawing


def map_stats(road: RoadMap) -> MapStats:
    """Counts and lengths of a processed map (:meth:`RoadMap.stats`)."""
    tunnel_way = np.array([w.tunnel for w in road.ways], dtype=bool)
    lengths = road.edge_length_m
    spacing = np.hypot(*np.diff(road.xy_m, axis=0).T)
    same_edge = (road.edge[1:] == road.edge[:-1]) & (road.edge[1:] >= 0)
    return MapStats(
        source=road.source,
        ways=len(road.ways),
        edges=len(road.edge_u),
        junctions=int(np.sum(road.vertex_degree >= 3)),
        vertices=len(road.vertex_degree),
        waypoints=len(road),
        road_km=float(lengths.sum() / 1000.0),
        tunnel_km=float(lengths[tunnel_way[road.edge_way_index]].sum() / 1000.0),
        mean_spacing_m=float(spacing[same_edge].mean()) if same_edge.any() else 0.0,
        build_s=road.build_s,
        from_cache=road.from_cache,
    )


_ARRAY_NAMES = (
    "xy_m",
    "yaw_rad",
    "s_m",
    "way_index",
    "edge",
    "join_vertex",
    "vertex_xy_m",
    "vertex_node_id",
    "vertex_degree",
    "edge_u",
    "edge_v",
    "edge_way_index",
    "edge_length_m",
    "edge_start",
    "edge_end",
)


def _split_at_junctions(osm_ways: list[OsmWay], xy_all: np.ndarray):
    """Ways split into edges at every node shared with another way (or itself) and at their ends:
    (vertex of each OSM node id, vertex positions, edges as (way index, u, v, polyline))."""
    node_ids_all = np.concatenate([w.node_ids for w in osm_ways])
    uniq, counts = np.unique(node_ids_all, return_counts=True)
    shared = set(uniq[counts >= 2].tolist())
    vertex_of: dict[int, int] = {}
    vertex_xy: list[np.ndarray] = []
    edges_raw: list[tuple[int, int, int, np.ndarray]] = []  # (way_index, u, v, polyline)
    offset = 0
    for wi, w in enumerate(osm_ways):
        n = len(w.node_ids)
        pts = xy_all[offset : offset + n]
        offset += n
        cut = [0] + [i for i in range(1, n - 1) if int(w.node_ids[i]) in shared] + [n - 1]
        for a, b in zip(cut[:-1], cut[1:]):
            ends = []
            for i in (a, b):
                nid = int(w.node_ids[i])
                if nid not in vertex_of:
                    vertex_of[nid] = len(vertex_xy)
                    vertex_xy.append(pts[i])
                ends.append(vertex_of[nid])
            if b > a:
                edges_raw.append((wi, ends[0], ends[1], pts[a : b + 1]))
    return vertex_of, vertex_xy, edges_raw


def _build_graph_and_points(osm_ways: list[OsmWay], xy_all: np.ndarray, cfg: RoadMapConfig) -> dict:
    """Split ways at junctions, process each edge's polyline and round the joins (every edge's polyline
    at once: :mod:`.polylines` does per point what :func:`.geometry.process_polyline` does per polyline)."""
    vertex_of, vertex_xy, edges_raw = _split_at_junctions(osm_ways, xy_all)
    n_edges = len(edges_raw)
    raw_off = polylines.offsets_of(np.array([len(e[3]) for e in edges_raw], dtype=np.int64))
    raw = np.concatenate([e[3] for e in edges_raw]) if edges_raw else np.zeros((0, 2))
    pts, s, yaw, off = polylines.process(raw, raw_off, cfg.spacing_m, cfg.smoothing_window_m)
    counts = np.diff(off)
    short = counts < 2  # a zero-length edge (duplicate nodes): no way-points, still an edge: its first node
    if short.any():
        keep = np.repeat(~short, counts)
        first = raw[raw_off[:-1][short]]
        counts = np.where(short, 1, counts)
        new_off = polylines.offsets_of(counts)
        xy_e, s_e, yaw_e = np.empty((new_off[-1], 2)), np.zeros(new_off[-1]), np.zeros(new_off[-1])
        dst = np.repeat(~short, counts)
        xy_e[dst], s_e[dst], yaw_e[dst] = pts[keep], s[keep], yaw[keep]
        xy_e[new_off[:-1][short]] = first
        pts, s, yaw, off = xy_e, s_e, yaw_e, new_off
    edge_u = np.array([e[1] for e in edges_raw], dtype=np.int32)
    edge_v = np.array([e[2] for e in edges_raw], dtype=np.int32)
    edge_way = np.array([e[0] for e in edges_raw], dtype=np.int32)
    edge_len = s[off[1:] - 1] if n_edges else np.zeros(0)

    vertex_degree = np.zeros(len(vertex_xy), dtype=np.int32)
    np.add.at(vertex_degree, edge_u.astype(np.intp), 1)
    np.add.at(vertex_degree, edge_v.astype(np.intp), 1)

    joins = _join_curves(pts, s, off, edge_u, edge_v, edge_way, vertex_degree, cfg)
    edge_of_point = np.repeat(np.arange(n_edges, dtype=np.int32), counts)

    vertex_node = np.empty(len(vertex_xy), dtype=np.int64)
    for nid, vi in vertex_of.items():
        vertex_node[vi] = nid
    return {
        "xy_m": np.concatenate([pts, joins["xy"]]).astype(np.float64),
        "yaw_rad": np.concatenate([yaw, joins["yaw"]]).astype(np.float64),
        "s_m": np.concatenate([s, joins["s"]]).astype(np.float32),
        "way_index": np.concatenate([edge_way[edge_of_point], joins["way_index"]]).astype(np.int32),
        "edge": np.concatenate([edge_of_point, np.full(len(joins["s"]), -1, dtype=np.int32)]).astype(np.int32),
        "join_vertex": np.concatenate([np.full(len(s), -1, dtype=np.int32), joins["join_vertex"]]).astype(np.int32),
        "vertex_xy_m": np.asarray(vertex_xy, dtype=np.float64).reshape(-1, 2),
        "vertex_node_id": vertex_node,
        "vertex_degree": vertex_degree,
        "edge_u": edge_u,
        "edge_v": edge_v,
        "edge_way_index": edge_way,
        "edge_length_m": np.asarray(edge_len, dtype=np.float64),
        "edge_start": np.asarray(off[:-1], dtype=np.int64),
        "edge_end": np.asarray(off[1:], dtype=np.int64),
    }


def _join_legs(xy: np.ndarray, s: np.ndarray, off: np.ndarray, edge_u, edge_v, degree, cfg):
    """Every edge end at a vertex of degree ≥ 2 where a join may start, in the order of the vertices'
    first appearance: (vertex, edge, the point ``join_radius_m`` back along the edge, the corner, the
    direction from the corner to that point), or None when there is none."""
    ends_at: dict[int, list[tuple[int, bool]]] = {}
    n = np.diff(off)
    for e, (u, v, ne) in enumerate(zip(edge_u.tolist(), edge_v.tolist(), n.tolist())):
        if ne < 2:
            continue
        ends_at.setdefault(u, []).append((e, True))  # edge leaves the vertex at its start
        ends_at.setdefault(v, []).append((e, False))  # edge arrives at the vertex at its end
    legs = [(vertex, e, at_start) for vertex, ends in ends_at.items() if degree[vertex] >= 2 and len(ends) >= 2
            for e, at_start in ends]
    if not legs:
        return None
    leg_vertex, leg_edge, leg_start = (np.array(c) for c in zip(*legs))
    length = s[off[leg_edge + 1] - 1]
    r = np.minimum(cfg.join_radius_m, 0.45 * length)
    ok = r >= cfg.spacing_m
    leg_vertex, leg_edge, leg_start, length, r = (a[ok] for a in (leg_vertex, leg_edge, leg_start, length, r))
    p = polylines.interp(np.where(leg_start, r, length - r), leg_edge, s, xy, off)
    corner = np.where(leg_start[:, None], xy[off[leg_edge]], xy[off[leg_edge + 1] - 1])
    d = p - corner
    return leg_vertex, leg_edge, p, corner, np.arctan2(d[:, 1], d[:, 0])


def _join_curves(xy: np.ndarray, s: np.ndarray, off: np.ndarray, edge_u, edge_v, edge_way, degree, cfg) -> dict:
    """Round the join of every pair of edges meeting at a vertex with a Bézier curve.

    The curve runs from ``join_radius_m`` back on one edge, through the corner, to
    ``join_radius_m`` along the other; its first half belongs to the first edge's way, the
    second half to the other's. Drawn once per unordered pair (both travel directions match it).
    Edge e's way-points are ``xy[off[e]:off[e + 1]]`` with arc lengths ``s``. Returns the curves'
    way-point arrays, in the order of the vertices' first appearance and of the pairs' legs.
    """
    empty = {"xy": np.zeros((0, 2)), "yaw": np.zeros(0), "s": np.zeros(0),
             "way_index": np.zeros(0, dtype=np.int32), "join_vertex": np.zeros(0, dtype=np.int32)}
    legs = _join_legs(xy, s, off, edge_u, edge_v, degree, cfg) if cfg.join_radius_m > 0 else None
    if legs is None:
        return empty
    leg_vertex, leg_edge, p, corner, angle = legs
    # every pair of legs at a vertex (i < j in the legs' order), vertex by vertex
    bounds = np.flatnonzero(np.r_[True, leg_vertex[1:] != leg_vertex[:-1], True])
    first, size = bounds[:-1], np.diff(bounds)
    pi_list, pj_list = [], []
    for m in np.unique(size[size >= 2]):
        a, b = np.triu_indices(int(m), 1)
        base = first[size == m]
        pi_list.append((base[:, None] + a[None, :]).ravel())
        pj_list.append((base[:, None] + b[None, :]).ravel())
    if not pi_list:
        return empty
    i = np.concatenate(pi_list)
    j = np.concatenate(pj_list)
    order = np.lexsort((j, i))  # legs are in vertex order, so (i, j) is the drawing order
    i, j = i[order], j[order]
    # arriving along leg i (direction angle_i + pi) and leaving along leg j (direction angle_j)
    turn = np.abs(wrap_angle(angle[j] - (angle[i] + np.pi)))
    keep = (turn >= np.radians(cfg.join_min_turn_deg)) & (turn <= np.radians(cfg.join_max_turn_deg))
    i, j = i[keep], j[keep]
    pts, c_off = polylines.quadratic_beziers(p[i], corner[i], p[j], cfg.spacing_m)
    cn = np.diff(c_off)
    big = cn >= 3
    sel = np.repeat(big, cn)
    pts, cn, i, j = pts[sel], cn[big], i[big], j[big]
    c_off = polylines.offsets_of(cn)
    local = polylines.local_index(c_off)
    half = np.repeat(cn // 2, cn)
    way = np.where(local < half, np.repeat(edge_way[leg_edge[i]], cn), np.repeat(edge_way[leg_edge[j]], cn))
    log.debug("added %d join curves", len(cn))
    return {"xy": pts, "yaw": polylines.headings(pts, c_off), "s": polylines.arc_length(pts, c_off),
            "way_index": way.astype(np.int32), "join_vertex": np.repeat(leg_vertex[i], cn).astype(np.int32)}


def load_roadmap(path: str | Path, config: RoadMapConfig | None = None, **kw) -> RoadMap:
    """:meth:`RoadMap.from_osm` under another name, resolving built-in map names first."""
    from .maps import resolve_map

    return RoadMap.from_osm(resolve_map(path), config, **kw)


__all__ = ["RoadMap", "RoadMapConfig", "WayInfo", "MapStats", "MapFileError", "load_roadmap"]
