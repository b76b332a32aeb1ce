"""Estimators as plug-ins: a method written outside the package, scored by ``mapfusion run`` beside Map-Fusion."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mapfusion.harness.cli import app
from mapfusion.harness.estimators import StreamingEstimator, load_class
from mapfusion.errors import InputError

runner = CliRunner()
TWIN = Path(__file__).resolve().parent / "estimator_twin.py"


class GpsDeadReckoning:
    """The odometry dead-reckoned from the last GPS fix, turned onto the fixes' bearing: a 30-line estimator."""

    def __init__(self, road, min_baseline_m: float = 10.0) -> None:
        self.projection, self.min_baseline_m = road.projection, min_baseline_m
        self.odo = np.eye(4)  # the odometry's own pose
        self.fixes: list[tuple[np.ndarray, np.ndarray]] = []  # (ENU position, odometry position) at each fix
        self.turn = None  # odometry frame → ENU rotation about z, once two fixes lie far enough apart

    def add_odometry(self, t_s: float, relative_pose: np.ndarray) -> None:
        self.odo = self.odo @ relative_pose

    def add_gps(self, t_s: float, lat: float, lon: float, alt=None, sigma_m=None) -> None:
        x, y = self.projection.to_enu(lat, lon)
        self.fixes.append((np.array([float(x), float(y)]), self.odo[:2, 3].copy()))
        first = self.fixes[0]
        d_enu, d_odo = self.fixes[-1][0] - first[0], self.fixes[-1][1] - first[1]
        if self.turn is None and np.linalg.norm(d_enu) >= self.min_baseline_m and np.linalg.norm(d_odo) > 0:
            self.turn = math.atan2(d_enu[1], d_enu[0]) - math.atan2(d_odo[1], d_odo[0])

    def estimate(self):
        if self.turn is None:
            return None
        c, s = math.cos(self.turn), math.sin(self.turn)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        enu, odo = self.fixes[-1]
        pose = np.eye(4)
        pose[:3, :3] = rot @ self.odo[:3, :3]
        pose[:2, 3] = enu + (rot[:2, :2] @ (self.odo[:2, 3] - odo))
        return pose


class Broken(GpsDeadReckoning):
    def add_gps(self, t_s, lat, lon, alt=None, sigma_m=None):
        raise RuntimeError("no satellites today")


def _family(tmp_path: Path, estimators: str) -> Path:
    fam = tmp_path / "f.toml"
    fam.write_text('[family]\nname = "plug"\nseeds = [1, 2]\n[base]\nmap = "grid"\nduration_s = 150.0\n'
                   'min_route_m = 800.0\n[base.gps]\nmode = "interval"\ninterval_s = 5.0\n' + estimators)
    return fam


@pytest.mark.slow
@pytest.mark.sumo
def test_an_estimator_written_outside_the_package_is_scored_beside_map_fusion(tmp_path):
    """The class above and its external twin (a script reading the run's files, writing TUM) on a family: both in
    results.jsonl, the table and the run directory, equal to 1e-9 m; a failing one fails its own column only."""
    me = "tests.harness.test_estimators"
    fam = _family(tmp_path, f'[[base.estimators]]\nname = "deadreck"\nuse = "{me}:GpsDeadReckoning"\n'
                  f'params = {{ min_baseline_m = 10.0 }}\n'
                  f'[[base.estimators]]\nname = "twin"\ncommand = "{sys.executable} {TWIN} {{odometry}} {{gps}} {{map}} {{out}}"\n'
                  f'[[base.estimators]]\nname = "broken"\nuse = "{me}:Broken"\n'
                  f'[[base.estimators]]\nname = "crashes"\ncommand = "{sys.executable} {TWIN} --fail {{out}}"\n')
    out = tmp_path / "out"
    r = runner.invoke(app, ["run", str(fam), "--out", str(out), "--no-plot", "-j", "2"])
    assert r.exit_code == 0, r.output
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert len(rows) == 2
    for row in rows:
        assert row["estimators"] == ["deadreck", "twin", "broken", "crashes"]
        assert row["ate_mapfusion_m"] > 0 and "error" not in row
        assert abs(row["ate_deadreck_m"] - row["ate_twin_m"]) <= 1e-9, row
        assert abs(row["online_rmse_deadreck_m"] - row["online_rmse_twin_m"]) <= 1e-9, row
        # GPS every 5 s keeps dead reckoning near the truth: a real score, not a placeholder
        assert 0.0 < row["ate_deadreck_m"] < 50.0 and row["delocalized_deadreck"] in (True, False)
        errors = row["estimator_errors"]
        assert sorted(errors) == ["broken", "crashes"]
        assert "no satellites today" in errors["broken"] and "exited 3" in errors["crashes"]
        assert "ate_broken_m" not in row
        assert (out / row["scenario"] / "estimate_deadreck.tum").stat().st_size > 0
        assert "estimators" in (out / row["scenario"] / "scenario.toml").read_text()
    assert "deadreck" in r.stdout and "twin" in r.stdout  # the table's rows
    assert "estimator broken failed" in r.stderr


