"""Road hypotheses (the online HMM on the road graph): a posterior that sums to one, the
single-frame match where nothing is ambiguous, and the right exit road after a junction."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapfusion import RoadMap
from mapfusion.roadmap import can_drive
from mapfusion.hypotheses import HmmParams, RoadHypotheses, candidates
from mapfusion.geometry import wrap_angle
from mapfusion.matcher import match
from tests.helpers import MAPS, circle_road, straight_road, write_osm

GRID = RoadMap.from_osm(MAPS / "synthetic" / "grid.osm")
CFG = HmmParams()
RADIUS_M, W_M_PER_DEG = 20.0, 1.0  # the matcher's search radius and angle weight (the engine's defaults)


def _step(h: RoadHypotheses, road: RoadMap, x: float, y: float, yaw: float, moved: float):
    near = road.query_radius(x, y, RADIUS_M)
    return h.step(candidates(road, near, x, y, yaw, W_M_PER_DEG), moved)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 40), noise=st.floats(0.0, 8.0))
def test_the_posterior_sums_to_one(seed, n, noise):
    rng = np.random.default_rng(seed)
    h = RoadHypotheses(GRID, CFG)
    i = int(rng.integers(len(GRID)))
    x, y, yaw = *GRID.xy_m[i], float(GRID.yaw_rad[i])
    for _ in range(n):
        st_ = _step(h, GRID, x + rng.normal(0, noise), y + rng.normal(0, noise), yaw + rng.normal(0, 0.2), 5.0)
        post = h.posterior()
        if st_.best is not None:
            assert math.isclose(sum(post.values()), 1.0, rel_tol=1e-9)
            assert 0.0 < st_.posterior <= 1.0 + 1e-12 and len(post) <= CFG.beam
        x, y = x + 5.0 * math.cos(yaw), y + 5.0 * math.sin(yaw)


@pytest.fixture(scope="module")
def lone_road(tmp_path_factory):
    p = write_osm(tmp_path_factory.mktemp("lone"), [(straight_road(2000.0, 0.3, (-900.0, -300.0)), {"highway": "primary"})])
    return RoadMap.from_osm(p, cache=False)


@settings(max_examples=40, deadline=None)
@given(along=st.floats(150.0, 1850.0), offset=st.floats(-6.0, 6.0), yaw_err=st.floats(-0.5, 0.5),
       backwards=st.booleans(), steps=st.integers(1, 20))
def test_on_a_lone_road_it_is_the_single_frame_match(lone_road, along, offset, yaw_err, backwards, steps):
    road = lone_road
    h = RoadHypotheses(road, CFG)
    (x0, y0), road_yaw = road.xy_m[0], float(road.yaw_rad[0])
    heading = road_yaw + (math.pi if backwards else 0.0)
    d = 5.0 * (-1.0 if backwards else 1.0)
    for k in range(steps):
        s = along + k * d
        x = x0 + s * math.cos(road_yaw) - offset * math.sin(road_yaw)
        y = y0 + s * math.sin(road_yaw) + offset * math.cos(road_yaw)
        st_ = _step(h, road, x, y, heading + yaw_err, 5.0)
    m = match(road, x, y, heading + yaw_err, RADIUS_M, W_M_PER_DEG)
    assert st_.best is not None and m is not None
    assert st_.best.edge == m.edge and st_.best.index == m.index
    assert (st_.best.direction < 0) == m.reversed
    if steps == 1:  # one road, two directions: the posterior is the emissions' alone
        cands = candidates(road, road.query_radius(x, y, RADIUS_M), x, y, heading + yaw_err,
                           W_M_PER_DEG)
        costs = sorted(c.cost for c in cands)
        assert len(costs) == 2
        assert st_.posterior == pytest.approx(1.0 / (1.0 + math.exp(-(costs[1] - costs[0]) / CFG.emission_scale_m)))
    else:  # after a second step the other direction has moved against the odometry: it is ruled out
        assert st_.posterior == pytest.approx(1.0)


def _junction_drives(road: RoadMap):
    """(vertex, entering edge, leaving edge) of every junction of the grid."""
    ends: dict[int, list[int]] = {}
    for e in range(len(road.edge_u)):
        ends.setdefault(int(road.edge_u[e]), []).append(e)
        ends.setdefault(int(road.edge_v[e]), []).append(e)
    def other_end(e: int, v: int) -> int:
        return int(road.edge_u[e]) if int(road.edge_v[e]) == v else int(road.edge_v[e])

    # only the drives a vehicle may make: into the junction and out of it along each road's legal direction
    return [(v, a, b) for v, es in ends.items() if road.vertex_degree[v] >= 3 for a in es for b in es
            if a != b and can_drive(road, a, v) and can_drive(road, b, other_end(b, v))]


def _ordered(road: RoadMap, e: int, v: int, towards: bool) -> np.ndarray:
    """Way-points of edge e ordered towards (or away from) its end v, leaving out the 15 m at its
    other end: the drive must be on this edge, not at the next junction."""
    idx = np.arange(road.edge_start[e], road.edge_end[e])
    from_v = road.s_m[idx] if road.edge_u[e] == v else road.edge_length_m[e] - road.s_m[idx]
    idx = idx[from_v <= road.edge_length_m[e] - 15.0]
    idx = idx[np.argsort(-from_v[from_v <= road.edge_length_m[e] - 15.0])]  # now ordered towards v
    return idx if towards else idx[::-1]


DRIVES = _junction_drives(GRID)


@settings(max_examples=60, deadline=None)
@given(pick=st.integers(0, len(DRIVES) - 1), seed=st.integers(0, 1000), offset=st.floats(0.0, 1.5),
       yaw_err=st.floats(0.0, 5.0))
def test_a_drive_through_a_junction_ends_on_the_true_exit_road(pick, seed, offset, yaw_err):
    v, e_in, e_out = DRIVES[pick]
    road = GRID
    path = np.concatenate([_ordered(road, e_in, v, True)[-60:], _ordered(road, e_out, v, False)[:60]])
    rng = np.random.default_rng(seed)
    h = RoadHypotheses(road, CFG)
    prev = None
    for j in range(0, len(path) - 1, 3):
        i, nxt = path[j], path[j + 1]
        heading = math.atan2(road.xy_m[nxt, 1] - road.xy_m[i, 1], road.xy_m[nxt, 0] - road.xy_m[i, 0])
        o = rng.uniform(-offset, offset)
        x, y = road.xy_m[i, 0] - math.sin(heading) * o, road.xy_m[i, 1] + math.cos(heading) * o
        moved = 0.0 if prev is None else float(np.hypot(*(road.xy_m[i] - road.xy_m[prev])))
        st_ = _step(h, road, x, y, heading + math.radians(rng.uniform(-yaw_err, yaw_err)), moved)
        prev = i
    assert st_.best is not None and st_.best.edge == e_out
    assert st_.posterior > 0.9


@pytest.fixture(scope="module")
def ring_road(tmp_path_factory):
    p = write_osm(tmp_path_factory.mktemp("ring"), [(circle_road(60.0, n=90), {"highway": "primary"})])
    return RoadMap.from_osm(p, cache=False)


@settings(max_examples=60, deadline=None)
@given(angle=st.floats(0.0, 2 * math.pi), offset=st.floats(-15.0, 15.0), yaw=st.floats(-math.pi, math.pi),
       other_yaw=st.floats(-math.pi, math.pi))
def test_a_candidate_stands_at_the_foot_of_the_pose(ring_road, angle, offset, yaw, other_yaw):
    """On a curve: each candidate is its edge's way-point nearest the pose (whatever the heading, which
    changes only the cost), its cost D = E + w·A there, and its position along the edge the pose
    projected onto the road's direction there."""
    road, w = ring_road, W_M_PER_DEG
    x, y = (60.0 + offset) * math.cos(angle), (60.0 + offset) * math.sin(angle)
    near = road.query_radius(x, y, RADIUS_M)
    got = candidates(road, near, x, y, yaw, w)
    assert got and {c.direction for c in got} == {1, -1}
    for c in got:
        on_edge = near[(road.edge[near] == c.edge) & ~road.is_join[near]]
        dist = np.hypot(road.xy_m[on_edge, 0] - x, road.xy_m[on_edge, 1] - y)
        assert math.hypot(road.xy_m[c.index, 0] - x, road.xy_m[c.index, 1] - y) == pytest.approx(dist.min())
        road_yaw = float(road.yaw_rad[c.index]) + (0.0 if c.direction > 0 else math.pi)
        assert c.cost == pytest.approx(dist.min() + w * abs(math.degrees(float(wrap_angle(yaw - road_yaw)))), abs=1e-6)
        proj = float(road.s_m[c.index]) + (x - road.xy_m[c.index, 0]) * math.cos(road.yaw_rad[c.index]) \
            + (y - road.xy_m[c.index, 1]) * math.sin(road.yaw_rad[c.index])
        assert c.along_m == pytest.approx(min(max(proj, 0.0), float(road.edge_length_m[c.edge])), abs=1e-6)
    turned = candidates(road, near, x, y, other_yaw, w)
    assert [(c.edge, c.direction, c.index, c.along_m) for c in turned] == [(c.edge, c.direction, c.index, c.along_m)
                                                                           for c in got]


