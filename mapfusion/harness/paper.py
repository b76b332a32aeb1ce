"""The paper's tables beside the test bed's: its figures for DROID-SLAM and ORB-SLAM3 VIO, without and with
Map-Fusion, and the families that stand for its datasets fused with the ``droid`` and ``orb-vio`` presets.

The paper's protocol (section IV): ATE after alignment, projected to 2-D; de-localised (x) above 20 m, and for
ORB-SLAM3 also at a map reset; ORB-SLAM3 run three times a sequence, the mean reported, x when any run
de-localised. The test bed reports every preset that way over a family's seeds: a column is one kind of drive
(a KITTI drive, or a simulated stand-in for one of the paper's sequences), its figure the mean of its runs.
The fit of a preset to the paper's no-map row of Table I is judged on the median over many seeds
(:func:`no_map_runs`), which costs one fusion without the map per run.
"""

from __future__ import annotations

import dataclasses
import statistics
from pathlib import Path
from .results import Estimator, ate_key, delocalized_key, finished

Figures = dict[str, float | None]  # ATE (m) by column; None = de-localised, the paper's x

#: Table I of the paper on the development drives, by preset: (without the map, with Map-Fusion). DROID-SLAM:
#: stereo, global optimisation off; ORB-SLAM3: stereo VIO with loop closure.
TABLE_I: dict[str, tuple[Figures, Figures]] = {
    "droid": ({"00": 2.98, "01": None, "02": 5.77, "05": 2.29, "07": 1.01},
              {"00": 2.20, "01": None, "02": 3.18, "05": 3.14, "07": 1.02}),
    "orb-vio": ({"00": None, "01": 3.93, "02": 13.43, "05": 2.60, "07": 2.32},
                {"00": None, "01": 2.88, "02": 4.61, "05": 2.36, "07": 1.19}),
}
#: The paper's name of each preset's method.
METHOD = {"droid": "DROID-SLAM", "orb-vio": "ORB-SLAM3 VIO"}
#: A preset's no-map ATE must lie within this share of the paper's, per drive (median over seeds).
FIT_TOLERANCE = 0.35
#: A run is de-localised above this ATE (m), as in the paper.
DELOCALISED_M = 20.0


@dataclasses.dataclass(frozen=True)
class Column:
    """A column of a table: ``key`` names its runs (:func:`column_of`), ``heading`` heads it, ``paper`` is the
    paper's sequence and ``stand_in`` the test bed's drive that stands for it."""

    key: str
    heading: str
    paper: str
    stand_in: str


@dataclasses.dataclass(frozen=True)
class PaperTable:
    """One of the paper's tables: its dataset, the family standing for it, its columns and, per preset, the
    paper's two rows (without the map, with Map-Fusion)."""

    number: str
    dataset: str
    family: str  # scenarios/families/<family>.toml
    columns: tuple[Column, ...]
    figures: dict[str, tuple[Figures, Figures]]
    gps: str = ""  # the GPS the paper's rows had beyond initialisation ("+ GPS every 5s")

    def keys(self) -> list[str]:
        return [c.key for c in self.columns]


def _kitti(drive: str) -> Column:
    return Column(drive, drive, f"KITTI {drive}", f"the real drive {drive}, simulated odometry")


_ZONE = "1000.0-1600.0"  # 4seasons-paper's tunnel zone (m along the route), as its runs' names spell it

