"""Many polylines at once (issue 21): the road-map build's interpolation, smoothing, re-spacing and
join curves over every edge in a handful of numpy calls instead of tens of thousands of small ones.

Each function does, element by element, the very arithmetic of its one-polyline counterpart in
:mod:`mapfusion.geometry` (the same operations in the same order), so a map built either way is the
same to the bit. A set of polylines is "ragged": points ``(M, 2)`` and ``offsets`` ``(K + 1,)``,
polyline i being ``points[offsets[i]:offsets[i + 1]]``. Running sums along a polyline are taken
row by row of a padded table (``np.cumsum`` along a row adds in the order one polyline's own
``np.cumsum`` does); interpolation searches each polyline's own arc lengths (a complex key orders by
polyline, then arc length) and interpolates as ``np.interp`` does.
"""

from __future__ import annotations

import numpy as np


def lengths_of(offsets: np.ndarray) -> np.ndarray:
    return np.diff(offsets)


def segment_ids(offsets: np.ndarray) -> np.ndarray:
    """The polyline of every point."""
    return np.repeat(np.arange(len(offsets) - 1), lengths_of(offsets))


def local_index(offsets: np.ndarray) -> np.ndarray:
    """Every point's index within its polyline."""
    n = lengths_of(offsets)
    return np.arange(int(offsets[-1])) - np.repeat(offsets[:-1], n)


def offsets_of(lengths: np.ndarray) -> np.ndarray:
    out = np.zeros(len(lengths) + 1, dtype=np.int64)
    np.cumsum(lengths, out=out[1:])
    return out


