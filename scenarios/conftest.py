"""pytest scenarios/: families run once per session (two worker processes), each run a test case.

``--update-baselines`` rewrites scenarios/baselines.json from this session's results (nothing else ever
writes it): it prints each family's change (mean ATE, de-localised, worst run against odometry) and refuses
a family that got worse unless it is named with ``--accept-worse FAMILY``. ``scenarios/noise_floor.json``
(``mapfusion noise``) gives the regression checks their tolerances. ``--engine-param KEY=VALUE`` fuses
every run with that engine parameter changed (an injected regression must fail the checks). The
paper-style table of every family is printed at the end.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest


HERE = Path(__file__).resolve().parent
FAMILIES = HERE / "families"
BASELINES = HERE / "baselines.json"
NOISE_FLOOR = HERE / "noise_floor.json"
_RESULTS: dict[str, dict[str, dict]] = {}
#: Text tables a test leaves for the end-of-session summary (the realism table), by title.
REPORTS: dict[str, list[str]] = {}


def pytest_addoption(parser):
    parser.addoption("--update-baselines", action="store_true", default=False,
                     help="rewrite scenarios/baselines.json from this run's results")
    parser.addoption("--scenario-workers", type=int, default=2, help="worker processes for the family runs")
    parser.addoption("--accept-worse", action="append", default=[], metavar="FAMILY",
                     help="with --update-baselines: record this family even though it got worse (repeatable)")
    parser.addoption("--engine-param", action="append", default=[], metavar="KEY=VALUE",
                     help="fuse every run with this engine (FusionConfig) parameter changed (repeatable)")


def real_data(sub: str, why: str) -> str:
    """``$MAPFUSION_DATA`` when it holds ``sub``; otherwise the test is skipped, saying ``why``."""
    import os

    d = os.environ.get("MAPFUSION_DATA")
    if not d or not os.path.isdir(os.path.join(d, sub)):
        pytest.skip(f"{why} ($MAPFUSION_DATA/{sub})")
    return d


def family_group(name: str) -> str:
    """The pytest-xdist group of the tests that read a family: the simulated and the real KITTI odometry share
    one (issue 22's verdict compares them), every other family is its own."""
    return "family:kitti-realism" if name in ("kitti-real", "kitti-realism") else f"family:{name}"


def family_results(config, name: str) -> dict[str, dict]:
    """Metrics of every run of a family, computed once per session."""
    if name not in _RESULTS:
        from mapfusion.harness.batch import run_many
        from sim.scenario import load_family

        fam = load_family(FAMILIES / f"{name}.toml")
        scenarios = list(fam.scenarios)
        params = engine_params(config)
        if params:
            from mapfusion.harness.noise import with_engine_params

            scenarios = with_engine_params(scenarios, params, "--engine-param")
        rows = run_many(scenarios, workers=config.getoption("--scenario-workers"))
        _RESULTS[name] = {r["scenario"]: r for r in rows}
    return _RESULTS[name]


def engine_params(config) -> dict:
    """``--engine-param KEY=VALUE`` options as a [mapfusion] table (values parsed as TOML values)."""
    from mapfusion.harness.noise import parse_params

    try:
        return parse_params(config.getoption("--engine-param"))
    except ValueError as exc:
        raise pytest.UsageError(f"--engine-param {exc}") from None


def load_baselines() -> dict:
    return json.loads(BASELINES.read_text()) if BASELINES.exists() else {}


def load_noise_floor() -> dict[str, dict]:
    """The noise floor's entry of every run (empty without scenarios/noise_floor.json)."""
    return json.loads(NOISE_FLOOR.read_text()).get("runs", {}) if NOISE_FLOOR.exists() else {}


def _is_worker(config) -> bool:
    """Under pytest-xdist: a worker process (the controller gathers their results, prints, writes)."""
    return hasattr(config, "workerinput")


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    """Controller side of pytest-xdist: the families a worker ran come back with it."""
    got = getattr(node, "workeroutput", {}).get("scenario_results")
    if got:
        _RESULTS.update(json.loads(got))
    reports = getattr(node, "workeroutput", {}).get("scenario_reports")
    if reports:
        REPORTS.update(json.loads(reports))


def pytest_sessionfinish(session, exitstatus):
    if _is_worker(session.config):
        session.config.workeroutput["scenario_results"] = json.dumps(_RESULTS)
        session.config.workeroutput["scenario_reports"] = json.dumps(REPORTS)
        return
    if session.config.getoption("--update-baselines") and _RESULTS:
        from mapfusion.harness.regression import rerecord

        if engine_params(session.config):
            REPORTS["baselines"] = ["not re-recorded: --engine-param changes the engine"]
            return
        data, report, refused = rerecord(load_baselines(), _RESULTS, load_noise_floor(),
                                         set(session.config.getoption("--accept-worse")))
        BASELINES.write_text(json.dumps(data, indent=1) + "\n")
        REPORTS["baselines"] = report
        if refused:
            session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    if _is_worker(config):
        return
    for title, lines in REPORTS.items():
        terminalreporter.write_sep("=", title)
        terminalreporter.write("\n".join(lines) + "\n")
    if not _RESULTS:
        return
    from io import StringIO

    from rich.console import Console

    from mapfusion.harness.tables import family_summary_line, paper_table, table_one

    buf = StringIO()
    width = max(120, 15 * (2 + max(len(r) for r in _RESULTS.values())))
    con = Console(file=buf, width=width, force_terminal=False)
    for fam, runs in _RESULTS.items():
        rows = list(runs.values())
        if fam.startswith("kitti") and not fam.startswith("kitti-real"):  # real odometry: a row per run
            con.print(table_one(rows, f"family {fam}: Table I, ATE (m) per KITTI sequence "
                                      "(synthetic odometry on the real drives, real OSM, RTK GPS for initialisation)"))
        else:
            con.print(paper_table(rows, f"family {fam}: ATE (m) per run", strip_prefix=f"{fam}-", width=con.width))
        con.print(family_summary_line(rows))
    terminalreporter.write_sep("=", "scenario families")
    terminalreporter.write(buf.getvalue())
