"""Registering a window of GPS fixes on the road network (issue 17).

Fixes that share one bias (a receiver locked onto a reflection for minutes, a wrong datum, the
``kidnapped`` family's biased fix windows) draw the true path's shape shifted by that bias: off the roads
for most of their length. The shift that puts the fixes back on the roads is the bias, and a path with a
turn or two fixes it without ambiguity — found at once, where a search on the road network fed by the
odometry needs the path's turns to come one by one.

:func:`register_on_roads` scores every shift within a disc on a grid of ``cell_m``: the mean, over the
fixes (thinned to one per ``thin_m`` of path, so a standstill does not outweigh the driving), of the squared
distance to the nearest road way-point, each capped at ``cap_m`` (a fix far off any road, an outlier,
costs the same wherever it lands). The distances come from one Euclidean distance transform of the
way-points rasterised on the grid. The answer is the best shift, its RMS and the best RMS among the shifts
farther than ``separation_m`` from it: a straight path fits every shift along its road, a grid of streets
every block, and the caller accepts only a best shift clearly better than its runner-up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .roadmap import RoadMap

__all__ = ["Registration", "register_on_roads", "thin_path"]

#: RMS (m) below which a fit is as good as perfect on the 2 m grid (points, shifts and roads each within a cell).
RMS_FLOOR_M = 1.0
#: With headings: the points' headings are binned this finely, and a way-point counts for a bin when one may drive
#: along it within HEADING_TOLERANCE_DEG of the bin's heading.
HEADING_BIN_DEG = 30.0
HEADING_TOLERANCE_DEG = 60.0


@dataclass(frozen=True)
class Registration:
    """The shift (map frame, m) that best puts a set of points on the roads, and how sure it is."""

    dx_m: float
    dy_m: float
    rms_m: float  # RMS of the capped distances to the roads at the best shift
    runner_up_rms_m: float  # the same at the best shift farther than separation_m from it (inf: none)
    rms_unshifted_m: float  # the same with no shift
    points: int

    @property
    def shift_m(self) -> float:
        return math.hypot(self.dx_m, self.dy_m)

    def decisive(self, ratio: float, max_rms_m: float, min_shift_m: float) -> bool:
        """Is the shift an answer: longer than ``min_shift_m`` (nearer is the same place), its RMS within
        ``max_rms_m``, and the runner-up's at least ``ratio`` times its own (taken as at least RMS_FLOOR_M: on the
        grid an RMS below it is quantisation, and two shifts that both fit perfectly are no answer)?"""
        return self.shift_m > min_shift_m and self.rms_m <= max_rms_m \
            and self.runner_up_rms_m >= ratio * max(self.rms_m, RMS_FLOOR_M)


def thin_path(xy_m: np.ndarray, thin_m: float) -> np.ndarray:
    """The points of a path (N, 2) kept at least ``thin_m`` apart along it (the first always kept)."""
    xy = np.asarray(xy_m, dtype=float).reshape(-1, 2)
    return xy[_thin_index(xy, thin_m)]


def _thin_index(xy: np.ndarray, thin_m: float) -> np.ndarray:
    if len(xy) == 0 or thin_m <= 0:
        return np.arange(len(xy))
    keep = [0]
    lx, ly = xy[0]
    for i in range(1, len(xy)):
        x, y = xy[i]
        if math.hypot(x - lx, y - ly) >= thin_m:
            keep.append(i)
            lx, ly = x, y
    return np.asarray(keep)


def _distance_fields(road: RoadMap, inside: np.ndarray, x0: float, y0: float, shape: tuple[int, int], cell_m: float,
                     cap_m: float, bins: np.ndarray | None) -> dict[int, np.ndarray]:
    """The capped squared distance to the way-points on the grid: one field (key -1), or, per heading bin in
    ``bins``, one to the way-points a vehicle heading that way may drive along (within HEADING_TOLERANCE_DEG)."""
    keys = [-1] if bins is None else sorted(set(bins.tolist()))
    fields = {}
    for key in keys:
        sel = inside
        if key >= 0:
            c = math.cos(math.radians(key * HEADING_BIN_DEG)) * road.legal_cos + \
                math.sin(math.radians(key * HEADING_BIN_DEG)) * road.legal_sin
            c = np.where(road.two_way_sign < 0, np.abs(c), c)
            sel = inside & (c >= math.cos(math.radians(HEADING_TOLERANCE_DEG)))
        cost = np.full(shape, cap_m * cap_m)
        if sel.any():
            occupied = np.zeros(shape, dtype=bool)
            rows = ((road.xy_m[sel, 1] - y0) // cell_m).astype(np.int64)
            cols = ((road.xy_m[sel, 0] - x0) // cell_m).astype(np.int64)
            occupied[rows, cols] = True
            dist = ndimage.distance_transform_edt(~occupied, sampling=cell_m)
            cost = np.minimum(dist, cap_m) ** 2
        fields[key] = cost
    return fields


def register_on_roads(road: RoadMap, xy_m: np.ndarray, radius_m: float, cell_m: float = 2.0, cap_m: float = 10.0,
                      separation_m: float = 30.0, thin_m: float = 5.0,
                      headings_rad: np.ndarray | None = None) -> Registration | None:
    """The shift within ``radius_m`` (m) that best puts the points ``xy_m`` (N, 2, map frame, m) on the
    road way-points (see the module docstring); None when fewer than three points remain after thinning.
    With ``headings_rad`` (N,: the path's heading at each point) a point counts only the way-points it may drive
    along in that direction (to HEADING_BIN_DEG): a path is not put on a dual carriageway's other half."""
    if not (radius_m > 0 and cell_m > 0 and cap_m > 0 and separation_m >= 0):
        raise ValueError(f"register_on_roads: radius_m, cell_m and cap_m must be > 0, separation_m ≥ 0; got "
                         f"{radius_m}, {cell_m}, {cap_m}, {separation_m}")
    xy = np.asarray(xy_m, dtype=float).reshape(-1, 2)
    idx = _thin_index(xy, thin_m)
    pts = xy[idx]
    bins = None
    if headings_rad is not None:
        h = np.asarray(headings_rad, dtype=float).reshape(-1)
        if h.shape != (len(xy),):
            raise ValueError(f"register_on_roads: {len(xy)} points but {h.shape} headings")
        bins = np.round(np.degrees(h[idx]) / HEADING_BIN_DEG).astype(np.int64) % int(round(360 / HEADING_BIN_DEG))
    ok = np.isfinite(pts).all(axis=1) & (np.isfinite(h[idx]) if headings_rad is not None else True)
    pts = pts[ok]
    bins = bins[ok] if bins is not None else None
    if len(pts) < 3:
        return None
    r = int(math.ceil(radius_m / cell_m))
    pad = (r + 2) * cell_m
    x0, y0 = pts[:, 0].min() - pad, pts[:, 1].min() - pad
    nx = int(math.ceil((pts[:, 0].max() + pad - x0) / cell_m)) + 1
    ny = int(math.ceil((pts[:, 1].max() + pad - y0) / cell_m)) + 1
    way = road.xy_m
    inside = (way[:, 0] >= x0) & (way[:, 0] < x0 + nx * cell_m) & (way[:, 1] >= y0) & (way[:, 1] < y0 + ny * cell_m)
    fields = _distance_fields(road, inside, x0, y0, (ny, nx), cell_m, cap_m, bins)
    # every point's cost over the (2r + 1)² shifts is a window of its field: their sum, one window per point
    ix = ((pts[:, 0] - x0) // cell_m).astype(np.int64)
    iy = ((pts[:, 1] - y0) // cell_m).astype(np.int64)
    keys = [-1] * len(pts) if bins is None else bins.tolist()
    total = np.zeros((2 * r + 1, 2 * r + 1))
    for cx, cy, key in zip(ix.tolist(), iy.tolist(), keys):
        total += fields[key][cy - r:cy + r + 1, cx - r:cx + r + 1]
    total /= len(pts)
    offs = np.arange(-r, r + 1) * cell_m
    within = offs[None, :] ** 2 + offs[:, None] ** 2 <= radius_m * radius_m
    total = np.where(within, total, np.inf)
    by, bx = np.unravel_index(int(np.argmin(total)), total.shape)
    dx, dy = float(offs[bx]), float(offs[by])
    far = (offs[None, :] - dx) ** 2 + (offs[:, None] - dy) ** 2 > separation_m * separation_m
    runner_up = float(total[far].min()) if far.any() else math.inf
    return Registration(dx, dy, math.sqrt(float(total[by, bx])), math.sqrt(runner_up), math.sqrt(float(total[r, r])),
                        len(pts))
