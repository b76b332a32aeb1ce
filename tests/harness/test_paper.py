"""Table I beside the paper's: the paper's protocol over repeated runs, the fit verdicts, the printed table."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from mapfusion.harness.paper import (FIT_TOLERANCE, TABLE_I, Cell, average, fit_medians, fit_verdicts, paper_cell,
                                     table_one_lines, cells_of)
from mapfusion.harness.results import Estimator

_ATE = st.floats(0.01, 19.99)


@given(st.lists(st.one_of(st.none(), _ATE), min_size=1, max_size=5))
def test_a_drive_is_x_when_any_run_is_and_else_the_mean(ates):
    c = paper_cell(ates)
    assert c.runs == len(ates)
    if None in ates:
        assert c.ate_m is None and c.text() == "x"
    else:
        assert c.ate_m is not None and math.isclose(c.ate_m, sum(ates) / len(ates))


def test_no_run_is_no_figure():
    assert paper_cell([]).text() == "–"


def _row(drive: str, preset: str, seed: int, odo: float, mf: float, lost: bool = False) -> dict:
    return {"scenario": f"kitti-paper-{drive}-{preset}-s{seed}", "seed": seed, "odometry": preset,
            "recorded": f"/data/kitti/{drive}", "ate_odometry_m": odo, "ate_mapfusion_m": mf,
            "delocalized_odometry": lost or odo > 20, "delocalized_mapfusion": lost or mf > 20}


def test_cells_of_group_by_drive_and_preset():
    rows = [_row("00", "droid", 1, 3.0, 2.0), _row("00", "droid", 2, 5.0, 4.0), _row("00", "orb-vio", 1, 1.0, 1.0),
            _row("01", "droid", 1, 50.0, 30.0), _row("01", "droid", 2, 2.0, 1.0), {"scenario": "failed", "error": "x"}]
    cells = cells_of(rows, "droid", Estimator.odometry)
    assert cells["00"] == Cell(4.0, 2) and cells["01"] == Cell(None, 2)
    assert cells_of(rows, "droid", Estimator.mapfusion)["00"] == Cell(3.0, 2)
    assert average(cells, ["00", "01"]) == 4.0  # the de-localised drive left out, as the paper's Avg


@given(st.floats(0.1, 30.0), st.floats(0.0, 100.0))
def test_a_preset_fits_within_the_tolerance_and_lost_only_where_the_paper_is(paper, got):
    table = {"_t": ({"00": paper, "01": None}, {"00": None, "01": None})}
    v = {(p, d): ok for p, d, _, _, ok in fit_verdicts({("_t", "00"): got, ("_t", "01"): got}, table)}
    assert v[("_t", "00")] == (abs(got - paper) <= FIT_TOLERANCE * paper)
    assert v[("_t", "01")] == (got > 20.0)


def test_fit_medians_count_a_lost_run_as_infinite():
    runs = [{"preset": "droid", "drive": "00", "ate_m": a, "delocalized": a > 20} for a in (1.0, 2.0, 30.0)]
    runs += [{"preset": "droid", "drive": "01", "ate_m": 3.0, "delocalized": True} for _ in range(2)]
    runs += [{"preset": "droid", "drive": "01", "ate_m": 1.0, "delocalized": False}, {"error": "boom"}]
    med = fit_medians(runs)
    assert med[("droid", "00")] == 2.0 and med[("droid", "01")] == math.inf  # a reset de-localises at 3 m


def test_table_one_prints_the_papers_rows_beside_the_test_beds():
    rows = [_row(d, p, s, 3.0, 2.0) for d in ("00", "01", "02", "05", "07") for p in TABLE_I for s in (1, 2, 3)]
    lines = table_one_lines(rows)
    assert lines[0].split()[-6:] == ["00", "01", "02", "05", "07", "Avg"]
    paper = next(line for line in lines if line.startswith("DROID-SLAM (paper)"))
    assert paper.split()[-6:] == ["2.98", "x", "5.77", "2.29", "1.01", f"{(2.98 + 5.77 + 2.29 + 1.01) / 4:.2f}"]
    ours = next(line for line in lines if line.startswith("orb-vio + Map-Fusion (test bed)"))
    assert ours.split()[-6:] == ["2.00"] * 6
    assert len(lines) == 1 + 4 * len(TABLE_I)
