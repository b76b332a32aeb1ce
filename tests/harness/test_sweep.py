"""mapfusion sweep and mapfusion tune: simulations reused, resume, a study that improves."""

from __future__ import annotations

import numpy as np

import json

import pytest
from typer.testing import CliRunner

from mapfusion.harness.cli import app

pytestmark = pytest.mark.sumo
runner = CliRunner()

TINY = ('[family]\nname = "tiny"\nseeds = [SEEDS]\n[family.axes]\nmap = ["grid"]\n'
        '[base]\nduration_s = 150.0\nmin_route_m = 800.0\n[base.weather]\nkind = "rain"\n')


def _family(tmp_path, seeds="1, 2", weather="rain"):
    p = tmp_path / "tiny.toml"
    p.write_text(TINY.replace("SEEDS", seeds).replace('"rain"', f'"{weather}"'))
    return p


@pytest.mark.slow
def test_sweep_simulates_each_scenario_once_and_resumes(tmp_path):
    fam = _family(tmp_path)
    out = tmp_path / "sw"
    args = ["sweep", str(fam), "-p", "lane_width_m=2,3", "-p", "yaw_sigma_deg=5,10", "--out", str(out), "--workers", "2"]
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output
    assert "2 simulation(s) for 8 fusion(s)" in r.stdout
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert len(rows) == 8 and sum(r["simulated"] for r in rows) == 2
    assert {json.dumps(r["params"], sort_keys=True) for r in rows} == {
        json.dumps({"lane_width_m": lw, "yaw_sigma_deg": ys}, sort_keys=True) for lw in (2.0, 3.0) for ys in (5.0, 10.0)}
    assert (out / "sweep_heatmap.png").stat().st_size > 0
    # the grid point at the defaults is what mapfusion run gets for the same scenario
    run = runner.invoke(app, ["run", str(fam), "--out", str(tmp_path / "run"), "--no-plot"])
    assert run.exit_code == 0, run.output
    ref = {json.loads(x)["scenario"]: json.loads(x) for x in (tmp_path / "run" / "results.jsonl").read_text().splitlines()}
    for r in rows:
        if r["params"] == {"lane_width_m": 3.0, "yaw_sigma_deg": 10.0}:
            assert r["ate_mapfusion_m"] == pytest.approx(ref[r["scenario"]]["ate_mapfusion_m"], abs=1e-9)
            assert r["ate_odometry_m"] == pytest.approx(ref[r["scenario"]]["ate_odometry_m"], abs=1e-9)
    again = runner.invoke(app, args)
    assert again.exit_code == 0 and "0 simulation(s) for 0 fusion(s)" in again.stdout and "resuming" in again.stderr


@pytest.mark.slow
def test_sweep_variants_are_named_configurations(tmp_path):
    fam = _family(tmp_path, "1")
    narrow = tmp_path / "narrow.toml"
    narrow.write_text("[mapfusion]\nlane_width_m = 2.0\n")
    out = tmp_path / "sv"
    r = runner.invoke(app, ["sweep", str(fam), "-V", "defaults", "-V", "faithful", "-V", f"narrow={narrow}",
                            "--out", str(out), "--workers", "1"])
    assert r.exit_code == 0, r.output
    assert "1 simulation(s) for 3 fusion(s)" in r.stdout
    rows = {r["params"]["variant"]: r for r in map(json.loads, (out / "results.jsonl").read_text().splitlines())}
    assert set(rows) == {"defaults", "faithful", "narrow"}
    # a variant file is the same as the equivalent grid point
    grid = runner.invoke(app, ["sweep", str(fam), "-p", "lane_width_m=2,3", "--out", str(tmp_path / "sg"), "--workers", "1"])
    assert grid.exit_code == 0, grid.output
    by_lw = {r["params"]["lane_width_m"]: r for r in map(json.loads, (tmp_path / "sg" / "results.jsonl").read_text().splitlines())}
    assert rows["narrow"]["ate_mapfusion_m"] == pytest.approx(by_lw[2.0]["ate_mapfusion_m"], abs=1e-9)
    assert rows["defaults"]["ate_mapfusion_m"] == pytest.approx(by_lw[3.0]["ate_mapfusion_m"], abs=1e-9)
    # the faithful reading changes the engine (free Pose3, ISAM2, no gates): not the defaults' figure
    assert rows["faithful"]["ate_mapfusion_m"] != pytest.approx(rows["defaults"]["ate_mapfusion_m"], abs=1e-6)


def test_parse_variants_faithful_is_the_papers_reading():
    from mapfusion.config import FusionConfig
    from mapfusion.harness.sweep import parse_variants, with_params

    v = parse_variants(["faithful", "defaults"])
    assert with_params(FusionConfig(), v["faithful"]) == FusionConfig.faithful()
    assert with_params(FusionConfig(), v["defaults"]) == FusionConfig()


@pytest.mark.parametrize("spec,needle", [("nope", "expected defaults or faithful"), ("x=missing.toml", "missing.toml: no such"),
                                         ("x=BAD", "lane_width_m")])
