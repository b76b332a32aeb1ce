"""The paper's tables beside the test bed's: the paper's protocol over repeated runs, the columns of a family's
runs, the averages compared, the fit verdicts, the printed tables."""

from __future__ import annotations

import json
import math
from pathlib import Path

from hypothesis import given
from hypothesis import strategies as st

from mapfusion.harness.paper import (FIT_TOLERANCE, TABLE_I, TABLES, Cell, average, both_averages, cells_of,
                                     column_of, fit_medians, fit_verdicts, paper_cell, paper_cells, table,
                                     table_lines)
from mapfusion.harness.results import Estimator

FAMILIES = Path(__file__).resolve().parents[2] / "scenarios" / "families"

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
    lines = table_lines(table("I"), rows)
    assert lines[0].split()[-6:] == ["00", "01", "02", "05", "07", "Avg"]
    paper = next(line for line in lines if line.startswith("DROID-SLAM (paper)"))
    assert paper.split()[-6:] == ["2.98", "x", "5.77", "2.29", "1.01", f"{(2.98 + 5.77 + 2.29 + 1.01) / 4:.2f}"]
    ours = next(line for line in lines if line.startswith("orb-vio + Map-Fusion (test bed)"))
    assert ours.split()[-6:] == ["2.00"] * 6
    assert len(lines) == 1 + 4 * len(TABLE_I)


def test_a_runs_column_is_its_name_without_family_preset_and_seed():
    row = {"scenario": "oxford-paper-rain-40-s2", "seed": 2, "odometry": "droid"}
    assert column_of(row, "oxford-paper") == "rain-40"
    assert column_of({"scenario": "4seasons-paper-orb-vio-clear-False-s12", "seed": 12, "odometry": "orb-vio"},
                     "4seasons-paper") == "clear-False"
    assert column_of({"scenario": "x-s1-s1", "seed": 1, "odometry": "droid", "recorded": "/d/kitti/05"}, "x") == "05"


def test_every_family_of_a_table_names_its_columns_by_its_zip():
    """The column keys of each table are the run names' zip slugs of its family file, one column per zip entry,
    and every preset row names every column."""
    from sim.scenario import load_family

    for t in TABLES[1:]:
        fam = load_family(FAMILIES / f"{t.family}.toml")
        found = {column_of({"scenario": sc.name, "seed": sc.seed, "odometry": sc.odometry.kind.value}, t.family)
                 for sc in fam.scenarios}
        assert found == set(t.keys()), t.number
        assert {sc.odometry.kind.value for sc in fam.scenarios} == set(t.figures), t.number
        for none, mf in t.figures.values():
            assert set(none) == set(mf) == set(t.keys()), t.number


@given(st.lists(st.one_of(st.none(), _ATE), min_size=3, max_size=3),
       st.lists(st.one_of(st.none(), _ATE), min_size=3, max_size=3))
def test_averages_are_compared_over_the_columns_both_have(ours_v, paper_v):
    cols = ["a", "b", "c"]
    ours, paper = (paper_cells(dict(zip(cols, v))) for v in (ours_v, paper_v))
    o, p, lost = both_averages(ours, paper, cols)
    common = [i for i in range(3) if ours_v[i] is not None and paper_v[i] is not None]
    if not common:
        assert o is None and p is None
    else:
        assert math.isclose(o, sum(ours_v[i] for i in common) / len(common))
        assert math.isclose(p, sum(paper_v[i] for i in common) / len(common))
    assert lost == [c for i, c in enumerate(cols) if paper_v[i] is not None and ours_v[i] is None]


def test_a_table_beyond_the_first_prints_what_each_column_stands_for():
    t = table("II")
    rows = [{"scenario": f"{t.family}-{k}-s{s}", "seed": s, "odometry": "droid", "ate_odometry_m": 8.0,
             "ate_mapfusion_m": 4.0, "delocalized_odometry": False, "delocalized_mapfusion": False}
            for k in t.keys() for s in (1, 2, 3)]
    lines = table_lines(t, rows)
    assert lines[0].split()[-1] == "Avg" and len(lines) == 1 + 4 * len(t.figures) + len(t.columns)
    ours = next(line for line in lines if line.startswith("droid + Map-Fusion (test bed)"))
    assert ours.split()[-5:] == ["4.00"] * 5
    assert any("2014-11-21-16-07-03" in line and "heavy rain" in line for line in lines)


def test_a_table_prints_from_a_results_file_and_bad_input_exits_2(tmp_path, capsys):
    from mapfusion.harness.paper import main

    t = table("IV")
    rows = [{"scenario": f"{t.family}-{k}-s1", "seed": 1, "odometry": "droid", "ate_odometry_m": 3.0,
             "ate_mapfusion_m": 2.5, "delocalized_odometry": False, "delocalized_mapfusion": False} for k in t.keys()]
    f = tmp_path / "results.jsonl"
    f.write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert main(["--table", "iv", str(f)]) == 0
    out = capsys.readouterr().out
    assert "droid + Map-Fusion (test bed)" in out and "7.02" in out
    assert main(["--table", "V", str(f)]) == 2
    assert main(["--table", "II", str(tmp_path / "missing.jsonl")]) == 2
    err = capsys.readouterr().err
    assert "no table 'V'" in err and "missing.jsonl" in err