def cumsum(values: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """``np.cumsum(values[a:b], axis=0)`` of every polyline, concatenated (bit for bit: each row of a
    padded table is summed in order; polylines are grouped by length so the padding stays small)."""
    values = np.asarray(values, dtype=float)
    out = np.empty_like(values)
    n = lengths_of(offsets)
    if len(n) == 0:
        return out
    bucket = np.ceil(np.log2(np.maximum(n, 1))).astype(int)
    for b in np.unique(bucket):
        rows = np.flatnonzero((bucket == b) & (n > 0))
        if rows.size == 0:
            continue
        width = int(n[rows].max())
        cols = np.arange(width)
        valid = cols[None, :] < n[rows, None]
        idx = (offsets[rows, None] + cols[None, :])[valid]
        table = np.zeros((rows.size, width) + values.shape[1:])
        table[valid] = values[idx]
        np.cumsum(table, axis=1, out=table)
        out[idx] = table[valid]
    return out


def _starts(offsets: np.ndarray) -> np.ndarray:
    """The first point of every non-empty polyline."""
    return offsets[:-1][lengths_of(offsets) > 0]


def drop_repeated(points: np.ndarray, offsets: np.ndarray, tol_m: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """:func:`mapfusion.geometry.drop_repeated` of every polyline."""
    keep = np.ones(len(points), dtype=bool)
    d = np.diff(points, axis=0)  # (across two polylines too: overwritten at each polyline's start)
    keep[1:] = np.hypot(d[:, 0], d[:, 1]) > tol_m
    keep[_starts(offsets)] = True
    single = np.repeat(lengths_of(offsets) < 2, lengths_of(offsets))
    keep |= single  # a polyline of fewer than two points is returned as it is
    counts = np.bincount(segment_ids(offsets), weights=keep, minlength=len(offsets) - 1).astype(np.int64)
    return points[keep], offsets_of(counts)


def arc_length(points: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """:func:`mapfusion.geometry.cumulative_length` of every polyline, concatenated."""
    step = np.zeros(len(points))
    d = np.diff(points, axis=0)
    step[1:] = np.hypot(d[:, 0], d[:, 1])
    step[_starts(offsets)] = 0.0
    return cumsum(step, offsets)


def interp(x: np.ndarray, x_seg: np.ndarray, xp: np.ndarray, fp: np.ndarray, xp_offsets: np.ndarray) -> np.ndarray:
    """``np.interp(x, xp_i, fp_i)`` for every x (of every column of ``fp``), i = ``x_seg`` its polyline;
    each polyline's ``xp`` strictly increasing and ``x`` within its range (as the callers here guarantee)."""
    xp_seg = segment_ids(xp_offsets)
    j = np.searchsorted(xp_seg + 1j * xp, x_seg + 1j * x, side="right") - 1
    last = xp_offsets[x_seg + 1] - 1
    k = np.minimum(j, last - 1)  # the knot interval; at a knot x − xp[k] = 0 gives fp[k] exactly, as np.interp
    dxp = np.diff(xp)[k]
    dt = x - xp[k]
    at_end = np.flatnonzero(j >= last)  # at (or past) a polyline's last knot: its value, as np.interp
    cols = [fp] if fp.ndim == 1 else [np.ascontiguousarray(fp[:, c]) for c in range(fp.shape[1])]
    out = []
    for f in cols:
        v = np.diff(f)[k] / dxp
        v *= dt
        v += f[k]
        v[at_end] = f[last[at_end]]
        out.append(v)
    return out[0] if fp.ndim == 1 else np.column_stack(out)


def resample(points: np.ndarray, offsets: np.ndarray, spacing_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`mapfusion.geometry.resample` of every polyline: (points, arc lengths, offsets)."""
    pts, off = drop_repeated(np.asarray(points, dtype=float), offsets)
    n_pts = lengths_of(off)
    s = arc_length(pts, off)
    ok = n_pts >= 2
    total = np.where(ok, s[np.maximum(off[1:] - 1, 0)] if len(s) else 0.0, 0.0)
    intervals = np.maximum(1, np.rint(total / spacing_m).astype(np.int64))
    new_n = np.where(ok, intervals + 1, n_pts)  # (fewer than two points: returned as they are)
    new_off = offsets_of(new_n)
    seg = segment_ids(new_off)
    i = local_index(new_off).astype(float)
    step = total / np.where(ok, intervals, 1)
    s_new = i * step[seg]
    s_new += 0.0  # (np.linspace's "+ start")
    ends = new_off[1:][ok] - 1
    s_new[ends] = total[ok]
    out = np.empty((len(s_new), 2))
    moved = ok[seg]
    src = np.flatnonzero(moved)
    out[src] = interp(s_new[src], seg[src], s, pts, off)
    kept = np.flatnonzero(~moved)  # polylines of 0 or 1 points: copied, arc length 0
    out[kept] = pts[np.repeat(off[:-1], new_n)[kept] + local_index(new_off)[kept]]
    s_new[kept] = 0.0
    return out, s_new, new_off


def rolling_mean(points: np.ndarray, offsets: np.ndarray, half_window: int) -> np.ndarray:
    """:func:`mapfusion.geometry.rolling_mean` of every polyline."""
    n = lengths_of(offsets)
    if half_window <= 0 or len(points) == 0:
        return points.copy()
    seg = segment_ids(offsets)
    idx = local_index(offsets)
    nn = n[seg]
    k = np.minimum(np.minimum(idx, nn - 1 - idx), half_window)
    csum = cumsum(points, offsets)
    start = offsets[:-1][seg]
    hi = csum[start + idx + k]  # csum row idx + k + 1 of the padded table is cumsum row idx + k
    lo_row = idx - k
    lo = np.where((lo_row > 0)[:, None], csum[np.maximum(start + lo_row - 1, 0)], 0.0)
    out = (hi - lo) / (2 * k + 1)[:, None]
    short = nn < 3
    out[short] = points[short]
    return out


def headings(points: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """:func:`mapfusion.geometry.headings` of every polyline."""
    h = np.zeros(len(points))
    d = np.diff(points, axis=0)
    h[:-1] = np.arctan2(d[:, 1], d[:, 0])
    n = lengths_of(offsets)
    h[offsets[1:][n == 1] - 1] = 0.0
    ends = offsets[1:][n >= 2] - 1
    h[ends] = h[ends - 1]
    return h


def process(points: np.ndarray, offsets: np.ndarray, spacing_m: float, smoothing_window_m: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`mapfusion.geometry.process_polyline` of every polyline: (points, arc lengths, headings, offsets)."""
    dense, _, off = resample(points, offsets, spacing_m)
    half = int(round(0.5 * smoothing_window_m / spacing_m))
    smooth = rolling_mean(dense, off, half)
    pts, s, off = resample(smooth, off, spacing_m)
    return pts, s, headings(pts, off), off


def quadratic_beziers(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray, spacing_m: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`mapfusion.geometry.quadratic_bezier` for every row of p0, p1, p2 (K, 2): (points, offsets)."""
    approx = np.hypot(*(p1 - p0).T) + np.hypot(*(p2 - p1).T)
    n = np.maximum(2, np.ceil(approx / spacing_m).astype(np.int64) + 1)
    samples = 4 * n
    off = offsets_of(samples)
    seg = segment_ids(off)
    i = local_index(off).astype(float)
    t = i * (1.0 / (samples - 1))[seg]
    t += 0.0
    t[off[1:] - 1] = 1.0
    t = t[:, None]
    curve = (1 - t) ** 2 * p0[seg] + 2 * (1 - t) * t * p1[seg] + t**2 * p2[seg]
    pts, _, out_off = resample(curve, off, spacing_m)
    return pts, out_off