TABLES: tuple[PaperTable, ...] = (
    PaperTable("I", "KITTI", "kitti-paper", tuple(_kitti(d) for d in ("00", "01", "02", "05", "07")), TABLE_I),
    PaperTable("II", "Oxford RobotCar", "oxford-paper", (
        Column("clear-0", "clear", "2014-12-09-13-21-02 (clear)", "Helsinki, clear"),
        Column("rain-0", "rain", "2015-10-29-12-18-17 (rain)", "Helsinki, rain"),
        Column("rain-40", "rain+tr", "2014-11-25-09-18-32 (rain)", "Helsinki, rain, 40 other vehicles"),
        Column("heavy_rain-0", "r+night", "2014-11-21-16-07-03 (rain + night)", "Helsinki, heavy rain"),
    ), {"droid": ({"clear-0": 10.19, "rain-0": 10.36, "rain-40": 18.18, "heavy_rain-0": None},
                  {"clear-0": 3.44, "rain-0": 4.02, "rain-40": 10.07, "heavy_rain-0": None})}),
    PaperTable("III", "4Seasons", "4seasons-paper", (
        Column("clear-False-none", "clear", "neighborhood_2_train (clear)", "Helsinki, clear"),
        Column("rain-False-none", "rain", "neighborhood_3_train (rain)", "Helsinki, rain"),
        Column(f"clear-True-{_ZONE}", "clear+t", "city_loop_3_train (clear + tunnel)",
               "Helsinki, clear, a 600 m tunnel"),
        Column(f"rain-True-{_ZONE}", "rain+t", "city_loop_1_train (rain + tunnel)", "Helsinki, rain, a 600 m tunnel"),
    ), {"droid": ({"clear-False-none": 0.50, "rain-False-none": 0.56, f"clear-True-{_ZONE}": None,
                   f"rain-True-{_ZONE}": None},
                  {"clear-False-none": 0.49, "rain-False-none": 0.57, f"clear-True-{_ZONE}": None,
                   f"rain-True-{_ZONE}": None}),
        "orb-vio": ({"clear-False-none": 0.51, "rain-False-none": 0.64, f"clear-True-{_ZONE}": 5.49,
                     f"rain-True-{_ZONE}": None},
                    {"clear-False-none": 0.50, "rain-False-none": 0.60, f"clear-True-{_ZONE}": 3.80,
                     f"rain-True-{_ZONE}": None})},
        gps=" + GPS every 5s"),
    PaperTable("IV", "Singapore", "singapore-paper", (
        Column("4500.0", "Zero", "Zero (heavy rain)", "Helsinki, heavy rain, a route of 4.5 km or more"),
        Column("3000.0", "One", "One (heavy rain)", "Helsinki, heavy rain, 3 km or more"),
        Column("1500.0", "Five", "Five (heavy rain)", "Helsinki, heavy rain, 1.5 km or more"),
    ), {"droid": ({"4500.0": 7.88, "3000.0": 2.82, "1500.0": 1.57}, {"4500.0": 7.02, "3000.0": 2.58, "1500.0": 1.19})},
        gps=" + GPS every 5s"),
)


def table(number: str) -> PaperTable:
    """The paper's table ``number`` ("I" … "IV")."""
    return next(t for t in TABLES if t.number == number)


def drive_of(row: dict) -> str:
    """The KITTI drive ("00") of a run of a recorded drive."""
    return Path(str(row.get("recorded", ""))).name


def column_of(row: dict, family: str = "") -> str:
    """The column of a run: its KITTI drive, or its name without ``family``, the preset and the seed (the
    slugs of the family's ``zip`` values: ``oxford-paper-rain-40-s2`` → ``rain-40``)."""
    if row.get("recorded"):
        return drive_of(row)
    name = str(row.get("scenario", "")).removeprefix(f"{family}-").removesuffix(f"-s{row.get('seed')}")
    return name.removeprefix(f"{row.get('odometry')}-")


@dataclasses.dataclass(frozen=True)
class Cell:
    """One column of one row of a table: the mean ATE (m) of its runs, or de-localised."""

    ate_m: float | None  # None: de-localised (x)
    runs: int

    def text(self) -> str:
        if self.runs == 0:
            return "–"
        return "x" if self.ate_m is None else f"{self.ate_m:.2f}"


def paper_cell(ates_m: list[float | None]) -> Cell:
    """The paper's protocol over repeated runs: x when any run de-localised, else their mean."""
    if not ates_m:
        return Cell(None, 0)
    if any(a is None for a in ates_m):
        return Cell(None, len(ates_m))
    return Cell(statistics.fmean(a for a in ates_m if a is not None), len(ates_m))


def _ate_or_lost(row: dict, e: Estimator) -> float | None:
    return None if row[delocalized_key(e)] else float(row[ate_key(e)])


def cells_of(rows: list[dict], preset: str, e: Estimator, family: str = "") -> dict[str, Cell]:
    """Per column, the runs of ``preset`` (of ``family``) scored for estimator ``e`` under the paper's protocol."""
    by: dict[str, list[float | None]] = {}
    for r in rows:
        if finished(r) and r.get("odometry") == preset:
            by.setdefault(column_of(r, family), []).append(_ate_or_lost(r, e))
    return {d: paper_cell(v) for d, v in by.items()}


