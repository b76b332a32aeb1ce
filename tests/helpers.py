"""Shared helpers for the tests: synthetic trajectories, polylines and maps.

Every test module that needs a synthetic road or trajectory takes it from here, so the shapes
the tests reason about are defined once.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import strategies as st

from mapfusion.synthetic import OsmBuilder

REPO = Path(__file__).resolve().parent.parent
MAPS = REPO / "mapfusion" / "data" / "maps"
#: The real data (KITTI drives, OSM cities, VO results): never in the repository.
DATA = os.environ.get("MAPFUSION_DATA")


def data_required(folder: str) -> pytest.MarkDecorator:
    """Skip unless ``$MAPFUSION_DATA/folder`` is there (``.ci/run`` points it at ../shared/data)."""
    return pytest.mark.skipif(not DATA or not (Path(DATA) / folder).is_dir(),
                              reason="MAPFUSION_DATA is not set (.ci/run points it at ../shared/data)")


@st.composite
def polylines(draw, min_segments: int = 1, max_segments: int = 6, min_seg_m: float = 8.0,
              max_seg_m: float = 150.0, max_turn_deg: float = 100.0) -> np.ndarray:
    """A random road-like polyline (N, 2) in metres: segments of bounded length and turns."""
    n = draw(st.integers(min_segments, max_segments))
    heading = draw(st.floats(-math.pi, math.pi))
    x0 = draw(st.floats(-5000, 5000))
    y0 = draw(st.floats(-5000, 5000))
    pts = [(x0, y0)]
    for i in range(n):
        if i:
            heading += math.radians(draw(st.floats(-max_turn_deg, max_turn_deg)))
        length = draw(st.floats(min_seg_m, max_seg_m))
        x, y = pts[-1]
        pts.append((x + length * math.cos(heading), y + length * math.sin(heading)))
    return np.asarray(pts)


def straight_road(length_m: float = 500.0, heading_rad: float = 0.0, origin=(0.0, 0.0)) -> np.ndarray:
    """Two-point polyline of a straight road."""
    d = np.array([math.cos(heading_rad), math.sin(heading_rad)])
    o = np.asarray(origin, float)
    return np.array([o, o + length_m * d])


def circle_road(radius_m: float = 100.0, center=(0.0, 0.0), n: int = 72) -> np.ndarray:
    """Closed polygonal circle (first point repeated at the end)."""
    a = np.linspace(0, 2 * math.pi, n + 1)
    return np.column_stack([center[0] + radius_m * np.cos(a), center[1] + radius_m * np.sin(a)])


def write_osm(tmp_path: Path, roads: list[tuple[np.ndarray, dict]], name: str = "map.osm",
              origin=(60.2, 24.9)) -> Path:
    """Write roads (polyline, tags) as an OSM XML file and return its path."""
    b = OsmBuilder(origin=origin)
    for pts, tags in roads:
        b.way([tuple(p) for p in pts], **tags)
    p = tmp_path / name
    p.write_text(b.to_xml())
    return p



def six_lane_ring(tmp_path: Path):
    """A one-way six-lane ring of radius 100 m (18 m wide with the paper's 3 m lanes), like Berlin's Großer Stern."""
    from mapfusion import RoadMap

    return RoadMap.from_osm(write_osm(tmp_path, [(circle_road(100.0, n=180), {
        "highway": "primary", "oneway": "yes", "lanes": "6", "junction": "roundabout"})]), cache=False)

@dataclass
class TruthTrack:
    """A level ground-truth trajectory in a map's ENU frame (the fields of ``sim.sensors.Truth``)."""

    t_s: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    z_m: np.ndarray
    yaw_rad: np.ndarray
    gps_denied: np.ndarray
    visually_degraded: np.ndarray
    imu_missing: np.ndarray | None = None  # None: the IMU measures throughout

    def __post_init__(self) -> None:
        if self.imu_missing is None:
            self.imu_missing = np.zeros(len(self.t_s), dtype=bool)

    def __len__(self) -> int:
        return len(self.t_s)

    def poses(self) -> np.ndarray:
        """(N, 4, 4) level poses."""
        n = len(self.t_s)
        m = np.tile(np.eye(4), (n, 1, 1))
        c, s = np.cos(self.yaw_rad), np.sin(self.yaw_rad)
        m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1] = c, -s, s, c
        m[:, 0, 3], m[:, 1, 3], m[:, 2, 3] = self.x_m, self.y_m, self.z_m
        return m


