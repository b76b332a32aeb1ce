"""Many polylines at once (mapfusion.polylines) give, to the bit, what geometry's one-polyline
functions give for each (issue 21: the road-map build's results must not change)."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from mapfusion import geometry, polylines
from tests.helpers import polylines as polyline_strategy

SPACINGS = st.sampled_from([0.5, 1.0, 2.0])


@st.composite
def ragged(draw, max_polylines: int = 6):
    """Polylines (some with a repeated point, some of 0 or 1 points) as (points, offsets, list)."""
    polys = []
    for _ in range(draw(st.integers(1, max_polylines))):
        kind = draw(st.sampled_from(["road", "road", "road", "empty", "single", "repeated"]))
        if kind == "empty":
            p = np.zeros((0, 2))
        elif kind == "single":
            p = draw(polyline_strategy(max_segments=1))[:1]
        else:
            p = draw(polyline_strategy(min_seg_m=0.3, max_seg_m=60.0))
            if kind == "repeated":
                p = np.insert(p, 1, p[0], axis=0)
        polys.append(p)
    offsets = polylines.offsets_of(np.array([len(p) for p in polys]))
    return np.concatenate(polys), offsets, polys


def _same(a, b) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b)


@given(ragged(), SPACINGS, st.sampled_from([0.0, 5.0, 10.0]))
def test_process_is_process_polyline_of_each(r, spacing, window):
    points, offsets, polys = r
    pts, s, yaw, off = polylines.process(points, offsets, spacing, window)
    assert len(off) == len(polys) + 1
    for k, p in enumerate(polys):
        if len(p) == 0:
            assert off[k + 1] == off[k]
            continue
        ref = geometry.process_polyline(p, spacing, window)
        got = (pts[off[k]:off[k + 1]], s[off[k]:off[k + 1]], yaw[off[k]:off[k + 1]])
        assert all(_same(a, b) for a, b in zip(ref, got)), k


@given(ragged(), SPACINGS)
def test_resample_is_resample_of_each(r, spacing):
    points, offsets, polys = r
    pts, s, off = polylines.resample(points, offsets, spacing)
    for k, p in enumerate(polys):
        ref_pts, ref_s = geometry.resample(p, spacing)
        assert _same(ref_pts, pts[off[k]:off[k + 1]]) and _same(ref_s, s[off[k]:off[k + 1]]), k


@given(ragged(), st.integers(0, 6))
def test_rolling_mean_and_headings_of_each(r, half):
    points, offsets, polys = r
    smooth = polylines.rolling_mean(points, offsets, half)
    yaw = polylines.headings(points, offsets)
    length = polylines.arc_length(points, offsets)
    for k, p in enumerate(polys):
        sl = slice(offsets[k], offsets[k + 1])
        assert _same(geometry.rolling_mean(p, half), smooth[sl]), k
        assert _same(geometry.headings(p), yaw[sl]), k
        if len(p):
            assert _same(geometry.cumulative_length(p), length[sl]), k


@given(st.lists(st.tuples(*[st.floats(-500, 500)] * 6), min_size=1, max_size=8), SPACINGS)
def test_quadratic_beziers_are_each_bezier(rows, spacing):
    a = np.array(rows)
    p0, p1, p2 = a[:, 0:2], a[:, 2:4], a[:, 4:6]
    pts, off = polylines.quadratic_beziers(p0, p1, p2, spacing)
    for k in range(len(a)):
        assert _same(geometry.quadratic_bezier(p0[k], p1[k], p2[k], spacing), pts[off[k]:off[k + 1]]), k


@given(ragged(), st.data())
def test_interp_is_np_interp_within_each(r, data):
    points, offsets, polys = r
    pts, off = polylines.drop_repeated(points, offsets)
    s = polylines.arc_length(pts, off)
    lengths = np.diff(off)
    usable = np.flatnonzero(lengths >= 2)
    if usable.size == 0:
        return
    seg = np.array(data.draw(st.lists(st.sampled_from(usable.tolist()), min_size=1, max_size=20)))
    total = s[off[seg + 1] - 1]
    frac = np.array(data.draw(st.lists(st.sampled_from([0.0, 0.25, 0.5, 1.0, 1 / 3]), min_size=len(seg),
                                       max_size=len(seg))))
    x = frac * total
    x[frac == 1.0] = total[frac == 1.0]  # exactly at the last knot
    got = polylines.interp(x, seg, s, pts, off)
    for i, k in enumerate(seg):
        sl = slice(off[k], off[k + 1])
        ref = [np.interp(x[i], s[sl], pts[sl, c]) for c in (0, 1)]
        assert got[i, 0] == ref[0] and got[i, 1] == ref[1], (k, x[i])


def test_cumsum_is_each_cumsum_over_lengths_of_every_size():
    rng = np.random.default_rng(3)
    lengths = np.array([0, 1, 2, 3, 7, 8, 9, 300, 1, 0, 4096, 5000])
    offsets = polylines.offsets_of(lengths)
    values = rng.normal(0, 1e3, (int(offsets[-1]), 2))
    got = polylines.cumsum(values, offsets)
    for k in range(len(lengths)):
        sl = slice(offsets[k], offsets[k + 1])
        assert _same(np.cumsum(values[sl], axis=0), got[sl]), k