def test_sweep_bad_variant_exit_2(tmp_path, spec, needle):
    (tmp_path / "bad.toml").write_text("[mapfusion]\nlane_width_m = 0.1\n")
    spec = spec.replace("BAD", str(tmp_path / "bad.toml"))
    r = runner.invoke(app, ["sweep", str(_family(tmp_path)), "-V", spec, "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and needle in r.stderr, r.output


@pytest.mark.parametrize("param,needle", [("nope=1,2", "not a FusionConfig field"), ("lane_width_m=0.1", "lane_width_m"),
                                          ("lane_width_m", "NAME=V1,V2")])
def test_sweep_bad_params_exit_2(tmp_path, param, needle):
    r = runner.invoke(app, ["sweep", str(_family(tmp_path)), "-p", param, "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and needle in r.stderr


@pytest.mark.slow
def test_tune_improves_on_a_deliberately_bad_start_and_resumes(tmp_path):
    import optuna

    # heavy rain: on the short rain drive the odometry stays inside the roads' band and no setting
    # of the map's parameters matters much
    fam = _family(tmp_path, "1", "heavy_rain")
    out = tmp_path / "tn"
    bad = "lane_width_m=6,yaw_sigma_deg=40,angle_weight_m_per_deg=4,search_radius_m=5"
    r = runner.invoke(app, ["tune", str(fam), "--trials", "6", "--out", str(out), "--start", bad])
    assert r.exit_code == 0, r.output
    study = optuna.load_study(study_name="tiny", storage=f"sqlite:///{out / 'study.db'}")
    start = next(t for t in study.trials if t.user_attrs.get("start") == "given")
    assert start.params["search_radius_m"] == 5.0
    assert study.best_value < start.value
    assert "paper" in r.stdout and (out / "tune_sensitivity.png").stat().st_size > 0
    r = runner.invoke(app, ["tune", str(fam), "--trials", "2", "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert len(optuna.load_study(study_name="tiny", storage=f"sqlite:///{out / 'study.db'}").trials) == 8


def _open_after(url: str, barrier, results) -> None:
    from mapfusion.harness.sweep import open_storage

    barrier.wait()
    try:
        open_storage(url)
        results.put("ok")
    except Exception as exc:  # noqa: BLE001 - reported to the test
        results.put(f"{type(exc).__name__}: {exc}")


@pytest.mark.slow
def test_processes_opening_a_new_study_database_at_once_all_succeed(tmp_path):
    """Several tunes (or a tune and a reader) opening one new SQLite study at once each create its
    tables; without a second look all but one fail with 'table ... already exists' (measured: every
    one of 10 tries of six openers failed before open_storage looked again)."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    for rep in range(2):
        url = f"sqlite:///{tmp_path / f'study{rep}.db'}"
        barrier, results = ctx.Barrier(6), ctx.Queue()
        procs = [ctx.Process(target=_open_after, args=(url, barrier, results)) for _ in range(6)]
        for p in procs:
            p.start()
        outcome = [results.get(timeout=120) for _ in procs]
        for p in procs:
            p.join(timeout=60)
        assert outcome == ["ok"] * 6, outcome


def test_tune_bad_range_exits_2(tmp_path):
    r = runner.invoke(app, ["tune", str(_family(tmp_path, "1")), "--range", "lane_width_m=5:2", "--out", str(tmp_path / "t")])
    assert r.exit_code == 2 and "below the high end" in r.stderr


def test_a_failing_grid_point_costs_only_itself(tmp_path, monkeypatch):
    import mapfusion.harness.pipeline

    real = mapfusion.harness.pipeline.fuse_and_evaluate

    def flaky(simulation, cfg, baseline=None):
        if cfg.lane_width_m == 2.0:
            raise IndexError("boom at 2 m")
        return real(simulation, cfg, baseline)

    monkeypatch.setattr(mapfusion.harness.pipeline, "fuse_and_evaluate", flaky)  # the forked worker inherits it
    out = tmp_path / "sf"
    r = runner.invoke(app, ["sweep", str(_family(tmp_path, "1")), "-p", "lane_width_m=2,3", "--out", str(out),
                            "--workers", "1"])
    assert r.exit_code == 0, r.output
    rows = {r["params"]["lane_width_m"]: r for r in map(json.loads, (out / "results.jsonl").read_text().splitlines())}
    assert rows[2.0]["error"] == "IndexError: boom at 2 m" and "traceback" in rows[2.0]
    assert "error" not in rows[3.0] and rows[3.0]["ate_mapfusion_m"] > 0


def test_the_baseline_ignores_the_map_only_fields(tmp_path):
    from mapfusion.config import FusionConfig, PriorMode
    from mapfusion.engine import MapFusion
    from mapfusion.harness.sweep import MAP_ONLY_FIELDS, _baseline_key
    from tests.mapfusion.test_engine import _biased_straight_drive, _feed, _online_xy

    road, truth, odo, gt, gxy = _biased_straight_drive(tmp_path)
    changed = dict(angle_weight_m_per_deg=3.0, search_radius_m=7.0, prior_mode=PriorMode.paper,
                   prior_lambda_floor_m2=1.0, robust_kernel="cauchy", robust_k=3.0,
                   prior_max_angle_deg=90.0, prior_ambiguity_m=0.0, prior_ambiguity_line_m=0.0, prior_on_joins=True)
    assert set(changed) == MAP_ONLY_FIELDS
    base = FusionConfig(use_map=False)
    other = FusionConfig(use_map=False, **{k: (v if k != "robust_kernel" else type(base.robust_kernel)(v))
                                           for k, v in changed.items()})
    assert _baseline_key(base) == _baseline_key(other)
    assert _baseline_key(base) != _baseline_key(FusionConfig(use_map=False, lane_width_m=2.0))
    a = _online_xy(_feed(MapFusion(road, base), road, truth.t_s, odo, gt, gxy, sigma=1.0))[1]
    b = _online_xy(_feed(MapFusion(road, other), road, truth.t_s, odo, gt, gxy, sigma=1.0))[1]
    np.testing.assert_array_equal(a, b)
