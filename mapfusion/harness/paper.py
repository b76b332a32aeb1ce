"""The paper's Table I beside the test bed's: its KITTI figures for DROID-SLAM and ORB-SLAM3 VIO, without
and with Map-Fusion, and the same drives fused with the ``droid`` and ``orb-vio`` presets.

The paper's protocol (section IV): GPS for initialisation only, ATE after alignment, projected to 2-D;
de-localised (x) above 20 m, and for ORB-SLAM3 also at a map reset; ORB-SLAM3 run three times a drive, the
mean reported, x when any run de-localised. The test bed reports every preset that way over the family's
seeds. The fit of a preset to the paper's no-map row is judged on the median over many seeds
(:func:`no_map_runs`), which costs one fusion without the map per run.
"""

from __future__ import annotations

import dataclasses
import statistics
from pathlib import Path
from .results import Estimator, ate_key, delocalized_key, finished

#: Table I of the paper on the development drives (ATE, m; None = de-localised, the paper's x), by preset:
#: (without the map, with Map-Fusion). DROID-SLAM: stereo, global optimisation off; ORB-SLAM3: stereo VIO
#: with loop closure.
TABLE_I: dict[str, tuple[dict[str, float | None], dict[str, float | None]]] = {
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


def drive_of(row: dict) -> str:
    """The KITTI drive ("00") of a run of a recorded drive."""
    return Path(str(row.get("recorded", ""))).name


@dataclasses.dataclass(frozen=True)
class Cell:
    """One drive of one row of the table: the mean ATE (m) of its runs, or de-localised."""

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


def cells_of(rows: list[dict], preset: str, e: Estimator) -> dict[str, Cell]:
    """Per drive, the runs of ``preset`` scored for estimator ``e`` under the paper's protocol."""
    by: dict[str, list[float | None]] = {}
    for r in rows:
        if finished(r) and r.get("odometry") == preset:
            by.setdefault(drive_of(r), []).append(_ate_or_lost(r, e))
    return {d: paper_cell(v) for d, v in by.items()}


def paper_cells(figures: dict[str, float | None]) -> dict[str, Cell]:
    """A row of the paper's table (ATE m, None = x) as cells, one run each."""
    return {d: paper_cell([v]) for d, v in figures.items()}


def average(cells: dict[str, Cell], drives: list[str]) -> float | None:
    """The mean over the drives not de-localised (the paper's Avg); None when every drive is."""
    vals = [c.ate_m for d in drives if (c := cells.get(d)) is not None and c.ate_m is not None]
    return statistics.fmean(vals) if vals else None


def table_one_lines(rows: list[dict]) -> list[str]:
    """Table I side by side: per preset, the paper's two rows and the test bed's two (mean of the family's
    seeds, x when any de-localised), with the average over the drives not de-localised."""
    drives = sorted(next(iter(TABLE_I.values()))[0])
    head = f"{'ATE (m)':<36}" + "".join(f"{d:>7}" for d in drives) + f"{'Avg':>7}"
    lines = [head]
    for preset, (paper_none, paper_mf) in TABLE_I.items():
        name = METHOD[preset]
        ours = {e: cells_of(rows, preset, e) for e in (Estimator.odometry, Estimator.mapfusion)}
        rows_out = [(f"{name} (paper)", paper_cells(paper_none)),
                    (f"{name} + Map-Fusion (paper)", paper_cells(paper_mf)),
                    (f"{preset} (test bed)", ours[Estimator.odometry]),
                    (f"{preset} + Map-Fusion (test bed)", ours[Estimator.mapfusion])]
        for label, cells in rows_out:
            text = [cells.get(d, Cell(None, 0)).text() for d in drives]
            avg = average(cells, drives)
            avg_text = "x" if avg is None else f"{avg:.2f}"
            lines.append(f"{label:<36}" + "".join(f"{t:>7}" for t in text) + f"{avg_text:>7}")
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


def main(argv: list[str] | None = None) -> int:
    """``python -m mapfusion.harness.paper [--seeds A-B] [--workers N]``: the presets' fit to Table I without the
    map (the median over the seeds of each drive's no-map ATE), as ``scenarios/test_paper.py`` checks it."""
    import argparse

    from sim.scenario import load_family

    ap = argparse.ArgumentParser(prog="python -m mapfusion.harness.paper", description=main.__doc__)
    ap.add_argument("--seeds", default="1-50", help="seeds A-B (inclusive)")
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args(argv)
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
