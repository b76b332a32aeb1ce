"""Recorded drives in place of SUMO: the real KITTI drives, their RTK GPS, and the kitti runs."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mapfusion.harness.cli import app
from mapfusion.errors import InputError
from mapfusion.roadmap import RoadMap
from sim.recorded import load_recorded, recorded_gps
from sim.scenario import GpsMode, scenario_from_dict
from tests.helpers import DATA, data_required

pytestmark = data_required("kitti")


def _kitti(seq: str = "07", **kw):
    d = {"name": f"k{seq}", "truth": f"{DATA}/kitti/{seq}", "duration_s": 86400.0,
         "gps": {"source": "recorded", "rate_hz": 10.0, "init_window_s": 30.0, "sigma_m": 0.5}}
    d.update(kw)
    sc = scenario_from_dict(d, "test")
    return sc, RoadMap.from_osm(sc.map)


def test_recorded_gps_is_the_rtk_track_at_the_camera():
    sc, road = _kitti("07")
    rec = load_recorded(sc.truth, sc, road)
    assert len(rec.truth) == 1101 and rec.georef_residual_m < 0.5
    g = recorded_gps(rec, sc.gps)
    t = g.t_s - rec.truth.t_s[0]
    assert t.max() < 30.0 + 0.11 and 290 <= len(t) <= 302  # 10 Hz for 30 s (the first frame at or after a tick)
    err = np.hypot(g.x_m - rec.truth.x_m[g.frame_index], g.y_m - rec.truth.y_m[g.frame_index])
    assert np.sqrt(np.mean(err**2)) < 0.5  # the lever arm is removed: fixes sit on camera 0
    assert not g.outlier.any() and np.all(g.sigma_m == 0.5)


def test_interval_mode_and_zones_deny_recorded_fixes():
    sc, road = _kitti("07", gps={"source": "recorded", "mode": "interval", "rate_hz": 1.0, "init_window_s": 20.0,
                                 "interval_s": 5.0}, tunnels=[{"start_m": 300.0, "end_m": 450.0}])
    rec = load_recorded(sc.truth, sc, road)
    g = recorded_gps(rec, sc.gps)
    t = g.t_s - rec.truth.t_s[0]
    late = t[t > 20.5]
    assert len(late) > 5 and np.allclose(np.diff(late)[np.diff(late) < 6.0], 5.0, atol=0.15)
    dist = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(rec.truth.x_m), np.diff(rec.truth.y_m)))))
    d_fix = dist[g.frame_index]
    assert not np.any((d_fix >= 300.0) & (d_fix <= 450.0))
    assert rec.truth.visually_degraded.any()


def test_a_tum_truth_with_its_gps_csv_is_the_same_drive(tmp_path):
    sc, road = _kitti("07")
    d = Path(DATA) / "kitti" / "07"
    run = tmp_path / "imp"
    r = CliRunner().invoke(app, ["import", "kitti", "--poses", str(d / "poses.txt"), "--times", str(d / "times.txt"),
                                 "--gps", str(d / "rtk_gps.kml"), "--out", str(run)])
    assert r.exit_code == 0, r.output
    a = load_recorded(sc.truth, sc, road)
    b = load_recorded(run / "truth.tum", sc, road)
    assert np.allclose(a.truth.x_m, b.truth.x_m, atol=1e-3) and np.allclose(a.truth.yaw_rad, b.truth.yaw_rad, atol=1e-5)
    ga, gb = recorded_gps(a, sc.gps), recorded_gps(b, sc.gps)
    assert np.allclose(ga.t_s, gb.t_s) and np.allclose(ga.x_m, gb.x_m, atol=1e-3)
    (run / "gps.csv").unlink()
    with pytest.raises(InputError, match="has no GPS"):
        recorded_gps(load_recorded(run / "truth.tum", sc, road), sc.gps)


def test_duration_cuts_the_recorded_drive():
    sc, road = _kitti("07", duration_s=50.0)
    rec = load_recorded(sc.truth, sc, road)
    assert rec.truth.t_s[-1] - rec.truth.t_s[0] <= 50.0 and len(rec.truth) > 450


def test_a_kitti_run_end_to_end():
    from mapfusion.harness.pipeline import run_scenario

    sc, _ = _kitti("07", weather={"kind": "rain"})
    m = run_scenario(sc, plot=False).metrics
    assert "error" not in m, m.get("error")
    assert m["frames"] == 1101 and m["georef_residual_m"] < 0.5 and m["match_rate"] is None
    assert m["gps_mode"] == GpsMode.init_only.value and m["initialised_at_s"] < 30.0
    assert not m["delocalized_mapfusion"] and m["ate_mapfusion_m"] < 5.0
