"""The regression checks and the noise floor they read: perturbation at the last bits, tolerances from the
measured spread, family checks that see a shift of a few percent, and re-recording that refuses a worse family."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from typer.testing import CliRunner

from mapfusion.harness.noise import (MIN_TOLERANCE_M, RANGE_FACTOR, code_paths, draw_seed, numpy_features_off,
                                     perturbed, run_tolerance_m, spread_of)
from mapfusion.harness.regression import check_family, check_run, figures, rerecord
from sim.sensors import GpsOutput, ImuOutput, OdometryOutput, SensorData, WheelOutput


def _sensors(rng, n=50, wheel=True):
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = rng.normal(0, 100, (n, 3))
    odo = OdometryOutput(np.arange(n) * 0.1, poses, np.arange(n), np.zeros(n, bool), np.zeros(n, bool))
    gps = GpsOutput(np.arange(5.0), rng.normal(0, 500, 5), rng.normal(0, 500, 5), rng.normal(0, 10, 5), np.ones(5),
                    np.zeros(5, bool), np.arange(5))
    imu = ImuOutput(np.arange(n) * 0.1, rng.normal(0, 1, (n, 3)), rng.normal(0, 0.1, (n, 3)))
    w = WheelOutput(np.arange(n) * 0.02, rng.uniform(0, 20, n), 0.01) if wheel else None
    return SensorData(odo, imu, gps, params=None, wheel=w)


@given(seed=st.integers(0, 2**32 - 1), rel=st.sampled_from([1e-15, 1e-12, 1e-9]), wheel=st.booleans())
def test_perturbation_moves_every_value_by_its_relative_size_and_nothing_else(seed, rel, wheel):
    rng = np.random.default_rng(seed)
    s = _sensors(rng, wheel=wheel)
    p = perturbed(s, rel, np.random.default_rng(seed + 1))

    def close(a, b):
        a, b = np.asarray(a, float), np.asarray(b, float)
        return np.all(np.abs(b - a) <= 6 * rel * np.abs(a) + 1e-300)

    assert close(s.odometry.poses, p.odometry.poses)
    assert np.array_equal(s.odometry.poses[:, 3, :], p.odometry.poses[:, 3, :])  # the homogeneous row stays
    assert np.array_equal(s.odometry.t_s, p.odometry.t_s) and np.array_equal(s.gps.t_s, p.gps.t_s)
    assert np.array_equal(s.gps.sigma_m, p.gps.sigma_m)
    for a, b in ((s.gps.x_m, p.gps.x_m), (s.gps.y_m, p.gps.y_m), (s.imu.gyro_radps, p.imu.gyro_radps)):
        assert close(a, b)
    # something moved (the odds of 300 draws all rounding away are nil at 1e-12 and above)
    if rel >= 1e-12:
        assert not np.array_equal(s.odometry.poses, p.odometry.poses)
    assert (p.wheel is None) == (not wheel)
    if wheel:
        assert close(s.wheel.speed_mps, p.wheel.speed_mps)
    assert p.odometry.poses is not s.odometry.poses  # the original is not changed in place


def test_draw_seeds_are_stable_and_distinct():
    seeds = {draw_seed(n, s, d) for n in ("a-s1", "a-s2", "b-s1") for s in (0, 1) for d in range(6)}
    assert len(seeds) == 36
    assert draw_seed("rain-helsinki-vo-s1", 0, 3) == draw_seed("rain-helsinki-vo-s1", 0, 3)


def test_code_paths_change_glibc_and_numpy():
    paths = code_paths()
    assert paths["glibc"] == {"GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX2,-FMA,-AVX512F"}
    off = numpy_features_off()
    if off:  # every named feature is one numpy knows
        from numpy._core._multiarray_umath import __cpu_dispatch__

        assert set(off.split(",")) <= set(__cpu_dispatch__)
        assert paths["numpy"]["NPY_DISABLE_CPU_FEATURES"] == off


def _entry(ates, deloc=None, paths=None, odo=30.0):
    e = {"draws": {"ate_mapfusion_m": list(ates), "ate_odometry_m": [odo] * len(ates),
                   "delocalized_mapfusion": deloc or [a > 20 for a in ates], "match_rate": [0.9] * len(ates)}}
    if paths:
        e["code_paths"] = {k: {"ate_mapfusion_m": v, "ate_odometry_m": odo, "delocalized_mapfusion": v > 20,
                               "match_rate": 0.9} for k, v in paths.items()}
    e.update(spread_of(e))
    return e


def test_spread_is_the_range_over_the_median_of_every_fusion():
    # the TrianFlow 02 draws: a 6% spread
    e = _entry([16.94, 17.10, 17.10, 16.96], paths={"glibc": 17.91})
    assert e["range_m"] == pytest.approx(0.97)
    assert e["spread"] == pytest.approx(0.97 / 17.10)
    assert not e["delocalized_flips"]
    assert _entry([19.0, 21.0])["delocalized_flips"]


@given(base=st.floats(0.5, 100.0), rng=st.floats(0.0, 5.0))
def test_a_run_tolerance_is_twice_its_range_and_never_below_the_floor(base, rng):
    e = _entry([base, base + rng])
    tol = run_tolerance_m(e, base)
    assert tol == pytest.approx(max(MIN_TOLERANCE_M, RANGE_FACTOR * rng))
    # inside it: no finding; beyond it: the ATE named
    row = {"ate_mapfusion_m": base + 0.99 * tol, "delocalized_mapfusion": False, "match_rate": 0.9}
    b = {"ate_mapfusion_m": base, "delocalized_mapfusion": False, "match_rate": 0.9}
    assert check_run(row, b, e) == [] or row["ate_mapfusion_m"] > 20  # (de-localisation is another check)
    assert any("ATE" in p for p in check_run({**row, "ate_mapfusion_m": base + 1.01 * tol + 1e-9}, b, e))


def test_a_run_without_noise_floor_gets_ten_percent():
    assert run_tolerance_m(None, 10.0) == pytest.approx(1.0)
    assert run_tolerance_m(None, 1.0) == pytest.approx(0.25)


def test_a_new_delocalisation_fails_unless_it_flips_in_the_noise_floor():
    b = {"ate_mapfusion_m": 19.5, "delocalized_mapfusion": False, "match_rate": None}
    row = {"ate_mapfusion_m": 20.5, "delocalized_mapfusion": True, "match_rate": None}
    assert "de-localised where the baseline was not" in check_run(row, b, _entry([19.5, 19.6]))
    assert "de-localised where the baseline was not" not in check_run(row, b, _entry([19.5, 20.6]))


def _family(n, rng, shift=0.0, noise_rel=0.002, draws=6):
    """n runs with baselines, their noise-floor entries (``draws`` fusions each, relative noise ``noise_rel``)
    and this session's rows, every run's ATE ``shift`` (relative) above its baseline."""
    base, noise, rows = {}, {}, []
    for i in range(n):
        name = f"f-s{i}"
        a = float(rng.uniform(2.0, 12.0))
        odo = a + float(rng.uniform(-0.2, 10.0))
        base[name] = {"ate_mapfusion_m": a, "ate_odometry_m": odo, "delocalized_mapfusion": False,
                      "delocalized_odometry": odo > 20, "match_rate": None}
        noise[name] = _entry(a * (1 + noise_rel * rng.standard_normal(draws)), odo=odo)
        rows.append({"scenario": name, "ate_mapfusion_m": a * (1 + shift), "ate_odometry_m": odo,
                     "delocalized_mapfusion": False, "delocalized_odometry": odo > 20, "match_rate": None})
    return base, noise, rows


@given(seed=st.integers(0, 10_000), n=st.integers(6, 20))
def test_a_family_shifted_by_a_few_percent_fails_though_every_run_passes(seed, n):
    rng = np.random.default_rng(seed)
    base, noise, rows = _family(n, rng, shift=0.03)
    assert check_family(rows, base, noise)
    # the same family with its noise alone passes
    still = [{**r, "ate_mapfusion_m": base[r["scenario"]]["ate_mapfusion_m"]} for r in rows]
    assert check_family(still, base, noise) == []


def test_family_checks_name_each_figure():
    rng = np.random.default_rng(3)
    base, noise, rows = _family(8, rng)
    worse = [dict(r) for r in rows]
    worse[0].update(ate_mapfusion_m=45.0, delocalized_mapfusion=True)
    found = " ".join(check_family(worse, base, noise))
    assert "mean ATE" in found and "de-localised" in found and "worst run against odometry" in found


def test_rerecording_refuses_a_worse_family_unless_told_by_name():
    rng = np.random.default_rng(5)
    base, noise, rows = _family(8, rng, shift=0.10)
    ok_base, ok_noise, ok_rows = _family(4, np.random.default_rng(6), shift=-0.05)
    ok_rows = [{**r, "scenario": "g" + r["scenario"]} for r in ok_rows]
    old = {**base, **{"g" + k: v for k, v in ok_base.items()}}
    noise.update({"g" + k: v for k, v in ok_noise.items()})
    fams = {"worse": {r["scenario"]: r for r in rows}, "better": {r["scenario"]: r for r in ok_rows}}
    data, report, refused = rerecord(old, fams, noise, set())
    assert refused == ["worse"]
    assert all(data[r["scenario"]] == old[r["scenario"]] for r in rows)  # kept as they were
    assert all(data[r["scenario"]]["ate_mapfusion_m"] == r["ate_mapfusion_m"] for r in ok_rows)
    assert any(line.startswith("worse:") and "REFUSED" in line for line in report)
    data, report, refused = rerecord(old, fams, noise, {"worse"})
    assert refused == [] and all(data[r["scenario"]]["ate_mapfusion_m"] == r["ate_mapfusion_m"] for r in rows)
    assert figures(rows).runs == 8


def test_the_noise_command_writes_and_merges_a_noise_floor(tmp_path):
    """One short drive, two draws, no other code paths: the document's shape, and a second family merged in."""
    from mapfusion.harness.cli import app

    fam = tmp_path / "f.toml"
    fam.write_text('[family]\nname = "f"\nseeds = [1]\n[base]\nmap = "grid"\nduration_s = 120.0\n'
                   'min_route_m = 600.0\n[base.weather]\nkind = "rain"\n')
    out = tmp_path / "noise.json"
    out.write_text(json.dumps({"runs": {"other-s1": {"family": "other"}}}))
    r = CliRunner().invoke(app, ["noise", str(fam), "--out", str(out), "--draws", "2", "--no-code-paths", "-j", "1"])
    assert r.exit_code == 0, r.output
    doc = json.loads(out.read_text())
    assert set(doc["runs"]) == {"other-s1", "f-s1"}
    e = doc["runs"]["f-s1"]
    assert e["family"] == "f" and len(e["draws"]["ate_mapfusion_m"]) == 3
    assert e["range_m"] == pytest.approx(max(e["draws"]["ate_mapfusion_m"]) - min(e["draws"]["ate_mapfusion_m"]))
    assert "noise floor" in r.stdout
