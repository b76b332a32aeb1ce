"""The realism checks' own arithmetic (issue 22): the ±30% range test and the verdict pairing."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from mapfusion.harness.realism import DRIVES, RANGE_SLACK, StatRow, verdict, verdict_pairs, within_real_range


def _row(drive: str, t_err: float) -> StatRow:
    return StatRow(drive, "x", t_err, 1.0, 0.0, 0.0, 0.0, 0.0)


@given(lo=st.floats(0.1, 10.0), span=st.floats(0.0, 10.0), x=st.floats(0.0, 40.0))
def test_a_figure_is_inside_exactly_when_within_the_widened_real_range(lo, span, x):
    real = [_row("00", lo), _row("01", lo + span)]
    outside = within_real_range([_row("05", x)], real, "t_err_percent")
    inside = lo * (1 - RANGE_SLACK) <= x <= (lo + span) * (1 + RANGE_SLACK)  # RANGE_SLACK is the 30%
    assert RANGE_SLACK == 0.30
    assert (not outside) == inside


def test_verdict_is_better_only_when_the_map_lowers_the_ate():
    assert verdict({"ate_odometry_m": 2.0, "ate_mapfusion_m": 1.0}) == "better"
    assert verdict({"ate_odometry_m": 2.0, "ate_mapfusion_m": 2.0}) == "worse"
    assert verdict({"error": "boom"}) is None


def test_simulated_verdict_is_that_of_the_mean_over_seeds_and_pairs_match_by_drive_and_method():
    # seed 1 much better with the map, seeds 2 and 3 slightly worse: the mean says better
    sim = [{"scenario": f"kitti-realism-00-vo-s{s}", "ate_odometry_m": o, "ate_mapfusion_m": m}
           for s, o, m in ((1, 20.0, 5.0), (2, 5.0, 5.5), (3, 5.0, 5.5))]
    real = [{"scenario": "kitti-real-00-cvo_stereo_00-s1", "ate_odometry_m": 38.8, "ate_mapfusion_m": 5.6},
            {"scenario": "kitti-real-00-trianflow_00-s1", "ate_odometry_m": 64.5, "ate_mapfusion_m": 66.6}]
    pairs = {(d, p): (s, r) for d, p, s, r in verdict_pairs(sim, real)}
    assert len(pairs) == 2 * len(DRIVES)
    assert pairs[("00", "vo")] == ("better", "better")
    assert pairs[("00", "mono")] == (None, "worse")  # no simulated mono run: no verdict, never agreement
    assert pairs[("01", "vo")] == (None, None)