def synthetic_truth(kind: str = "straight", n: int = 600, dt_s: float = 0.1, speed_mps: float = 10.0,
                    radius_m: float = 100.0, seed: int = 0, denied: tuple[int, int] | None = None):
    """A level ground-truth trajectory (:class:`TruthTrack`, the fields of ``sim.sensors.Truth``, which
    the sensor models read; the engine's tests use it without importing ``sim``).

    ``straight``: due east; ``circle``: counter-clockwise on ``radius_m``; ``random``: smooth
    random yaw rate and speed. ``denied`` = (first, last) frame of a GPS-denied, visually
    degraded zone.
    """
    t = np.arange(n) * dt_s
    if kind == "straight":
        yaw = np.zeros(n)
        v = np.full(n, speed_mps)
    elif kind == "circle":
        yaw = speed_mps / radius_m * t
        v = np.full(n, speed_mps)
    elif kind == "random":
        rng = np.random.default_rng(seed)
        w = min(30, n)
        rate = np.convolve(rng.normal(0, 0.15, n), np.ones(w) / w, mode="same")
        yaw = np.cumsum(rate) * dt_s
        v = np.clip(speed_mps + np.cumsum(rng.normal(0, 0.05, n)), 1.0, 30.0)
    else:
        raise ValueError(kind)
    x = np.concatenate(([0.0], np.cumsum(v[:-1] * np.cos(yaw[:-1]) * dt_s)))
    y = np.concatenate(([0.0], np.cumsum(v[:-1] * np.sin(yaw[:-1]) * dt_s)))
    flag = np.zeros(n, dtype=bool)
    if denied is not None:
        flag[denied[0]:denied[1] + 1] = True
    return TruthTrack(t, x, y, np.zeros(n), (yaw + np.pi) % (2 * np.pi) - np.pi, flag.copy(), flag.copy())



def wheel_gyro_samples(truth, scale_error: float = 0.0, bias_radps: float = 0.0, speed_noise_mps: float = 0.0,
                       gyro_noise_radps: float = 0.0, seed: int = 0, wheel_hz: float = 50.0, gyro_hz: float = 100.0):
    """Wheel speed and yaw rate sampled from a :class:`TruthTrack` (a polyline driven at each step's
    constant speed and turn rate): ((t, speed), (t, yaw rate)), with a scale error, a gyro bias and
    white noise; noise-free they integrate back to the truth's path length and heading."""
    rng = np.random.default_rng(seed)
    t = np.asarray(truth.t_s, float)
    dt = np.diff(t)
    v = np.hypot(np.diff(truth.x_m), np.diff(truth.y_m)) / dt
    w = np.diff(np.unwrap(truth.yaw_rad)) / dt
    tw = np.arange(t[0], t[-1], 1.0 / wheel_hz)
    tg = np.arange(t[0], t[-1], 1.0 / gyro_hz)
    iw = np.clip(np.searchsorted(t, tw, side="right") - 1, 0, len(v) - 1)
    ig = np.clip(np.searchsorted(t, tg, side="right") - 1, 0, len(w) - 1)
    speed = np.maximum(v[iw] * (1.0 + scale_error) + rng.normal(0.0, speed_noise_mps, len(tw)) * (v[iw] > 0), 0.0)
    rate = w[ig] + bias_radps + rng.normal(0.0, gyro_noise_radps, len(tg))
    return (tw, speed), (tg, rate)