def test_the_protocol_and_the_loader():
    assert isinstance(GpsDeadReckoning.__new__(GpsDeadReckoning), StreamingEstimator)
    assert load_class("tests.harness.test_estimators:GpsDeadReckoning") is GpsDeadReckoning
    for bad, needle in [("tests.harness.test_estimators:Nope", "has no Nope"), ("no_such_module_x:A", "cannot import"),
                        ("nothing-registered", "entry point"), ("tests.harness.test_estimators:math", "not a class"),
                        ("tests.harness.test_estimators:Path", "has no add_odometry")]:
        with pytest.raises(InputError, match=needle):
            load_class(bad)


def test_a_class_that_cannot_be_imported_is_refused_before_any_run(tmp_path):
    fam = _family(tmp_path, '[[base.estimators]]\nname = "ghost"\nuse = "no_such_module_x:Filter"\n')
    r = runner.invoke(app, ["run", str(fam), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "no_such_module_x" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o" / "results.jsonl").exists()


@pytest.mark.slow
@pytest.mark.sumo
def test_a_sweep_scores_the_plug_ins_once_per_run_in_every_row(tmp_path):
    fam = _family(tmp_path, '[[base.estimators]]\nname = "deadreck"\nuse = "tests.harness.test_estimators:GpsDeadReckoning"\n')
    fam.write_text(fam.read_text().replace("seeds = [1, 2]", "seeds = [1]"))
    r = runner.invoke(app, ["sweep", str(fam), "--out", str(tmp_path / "sw"), "-p", "lane_width_m=2,4", "-j", "1"])
    assert r.exit_code == 0, r.output
    rows = [json.loads(line) for line in (tmp_path / "sw" / "results.jsonl").read_text().splitlines()]
    assert len(rows) == 2 and rows[0]["params"] != rows[1]["params"]
    assert rows[0]["ate_deadreck_m"] == rows[1]["ate_deadreck_m"] > 0.0
    assert "deadreck" in r.stdout


def test_the_tables_show_a_row_per_plug_in():
    """The paper table and Table I: a row per plug-in, its Avg leaving its de-localised runs out, `failed` where
    it failed on a run."""
    from io import StringIO

    from rich.console import Console

    from mapfusion.harness.tables import paper_table, table_one

    def row(seq, seed, ekf, deloc=False, failed=False):
        r = {"scenario": f"kitti-{seq}-clear-vo-s{seed}", "recorded": f"/d/kitti/{seq}", "odometry": "vo",
             "weather": "clear", "ate_odometry_m": 5.0, "ate_mapfusion_m": 2.0, "ate_reduction_m": 3.0,
             "delocalized_odometry": False, "delocalized_mapfusion": False, "estimators": ["ekf"]}
        if failed:
            r["estimator_errors"] = {"ekf": "boom"}
        else:
            r.update({"ate_ekf_m": ekf, "delocalized_ekf": deloc})
        return r

    rows = [row("00", 1, 4.0), row("00", 2, 30.0, deloc=True), row("05", 1, 0.0, failed=True), row("07", 1, 6.0)]

    def cells(table):
        buf = StringIO()
        Console(file=buf, width=250).print(table)
        return {ln.split("│")[1].strip(): [c.strip() for c in ln.split("│")[2:-1]] for ln in buf.getvalue().splitlines()
                if ln.startswith("│")}

    assert cells(paper_table(rows, "t"))["ekf"] == ["4.00", "x", "failed", "6.00", "5.00"]
    assert cells(table_one(rows, "t"))["VO clear ekf"] == ["4.00", "failed", "6.00", "5.00"]
