"""The command line: outputs, and one clear line with exit code 2 on bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from mapfusion.cli import app
from tests.helpers import MAPS

runner = CliRunner()


def test_maps_build_json():
    r = runner.invoke(app, ["maps", "build", str(MAPS / "synthetic" / "grid.osm"), "--json"])
    assert r.exit_code == 0, r.output
    stats = json.loads(r.stdout)
    for key in ("ways", "junctions", "waypoints", "road_km", "tunnel_km", "mean_spacing_m", "build_s"):
        assert key in stats
    assert stats["ways"] == 13


def test_maps_build_table_by_builtin_name():
    r = runner.invoke(app, ["maps", "build", "tunnel"])
    assert r.exit_code == 0
    assert "tunnel length" in r.stdout and "0.70 km" in r.stdout


def test_maps_generate(tmp_path):
    out = tmp_path / "g.osm"
    r = runner.invoke(app, ["maps", "generate", "grid", "--out", str(out), "-p", "cols=3", "-p", "rows=2"])
    assert r.exit_code == 0, r.output
    assert out.read_text().startswith("<?xml")


@pytest.mark.parametrize(
    "args,needle",
    [
        (["maps", "build", "/no/such/map.osm"], "/no/such/map.osm"),
        (["maps", "generate", "spiral", "--out", "x.osm"], "spiral"),
        (["maps", "generate", "grid", "--out", "x.osm", "-p", "colz=3"], "colz"),
        (["maps", "generate", "grid", "--out", "x.osm", "-p", "cols=many"], "cols"),
        (["maps", "generate", "city", "--out", "x.osm", "-p", "width_km=40"], "10 km"),
    ],
)
def test_bad_input_exits_2(args, needle, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    r = runner.invoke(app, args)
    assert r.exit_code == 2
    assert needle in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert "Traceback" not in r.output


def test_console_script_bad_file_one_line(tmp_path):
    bad = tmp_path / "broken.osm.pbf"
    bad.write_bytes((MAPS / "kotka.osm.pbf").read_bytes()[:5000])
    p = subprocess.run([sys.executable, "-m", "mapfusion.cli", "maps", "build", str(bad)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "broken.osm.pbf" in lines[0] and "Traceback" not in p.stderr


def test_help_on_every_command():
    for args in (["--help"], ["maps", "--help"], ["maps", "build", "--help"], ["maps", "generate", "--help"], ["demo", "--help"]):
        r = runner.invoke(app, args)
        assert r.exit_code == 0 and "Usage" in r.stdout


@pytest.mark.sumo
def test_simulate_writes_the_run_directory(tmp_path):
    sc = tmp_path / "s.toml"
    sc.write_text('name = "cli"\nmap = "grid"\nseed = 2\nduration_s = 60.0\nmin_route_m = 500.0\n')
    out = tmp_path / "run"
    r = runner.invoke(app, ["simulate", str(sc), "--out", str(out)])
    assert r.exit_code == 0, r.output
    for f in ("scenario.toml", "truth.tum", "truth.csv", "drive.json"):
        assert (out / f).stat().st_size > 0
    header = (out / "truth.csv").read_text().splitlines()[0].split(",")
    assert header[:11] == ["t", "x", "y", "z", "yaw", "speed", "lat", "lon", "sumo_edge", "osm_way", "in_tunnel"]
    assert "/maps/synthetic/grid.osm" in (out / "scenario.toml").read_text()  # fully resolved


@pytest.mark.sumo
@pytest.mark.parametrize(
    "text,needle",
    [
        ('map = "grid"\n[gps]\nsigmaa_m = 3\n', "gps.sigmaa_m"),
        ('map = "atlantis.osm"\n', "atlantis.osm"),
        ('map = "grid"\n[route]\nedges = ["nope"]\n', "nope"),
        ('map = "y-split"\nmin_route_m = 150000.0\n[route]\nmax_trips = 3\n', "no route"),
    ],
)
def test_simulate_bad_input_exits_2(tmp_path, text, needle):
    sc = tmp_path / "bad.toml"
    sc.write_text(text)
    r = runner.invoke(app, ["simulate", str(sc), "--out", str(tmp_path / "r")])
    assert r.exit_code == 2, r.output
    assert needle in r.stderr and len(r.stderr.strip().splitlines()) == 1
