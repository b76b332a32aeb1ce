"""Parameter grids and Optuna studies over engine parameters (``mapfusion sweep`` / ``mapfusion tune``).

Both simulate each scenario once and fuse it many times: the drive and the sensors do not depend
on engine parameters. A sweep's task is one scenario with every grid point still to do; its rows
carry ``params`` and ``simulated`` (true on the one row per simulation), so reuse is counted.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import logging
import math
import time
import traceback
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapfusion.config import FusionConfig, from_mapping, to_mapping
from mapfusion.errors import ConfigError, InputError
from mapfusion.formats import read_toml

from sim.scenario import Scenario

log = logging.getLogger(__name__)

#: The parameters ``mapfusion tune`` searches by default, with their ranges (paper defaults inside).
TUNE_RANGES: dict[str, tuple[float, float]] = {
    "lane_width_m": (1.5, 6.0),
    "yaw_sigma_deg": (2.0, 40.0),
    "angle_weight_m_per_deg": (0.0, 4.0),
    "search_radius_m": (5.0, 50.0),
}
PAPER_DEFAULTS = {k: getattr(FusionConfig(), k) for k in TUNE_RANGES}


def with_params(cfg: FusionConfig, params: dict, where: str = "--param") -> FusionConfig:
    """``cfg`` with ``params`` replaced, validated as a ``[mapfusion]`` table is (ConfigError)."""
    return from_mapping(FusionConfig, {**to_mapping(cfg), **params}, where)


def parse_grid(specs: list[str]) -> dict[str, list]:
    """``["lane_width_m=2,3,4", ...]`` → {"lane_width_m": [2.0, 3.0, 4.0]}; every value validated."""
    grid: dict[str, list] = {}
    fields = {f.name: f for f in dataclasses.fields(FusionConfig)}
    for spec in specs:
        name, sep, values = spec.partition("=")
        name = name.strip()
        if not sep or not values.strip():
            raise InputError(f"--param {spec!r}: expected NAME=V1,V2,...")
        if name not in fields:
            raise InputError(f"--param {name}: not a FusionConfig field (known: {', '.join(sorted(fields))})")
        if name in grid:
            raise InputError(f"--param {name} given twice")
        out = []
        for v in values.split(","):
            v = v.strip()
            try:
                val = json.loads(v)
            except json.JSONDecodeError:
                val = v  # enum values and the like
            if fields[name].type in ("float", float) and isinstance(val, int) and not isinstance(val, bool):
                val = float(val)
            with_params(FusionConfig(), {name: val}, f"--param {name}")
            out.append(val)
        grid[name] = out
    if not grid:
        raise InputError("give at least one --param NAME=V1,V2,...")
    return grid


#: Named configurations every sweep knows: the engine's defaults and the paper's section III read directly.
BUILTIN_VARIANTS: dict[str, Callable[[], FusionConfig]] = {"defaults": FusionConfig, "faithful": FusionConfig.faithful}


def variant_params(cfg: FusionConfig) -> dict:
    """The fields of ``cfg`` that differ from the defaults, as ``[mapfusion]`` values."""
    base = to_mapping(FusionConfig())
    return {k: v for k, v in to_mapping(cfg).items() if base.get(k) != v}


def parse_variants(specs: list[str]) -> dict[str, dict]:
    """``["faithful", "pose3=pose3.toml"]`` → {name: overrides}. A variant is a built-in name
    (``defaults``, ``faithful``) or NAME=FILE.toml whose ``[mapfusion]`` table (or top-level keys)
    overrides the scenario's engine configuration; every one is validated."""

    out: dict[str, dict] = {}
    for spec in specs:
        name, sep, path = (x.strip() for x in spec.partition("="))
        if not sep:
            if name not in BUILTIN_VARIANTS:
                raise InputError(f"--variant {spec!r}: expected {' or '.join(BUILTIN_VARIANTS)}, or NAME=FILE.toml")
            params = variant_params(BUILTIN_VARIANTS[name]())
        else:
            if not name or not path:
                raise InputError(f"--variant {spec!r}: expected NAME=FILE.toml")
            try:
                data = read_toml(path, "TOML file")
            except InputError as exc:
                raise InputError(f"--variant {name}: {exc}") from None
            params = data.get("mapfusion", data)
            if not isinstance(params, dict):
                raise InputError(f"--variant {name}: {path}: [mapfusion] must be a table")
        if name in out:
            raise InputError(f"--variant {name} given twice")
        with_params(FusionConfig(), params, f"--variant {name}")
        out[name] = params
    return out


