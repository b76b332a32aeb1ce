"""A SUMO drive with libsumo: routes, background traffic and the ground truth in the map's frame.

libsumo runs one simulation per process at a time: :func:`run_drive` starts it, steps it and
always closes it. Positions reach the road map's ENU frame through lat/lon (SUMO's own x/y is
never mixed with it), and SUMO's position (the front bumper) is moved back to the vehicle's
centre.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from mapfusion.geometry import rolling_mean
from mapfusion.roadmap import RoadMap

from .network import Network, RouteError, SimulationError, build_network, ensure_sumo_env
from .scenario import Scenario

log = logging.getLogger(__name__)

EGO = "ego"


@dataclass
class Track:
    """One vehicle's recorded states, one row a step (arrays of equal length)."""

    vehicle: str
    t_s: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    z_m: np.ndarray
    yaw_rad: np.ndarray
    speed_mps: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    sumo_edge: list[str]
    sumo_lane: list[str]
    osm_way: np.ndarray  # -1 inside junctions (SUMO's internal edges)
    in_tunnel: np.ndarray
    distance_m: np.ndarray  # odometer since departure
    sumo_speed_mps: np.ndarray  # SUMO's speed (along lane lengths, see _to_track)

    def __len__(self) -> int:
        return len(self.t_s)


@dataclass
class DriveResult:
    """What a drive produced: the ego's track, the fleet's (in fleet mode) and the route."""

    ego: Track
    route_edges: list[str]
    route_length_m: float
    fleet: dict[str, Track] = field(default_factory=dict)
    wall_s: float = 0.0
    sim_s: float = 0.0
    vehicles: int = 1

    @property
    def realtime_factor(self) -> float:
        """Simulated seconds per wall-clock second."""
        return self.sim_s / self.wall_s if self.wall_s > 0 else float("inf")


_VARS = None


def _vars(ls):
    global _VARS
    if _VARS is None:
        _VARS = (ls.VAR_POSITION3D, ls.VAR_ANGLE, ls.VAR_SPEED, ls.VAR_ROAD_ID, ls.VAR_LANE_ID, ls.VAR_DISTANCE)
    return _VARS


def _route_length(net: Network, edges: list[str]) -> float:
    return float(sum(net.edges[e].length_m for e in edges if e in net.edges))


def _find(ls, a: str, b: str) -> list[str]:
    try:
        r = ls.simulation.findRoute(a, b, vType="DEFAULT_VEHTYPE")
    except Exception:  # libsumo raises TraCIException for unknown edges
        return []
    return list(r.edges)


def _chain(ls, net: Network, rng: np.random.Generator, route: list[str], min_length_m: float, max_trips: int,
           candidates: list[str]) -> list[str]:
    """``route`` extended by random trips, end to start, until it is ``min_length_m`` long (or stuck)."""
    for _trip in range(max_trips):
        if _route_length(net, route) >= min_length_m:
            break
        nxt = []
        for _try in range(10):
            target = candidates[int(rng.integers(len(candidates)))]
            if target == route[-1]:
                continue
            nxt = _find(ls, route[-1], target)
            if len(nxt) > 1:
                break
        if len(nxt) <= 1:
            break
        route.extend(nxt[1:])
    return route


def plan_route(ls, net: Network, rng: np.random.Generator, min_length_m: float, max_trips: int,
               via_tunnel: bool = False, tunnel_after_m: float = 1500.0) -> list[str]:
    """A seeded random route of at least ``min_length_m``: random trips chained end to start. With
    ``via_tunnel`` a random OSM tunnel edge is on the route, reached after a lead-in of ``tunnel_after_m``."""
    candidates = [e for e in net.routable_edges if net.edges[e].length_m > 5.0] or net.routable_edges
    tunnels = [e for e in net.routable_edges if net.edges[e].tunnel]
    if via_tunnel and not tunnels:
        raise RouteError("route.via_tunnel: the map has no tunnel (no OSM way tagged tunnel=yes or covered=yes)")
    route: list[str] = []
    for _attempt in range(20):
        route = [candidates[int(rng.integers(len(candidates)))]]
        if via_tunnel:
            route = _chain(ls, net, rng, route, tunnel_after_m, max_trips, candidates)
            tunnel = tunnels[int(rng.integers(len(tunnels)))]
            path = [tunnel] if tunnel == route[-1] else _find(ls, route[-1], tunnel)
            if not path:
                continue
            route.extend(path[1:])
        route = _chain(ls, net, rng, route, min_length_m, max_trips, candidates)
        if _route_length(net, route) >= min_length_m:
            return route
    raise RouteError(f"no route of {min_length_m:.0f} m{' through a tunnel' if via_tunnel else ''} could be built "
                     f"on this map (the longest chain reached {_route_length(net, route):.0f} m)")