@pytest.mark.parametrize("tag, directions", [(None, {1, -1}), ("yes", {1}), ("-1", {-1})])
def test_a_one_way_edge_is_a_candidate_in_its_legal_direction_only(tmp_path, tag, directions):
    tags = {"highway": "primary", **({"oneway": tag} if tag else {})}
    road = RoadMap.from_osm(write_osm(tmp_path, [(straight_road(300.0, 0.0), tags)]), cache=False)
    for yaw in (0.0, math.pi, 1.0):  # with the drawing, against it, across: the heading never adds a direction
        got = candidates(road, road.query_radius(150.0, 2.0, 20.0), 150.0, 2.0, yaw, 1.0)
        assert {c.direction for c in got} == directions


@settings(max_examples=30, deadline=None)
@given(along=st.floats(200.0, 1500.0), gap_steps=st.integers(1, 8), backwards=st.booleans())
def test_a_step_with_no_road_in_range_carries_the_hypotheses_forward(lone_road, along, gap_steps, backwards):
    """A few metres out of the map's reach (a wide road's far side, a bridge) do not erase which road it
    was: the posterior stays, the road's position moves on with the odometry, the step is unexplained."""
    road = lone_road
    h = RoadHypotheses(road, CFG)
    (x0, y0), road_yaw = road.xy_m[0], float(road.yaw_rad[0])
    heading = road_yaw + (math.pi if backwards else 0.0)
    sign = -1.0 if backwards else 1.0
    for k in range(5):
        s = along + sign * 5.0 * k
        st_ = _step(h, road, x0 + s * math.cos(road_yaw), y0 + s * math.sin(road_yaw), heading, 5.0)
    before = h.posterior()
    for _ in range(gap_steps):
        gap = h.step([], 5.0)
        assert gap.best is not None and (gap.best.edge, gap.best.direction) == (st_.best.edge, st_.best.direction)
        assert not gap.explained and gap.posterior == pytest.approx(st_.posterior)
    assert h.posterior() == pytest.approx(before)
    moved = (gap.best.along_m - st_.best.along_m) * sign
    assert moved == pytest.approx(5.0 * gap_steps)
