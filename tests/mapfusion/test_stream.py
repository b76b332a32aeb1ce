"""Streaming the engine (issue 19): a bounded history, and output identical to the kept-whole run."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mapfusion.config import FusionConfig
from mapfusion.engine import MapFusion
from mapfusion.roadmap import RoadMap
from mapfusion.stream import BATCH_FRAMES, history_s
from mapfusion.track import History
from tests.helpers import circle_road, synthetic_truth, write_osm


@given(n=st.integers(0, 200), drops=st.lists(st.integers(0, 250), max_size=5))
def test_history_is_a_list_that_forgets_its_front(n, drops):
    h: History[int] = History()
    for i in range(n):
        h.append(10 * i)
    for d in sorted(drops):
        h.drop_before(d)
    assert len(h) == n
    first = min(max([0] + drops), n)
    assert h.first == first
    for k in range(first, n):
        assert h[k] == 10 * k and h[k - n] == 10 * k
    for k in range(0, first):
        with pytest.raises(IndexError):
            h[k]
    assert [k for k, _ in h.held()] == list(range(first, n))
    if first < n:
        h[-1] = -1
        assert h[n - 1] == -1


def _drive(road: RoadMap, n: int, on_final=None, engines: list | None = None) -> MapFusion:
    """A circular drive with drifting odometry and GPS for its first 120 s; ``engines`` receives the
    engine as soon as it exists (so a callback can look at it)."""
    tr = synthetic_truth("circle", n=n, speed_mps=10.0, radius_m=300.0)
    x, y = tr.x_m, tr.y_m - 300.0
    rng = np.random.default_rng(3)
    drift = np.cumsum(rng.normal(0.0, 0.003, (n, 2)), axis=0)
    lat, lon = road.projection.to_geo(x, y)
    eng = MapFusion(road, FusionConfig(), on_final=on_final)
    if engines is not None:
        engines.append(eng)
    prev = np.eye(4)
    for k in range(n):
        c, s = np.cos(tr.yaw_rad[k]), np.sin(tr.yaw_rad[k])
        cur = np.array([[c, -s, 0, x[k] + drift[k, 0]], [s, c, 0, y[k] + drift[k, 1]], [0, 0, 1, 0], [0, 0, 0, 1.0]])
        if k % 10 == 0 and k < 1200:
            eng.add_gps(tr.t_s[k], lat[k], lon[k], None, 2.0)
        eng.add_odometry(tr.t_s[k], np.linalg.inv(prev) @ cur)
        prev = cur
    eng.finish()
    return eng


@pytest.mark.slow
def test_a_streamed_drive_gives_the_same_estimates_in_bounded_memory(tmp_path):
    road = RoadMap.from_osm(write_osm(tmp_path, [(circle_road(300.0, n=180), {"highway": "primary", "lanes": "2"})]))
    n = 9000  # 900 s: beyond the history, so frames are handed out and forgotten on the way
    whole = _drive(road, n)
    t_whole, online_whole = whole.online_estimates()
    smoothed_whole = whole.trajectory()
    out: list = []
    held: list[int] = []
    engines: list[MapFusion] = []

    def on_final(t, online, smoothed):
        out.append((t, online, smoothed))
        held.append(len(engines[0].track) - engines[0].track.first)

    streamed = _drive(road, n, on_final, engines)
    assert [o[0] for o in out] == list(t_whole)
    for (t, online, smoothed), ref in zip(out, online_whole):
        assert (online is None) == (ref is None)
        if ref is not None:
            assert np.array_equal(online.matrix(), ref.matrix())
        if t in smoothed_whole:
            assert smoothed is not None and np.array_equal(smoothed.matrix(), smoothed_whole[t].matrix())
        else:
            assert smoothed is None
    # while driving, the engine held about the history's frames, never the whole drive
    bound = history_s(FusionConfig()) * 10 + BATCH_FRAMES + 200
    assert max(held[:-1000]) <= bound < n
    assert len(streamed.track) == n and streamed.track.first == n  # everything handed out at the end