def point_params(point: dict, variants: dict[str, dict]) -> dict:
    """A grid point's engine overrides: its variant's (if any), then its own parameters."""
    rest = {k: v for k, v in point.items() if k != "variant"}
    if "variant" in point:
        return {**variants[point["variant"]], **rest}
    return rest


def grid_points(grid: dict[str, list]) -> list[dict]:
    keys = list(grid)
    return [dict(zip(keys, combo)) for combo in itertools.product(*(grid[k] for k in keys))]


def row_key(row: dict) -> str:
    """A sweep row's identity: scenario (its name and content hash) and grid point."""
    return f"{row['scenario']}|{row.get('scenario_sha256')}|{json.dumps(row.get('params', {}), sort_keys=True)}"


#: Fields the baseline (map priors off) never reads: changing them leaves it as it is.
MAP_ONLY_FIELDS = frozenset({"angle_weight_m_per_deg", "search_radius_m", "prior_mode", "prior_lambda_floor_m2",
                             "robust_kernel", "robust_k", "prior_max_angle_deg",
                             "prior_ambiguity_m", "prior_ambiguity_line_m", "prior_on_joins"})


def _baseline_key(cfg: FusionConfig) -> str:
    """What the baseline of ``cfg`` depends on: everything but the map-only fields."""
    m = to_mapping(dataclasses.replace(cfg, use_map=False))
    return json.dumps({k: v for k, v in m.items() if k not in MAP_ONLY_FIELDS}, sort_keys=True)


def _fuse_reusing_baseline(sim, cfg: FusionConfig, baselines: dict) -> dict:
    """``fuse_and_evaluate`` on one simulation, reusing the baseline already fused for what it
    reads (``baselines``: that simulation's cache, filled here); the metrics."""
    from .pipeline import fuse_and_evaluate

    key = _baseline_key(cfg)  # odometry priors read lane width and yaw σ
    m, baselines[key], _ = fuse_and_evaluate(sim, cfg, baselines.get(key))
    return m


def sweep_task(job: tuple[Scenario, list[dict], dict[str, dict]]) -> list[dict]:
    """One scenario simulated once, then fused at every grid point (a task of ``run_tasks``);
    ``job`` is (scenario, points, the variants the points may name)."""
    from .pipeline import simulate_scenario

    sc, points, variants = job
    digest = sc.content_hash()
    try:
        sim = simulate_scenario(sc)
    except InputError as exc:
        return [{"scenario": sc.name, "seed": sc.seed, "scenario_sha256": digest, "params": p, "error": str(exc)}
                for p in points]
    others: dict = {}
    if sc.estimators:  # (the plug-in estimators read no engine parameter: scored once, in every row)
        from .pipeline import score_estimators

        score_estimators(sim, others)
    rows, baselines = [], {}
    for i, params in enumerate(points):
        try:
            m = _fuse_reusing_baseline(sim, with_params(sc.mapfusion, point_params(params, variants)), baselines)
        except Exception as exc:  # noqa: BLE001 - one failed grid point must not cost the others
            log.warning("%s at %s failed: %r", sc.name, params, exc)
            m = {"scenario": sc.name, "seed": sc.seed, "error": f"{type(exc).__name__}: {exc}",
                 "traceback": traceback.format_exc()}
        if "error" not in m:
            m.update(others)
        m["params"] = params
        m["scenario_sha256"] = digest
        m["simulated"] = i == 0
        rows.append(m)
    return rows


