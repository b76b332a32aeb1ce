"""The cell index and the matcher's fast paths (issue 21) answer exactly what a brute-force search
over every way-point answers."""

from __future__ import annotations

import dataclasses
import math

import gtsam
import numpy as np
from hypothesis import given
from hypothesis.extra import numpy as hnp
from hypothesis import strategies as st

from mapfusion.geometry import as_complex
from mapfusion.matcher import Match, _clip, lateral_bound_ok, map_pose, match, match_candidates
from mapfusion.spatial import CellIndex

angles = st.floats(-math.pi, math.pi)


@given(st.integers(0, 400), st.floats(-300, 300), st.floats(-300, 300), st.floats(0.5, 120.0),
       st.integers(0, 2**31 - 1), st.sampled_from([5.0, 20.0, 50.0]), st.booleans())
def test_cell_query_is_every_point_within_the_radius(n, x, y, radius, seed, cell, table):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-250, 250, (n, 2))
    yaw = rng.uniform(-math.pi, math.pi, n)
    idx = CellIndex(xy, np.cos(yaw), np.sin(yaw), cell_m=cell)
    if not table:  # the binary search a sparse map's index uses in place of the table
        idx.key = np.searchsorted(np.array(idx._start), np.arange(len(idx.rank)), "right") - 1
        idx._start = None
    got = idx.query(x, y, radius)
    want = np.flatnonzero((xy[:, 0] - x) ** 2 + (xy[:, 1] - y) ** 2 <= radius * radius)
    # in row-major cell order, then by index (what relocalisation's particle spread is drawn over), each once
    lo = xy.min(axis=0) if n else np.zeros(2)
    cell = np.floor((xy[want, 1] - lo[1]) / cell) * 1e6 + np.floor((xy[want, 0] - lo[0]) / cell)
    assert got.tolist() == want[np.lexsort((want, cell))].tolist()


@given(st.integers(1, 300), st.integers(0, 2**31 - 1), st.sampled_from([1.0, 5.0, 20.0]))
def test_every_point_is_in_the_bands_of_its_row_and_the_two_rows_before(n, seed, cell):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 120, (n, 2))
    idx = CellIndex(xy, np.ones(n), np.zeros(n), cell_m=cell)
    row = np.floor((xy[:, 1] - xy[:, 1].min()) / cell).astype(int)
    entries = np.arange(len(idx.rank))
    key = idx.key if idx.key is not None else np.searchsorted(np.array(idx._start), entries, "right") - 1
    band = key // idx.ncol
    point = idx.by_cell[idx.rank]
    for i in range(n):
        assert sorted(band[point == i].tolist()) == [b for b in (row[i] - 2, row[i] - 1, row[i]) if b >= 0]
    assert np.all(np.diff(key) >= 0)  # bands, then columns, in order
    assert np.array_equal(idx.z.real, xy[point, 0]) and np.array_equal(idx.z.imag, xy[point, 1])
    assert np.array_equal(idx.block[0], np.ones(len(point))) and np.array_equal(idx.block[2], -np.ones(len(point)))


def test_a_sparse_map_uses_the_binary_search_and_answers_the_same():
    xy = np.array([[0.0, 0.0], [1e6, 1e6], [5.0, 3.0], [1e6 + 4.0, 1e6 - 2.0]])
    idx = CellIndex(xy, np.ones(4), np.zeros(4), cell_m=1.0)  # 1e12 cells: no table
    assert idx._start is None
    assert sorted(idx.query(1e6, 1e6, 10.0).tolist()) == [1, 3]
    assert sorted(idx.query(0.0, 0.0, 6.0).tolist()) == [0, 2]
    assert idx.query(5e5, 5e5, 10.0).size == 0
    assert idx.query(5.0, 3.0, 0.5).tolist() == [2]  # one band's slice


def _brute(road, x, y, yaw, radius):
    d = np.abs(road.xy_complex - complex(x, y))  # the matcher's distance E (next test: hypot's, to 2 ulp)
    near = np.flatnonzero(d <= radius)
    if near.size == 0:
        return None
    return match(road, x, y, yaw, radius, candidates=near)


@given(hnp.arrays(np.float64, st.integers(1, 50), elements=st.floats(-1e5, 1e5)),
       hnp.arrays(np.float64, st.integers(1, 50), elements=st.floats(-1e5, 1e5)), st.floats(-1e5, 1e5),
       st.floats(-1e5, 1e5))
