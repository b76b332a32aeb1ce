"""Property tests of the polyline processing behind the road map."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import assume, given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from mapfusion.geometry import (
    cumulative_length,
    fast_clip,
    headings,
    point_segment_distance,
    process_polyline,
    resample,
    rolling_mean,
    wrap_angle,
)
from tests.helpers import polylines

SPACING = 1.0
WINDOW = 5.0
HALF_LANE = 1.5


@given(polylines(min_seg_m=5.0), st.sampled_from([0.5, 1.0, 2.0]))
def test_spacing_within_ten_percent(poly, spacing):
    pts, s, _ = process_polyline(poly, spacing, WINDOW)
    # round(L / spacing) intervals are within 10% of the spacing once L is five spacings or more
    assume(s[-1] >= 5 * spacing)
    gaps = np.hypot(*np.diff(pts, axis=0).T)
    assert np.all(np.abs(gaps - spacing) <= 0.1 * spacing), (gaps.min(), gaps.max())
    assert np.allclose(np.diff(s), s[-1] / (len(s) - 1))


@given(polylines(max_turn_deg=120.0))
def test_ends_are_kept(poly):
    pts, _, _ = process_polyline(poly, SPACING, WINDOW)
    assert np.allclose(pts[0], poly[0], atol=1e-9) and np.allclose(pts[-1], poly[-1], atol=1e-9)


@given(polylines(min_seg_m=15.0))
def test_headings_follow_segments_away_from_joins(poly):
    pts, s, yaw = process_polyline(poly, SPACING, WINDOW)
    raw_s = cumulative_length(poly)
    seg_dir = np.arctan2(np.diff(poly[:, 1]), np.diff(poly[:, 0]))
    margin = WINDOW + 2 * SPACING
    for i, p in enumerate(pts[:-1]):
        if np.min(np.hypot(*(poly - p).T)) < margin:
            continue  # near a join: the heading turns there by design
        per_segment = [point_segment_distance(p[None], poly[j : j + 1], poly[j + 1 : j + 2])[0] for j in range(len(poly) - 1)]
        k = int(np.argmin(per_segment))
        assert per_segment[k] < 1e-6
        assert abs(math.degrees(wrap_angle(yaw[i] - seg_dir[k]))) < 1.0
    assert raw_s[-1] >= s[-1] - 1e-6  # smoothing never lengthens a road


@given(polylines(max_turn_deg=150.0, min_seg_m=3.0))
def test_smoothing_stays_within_half_a_lane(poly):
    pts, _, _ = process_polyline(poly, SPACING, WINDOW)
    d = point_segment_distance(pts, poly[:-1], poly[1:])
    assert d.max() <= HALF_LANE, d.max()


@given(st.integers(3, 40), st.integers(0, 6))
def test_rolling_mean_is_identity_on_a_line(n, half):
    line = np.column_stack([np.arange(n, dtype=float), 2.0 * np.arange(n)])
    assert np.allclose(rolling_mean(line, half), line)


def test_rolling_mean_hand_computed():
    pts = np.array([[0, 0], [1, 0], [2, 3], [3, 0], [4, 0]], dtype=float)
    out = rolling_mean(pts, 1)
    assert np.allclose(out[2], [2.0, 1.0])
    assert np.allclose(out[1], [1.0, 1.0])
    assert np.allclose(out[[0, -1]], pts[[0, -1]])


def test_headings_last_takes_previous():
    pts = np.array([[0, 0], [1, 0], [1, 1]], dtype=float)
    assert np.allclose(headings(pts), [0.0, math.pi / 2, math.pi / 2])


@given(st.floats(1.0, 500.0), st.floats(0.3, 3.0))
def test_resample_straight_line(length, spacing):
    pts, s = resample(np.array([[0.0, 0.0], [length, 0.0]]), spacing)
    assert np.isclose(s[-1], length) and np.allclose(pts[:, 1], 0.0)
    n = max(1, round(length / spacing))
    assert len(pts) == n + 1


@given(hnp.arrays(np.float64, st.integers(0, 300), elements=st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.floats(-7.0, 7.0),
    st.sampled_from([0.0, -0.0, math.pi, -math.pi, 2 * math.pi, math.pi - 2**-50, -math.pi - 2**-50]))))
def test_wrap_angle_of_an_array_is_the_formula_to_the_bit(a):
    """Long arrays take a faster path (issue 21) that must give (a + π) mod 2π − π exactly, NaN and ±∞ included."""
    want = (a + np.pi) % (2 * np.pi) - np.pi
    got = wrap_angle(a)
    assert got.dtype == want.dtype and np.array_equal(got, want, equal_nan=True)
    assert np.array_equal(np.signbit(got), np.signbit(want))


@given(st.floats(-1e6, 1e6, allow_nan=False))
def test_wrap_angle_range(a):
    w = float(wrap_angle(a))
    assert -math.pi <= w < math.pi
    assert math.isclose(math.cos(w), math.cos(a), abs_tol=1e-6)


@given(hnp.arrays(np.float64, st.integers(0, 50), elements=st.floats(allow_nan=True)),
       st.floats(-1e6, 1e6), st.floats(0.0, 1e6))
def test_fast_clip_is_np_clip(v, lo, width):
    """The particles' and the matcher's clip: np.clip's values (NaN kept) without its Python wrapper."""
    hi = lo + width
    np.testing.assert_array_equal(fast_clip(v, lo, hi), np.clip(v, lo, hi))
