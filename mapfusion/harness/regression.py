"""Regression checks that tell noise from change: a family's runs against their recorded baselines, with
tolerances taken from the family's measured noise floor (:mod:`mapfusion.harness.noise`).

Per run: Map-Fusion's ATE within :func:`~mapfusion.harness.noise.run_tolerance_m` of its baseline, no new
de-localisation (unless the noise floor saw it flip), the match rate within a point (or its own noise).
Per family, where a few-percent shift shows even when every run is within its own noise: the mean ATE, the
de-localised count and the worst run against the odometry, each within the spread the same figure has over
the noise floor's fusions (:func:`family_tolerance`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .noise import RANGE_FACTOR, run_tolerance_m

#: The smallest tolerance of a family's mean ATE, relative to it: a shift of a few percent must show.
FAMILY_MEAN_MIN_REL = 0.01
#: The smallest tolerance of a family's worst run against the odometry (m).
FAMILY_WORST_MIN_M = 0.05


@dataclass(frozen=True)
class FamilyFigures:
    runs: int
    mean_ate_m: float
    delocalized: int
    worst_vs_odometry_m: float  # the largest ate_mapfusion − ate_odometry of a run

    def line(self) -> str:
        return (f"mean ATE {self.mean_ate_m:.3f} m, de-localised {self.delocalized}/{self.runs}, "
                f"worst against odometry {self.worst_vs_odometry_m:+.3f} m")


def figures(rows: list[dict]) -> FamilyFigures:
    """A family's figures from its rows (runs that failed are left out)."""
    ok = [r for r in rows if "error" not in r]
    if not ok:
        return FamilyFigures(0, float("nan"), 0, float("nan"))
    return FamilyFigures(len(ok), float(np.mean([r["ate_mapfusion_m"] for r in ok])),
                         sum(bool(r["delocalized_mapfusion"]) for r in ok),
                         float(max(r["ate_mapfusion_m"] - r["ate_odometry_m"] for r in ok)))


def _fusions(entries: dict[str, dict]) -> list[list[dict]]:
    """The noise floor's fusions of a family as whole families: draw 0's rows, draw 1's, ..., then each code
    path's (only the runs and fusions every entry has)."""
    ok = {n: e for n, e in entries.items() if e and "draws" in e}
    if not ok:
        return []
    n_draws = min(len(e["draws"]["ate_mapfusion_m"]) for e in ok.values())
    paths = set.intersection(*(set(e.get("code_paths", {})) for e in ok.values()))
    out = [[{k: e["draws"][k][d] for k in e["draws"]} for e in ok.values()] for d in range(n_draws)]
    out += [[e["code_paths"][p] for e in ok.values()] for p in sorted(paths)]
    return out


def family_tolerance(entries: dict[str, dict], stat: Callable[[FamilyFigures], float], floor: float) -> float:
    """How far a family figure may rise above its baseline: :data:`~mapfusion.harness.noise.RANGE_FACTOR`
    times its range over the noise floor's fusions, at least ``floor``."""
    values = [stat(figures(rows)) for rows in _fusions(entries)]
    rng = (max(values) - min(values)) if len(values) > 1 else 0.0
    return max(floor, RANGE_FACTOR * rng)


def check_run(row: dict, base: dict, entry: dict | None) -> list[str]:
    """Why a run regressed against its baseline (empty: it did not)."""
    out = []
    limit = base["ate_mapfusion_m"] + run_tolerance_m(entry, base["ate_mapfusion_m"])
    if row["ate_mapfusion_m"] > limit:
        out.append(f"ATE {row['ate_mapfusion_m']:.3f} m > {limit:.3f} m (baseline {base['ate_mapfusion_m']:.3f})")
    flips = bool(entry and entry.get("delocalized_flips"))
    if not base["delocalized_mapfusion"] and row["delocalized_mapfusion"] and not flips:
        out.append("de-localised where the baseline was not")
    if base.get("match_rate") is not None and row.get("match_rate") is not None:
        mr = [m for m in (entry or {}).get("draws", {}).get("match_rate", []) if m is not None]
        tol = max(0.01, RANGE_FACTOR * (max(mr) - min(mr))) if mr else 0.01
        if row["match_rate"] < base["match_rate"] - tol:
            out.append(f"match rate {row['match_rate']:.3f} < {base['match_rate']:.3f} − {tol:.3f}")
    return out


def check_family(rows: list[dict], baselines: dict[str, dict], noise: dict[str, dict]) -> list[str]:
    """Why a family regressed against its baselines (empty: it did not): its mean ATE, de-localised count
    and worst run against the odometry, over the runs that have a baseline, each against the noise floor's
    spread of the same figure."""
    ok = [r for r in rows if "error" not in r and r["scenario"] in baselines]
    if not ok:
        return []
    now, then = figures(ok), figures([{**baselines[r["scenario"]], "scenario": r["scenario"]} for r in ok])
    entries = {r["scenario"]: noise.get(r["scenario"]) for r in ok}
    out = []
    tol = family_tolerance(entries, lambda f: f.mean_ate_m, FAMILY_MEAN_MIN_REL * then.mean_ate_m)
    if now.mean_ate_m > then.mean_ate_m + tol:
        out.append(f"mean ATE {now.mean_ate_m:.3f} m > {then.mean_ate_m:.3f} + {tol:.3f} m")
    flips = sum(bool(e and e.get("delocalized_flips")) for e in entries.values())
    if now.delocalized > then.delocalized + flips:
        out.append(f"{now.delocalized} de-localised > {then.delocalized} (+{flips} that flip in the noise floor)")
    tol = family_tolerance(entries, lambda f: f.worst_vs_odometry_m, FAMILY_WORST_MIN_M)
    if now.worst_vs_odometry_m > then.worst_vs_odometry_m + tol:
        out.append(f"worst run against odometry {now.worst_vs_odometry_m:+.3f} m > "
                   f"{then.worst_vs_odometry_m:+.3f} + {tol:.3f} m")
    return out


BASELINE_KEYS = ("ate_odometry_m", "ate_mapfusion_m", "delocalized_odometry", "delocalized_mapfusion", "match_rate")


def rerecord(old: dict[str, dict], families: dict[str, dict[str, dict]], noise: dict[str, dict],
             accept_worse: set[str]) -> tuple[dict[str, dict], list[str], list[str]]:
    """New baselines from a session's families: (baselines, a report line per family, the families refused).

    A family whose figures got worse (:func:`check_family` against the old baselines) keeps its old rows
    unless it is named in ``accept_worse``."""
    data = dict(old)
    report, refused = [], []
    for fam, runs in sorted(families.items()):
        rows = [r for r in runs.values() if "error" not in r]
        if not rows:
            continue
        worse = check_family(rows, old, noise)
        before = [r for r in rows if r["scenario"] in old]
        was = figures([{**old[r["scenario"]]} for r in before]) if before else None
        line = f"{fam}: {figures(rows).line()}" + (f" (was {was.line()})" if was else " (new)")
        if worse and fam not in accept_worse:
            refused.append(fam)
            report.append(f"{line} — REFUSED, worse: {'; '.join(worse)} (--accept-worse {fam} to record it)")
            continue
        report.append(line + (f" — accepted worse: {'; '.join(worse)}" if worse else ""))
        for r in rows:
            data[r["scenario"]] = {k: r[k] for k in BASELINE_KEYS}
    return dict(sorted(data.items())), report, refused