def paper_cells(figures: Figures) -> dict[str, Cell]:
    """A row of the paper's table (ATE m, None = x) as cells, one run each."""
    return {d: paper_cell([v]) for d, v in figures.items()}


def average(cells: dict[str, Cell], columns: list[str]) -> float | None:
    """The mean over the columns not de-localised (the paper's Avg); None when every column is."""
    vals = [c.ate_m for d in columns if (c := cells.get(d)) is not None and c.ate_m is not None]
    return statistics.fmean(vals) if vals else None


def both_averages(ours: dict[str, Cell], paper: dict[str, Cell], columns: list[str]
                  ) -> tuple[float | None, float | None, list[str]]:
    """Our and the paper's averages over the columns both have a figure for, and the columns we lose where the
    paper does not (a comparison of averages over different columns would reward losing a hard drive)."""
    common = [c for c in columns if (o := ours.get(c)) is not None and o.ate_m is not None
              and (p := paper.get(c)) is not None and p.ate_m is not None]
    lost = [c for c in columns if (p := paper.get(c)) is not None and p.ate_m is not None
            and ((o := ours.get(c)) is None or o.ate_m is None)]
    return average(ours, common), average(paper, common), lost


def table_lines(t: PaperTable, rows: list[dict]) -> list[str]:
    """Table ``t`` side by side: per preset, the paper's two rows and the test bed's two (mean of the family's
    seeds, x when any de-localised) with the average over the columns not de-localised; then what each
    column stands for."""
    keys = t.keys()
    width = max(7, *(len(c.heading) + 1 for c in t.columns))
    label_w = 36 + len(t.gps)
    lines = [f"{'ATE (m)':<{label_w}}" + "".join(f"{c.heading:>{width}}" for c in t.columns) + f"{'Avg':>7}"]
    for preset, (paper_none, paper_mf) in t.figures.items():
        name = METHOD[preset]
        ours = {e: cells_of(rows, preset, e, t.family) for e in (Estimator.odometry, Estimator.mapfusion)}
        rows_out = [(f"{name}{t.gps} (paper)", paper_cells(paper_none)),
                    (f"{name} + Map-Fusion{t.gps} (paper)", paper_cells(paper_mf)),
                    (f"{preset} (test bed)", ours[Estimator.odometry]),
                    (f"{preset} + Map-Fusion (test bed)", ours[Estimator.mapfusion])]
        for label, cells in rows_out:
            text = [cells.get(k, Cell(None, 0)).text() for k in keys]
            avg = average(cells, keys)
            avg_text = "x" if avg is None else f"{avg:.2f}"
            lines.append(f"{label:<{label_w}}" + "".join(f"{x:>{width}}" for x in text) + f"{avg_text:>7}")
    if t.number != "I":
        lines += [f"  {c.heading}: {c.paper} ← {c.stand_in}" for c in t.columns]
    return lines


# ----------------------------------------------------------------------------- the fit without the map
def _no_map_runs(job: tuple) -> list[dict]:
    """One scenario fused without the map once per seed (one process: the map read once)."""
    from mapfusion.config import FusionConfig
    from mapfusion.replay import fuse

    from .pipeline import _evaluate, fixes_of, map_resets, motion_of, simulate_scenario

    base, seeds = job
    out = []
    for seed in seeds:
        sim = simulate_scenario(dataclasses.replace(base, seed=seed, name=f"{base.name}-n{seed}"))
        odo = sim.sensors.odometry
        res = fuse(sim.road, odo.t_s, odo.poses, fixes_of(sim.sensors, sim.road),
                   dataclasses.replace(FusionConfig(), use_map=False), motion=motion_of(sim.sensors))
        m = _evaluate(res, sim.truth, Estimator.odometry, DELOCALISED_M)
        resets, reset_lost = map_resets(sim)
        out.append({"drive": Path(base.truth).name, "preset": base.odometry.kind.value, "seed": seed,
                    "ate_m": m[ate_key(Estimator.odometry)], "map_resets": resets,
                    "delocalized": m[delocalized_key(Estimator.odometry)] or reset_lost})
    return out


def one_seed(scenarios: list) -> list:
    """A family's scenarios of its first seed: one per drive and preset, for :func:`no_map_runs` to seed."""
    return [sc for sc in scenarios if sc.seed == scenarios[0].seed]