def explicit_route(ls, net: Network, edges: tuple[str, ...]) -> list[str]:
    """The route through the given edges, consecutive ones joined by shortest paths."""
    for e in edges:
        if e not in net.edges:
            raise RouteError(f"route: unknown SUMO edge {e!r}")
    route = [edges[0]]
    for a, b in zip(edges[:-1], edges[1:]):
        path = _find(ls, a, b)
        if not path:
            raise RouteError(f"route: no connection from edge {a!r} to edge {b!r}")
        route.extend(path[1:])
    return route


def _start(ls, net: Network, sc: Scenario) -> None:
    ensure_sumo_env()
    ls.start([
        "sumo", "-n", str(net.net_path),
        "--step-length", f"{sc.step_s}",
        "--seed", str(sc.seed),
        "--begin", "0",
        "--no-step-log", "true",
        "--no-warnings", "true",
        "--time-to-teleport", "-1",  # a teleport would tear the ground truth
        "--collision.action", "warn",
        "--default.speeddev", "0.1",
    ])


def run_drive(sc: Scenario, road: RoadMap, net: Network | None = None, progress=None) -> DriveResult:
    """Simulate one drive and record the ego (and, in fleet mode, every vehicle) each step.

    ``progress(t_s, duration_s)`` is called now and then for a progress bar.
    """
    import libsumo as ls

    net = net or build_network(sc.map)
    rng = np.random.default_rng(sc.seed)
    t_wall = time.perf_counter()
    _start(ls, net, sc)
    try:
        if sc.route.edges:
            route = explicit_route(ls, net, sc.route.edges)
        else:
            route = plan_route(ls, net, rng, sc.min_route_m, sc.route.max_trips, sc.route.via_tunnel,
                                   sc.route.tunnel_after_m)
        ls.route.add("ego_route", route)
        ls.vehicletype.copy("DEFAULT_VEHTYPE", "ego_type")
        ls.vehicletype.setLength("ego_type", 4.5)
        ls.vehicle.add(EGO, "ego_route", typeID="ego_type", depart="0", departLane="best", departSpeed="0")
        n_bg = _add_background(ls, net, rng, sc)
        ls.vehicle.subscribe(EGO, _vars(ls))
        raw = _record(ls, sc, progress)
    except RouteError:
        raise
    except Exception as exc:  # libsumo's TraCIException and the like
        if exc.__class__.__name__ == "TraCIException":
            raise SimulationError(f"SUMO: {exc}") from None
        raise
    finally:
        ls.close()
    wall = time.perf_counter() - t_wall
    lengths = raw.pop("__lengths__")
    tracks = {vid: _to_track(vid, rows, lengths.get(vid, 4.5), net, road, sc) for vid, rows in raw.items()}
    if EGO not in tracks or len(tracks[EGO]) == 0:
        raise SimulationError("the ego vehicle never entered the network")
    ego = tracks.pop(EGO)
    fleet = ({EGO: ego} | tracks) if sc.traffic.fleet else {}
    return DriveResult(ego=ego, route_edges=route, route_length_m=_route_length(net, route), fleet=fleet,
                       wall_s=wall, sim_s=float(ego.t_s[-1]), vehicles=1 + n_bg)


def _add_background(ls, net: Network, rng: np.random.Generator, sc: Scenario) -> int:
    n = 0
    for i in range(sc.traffic.background_vehicles):
        try:
            r = plan_route(ls, net, rng, min(2000.0, max(sc.min_route_m, 500.0)), 10)
        except RouteError:
            continue
        rid = f"bg_route_{i}"
        ls.route.add(rid, r)
        depart = float(rng.uniform(0.0, sc.traffic.depart_spread_s))
        ls.vehicle.add(f"bg{i}", rid, depart=f"{depart:.1f}", departLane="best", departPos="random", departSpeed="max")
        n += 1
    return n


