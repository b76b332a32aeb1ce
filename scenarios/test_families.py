"""The scenario families: every run against its recorded baseline, and the method's claims per family.

Regression checks (mapfusion.harness.regression), with tolerances from each run's measured noise floor
(scenarios/noise_floor.json, written by ``mapfusion noise``): per run, Map-Fusion's ATE within twice
the range of its noise-floor fusions of its baseline, no new de-localisation, the match rate within a
point; per family, the mean ATE, the de-localised count and the worst run against the odometry within
twice their own noise-floor range (at least 1% of the mean, 0.05 m). Claims (the paper's): rain and heavy rain reduce the mean ATE by at least 40%;
in clear weather Map-Fusion is never worse than odometry by more than 0.3 m; at intersections the
match rate is at least 97%. Claims the engine does not meet yet are strict expected failures with
the measured figure, so that meeting them is noticed.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim.scenario import load_family

from mapfusion.harness.regression import check_family, check_run

from .conftest import FAMILIES, family_group, family_results, load_baselines, load_noise_floor

pytestmark = pytest.mark.sumo

FAMILY_NAMES = ("clear", "rain", "rain-tunnel", "heavy-rain", "intersections", "kitti", "kitti-real", "kitti-realism",
                "kidnapped")
# the families of the long KITTI drives (50 runs): `slow`, run by pytest -m slow (as CI does), not by default
SLOW_FAMILIES = ("kitti", "kitti-realism")
# the larger set: pytest -m full scenarios/ (kitti-real has one run per real odometry result: no larger set)
FULL_NAMES = tuple(f"{f}-full" for f in FAMILY_NAMES if (FAMILIES / f"{f}-full.toml").exists())


def family(name: str) -> pytest.MarkDecorator:
    """The family a test reads: under pytest-xdist its runs and every test of it go to one worker, which computes
    the family once (each family on its own, so that the families share both workers)."""
    return pytest.mark.xdist_group(family_group(name))


def _marks(fam: str) -> list:
    return ([family(fam)] + ([pytest.mark.full] if fam in FULL_NAMES else [])
            + ([pytest.mark.slow] if fam in SLOW_FAMILIES else []))


def _runs():
    """Every run of every family; a run whose real data is not available here ($MAPFUSION_DATA unset)
    is skipped, saying so."""
    out = []
    for fam in FAMILY_NAMES + FULL_NAMES:
        loaded = load_family(FAMILIES / f"{fam}.toml")
        marks = _marks(fam)
        out += [pytest.param(fam, sc.name, id=sc.name, marks=marks) for sc in loaded.scenarios]
        out += [pytest.param(fam, name, id=name, marks=marks + [pytest.mark.skip(reason=why)])
                for name, why in loaded.unavailable]
    return out


RUNS = _runs()


@pytest.mark.parametrize("family,run", RUNS)
def test_run_does_not_regress(request, family, run):
    r = family_results(request.config, family)[run]
    assert "error" not in r, r.get("error")
    if request.config.getoption("--update-baselines"):
        return
    base = load_baselines().get(run)
    assert base is not None, f"no recorded baseline for {run}: run pytest scenarios --update-baselines"
    problems = check_run(r, base, load_noise_floor().get(run))
    assert not problems, "; ".join(problems)


_FAMILY_PARAMS = [pytest.param(f, id=f, marks=_marks(f)) for f in FAMILY_NAMES + FULL_NAMES]


@pytest.mark.parametrize("name", _FAMILY_PARAMS)
def test_family_does_not_regress(request, name):
    """The family's mean ATE, de-localised count and worst run against the odometry, against its baselines
    and within its noise floor's spread: the shift of a few percent that no single run's tolerance sees."""
    rows = [r for r in family_results(request.config, name).values() if "error" not in r]
    if request.config.getoption("--update-baselines"):
        return
    if not rows:
        pytest.skip(f"no run of {name} can be made here")
    problems = check_family(rows, load_baselines(), load_noise_floor())
    assert not problems, "; ".join(problems)


def _whole(request, family):
    """Every run of the family, for a claim made over all of them: skipped where some need real data that is not
    here ($MAPFUSION_DATA), since the claim over the rest is another claim."""
    missing = load_family(FAMILIES / f"{family}.toml").unavailable
    if missing:
        pytest.skip(f"{len(missing)} runs of the family need real data: {missing[0][1]}")
    return _ok(request, family)


def _ok(request, family):
    rows = [r for r in family_results(request.config, family).values() if "error" not in r]
    assert rows, f"every run of {family} failed"
    return rows


def _reduction(rows) -> float:
    mo = np.mean([r["ate_odometry_m"] for r in rows])
    mm = np.mean([r["ate_mapfusion_m"] for r in rows])
    return 1.0 - mm / mo


@family("rain")
def test_rain_reduces_mean_ate_by_40_percent(request):
    assert _reduction(_ok(request, "rain")) >= 0.40


@family("heavy-rain")
def test_heavy_rain_reduces_mean_ate_by_40_percent(request):
    """52%, 5.71 → 2.72 m (pytest scenarios/ -k heavy_rain)."""
    assert _reduction(_ok(request, "heavy-rain")) >= 0.40


@family("clear")
def test_clear_never_worse_by_more_than_0_3_m(request):
    rows = _ok(request, "clear")
    assert max(r["ate_mapfusion_m"] - r["ate_odometry_m"] for r in rows) <= 0.3


@family("intersections")
@pytest.mark.xfail(strict=True, raises=AssertionError, reason=(
    "match rate 96.966% over the family, the same in all six noise-floor fusions (scenarios/noise_floor.json): "
    "0.034 points short, beyond its noise. The SUMO Helsinki runs match 85.2% and 72.3%: with the fitted VO's "
    "heading noise the estimate reaches junctions off its road and the single-frame match takes the crossing "
    "road; Berlin and Bayreuth 99.1-99.8% (pytest scenarios/ -k intersections)"))
def test_intersections_match_rate_at_least_97_percent(request):
    """Over the whole family, the real Berlin and Bayreuth extracts included: without $MAPFUSION_DATA
    the claim cannot be checked (the synthetic and Helsinki runs alone measured 96.9%)."""
    rows = _whole(request, "intersections")
    assert np.mean([r["match_rate"] for r in rows]) >= 0.97


def _real(request):
    missing = load_family(FAMILIES / "kitti-real.toml").unavailable
    if missing:
        pytest.skip(f"the real odometry results need real data: {missing[0][1]}")
    return _ok(request, "kitti-real")


@family("kitti-real")
def test_real_odometry_the_map_never_makes_a_drive_worse(request):
    """Issue 16: with real VO results on the real drives (RTK GPS for the first 30 s), Map-Fusion is
    never worse than the same engine without the map. (The one that was, TrianFlow 01, lost either way, is
    4 km of motorway whose VO's scale collapses eightfold inside the GPS: the track run re-scales it, 487.3 →
    405.7 m.)"""
    rows = _real(request)
    assert all(r["ate_mapfusion_m"] <= r["ate_odometry_m"] for r in rows)


@family("kitti-real")
def test_real_odometry_30_percent_better_on_average(request):
    assert _reduction(_real(request)) >= 0.30



@family("rain-tunnel")
@pytest.mark.xfail(strict=True, raises=AssertionError, reason=(
    "the vo+wheel zones' mean error 5.007 m (5.006-5.008 m over the six noise-floor fusions, "
    "scenarios/noise_floor.json: 0.007 m over the 5 m, three times its range); none de-localised; Andorra s2 "
    "10.4 m in its zone (pytest scenarios/ -k rain-tunnel)"))
def test_rain_tunnel_with_wheel_and_gyro_is_never_lost_and_within_5_m_in_the_zones(request):
    """Issue 18: with wheel speed and gyro beside the VO (odometry vo+wheel), no run de-localises,
    every run has estimates inside the GPS-denied, visually degraded zones (the estimate never stops
    where the camera fails), and their mean error there is at most 5 m: over the whole family, the Andorra
    extract included (without $MAPFUSION_DATA the claim cannot be checked)."""
    rows = [r for r in _whole(request, "rain-tunnel") if r["odometry"] == "vo+wheel"]
    assert rows, "the family has no vo+wheel runs"
    assert not [r["scenario"] for r in rows if r["delocalized_mapfusion"]]
    zones = [r["tunnel_rmse_mapfusion_m"] for r in rows]
    assert all(z is not None and np.isfinite(z) for z in zones), zones
    assert np.mean(zones) <= 5.0


def _kidnapped(request):
    rows = [r for r in _ok(request, "kidnapped") if r.get("kidnap")]
    assert rows, "no run of the family was kidnapped"
    return rows


@family("kidnapped")
def test_kidnapped_runs_are_relocalised_within_500_m(request):
    """Issue 17: after the kidnap (a biased fix window, or a VO that re-initialises 30–300 m off) and with no
    GPS after it, at least 90% of the runs are found again by the map within 500 m of driving: 8 of 8 here; seeds
    1–10 37 of 40 (mapfusion run k.toml, docs/method.md "Found again without GPS")."""
    rows = _kidnapped(request)
    found = [r for r in rows if r["relocalised"] and r["relocalisation_m"] <= 500.0]
    assert len(found) >= 0.9 * len(rows), sorted((r["scenario"], r["relocalisation_m"]) for r in rows)


@family("kidnapped")
@pytest.mark.xfail(strict=True, raises=AssertionError, reason="mean online error after re-localisation 5.85 m over this "
                   "family (3.1-9.2 m a run), none re-anchored wrong; seeds 1-10 7.26 m (mapfusion run k.toml). The "
                   "same runs re-anchored on the true pose where the after-error starts give 6.87 m and never "
                   "kidnapped 7.67 m (python -m mapfusion.harness.bounds kidnapped k.toml): no re-localisation "
                   "reaches 5 m on this VO's tracking without GPS, whose along-road error is 5-12 m between junctions")
def test_kidnapped_runs_are_within_5_m_after_relocalisation_and_never_stay_wrong(request):
    """Issue 17: after re-localisation the mean online error is at most 5 m; no wrong convergence stays
    wrong for more than 200 m."""
    rows = [r for r in _kidnapped(request) if r["relocalised"]]
    assert rows
    assert np.mean([r["online_mean_after_relocalisation_m"] for r in rows]) <= 5.0
    assert max(r["wrong_relocalisation_max_m"] for r in rows) <= 200.0