def no_map_runs(scenarios: list, seeds: list[int], workers: int = 2) -> list[dict]:
    """Every scenario fused without the map once per seed (a process per scenario): rows of drive, preset,
    seed, ATE (m), map resets and whether the run de-localised; a scenario that failed gives one row with
    ``error``."""
    from .batch import run_tasks

    out: list[dict] = []
    run_tasks([(sc, list(seeds)) for sc in scenarios], _no_map_runs, workers=workers,
              on_rows=lambda job, rows: out.extend(rows),
              on_failure=lambda job, err: out.append({"drive": Path(job[0].truth).name,
                                                      "preset": job[0].odometry.kind.value, "error": err["error"]}))
    return out


def fit_medians(runs: list[dict]) -> dict[tuple[str, str], float]:
    """The median no-map ATE (m) per (preset, drive); a de-localised run counts as infinite."""
    by: dict[tuple[str, str], list[float]] = {}
    for r in runs:
        if "error" in r:
            continue
        by.setdefault((r["preset"], r["drive"]), []).append(float("inf") if r["delocalized"] else r["ate_m"])
    return {k: float(statistics.median(v)) for k, v in by.items()}


def fit_verdicts(medians: dict[tuple[str, str], float], table: dict | None = None
                 ) -> list[tuple[str, str, float | None, float, bool]]:
    """Per (preset, drive) of ``table`` (Table I): (preset, drive, the paper's no-map ATE or None, the median,
    whether it fits): within ±FIT_TOLERANCE of the paper's, de-localised (median above 20 m) where the
    paper's is, and not elsewhere."""
    out = []
    for preset, (paper, _) in (TABLE_I if table is None else table).items():
        for d, want in sorted(paper.items()):
            got = medians.get((preset, d), float("nan"))
            ok = got > DELOCALISED_M if want is None else abs(got - want) <= FIT_TOLERANCE * want
            out.append((preset, d, want, got, bool(ok)))
    return out


def _print_table(number: str, results: str) -> int:
    """Print table ``number`` from a family run's results.jsonl (``mapfusion run FAMILY --out DIR``)."""
    import json
    import sys

    try:
        t = table(number.upper())
    except StopIteration:
        print(f"no table {number!r} (the paper's are {', '.join(t.number for t in TABLES)})", file=sys.stderr)
        return 2
    try:
        with open(results, encoding="utf-8") as f:
            rows = [json.loads(line) for line in f if line.strip()]
    except (OSError, ValueError) as exc:
        print(f"{results}: {exc}", file=sys.stderr)
        return 2
    print(*table_lines(t, rows), sep="\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m mapfusion.harness.paper [--seeds A-B] [--workers N]``: the presets' fit to Table I without the
    map (the median over the seeds of each drive's no-map ATE), as ``scenarios/test_paper.py`` checks it.
    ``python -m mapfusion.harness.paper --table II DIR/results.jsonl``: one of the paper's tables beside a run of
    its family."""
    import argparse

    from sim.scenario import load_family

    ap = argparse.ArgumentParser(prog="python -m mapfusion.harness.paper", description=main.__doc__)
    ap.add_argument("--seeds", default="1-50", help="seeds A-B (inclusive)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--table", help="print this table (I … IV) from the results file given after it")
    ap.add_argument("results", nargs="?", help="a family run's results.jsonl (with --table)")
    a = ap.parse_args(argv)
    if a.table:
        if not a.results:
            ap.error("--table needs a results.jsonl")
        return _print_table(a.table, a.results)
    lo, _, hi = a.seeds.partition("-")
    seeds = list(range(int(lo), int(hi or lo) + 1))
    fam = load_family(Path(__file__).resolve().parents[2] / "scenarios" / "families" / "kitti-paper.toml")
    if not fam.scenarios:
        print(f"no runs: {fam.unavailable[0][1] if fam.unavailable else 'the family is empty'}")
        return 2
    verdicts = fit_verdicts(fit_medians(no_map_runs(one_seed(list(fam.scenarios)), seeds, workers=a.workers)))
    print(f"median no-map ATE over seeds {seeds[0]}-{seeds[-1]} (m), against the paper's Table I (±35%)")
    for p, d, w, g, ok in verdicts:
        paper = "x" if w is None else f"{w:.2f}"
        print(f"{p:>8} {d:>3}  paper {paper:>6}  test bed {g:7.2f}  {'fits' if ok else 'OFF'}")
    return 0 if all(v[-1] for v in verdicts) else 1


if __name__ == "__main__":
    raise SystemExit(main())