def _record(ls, sc: Scenario, progress) -> dict:
    """Step the simulation until the ego arrives or time is up; rows of raw SUMO states per vehicle."""
    rows: dict[str, list] = {EGO: []}
    lengths: dict[str, float] = {}
    fleet = sc.traffic.fleet
    ego_seen = False
    steps = int(math.floor(sc.duration_s / sc.step_s + 1e-9))
    v = _vars(ls)
    for k in range(steps):
        ls.simulationStep()
        t = ls.simulation.getTime()
        if fleet:
            for vid in ls.simulation.getDepartedIDList():
                if vid != EGO:
                    ls.vehicle.subscribe(vid, v)
                    rows.setdefault(vid, [])
        results = ls.vehicle.getAllSubscriptionResults()
        for vid, res in results.items():
            if vid not in lengths:
                lengths[vid] = ls.vehicle.getLength(vid)
            if vid in rows:
                pos = res[v[0]]
                rows[vid].append((t, pos[0], pos[1], pos[2], res[v[1]], res[v[2]], res[v[3]], res[v[4]], res[v[5]]))
        if EGO in results:
            ego_seen = True
        elif ego_seen:
            break  # arrived
        if progress is not None and k % 200 == 0:
            progress(t, sc.duration_s)
    rows["__lengths__"] = lengths
    return rows


SMOOTH_HALF_WINDOW_M = 2.0
RESAMPLE_M = 0.25
HEADING_BASE_M = 1.0
MOVING_MPS = 0.3


def kinematic_truth(x: np.ndarray, y: np.ndarray, sumo_yaw: np.ndarray, speed: np.ndarray, step_s: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A kinematically consistent ground truth from SUMO's centre positions.

    Inside junctions SUMO moves vehicles between lane shapes that do not quite meet: the front
    bumper jumps sideways (even backwards) and the body angle swings tens of degrees off the
    direction of travel. Fed to the odometry model that would be motion no car makes. So the
    centre path is smoothed along its own length, by a moving average over ±2 m of path (on a
    10 m-radius turn this moves it about 0.07 m inwards; a standing vehicle does not move), and
    the heading is the path's direction over ±1 m of path (held while slower than 0.3 m/s;
    SUMO's own heading before the first move).
    """
    n = len(x)
    if n < 3:
        return x, y, np.asarray(sumo_yaw, dtype=float)
    s = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))))
    if s[-1] > 2 * RESAMPLE_M:
        # the path as a function of its length: keep one sample per distinct length (standstill repeats)
        keep = np.concatenate(([True], np.diff(s) > 1e-9))
        grid = np.arange(0.0, s[-1] + RESAMPLE_M, RESAMPLE_M)
        gx = np.interp(grid, s[keep], x[keep])
        gy = np.interp(grid, s[keep], y[keep])
        smooth = rolling_mean(np.column_stack([gx, gy]), int(round(SMOOTH_HALF_WINDOW_M / RESAMPLE_M)))
        x = np.interp(s, grid, smooth[:, 0])
        y = np.interp(s, grid, smooth[:, 1])
        s = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))))
    keep = np.concatenate(([True], np.diff(s) > 1e-9))
    sk, xk, yk = s[keep], x[keep], y[keep]
    ahead_x = np.interp(s + HEADING_BASE_M, sk, xk)
    ahead_y = np.interp(s + HEADING_BASE_M, sk, yk)
    back_x = np.interp(s - HEADING_BASE_M, sk, xk)
    back_y = np.interp(s - HEADING_BASE_M, sk, yk)
    motion_yaw = np.arctan2(ahead_y - back_y, ahead_x - back_x)
    moving = (speed > MOVING_MPS) & (np.hypot(ahead_x - back_x, ahead_y - back_y) > 0.5 * HEADING_BASE_M)
    yaw = np.empty(n)
    current = float(sumo_yaw[0])
    for i in range(n):
        if moving[i]:
            current = float(motion_yaw[i])
        yaw[i] = current
    return x, y, yaw


def path_speed_mps(x: np.ndarray, y: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Speed along a path: central differences of its arc length over time (one-sided at the ends)."""
    if len(t) < 2:
        return np.zeros(len(t))
    s = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))))
    return np.gradient(s, t)