def graph_route(road, seed: int, length_m: float, spacing_m: float = 1.0, start_edge: int | None = None):
    """A legal drive over a road map's graph from a random edge (or ``start_edge``), taking a random exit
    at each vertex, never turning back unless at a dead end: (x, y, yaw) arrays every ``spacing_m``
    along the road's own way-points (its geometry, not the filter's), and the edges driven."""
    rng = np.random.default_rng(seed)
    travel = np.array([road.ways[int(w)].travel for w in road.edge_way_index])
    edge = int(rng.integers(len(road.edge_u))) if start_edge is None else start_edge
    direction = 1 if travel[edge] >= 0 else -1
    pieces, edges, total = [], [], 0.0
    while total < length_m + 50.0:
        pts = road.xy_m[road.edge_start[edge]:road.edge_end[edge]]
        pts = pts if direction > 0 else pts[::-1]
        pieces.append(pts)
        edges.append(edge)
        total += float(road.edge_length_m[edge])
        vertex = int(road.edge_v[edge] if direction > 0 else road.edge_u[edge])
        nxt = [(e, 1) for e in np.flatnonzero(road.edge_u == vertex) if travel[e] >= 0 and e != edge] + \
              [(e, -1) for e in np.flatnonzero(road.edge_v == vertex) if travel[e] <= 0 and e != edge]
        if not nxt:
            nxt = [(edge, -direction)]
        edge, direction = nxt[int(rng.integers(len(nxt)))]
        edge = int(edge)
    xy = np.concatenate(pieces)
    keep = np.concatenate(([True], np.hypot(*np.diff(xy, axis=0).T) > 1e-6))
    xy = xy[keep]
    s = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))))
    u = np.arange(0.0, min(length_m, s[-1]), spacing_m)
    x, y = np.interp(u, s, xy[:, 0]), np.interp(u, s, xy[:, 1])
    yaw = np.arctan2(np.gradient(y), np.gradient(x))
    return x, y, yaw, edges


def drifting_odometry(x, y, yaw, seed: int, scale: float = 1.0, yaw_drift_rad_per_m: float = 0.0,
                      heading_rad: float = 0.0, noise_m: float = 0.0, spacing_m: float = 1.0):
    """The path (x, y) as an odometry would report it in its own frame, starting at the origin heading
    ``heading_rad``: each step's length times ``scale``, its heading off by a drift growing
    ``yaw_drift_rad_per_m`` per metre, plus white noise of ``noise_m`` per step. Returns (x, y, yaw)."""
    rng = np.random.default_rng(seed)
    dx, dy = np.diff(x), np.diff(y)
    step = np.hypot(dx, dy) * scale + rng.normal(0.0, noise_m, len(dx))
    head = np.arctan2(dy, dx) - yaw[0] + heading_rad + yaw_drift_rad_per_m * spacing_m * np.arange(len(dx))
    ox = np.concatenate(([0.0], np.cumsum(step * np.cos(head))))
    oy = np.concatenate(([0.0], np.cumsum(step * np.sin(head))))
    oyaw = np.concatenate(([heading_rad], head))
    return ox, oy, oyaw


def odometry_step(ox, oy, oyaw, k: int) -> np.ndarray:
    """The odometry's relative motion into step k (of :func:`drifting_odometry`'s path) as a 4×4 body-frame
    pose; the identity for k = 0."""
    if k == 0:
        return np.eye(4)
    c0, s0 = math.cos(oyaw[k - 1]), math.sin(oyaw[k - 1])
    dx, dy, dyaw = ox[k] - ox[k - 1], oy[k] - oy[k - 1], oyaw[k] - oyaw[k - 1]
    rel = np.eye(4)
    rel[:2, :2] = [[math.cos(dyaw), -math.sin(dyaw)], [math.sin(dyaw), math.cos(dyaw)]]
    rel[0, 3], rel[1, 3] = c0 * dx + s0 * dy, -s0 * dx + c0 * dy
    return rel


@contextlib.contextmanager
def search_params(**changes):
    """The engine's map search with these :class:`~mapfusion.relocalise.SearchParams` changed (its parts read
    ``mapfusion.relocalise.SEARCH_PARAMS`` when they decide) for the duration of the block."""
    from unittest import mock

    from mapfusion import relocalise

    with mock.patch.object(relocalise, "SEARCH_PARAMS", dataclasses.replace(relocalise.SEARCH_PARAMS, **changes)):
        yield
