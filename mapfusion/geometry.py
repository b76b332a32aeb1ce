"""Planar polyline geometry used to build the road map (all lengths in metres, angles in radians).

Every function here is pure and vectorised over the points of one polyline.
"""

from __future__ import annotations

import numpy as np

_TWO_PI = 2.0 * np.pi

#: numpy's clip ufunc itself, ``fast_clip(v, lo, hi[, out=])``: np.clip's Python wrapper costs more than the clipping
#: of a disc's few dozen points or a few hundred particles (issue 21); where a numpy lacks it, minimum then maximum
#: give the same values.
fast_clip = getattr(getattr(getattr(np, "_core", None), "umath", None), "clip", None) or (
    lambda v, lo, hi, out=None: np.maximum(np.minimum(v, hi, out=out), lo, out=out))


def as_complex(xy_m: np.ndarray) -> np.ndarray:
    """Positions (n, 2) as complex numbers x + iy (n,): a view where the array is contiguous float64."""
    return np.ascontiguousarray(xy_m, dtype=np.float64).reshape(-1, 2).view(np.complex128).reshape(-1)


def wrap_angle(angle_rad):
    """Wrap an angle (or array of angles) into [-pi, pi): (a + π) mod 2π − π."""
    t = np.asarray(angle_rad) + np.pi
    if t.ndim == 0 or t.size < 64:
        return t % _TWO_PI - np.pi
    # the same values as the line above, four times faster on the particles' tens of thousands (issue 21): the
    # remainder (numpy's slowest arithmetic) is exact, so it leaves t in [0, 2π) as it is (a zero becomes +0,
    # which gives −π as −0 does); only the others need it
    out = t.copy()
    outside = (t < 0.0) | (t >= _TWO_PI)
    if outside.any():
        out[outside] = t[outside] % _TWO_PI
    out -= np.pi
    return out


def cumulative_length(points_m: np.ndarray) -> np.ndarray:
    """Arc length at every vertex of a polyline (N, 2) → (N,), starting at 0."""
    seg = np.hypot(*np.diff(points_m, axis=0).T)
    return np.concatenate(([0.0], np.cumsum(seg)))


def drop_repeated(points_m: np.ndarray, tol_m: float = 1e-6) -> np.ndarray:
    """Remove consecutive duplicate vertices (zero-length segments break headings)."""
    if len(points_m) < 2:
        return points_m
    keep = np.ones(len(points_m), dtype=bool)
    keep[1:] = np.hypot(*np.diff(points_m, axis=0).T) > tol_m
    return points_m[keep]


def resample(points_m: np.ndarray, spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Evenly spaced points along a polyline, both ends kept.

    The number of intervals is ``round(length / spacing)`` (at least 1), so every interval has
    the same length, within ``spacing / (2·n)`` of the target: within 10% once the polyline is
    five spacings long or more. Returns ``(points (M, 2), arc_length (M,))``.
    """
    if spacing_m <= 0:
        raise ValueError(f"spacing_m must be > 0, got {spacing_m}")
    pts = drop_repeated(np.asarray(points_m, dtype=float))
    if len(pts) < 2:
        return pts.copy(), np.zeros(len(pts))
    s = cumulative_length(pts)
    n = max(1, int(round(s[-1] / spacing_m)))
    s_new = np.linspace(0.0, s[-1], n + 1)
    x = np.interp(s_new, s, pts[:, 0])
    y = np.interp(s_new, s, pts[:, 1])
    return np.column_stack([x, y]), s_new


def rolling_mean(points_m: np.ndarray, half_window: int) -> np.ndarray:
    """Centred rolling average of a polyline's points with ends held fixed.

    Near the ends the window shrinks symmetrically, so the first and last points never move:
    the road still meets its junction where OSM puts it.
    """
    n = len(points_m)
    if half_window <= 0 or n < 3:
        return points_m.copy()
    idx = np.arange(n)
    k = np.minimum(np.minimum(idx, n - 1 - idx), half_window)
    csum = np.vstack([np.zeros((1, 2)), np.cumsum(points_m, axis=0)])
    return (csum[idx + k + 1] - csum[idx - k]) / (2 * k + 1)[:, None]


def headings(points_m: np.ndarray) -> np.ndarray:
    """Heading of each point towards the next one; the last point takes the previous heading."""
    if len(points_m) < 2:
        return np.zeros(len(points_m))
    d = np.diff(points_m, axis=0)
    h = np.arctan2(d[:, 1], d[:, 0])
    return np.concatenate([h, h[-1:]])


def process_polyline(
    points_m: np.ndarray, spacing_m: float, smoothing_window_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Interpolate, smooth and re-space a raw OSM polyline.

    Steps (paper III.A): linear interpolation at ``spacing_m``, a rolling average over
    ``smoothing_window_m``, then a second even resampling so the smoothing's shortening of
    corners does not leave uneven gaps. Returns ``(points, arc_length, heading)``.
    """
    dense, _ = resample(points_m, spacing_m)
    half = int(round(0.5 * smoothing_window_m / spacing_m))
    smooth = rolling_mean(dense, half)
    pts, s = resample(smooth, spacing_m)
    return pts, s, headings(pts)


def point_at_distance(points_m: np.ndarray, dist_m: float) -> np.ndarray:
    """The point at arc length ``dist_m`` from the start of a polyline (clamped to its ends)."""
    s = cumulative_length(points_m)
    d = float(np.clip(dist_m, 0.0, s[-1]))
    return np.array([np.interp(d, s, points_m[:, 0]), np.interp(d, s, points_m[:, 1])])


def quadratic_bezier(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray, spacing_m: float) -> np.ndarray:
    """A quadratic Bézier from p0 to p2 with control point p1, sampled about every ``spacing_m``.

    Used to round the join between two roads: tangent to the incoming road at p0 and to the
    outgoing road at p2.
    """
    approx_len = np.hypot(*(p1 - p0)) + np.hypot(*(p2 - p1))
    n = max(2, int(np.ceil(approx_len / spacing_m)) + 1)
    t = np.linspace(0.0, 1.0, 4 * n)[:, None]
    curve = (1 - t) ** 2 * p0 + 2 * (1 - t) * t * p1 + t**2 * p2
    pts, _ = resample(curve, spacing_m)
    return pts


def point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from each point of ``p`` (N, 2) to the nearest of the segments ``a[i] → b[i]`` (M, 2).

    Returns (N,) distances. O(N·M) memory: meant for tests and small inputs.
    """
    ab = b - a
    ab2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18)
    ap = p[:, None, :] - a[None, :, :]
    t = np.clip(np.einsum("nmj,mj->nm", ap, ab) / ab2[None, :], 0.0, 1.0)
    closest = a[None, :, :] + t[..., None] * ab[None, :, :]
    return np.min(np.linalg.norm(p[:, None, :] - closest, axis=2), axis=1)


def on_line(origin_m: np.ndarray, heading_rad: float, points_m: np.ndarray, points_heading_rad: np.ndarray,
            tol_m: float, max_angle_rad: float) -> np.ndarray:
    """Which points lie on the line through ``origin_m`` (2,) along ``heading_rad``: within ``tol_m`` of it, their
    own heading within ``max_angle_rad`` of the line's in either direction. (N, 2), (N,) → (N,) bool."""
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    d = np.asarray(points_m, dtype=float) - np.asarray(origin_m, dtype=float)
    across = np.abs(c * d[:, 1] - s * d[:, 0])
    turn = np.abs(np.sin(np.asarray(points_heading_rad) - heading_rad))
    return (across <= tol_m) & (turn <= np.sin(max_angle_rad))
