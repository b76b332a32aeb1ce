"""mapfusion.harness.pipeline: one scenario simulated, then fused and evaluated (regressions found on real runs)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mapfusion.config import Backend, Factorization
from mapfusion.harness.pipeline import fuse_and_evaluate, simulate_scenario
from sim.scenario import load_family, scenario_from_dict
from mapfusion.harness.sweep import with_params
from mapfusion.metrics import ate
from tests.mapfusion.test_metrics import _evo_ape

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



@pytest.mark.slow
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


@pytest.mark.sumo
def test_ate_equals_evo_on_a_simulated_run():
    from mapfusion import RoadMap
    from mapfusion.config import FusionConfig
    from mapfusion.formats import GpsFixes
    from mapfusion.metrics import associate
    from mapfusion.replay import fuse
    from sim.drive import run_drive
    from sim.scenario import scenario_from_dict
    from sim.sensors import Truth, synthesise

    sc = scenario_from_dict({"name": "evo", "map": "grid", "seed": 4, "duration_s": 200.0, "min_route_m": 1000.0,
                             "weather": {"kind": "rain"}}, "test")
    road = RoadMap.from_osm(sc.map)
    drive = run_drive(sc, road)
    truth = Truth.from_track(drive.ego, gps=sc.gps)
    sensors = synthesise(sc, truth)
    lat, lon = road.projection.to_geo(sensors.gps.x_m, sensors.gps.y_m)
    fixes = GpsFixes(sensors.gps.t_s, np.asarray(lat), np.asarray(lon), np.full(len(lat), np.nan), sensors.gps.sigma_m)
    res = fuse(road, sensors.odometry.t_s, sensors.odometry.poses, fixes, FusionConfig())
    ok = [i for i, p in enumerate(res.online) if p is not None]
    est = np.array([[res.online[i].x(), res.online[i].y(), res.online[i].z()] for i in ok])
    ia, ib = associate(res.t_s[ok], drive.ego.t_s)
    gt = np.column_stack([drive.ego.x_m, drive.ego.y_m, drive.ego.z_m])[ib]
    assert len(ia) > 500
    assert ate(gt, est[ia]) == pytest.approx(_evo_ape(gt, est[ia]), abs=1e-6)
