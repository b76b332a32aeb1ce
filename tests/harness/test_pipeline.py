"""sim.run: one scenario simulated, then fused and evaluated (regressions found on real runs)."""

from __future__ import annotations

from pathlib import Path

import pytest

from mapfusion.config import Backend, Factorization
from sim.run import fuse_and_evaluate, simulate_scenario
from sim.scenario import load_family, scenario_from_dict
from sim.sweep import with_params

pytestmark = pytest.mark.sumo
FAMILIES = Path(__file__).parents[2] / "scenarios" / "families"


def test_isam2_with_cholesky_survives_a_failed_update():
    """The tunnel run that made ISAM2's Cholesky fail: the engine re-anchors and asks no marginal of
    a key the new Bayes tree does not hold (it raised IndexError before)."""
    fam = load_family(FAMILIES / "rain-tunnel.toml")
    sc = next(s for s in fam.scenarios if s.name == "rain-tunnel-tunnel-vo-s2")
    simulation = simulate_scenario(sc)
    cfg = with_params(sc.mapfusion, {"backend": Backend.isam2.value, "factorization": Factorization.cholesky.value})
    m, base, mf = fuse_and_evaluate(simulation, cfg)
    assert "error" not in m
    assert base.engine.counters.recoveries + mf.engine.counters.recoveries > 0  # the failure did happen



def test_a_scale_fit_bent_by_drift_does_not_replace_the_windows_median():
    """rain40-helsinki-vo-s8: rain drift inside the 120 s GPS window bends the odometry so that the
    least-squares similarity fit reads a 5% scale error where the windows' median is right (the
    simulated VO's scale error is 1 ± 0.5%); the fit must not replace a median it disagrees with."""
    sc = scenario_from_dict({"name": "rain-helsinki-vo-s8", "map": "helsinki", "seed": 8, "duration_s": 480.0,
                                "min_route_m": 1500.0, "weather": {"kind": "rain"}, "odometry": {"kind": "vo"},
                                "gps": {"mode": "init_only"}}, "test")
    simulation = simulate_scenario(sc)
    scales = {}
    for limit in (0.0, 3.0):
        _, base, _ = fuse_and_evaluate(simulation, with_params(sc.mapfusion, {"scale_fit_max_disagreement_sigma": limit}))
        scales[limit] = (base.engine.scale, base.engine.scale_windows)
    fit_alone, median = scales[0.0]
    assert abs(median - 1.0) < 0.01
    assert abs(fit_alone - 1.0) > 0.03  # the case the rule is for
    assert abs(scales[3.0][0] - 1.0) < 0.01