def test_the_matchers_distance_is_hypots_to_two_units_in_the_last_place(px, py, x, y):
    n = min(len(px), len(py))
    xy = np.column_stack([px[:n], py[:n]])
    want = np.hypot(xy[:, 0] - x, xy[:, 1] - y)
    _, _, e, _, _ = match_candidates(x, y, 0.0, xy, np.ones(n), np.zeros(n))
    got = np.abs(as_complex(xy) - complex(x, y))
    assert np.all(np.abs(got - want) <= 2 * np.spacing(want) + 1e-300)
    assert e == got.min()  # every heading along the pose's: D = E, the best is the nearest by that distance


@given(i=st.integers(0, 10**6), dx=st.floats(-30, 30), dy=st.floats(-30, 30), yaw=angles,
       radius=st.sampled_from([5.0, 20.0, 35.0]))
def test_match_through_the_cells_is_the_brute_force_match(helsinki, i, dx, dy, yaw, radius):
    j = i % len(helsinki)
    x, y = float(helsinki.xy_m[j, 0] + dx), float(helsinki.xy_m[j, 1] + dy)
    got, want = match(helsinki, x, y, yaw, radius), _brute(helsinki, x, y, yaw, radius)
    assert (got is None) == (want is None)
    if got is not None:
        assert got.cost == want.cost and got.way_id == want.way_id and got.lateral_m == want.lateral_m


@given(i=st.integers(0, 10**6), dx=st.floats(-12, 12), dy=st.floats(-12, 12), yaw=angles,
       pitch=st.floats(-0.4, 0.4), roll=st.floats(-0.4, 0.4), z=st.floats(-20, 20), width=st.floats(0.5, 12.0))
def test_the_lateral_bound_never_says_on_the_road_when_the_map_pose_says_off(helsinki, i, dx, dy, yaw, pitch,
                                                                          roll, z, width):
    j = i % len(helsinki)
    x, y = float(helsinki.xy_m[j, 0] + dx), float(helsinki.xy_m[j, 1] + dy)
    m = match(helsinki, x, y, yaw)
    if m is None:
        return
    pose = gtsam.Pose3(gtsam.Rot3.Ypr(yaw, pitch, roll), gtsam.Point3(x, y, z))
    _, lateral = map_pose(m, pose)
    if lateral_bound_ok(m, pose.matrix(), width):
        assert lateral <= width
    if lateral < width - 1e-6 * (1 + width + abs(m.longitudinal_m)):
        assert lateral_bound_ok(m, pose.matrix(), width)  # the bound is tight, not merely safe


def test_query_radius_refuses_a_non_finite_centre_and_holds_everything_in_an_infinite_radius(helsinki):
    import pytest

    for bad in ((math.nan, 0.0, 20.0), (0.0, math.inf, 20.0), (0.0, 0.0, math.nan)):
        with pytest.raises(ValueError, match="query_radius"):
            helsinki.query_radius(*bad)
    assert len(helsinki.query_radius(0.0, 0.0, math.inf)) == len(helsinki)
    assert helsinki.query_radius(0.0, 0.0, -1.0).size == 0


@given(i=st.integers(0, 10**6), dx=st.floats(-15, 15), dy=st.floats(-15, 15), yaw=angles)
def test_a_match_built_by_its_fast_path_is_the_dataclass_it_declares(helsinki, i, dx, dy, yaw):
    """The single call builds its Match without the frozen dataclass's __init__ (issue 21): the instance has
    every declared field and nothing else, and equals (and hashes as) the one __init__ builds."""
    j = i % len(helsinki)
    m = match(helsinki, float(helsinki.xy_m[j, 0] + dx), float(helsinki.xy_m[j, 1] + dy), yaw)
    assert m is not None  # (within 15 m of a way-point, inside the default 20 m)
    assert set(vars(m)) == {f.name for f in dataclasses.fields(Match)}
    rebuilt = Match(**vars(m))
    assert m == rebuilt and hash(m) == hash(rebuilt)
    assert m.is_join == (m.edge < 0) and m.lateral_m == abs(m.signed_lateral_m)


@given(hnp.arrays(np.float64, st.integers(0, 64), elements=st.floats(-3.0, 3.0)))
def test_the_matchers_clip_is_numpys(values):
    got = values.copy()
    _clip(got, -1.0, 1.0, out=got)
    assert np.array_equal(got, np.clip(values, -1.0, 1.0))
