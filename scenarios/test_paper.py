"""The paper's four tables reproduced: the ``droid`` and ``orb-vio`` presets (the paper's DROID-SLAM and
ORB-SLAM3 VIO) beside the paper's figures — Table I on the five KITTI development drives, Tables II–IV on the
families that stand for its Oxford RobotCar, 4Seasons and Singapore drives (``oxford-paper``,
``4seasons-paper``, ``singapore-paper``; docs/scenarios.md says what each column stands for).

- The presets are fitted to the paper's no-map row of Table I: per drive, the median ATE over seeds 1–50 (one
  fusion without the map per run) within ±35% of the paper's, de-localised where the paper's is and not
  elsewhere.
- Map-Fusion on the presets, every table (three seeds a column, the paper's protocol: the mean of the runs, x
  when any de-localised): its average no higher than the paper's Map-Fusion row over the columns both have a
  figure for, and no column worse than without the map by more than 0.3 m.

The tables side by side are printed at the end of ``pytest scenarios/``. Table I needs ``$MAPFUSION_DATA``;
Tables II–IV run on the built-in Helsinki map.
"""

from __future__ import annotations

import pytest

from mapfusion.harness.paper import (TABLE_I, TABLES, PaperTable, both_averages, cells_of, fit_medians, fit_verdicts,
                                     no_map_runs, one_seed, paper_cells, table, table_lines)
from mapfusion.harness.results import Estimator

from .conftest import FAMILIES, REPORTS, family_group, family_results, real_data

pytestmark = [pytest.mark.sumo, pytest.mark.slow]  # minutes of KITTI drives: pytest -m slow (CI)

FIT_SEEDS = list(range(1, 51))  # the seeds the presets were fitted on (docs/method.md: held-out seeds)
FAMILY = "kitti-paper"


@pytest.fixture(scope="module")
def data():
    return real_data("kitti", "Table I needs the KITTI drives")


@pytest.fixture(scope="module")
def fit(data, request):
    from sim.scenario import load_family

    fam = load_family(FAMILIES / f"{FAMILY}.toml")
    runs = no_map_runs(one_seed(list(fam.scenarios)), FIT_SEEDS, workers=request.config.getoption("--scenario-workers"))
    verdicts = fit_verdicts(fit_medians(runs))
    lines = [f"{'preset':>8} {'drive':>5} {'paper':>7} {'median':>7}  fits"]
    lines += [f"{p:>8} {d:>5} {'x' if w is None else f'{w:.2f}':>7} {g:>7.2f}  {'yes' if ok else 'NO'}"
              for p, d, w, g, ok in verdicts]
    REPORTS[f"Table I presets without the map: median ATE over seeds {FIT_SEEDS[0]}–{FIT_SEEDS[-1]} (m)"] = lines
    return verdicts, [r for r in runs if "error" in r]


@pytest.mark.parametrize("preset", list(TABLE_I))
def test_preset_without_the_map_fits_the_papers_table_one(fit, preset):
    verdicts, failed = fit
    assert not failed, failed
    off = [(d, w, round(g, 2)) for p, d, w, g, ok in verdicts if p == preset and not ok]
    assert not off, f"{preset}: drives whose median no-map ATE is not within ±35% of the paper's (drive, paper, " \
                    f"median): {off}"


def _table_rows(request, t: PaperTable) -> list[dict]:
    rows = list(family_results(request.config, t.family).values())
    REPORTS[f"Table {t.number}, {t.dataset}: the paper's rows beside the test bed's ({t.family}, ATE m, "
            "x = de-localised)"] = \
        table_lines(t, rows)
    return rows


@pytest.fixture(scope="module")
def rows(data, request):
    return _table_rows(request, TABLES[0])


def _average_no_higher(t: PaperTable, rows: list[dict], preset: str) -> None:
    ours = cells_of(rows, preset, Estimator.mapfusion, t.family)
    mine, paper, _ = both_averages(ours, paper_cells(t.figures[preset][1]), t.keys())
    assert mine is not None and paper is not None, f"Table {t.number} {preset}: no column both have a figure for"
    assert mine <= paper, f"Table {t.number} {preset}: Map-Fusion's average {mine:.2f} m above the paper's " \
                          f"{paper:.2f} m over the columns both have"


def _never_worse(t: PaperTable, rows: list[dict], preset: str) -> None:
    odo, mf = (cells_of(rows, preset, e, t.family) for e in (Estimator.odometry, Estimator.mapfusion))
    worse = {d: (odo[d].text(), mf[d].text()) for d in odo
             if odo[d].ate_m is not None and (mf[d].ate_m is None or mf[d].ate_m > odo[d].ate_m + 0.3)}
    assert not worse, f"Table {t.number} {preset}: columns where Map-Fusion is worse than the odometry by more " \
                      f"than 0.3 m: {worse}"


@pytest.mark.parametrize("preset", list(TABLE_I))
def test_map_fusion_average_no_higher_than_the_papers(rows, preset):
    _average_no_higher(TABLES[0], rows, preset)


@pytest.mark.parametrize("preset", list(TABLE_I))
def test_map_fusion_never_worse_than_its_odometry_on_a_drive_by_more_than_0_3_m(rows, preset):
    """Per drive, as the paper's table: the mean of its runs with the map against the mean without."""
    _never_worse(TABLES[0], rows, preset)


def _other(number: str, preset: str):
    """A (table, preset) of Tables II–IV, with its strict expected failure where the test bed falls short."""
    why = _SHORT.get((number, preset))
    return pytest.param(number, preset, id=f"{number}-{preset}",
                        marks=_group(number) + ([pytest.mark.xfail(strict=True, reason=why)] if why else []))


def _group(number: str) -> list:
    """Each table's tests on one pytest-xdist worker, its family computed once; the tables spread over workers."""
    return [pytest.mark.xdist_group(family_group(table(number).family))]


#: Where Map-Fusion on a preset does not meet a table's check: the measured figure and the part that falls short.
_SHORT = {
    ("III", "orb-vio"): "Map-Fusion's average over clear, rain and clear + tunnel 2.29 m against the paper's 1.63 m. "
                        "What falls short is the preset between the 5-s RTK fixes: without the map orb-vio errs "
                        "0.76 and 1.61 m in clear and rain against the paper's ORB-SLAM3 0.51 and 0.64 m (its "
                        "creep over the first 8 s of every stand, fitted to KITTI 05 and 07); Map-Fusion's own "
                        "reduction in the tunnel column, 6.32 → 4.58 m, is the paper's (5.49 → 3.80 m)",
}
OTHER = [_other(t.number, p) for t in TABLES[1:] for p in t.figures]


@pytest.mark.parametrize("number,preset", OTHER)
def test_tables_two_to_four_map_fusion_average_no_higher_than_the_papers(request, number, preset):
    t = table(number)
    _average_no_higher(t, _table_rows(request, t), preset)


@pytest.mark.parametrize("number,preset", [pytest.param(t.number, p, id=f"{t.number}-{p}", marks=_group(t.number))
                                           for t in TABLES[1:] for p in t.figures])
def test_tables_two_to_four_map_fusion_never_worse_than_its_odometry_by_more_than_0_3_m(request, number, preset):
    t = table(number)
    _never_worse(t, _table_rows(request, t), preset)