def _osm_ways(edges: list[str], x: np.ndarray, y: np.ndarray, net: Network, road: RoadMap) -> np.ndarray:
    """The OSM way under each frame; -1 inside junctions.

    Inside a junction means on one of SUMO's internal edges, or past the end of the OSM way: where
    ways meet at a shallow angle netconvert draws the incoming lane on across the junction's
    area, beyond the node where OSM ends the way. Where netconvert merged several OSM ways into
    one edge (its origId lists them all), the way is the listed one nearest to the frame.
    """
    out = np.full(len(edges), -1, dtype=np.int64)
    pts_of: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def geometry(w: int):
        if w not in pts_of:
            idx = road.waypoints_of_way(w)
            # the ends of the way's edges, with the outward direction there
            ends, outward = [], []
            for e in np.unique(road.edge[idx]):
                a, b = int(road.edge_start[e]), int(road.edge_end[e])
                if b - a >= 2:
                    p0, p1, q0, q1 = road.xy_m[a], road.xy_m[a + 1], road.xy_m[b - 1], road.xy_m[b - 2]
                    ends += [p0, q0]
                    outward += [(p0 - p1) / max(np.hypot(*(p0 - p1)), 1e-9), (q0 - q1) / max(np.hypot(*(q0 - q1)), 1e-9)]
            pts_of[w] = (road.xy_m[idx], np.array(ends).reshape(-1, 2), np.array(outward).reshape(-1, 2))
        return pts_of[w]

    for i, e in enumerate(edges):
        info = net.edges.get(e)
        if info is None or not info.osm_ways:
            continue
        candidates = [w for w in info.osm_ways if road.has_way(w)]
        if not candidates:
            out[i] = info.osm_ways[0]
            continue
        dists = []
        for w in candidates:
            pts = geometry(w)[0]
            dists.append(float(np.min(np.hypot(pts[:, 0] - x[i], pts[:, 1] - y[i]))) if len(pts) else np.inf)
        w = candidates[int(np.argmin(dists))]
        pts, ends, outward = geometry(w)
        if len(ends):
            rel = np.array([x[i], y[i]]) - ends
            beyond = np.einsum("ij,ij->i", rel, outward)
            k = int(np.argmin(np.hypot(*rel.T)))
            if beyond[k] > 1.0 and np.hypot(*rel[k]) <= min(dists) + 1e-6 + 1.0:
                continue  # past the end of the way: inside the junction
        out[i] = w
    return out


def _to_track(vid: str, rows: list, length_m: float, net: Network, road: RoadMap, sc: Scenario) -> Track:
    if not rows:
        e = np.zeros(0)
        return Track(vid, e, e, e, e, e, e, e, e, [], [], np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool), e, e)
    a = np.array([r[:6] for r in rows], dtype=float)
    t, fx, fy, z, angle_deg, speed = a.T
    dist = np.array([r[8] for r in rows], dtype=float)
    edges = [r[6] for r in rows]
    lanes = [r[7] for r in rows]
    # SUMO reports the front bumper, and its angle is the direction from the back bumper to the
    # front one: half a length back along that angle is the midpoint of the two, the centre
    ang = np.radians(angle_deg)
    cx = fx - 0.5 * length_m * np.sin(ang)
    cy = fy - 0.5 * length_m * np.cos(ang)
    lat, lon = net.sumo_xy_to_geo(cx, cy)
    x, y = road.projection.to_enu(lat, lon)
    # SUMO's angle is against its own projection's grid north (UTM), not the map's: carry the
    # heading through lat/lon too, as a point 1 m ahead along the body axis
    hlat, hlon = net.sumo_xy_to_geo(cx + np.sin(ang), cy + np.cos(ang))
    hx, hy = road.projection.to_enu(hlat, hlon)
    sumo_yaw = np.arctan2(np.asarray(hy) - y, np.asarray(hx) - x)
    x, y, yaw = kinematic_truth(np.asarray(x), np.asarray(y), sumo_yaw, speed, sc.step_s)
    # SUMO advances a vehicle along its lane's length attribute, which differs from the drawn lane
    # shape (lanes offset on curves share the centreline length; junction lanes up to 1.5×): the
    # truth speed is the speed along the truth path, SUMO's own value is kept beside it
    path_speed = path_speed_mps(x, y, t)
    lat, lon = road.projection.to_geo(x, y)
    osm_way = _osm_ways(edges, np.asarray(x), np.asarray(y), net, road)
    tunnel = np.zeros(len(rows), dtype=bool)
    last = False
    for i, e in enumerate(edges):
        info = net.edges.get(e)
        if info is not None:
            last = info.tunnel
        tunnel[i] = last  # inside a junction: as the edge it came from
    for zone in sc.tunnels:
        tunnel |= (dist >= zone.start_m) & (dist <= zone.end_m)
    return Track(vid, t, np.asarray(x), np.asarray(y), z, yaw, path_speed, np.asarray(lat), np.asarray(lon),
                 edges, lanes, osm_way, tunnel, dist, speed)
