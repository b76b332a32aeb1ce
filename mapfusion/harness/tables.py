"""The paper-style tables (rich), from result rows; every average comes from
:func:`mapfusion.harness.results.summarise`."""

from __future__ import annotations

from pathlib import Path

from rich.table import Table

from .results import Estimator, ate_key, delocalized_key, finished, summarise

_O, _M = Estimator.odometry, Estimator.mapfusion


def _fmt(v: float) -> str:
    return "–" if v != v else f"{v:.2f}"  # NaN: no run to average


def _cell(r: dict, e: Estimator) -> str:
    if not finished(r):
        return "failed"
    return "x" if r[delocalized_key(e)] else f"{r[ate_key(e)]:.2f}"


def others(rows: list[dict]) -> list[str]:
    """The plug-in estimators ([[estimators]]) the rows scored, in their order of first appearance."""
    names: list[str] = []
    for r in rows:
        names += [n for n in r.get("estimators", []) if n not in names]
    return names


def _other_cell(r: dict, name: str) -> str:
    if not finished(r) or name in r.get("estimator_errors", {}):
        return "failed"
    if ate_key(name) not in r:
        return "–"
    return "x" if r[delocalized_key(name)] else f"{r[ate_key(name)]:.2f}"


def _other_average(rows: list[dict], name: str) -> str:
    kept = [r[ate_key(name)] for r in rows if finished(r) and ate_key(name) in r and not r[delocalized_key(name)]]
    return _fmt(sum(kept) / len(kept) if kept else float("nan"))


def _reduction(r: dict) -> str:
    if not finished(r) or r[delocalized_key(_O)] or r[delocalized_key(_M)]:
        return "NA"
    return f"{r['ate_reduction_m']:.2f}"


def paper_table(rows: list[dict], title: str, strip_prefix: str = "", width: int | None = None) -> Table:
    """Runs as columns, rows odometry / + Map-Fusion / reduction (ATE, m), then a row per plug-in estimator;
    x = de-localised; the average leaves the de-localised runs out, as the paper's tables do. When the columns
    would not fit in ``width`` characters, the same table turned: a row per run, then Avg."""
    names = [r["scenario"].removeprefix(strip_prefix) for r in rows]
    extra = others(rows)
    s = summarise(rows)
    averages = (_fmt(s.paper_odometry_m), _fmt(s.paper_mapfusion_m), _fmt(s.paper_reduction_m))
    t = Table(title=title, show_lines=False)
    needed = len("+ Map-Fusion") + sum(max(len(n), 7) + 3 for n in names) + 10
    if width is not None and needed > width:
        t.add_column("run", no_wrap=True)
        for c in ("odometry", "+ Map-Fusion", "reduction", *extra):
            t.add_column(c, justify="right")
        for n, r in zip(names, rows):
            t.add_row(n, _cell(r, _O), _cell(r, _M), _reduction(r), *[_other_cell(r, e) for e in extra])
        t.add_row("Avg", *averages, *[_other_average(rows, e) for e in extra], style="bold")
        return t
    t.add_column("ATE (m)", no_wrap=True)
    for n in names:
        t.add_column(n, justify="right")
    t.add_column("Avg", justify="right", style="bold")
    t.add_row("odometry", *[_cell(r, _O) for r in rows], averages[0])
    t.add_row("+ Map-Fusion", *[_cell(r, _M) for r in rows], averages[1])
    t.add_row("reduction", *[_reduction(r) for r in rows], averages[2], style="italic")
    for e in extra:
        t.add_row(e, *[_other_cell(r, e) for r in rows], _other_average(rows, e))
    return t


def table_one(rows: list[dict], title: str) -> Table:
    """The paper's Table I layout for recorded drives: sequences as columns, for each odometry kind ×
    weather the rows odometry / + Map-Fusion / reduction (ATE, m). A cell over several seeds is the
    paper average of its runs; x = every seed de-localised; Avg leaves de-localised cells out, as
    the paper does."""
    def seq(r: dict) -> str:
        return Path(r.get("recorded", r["scenario"])).name

    columns = sorted({seq(r) for r in rows})
    extra = others(rows)
    groups = sorted({(r.get("odometry", "?"), r.get("weather", "?")) for r in rows})
    t = Table(title=title, show_lines=False)
    t.add_column("ATE (m)", no_wrap=True)
    for c in columns:
        t.add_column(c, justify="right")
    t.add_column("Avg", justify="right", style="bold")
    for odo, weather in groups:
        cells: list[tuple[str, float, float]] = []  # (state, odometry, Map-Fusion) per sequence
        for c in columns:
            runs = [r for r in rows if seq(r) == c and (r.get("odometry"), r.get("weather")) == (odo, weather)]
            s = summarise(runs)
            state = "" if not runs else "failed" if not s.runs else "ok"
            cells.append((state, s.paper_odometry_m, s.paper_mapfusion_m))

        def show(state: str, v: float) -> str:
            return state if state != "ok" else ("x" if v != v else f"{v:.2f}")

        def avg(vals: list[float]) -> str:
            vals = [v for v in vals if v == v]
            return f"{sum(vals) / len(vals):.2f}" if vals else "–"

        ok = [(a, b) for st, a, b in cells if st == "ok"]
        both = [(a, b) for a, b in ok if a == a and b == b]
        label = f"{odo.upper()} {weather.replace('_', ' ')}"
        t.add_row(label, *[show(st, a) for st, a, _ in cells], avg([a for a, _ in ok]))
        t.add_row(f"{label} + Map-Fusion", *[show(st, b) for st, _, b in cells], avg([b for _, b in ok]))
        red = [f"{a - b:.2f}" if st == "ok" and a == a and b == b else "NA" for st, a, b in cells]
        t.add_row("reduction", *red, avg([a - b for a, b in both]), style="italic", end_section=not extra)
        for n, e in enumerate(extra):  # the plug-in estimators: the paper average of their runs per sequence
            vals = []
            for c in columns:
                runs = [r for r in rows if seq(r) == c and (r.get("odometry"), r.get("weather")) == (odo, weather)]
                scored = [r for r in runs if finished(r) and ate_key(e) in r]
                kept = [r[ate_key(e)] for r in scored if not r[delocalized_key(e)]]
                state = "" if not runs else "ok" if scored else "failed"
                vals.append((state, sum(kept) / len(kept) if kept else float("nan")))
            t.add_row(f"{label} {e}", *[show(st, v) for st, v in vals], avg([v for st, v in vals if st == "ok"]),
                      end_section=n == len(extra) - 1)
    return t


def family_summary_line(rows: list[dict]) -> str:
    """One line under a family's table: means over every run, de-localised counts, match rate."""
    ok = [r for r in rows if finished(r)]
    if not ok:
        return ""
    s = summarise(ok)
    rates = [r["match_rate"] for r in ok if r.get("match_rate") is not None]
    line = (f"  mean ATE over all runs: odometry {s.mean_odometry_m:.2f} m, + Map-Fusion {s.mean_mapfusion_m:.2f} m "
            f"(reduction {100 * s.reduction_fraction:.0f}%); de-localised {s.delocalized_odometry} → "
            f"{s.delocalized_mapfusion} of {s.runs}")
    if rates:
        line += f"; match rate {100 * sum(rates) / len(rates):.1f}%"
    return line