def mean_ate_table(rows: list[dict], grid: dict[str, list]) -> dict[str, dict]:
    """Per grid point (its JSON): mean Map-Fusion ATE, mean odometry ATE, runs, de-localised, failed."""
    from .results import summarise

    out = {}
    for p in grid_points(grid):
        k = json.dumps(p, sort_keys=True)
        s = summarise(r for r in rows if json.dumps(r.get("params", {}), sort_keys=True) == k)
        out[k] = {"params": p, "runs": s.runs, "failed": s.failed, "ate_mapfusion_m": s.mean_mapfusion_m,
                  "ate_odometry_m": s.mean_odometry_m, "delocalized": s.delocalized_mapfusion}
        for name in others_of(rows):  # the plug-in estimators: their mean ATE over the runs that scored them
            vals = [r[f"ate_{name}_m"] for r in rows if json.dumps(r.get("params", {}), sort_keys=True) == k
                    and f"ate_{name}_m" in r]
            out[k][f"ate_{name}_m"] = sum(vals) / len(vals) if vals else float("nan")
    return out


def others_of(rows: list[dict]) -> list[str]:
    """The plug-in estimators the rows name, in their order of first appearance."""
    from .tables import others

    return others(rows)


def plot_heatmap(table: dict[str, dict], grid: dict[str, list], path: str | Path, title: str) -> Path:
    """Mean Map-Fusion ATE over the grid's first two parameters (averaged over any others)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = list(grid)
    kx = keys[0]
    ky = keys[1] if len(keys) > 1 else None
    ys = grid[ky] if ky else [None]
    z = np.full((len(ys), len(grid[kx])), np.nan)
    for j, yv in enumerate(ys):
        for i, xv in enumerate(grid[kx]):
            vals = [v["ate_mapfusion_m"] for v in table.values()
                    if v["params"][kx] == xv and (ky is None or v["params"][ky] == yv) and v["runs"]]
            if vals:
                z[j, i] = float(np.mean(vals))
    fig, ax = plt.subplots(figsize=(8, 6), dpi=100)
    im = ax.imshow(z, origin="lower", cmap="viridis_r", aspect="auto")
    ax.set_xticks(range(len(grid[kx])), [str(v) for v in grid[kx]])
    ax.set_xlabel(kx)
    if ky:
        ax.set_yticks(range(len(ys)), [str(v) for v in ys])
        ax.set_ylabel(ky)
    else:
        ax.set_yticks([])
    for j in range(z.shape[0]):
        for i in range(z.shape[1]):
            if np.isfinite(z[j, i]):
                ax.text(i, j, f"{z[j, i]:.2f}", ha="center", va="center", color="w" if z[j, i] > np.nanmean(z) else "k")
    fig.colorbar(im, ax=ax, label="mean Map-Fusion ATE (m)")
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


# ----------------------------------------------------------------------------- Optuna
@dataclass
class TuneResult:
    best_params: dict
    best_value: float
    best_mean_ate_m: float
    default_value: float | None
    default_mean_ate_m: float | None
    trials: int
    study_name: str
    storage: str


def objective_value(rows: list[dict], penalty_m: float) -> tuple[float, float, int]:
    """(objective, mean Map-Fusion ATE, de-localised): mean ATE over the runs plus ``penalty_m`` per
    de-localised run; a failed run costs the penalty too."""
    ok = [r for r in rows if "error" not in r]
    deloc = sum(r["delocalized_mapfusion"] for r in ok) + (len(rows) - len(ok))
    mean = float(np.mean([r["ate_mapfusion_m"] for r in ok])) if ok else math.inf
    return mean + penalty_m * deloc, mean, deloc


def tune(scenarios: list[Scenario], trials: int, storage, study_name: str,
         ranges: dict[str, tuple[float, float]] | None = None, penalty_m: float = 50.0,
         starts: list[dict] | None = None, seed: int = 0,
         on_trial: Callable[[int, float], None] | None = None) -> TuneResult:
    """Optuna (TPE, seeded) over ``ranges``; the paper's defaults and any ``starts`` are tried
    first. The study lives in ``storage`` (a URL, e.g. SQLite, or an opened storage), so a second
    call resumes it and several processes can share it."""
    import optuna

    from .pipeline import simulate_scenario

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    ranges = ranges or TUNE_RANGES
    check_ranges(ranges)
    if isinstance(storage, str):
        storage = open_storage(storage)
    sims = []
    for sc in scenarios:  # simulated once, fused at every trial
        sims.append(simulate_scenario(sc))
    study = optuna.create_study(study_name=study_name, storage=storage, direction="minimize", load_if_exists=True,
                                sampler=optuna.samplers.TPESampler(seed=seed))
    if not study.trials:
        defaults = {k: float(v) for k, v in PAPER_DEFAULTS.items() if k in ranges}
        study.enqueue_trial(defaults, user_attrs={"start": "paper defaults"})
        for s in starts or []:
            study.enqueue_trial(s, user_attrs={"start": "given"})

    baselines: list[dict] = [{} for _ in sims]  # per simulation: a baseline is fused once per what it reads

    def objective(trial) -> float:
        params = {k: trial.suggest_float(k, lo, hi) for k, (lo, hi) in ranges.items()}
        rows = []
        for sim, cache in zip(sims, baselines):
            rows.append(_fuse_reusing_baseline(sim, with_params(sim.sc.mapfusion, params), cache))
        value, mean, deloc = objective_value(rows, penalty_m)
        trial.set_user_attr("mean_ate_m", mean)
        trial.set_user_attr("delocalized", deloc)
        if on_trial:
            on_trial(trial.number, value)
        return value

    study.optimize(objective, n_trials=trials)
    best = study.best_trial
    default = next((t for t in study.trials if t.user_attrs.get("start") == "paper defaults" and t.value is not None), None)
    return TuneResult(best.params, best.value, best.user_attrs.get("mean_ate_m", math.nan),
                      default.value if default else None, default.user_attrs.get("mean_ate_m") if default else None,
                      len(study.trials), study_name, str(getattr(storage, "url", storage)))


def plot_sensitivity(storage: str, study_name: str, path: str | Path) -> Path:
    """Objective against each tuned parameter over every finished trial; the paper's value dashed."""
    import matplotlib
    import optuna

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    study = optuna.load_study(study_name=study_name, storage=storage)
    done = [t for t in study.trials if t.value is not None]
    names = sorted({k for t in done for k in t.params})
    fig, axes = plt.subplots(1, max(1, len(names)), figsize=(4 * max(1, len(names)), 4), dpi=100, squeeze=False)
    vals = np.array([t.value for t in done])
    finite = np.isfinite(vals)
    for ax, k in zip(axes[0], names):
        xs = np.array([t.params.get(k, np.nan) for t in done])
        ax.scatter(xs[finite], vals[finite], c=np.arange(len(done))[finite], cmap="viridis", s=18)
        if k in PAPER_DEFAULTS:
            ax.axvline(PAPER_DEFAULTS[k], ls="--", c="grey", label="paper")
            ax.legend(loc="upper right")
        ax.set_xlabel(k)
        ax.set_ylabel("objective (mean ATE + penalty, m)")
    fig.suptitle(f"{study_name}: {len(done)} trials (colour: trial order)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def parse_ranges(specs: list[str]) -> dict[str, tuple[float, float]]:
    """``mapfusion tune --range NAME=LOW:HIGH`` (repeatable) → ranges; none given: :data:`TUNE_RANGES`."""
    if not specs:
        return dict(TUNE_RANGES)
    ranges: dict[str, tuple[float, float]] = {}
    for spec in specs:
        name, sep, span = spec.partition("=")
        lo, sep2, hi = span.partition(":")
        if not sep or not sep2:
            raise InputError(f"--range {spec!r}: expected NAME=LOW:HIGH")
        try:
            ranges[name.strip()] = (float(lo), float(hi))
        except ValueError:
            raise InputError(f"--range {spec!r}: LOW and HIGH must be numbers") from None
    check_ranges(ranges)
    return ranges


def check_ranges(ranges: dict[str, tuple[float, float]]) -> None:
    """Every range names a FusionConfig field, both ends are valid values of it, and LOW < HIGH."""
    for k, (lo, hi) in ranges.items():
        with_params(FusionConfig(), {k: float(lo)}, f"--range {k}")
        with_params(FusionConfig(), {k: float(hi)}, f"--range {k}")
        if not lo < hi:
            raise ConfigError(f"--range {k}: the low end {lo:g} must be below the high end {hi:g}")


#: Optuna's heartbeat: a trial whose process died (killed, out of memory) stops beating, and after
#: the grace period the next trial of any process on the study marks it failed.
HEARTBEAT_S, GRACE_S = 30, 120


#: How often :func:`open_storage` tries, and the errors of another process creating the same schema.
OPEN_ATTEMPTS = 10
_SCHEMA_RACE = ("already exists", "database is locked", "UNIQUE constraint failed", "duplicate key")


def open_storage(url: str, option: str = "--storage"):
    """The Optuna storage at ``url``, opened now (driver loaded, database reachable) so that a bad
    URL is refused before any simulation; an :class:`InputError` naming ``option`` otherwise."""
    import optuna
    import sqlalchemy.exc
    from sqlalchemy.engine import make_url

    try:
        u = make_url(url)
    except (sqlalchemy.exc.ArgumentError, ValueError) as exc:
        raise InputError(f"{option} {url!r}: not a database URL ({exc})") from None
    if u.get_backend_name() == "sqlite" and u.database not in (None, "", ":memory:"):
        folder = Path(u.database).parent
        if not folder.is_dir():
            raise InputError(f"{option} {url}: no such directory {folder}")
    for attempt in range(OPEN_ATTEMPTS):
        try:
            with warnings.catch_warnings():  # the heartbeat is "experimental" to Optuna: no warning line on stderr
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                return optuna.storages.RDBStorage(url, heartbeat_interval=HEARTBEAT_S, grace_period=GRACE_S)
        except (sqlalchemy.exc.OperationalError, sqlalchemy.exc.IntegrityError) as exc:
            # Two processes opening a new database at once both create its tables: the loser's
            # CREATE TABLE or version row fails, and a second look finds the schema complete.
            if attempt + 1 < OPEN_ATTEMPTS and any(s in str(exc) for s in _SCHEMA_RACE):
                log.debug("storage %s: concurrent schema creation (%s), opening again", url, exc)
                time.sleep(0.05 * (attempt + 1))
                continue
            raise InputError(f"{option} {url}: cannot open the storage ({_first_line(exc)})") from None
        except (sqlalchemy.exc.SQLAlchemyError, ImportError, ValueError) as exc:
            raise InputError(f"{option} {url}: cannot open the storage ({_first_line(exc)})") from None
    raise AssertionError("unreachable")  # pragma: no cover - the last attempt returns or raises


def _first_line(exc: BaseException) -> str:
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


def fail_orphaned_trials(storage, study_name: str) -> int:
    """Mark every RUNNING trial of the study failed: only for a storage no other process can be using
    (the caller holds its lock), where a RUNNING trial is one whose process was killed. Returns how many."""
    import optuna
    from optuna.trial import TrialState

    try:
        study = optuna.load_study(study_name=study_name, storage=storage)
    except KeyError:  # no such study yet
        return 0
    running = study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
    for t in running:
        storage.set_trial_state_values(t._trial_id, TrialState.FAIL)
        log.warning("trial %d of %s was left running by a process that died: marked failed", t.number, study_name)
    return len(running)


def parse_starts(specs: list[str], ranges: dict[str, tuple[float, float]]) -> list[dict[str, float]]:
    """``mapfusion tune --start NAME=VALUE,...`` (repeatable) → first trials over the tuned parameters."""
    starts = []
    for spec in specs:
        d = {}
        for part in spec.split(","):
            k, sep, v = part.partition("=")
            if not sep or k.strip() not in ranges:
                raise InputError(f"--start {spec!r}: expected NAME=VALUE,... over the tuned parameters ({', '.join(ranges)})")
            try:
                d[k.strip()] = float(v)
            except ValueError:
                raise InputError(f"--start {spec!r}: {k} must be a number") from None
        starts.append(d)
    return starts


@dataclass
class SweepPlan:
    """A sweep over scenarios × grid points, and what ``results.jsonl`` already holds."""

    scenarios: list
    grid: dict[str, list]
    variants: dict[str, dict]
    results_path: Path
    jobs: list = dataclasses.field(default_factory=list)  # (scenario, grid points still to fuse, variants)
    changed: list = dataclasses.field(default_factory=list)  # names whose rows are of an earlier scenario content

    @property
    def total(self) -> int:
        return len(self.scenarios) * len(grid_points(self.grid))

    @property
    def left(self) -> int:
        return sum(len(j[1]) for j in self.jobs)


def plan_sweep(scenarios: list, params: list[str], variants: list[str], out: Path) -> SweepPlan:
    """Parse the grid and the variants (InputError) and find the fusions ``out/results.jsonl`` lacks."""
    from .batch import ResultsLog

    if not params and not variants:
        raise InputError("give at least one --param NAME=V1,V2,... or --variant")
    parsed = parse_variants(variants)
    grid: dict[str, list] = {"variant": list(parsed)} if parsed else {}
    if params:
        grid.update(parse_grid(params))
    plan = SweepPlan(scenarios, grid, parsed, Path(out) / "results.jsonl")
    done = ResultsLog(plan.results_path).done(row_key)
    named = {k.split("|", 1)[0] for k in done}
    for sc in scenarios:
        key = {"scenario": sc.name, "scenario_sha256": sc.content_hash()}
        todo = [p for p in grid_points(grid) if row_key({**key, "params": p}) not in done]
        if todo:
            plan.jobs.append((sc, todo, parsed))
            if sc.name in named and not any(k.startswith(f"{sc.name}|{key['scenario_sha256']}|") for k in done):
                plan.changed.append(sc.name)
    return plan


def run_sweep(plan: SweepPlan, workers: int, scheduler: str | None = None,
              on_row: Callable[[dict], None] | None = None) -> tuple[dict[str, dict], int]:
    """Run the plan's jobs (each finished row appended at once); returns the mean-ATE table over
    every row of the plan's scenarios and the number of simulations this call made."""
    from .batch import ResultsLog, run_tasks

    results = ResultsLog(plan.results_path)
    sims = 0

    def finished(job, rows):
        nonlocal sims
        for row in rows:
            sims += bool(row.get("simulated"))
            results.append(row)
            if on_row is not None:
                on_row(row)

    def failed(job, err):
        finished(job, [{"scenario": job[0].name, "seed": job[0].seed, "scenario_sha256": job[0].content_hash(),
                        "params": p, **err} for p in job[1]])

    run_tasks(plan.jobs, sweep_task, workers=workers, on_rows=finished, on_failure=failed, scheduler=scheduler)
    current = {(sc.name, sc.content_hash()) for sc in plan.scenarios}  # rows of edited scenarios are stale
    rows = [r for r in results.latest(row_key).values() if (r.get("scenario"), r.get("scenario_sha256")) in current]
    return mean_ate_table(rows, plan.grid), sims
