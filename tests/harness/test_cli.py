"""The command line: outputs, and one clear line with exit code 2 on bad input."""

from __future__ import annotations

import json
import math

import numpy as np
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from mapfusion.harness.cli import app
from tests.helpers import MAPS
from tests.harness.sim_helpers import simulated_grid_run

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
        (["maps", "generate", "city", "--out", "x.osm", "-p", "width_km=40"], "width_km"),
        (["bench", "--config", "nope.toml"], "nope.toml"),
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
    p = subprocess.run([sys.executable, "-m", "mapfusion.harness.cli", "maps", "build", str(bad)],
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


# ----------------------------------------------------------------------------- fuse
@pytest.fixture(scope="module")
def sim_run(tmp_path_factory):
    """A short simulated drive on the grid map with GPS throughout (so the engine initialises)."""
    return simulated_grid_run(tmp_path_factory.mktemp("run"), "f", 3)


@pytest.mark.sumo
def test_fuse_writes_an_estimate_near_the_truth(sim_run, tmp_path):
    from mapfusion.formats import read_tum
    from mapfusion.metrics import associate

    out = tmp_path / "est.tum"
    r = runner.invoke(app, ["fuse", "--map", "grid", "--odometry", str(sim_run / "odometry.tum"),
                            "--gps", str(sim_run / "gps.csv"), "--out", str(out), "--smoothed", str(tmp_path / "s.tum")])
    assert r.exit_code == 0, r.output
    te, xe, _ = read_tum(out)
    tt, xt, _ = read_tum(sim_run / "truth.tum")
    ia, ib = associate(te, tt)
    assert len(ia) > 0.5 * len(tt)
    err = np.hypot(*(xe[ia, :2] - xt[ib, :2]).T)
    assert np.sqrt(np.mean(err**2)) < 5.0  # GPS throughout at σ = 2 m
    assert (tmp_path / "s.tum").stat().st_size > 0


@pytest.mark.sumo
def test_fuse_reads_kitti_camera_poses(sim_run, tmp_path):
    from mapfusion.formats import read_tum, tum_to_matrices
    from mapfusion.replay import body_to_camera

    t, xyz, q = read_tum(sim_run / "odometry.tum")
    cam = body_to_camera(tum_to_matrices(xyz, q))
    (tmp_path / "poses.txt").write_text("\n".join(" ".join(f"{v:.9f}" for v in m[:3, :4].ravel()) for m in cam) + "\n")
    (tmp_path / "times.txt").write_text("\n".join(f"{v:.6f}" for v in t) + "\n")
    args = ["fuse", "--map", "grid", "--odometry", str(tmp_path / "poses.txt"), "--odometry-format", "kitti",
            "--times", str(tmp_path / "times.txt"), "--odometry-frame", "camera", "--gps", str(sim_run / "gps.csv")]
    r = runner.invoke(app, args + ["--out", str(tmp_path / "k.tum")])
    assert r.exit_code == 0, r.output
    r2 = runner.invoke(app, ["fuse", "--map", "grid", "--odometry", str(sim_run / "odometry.tum"),
                             "--gps", str(sim_run / "gps.csv"), "--out", str(tmp_path / "b.tum")])
    assert r2.exit_code == 0
    _, a, _ = read_tum(tmp_path / "k.tum")
    _, b, _ = read_tum(tmp_path / "b.tum")
    assert np.abs(a - b).max() < 1e-3  # the same motion, whichever file format and frame


@pytest.mark.sumo
@pytest.mark.parametrize(
    "mutate,needle",
    [
        (lambda p: p.write_text(p.read_text() + "1 2 3 4 5 6 7 8 9 10 11\n"), ":"),
        (lambda p: p.write_text("1 2 3\n"), ":1:"),
    ],
)
def test_fuse_bad_kitti_lines_exit_2(sim_run, tmp_path, mutate, needle):
    poses = tmp_path / "poses.txt"
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1 0 1 0 0 0 0 1 0\n")
    mutate(poses)
    times = tmp_path / "times.txt"
    times.write_text("0.0\n0.1\n0.2\n")
    r = runner.invoke(app, ["fuse", "--map", "grid", "--odometry", str(poses), "--odometry-format", "kitti",
                            "--times", str(times), "--gps", str(sim_run / "gps.csv"), "--out", str(tmp_path / "x.tum")])
    assert r.exit_code == 2
    assert "poses.txt" in r.stderr and needle in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.sumo
def test_fuse_no_map_adds_no_priors(sim_run, tmp_path):
    r = runner.invoke(app, ["fuse", "--map", "grid", "--odometry", str(sim_run / "odometry.tum"),
                            "--gps", str(sim_run / "gps.csv"), "--out", str(tmp_path / "n.tum"), "--no-map"])
    assert r.exit_code == 0 and "map priors 0" in r.stdout


def test_camera_body_round_trip():
    from mapfusion.replay import body_to_camera, camera_to_body

    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    m = np.tile(np.eye(4), (20, 1, 1))
    m[:, :3, :3] = Rotation.random(20, random_state=1).as_matrix()
    m[:, :3, 3] = rng.normal(0, 10, (20, 3))
    assert np.allclose(body_to_camera(camera_to_body(m)), m)
    # a camera moving along its z (forward) moves along the body's x
    fwd = np.eye(4)
    fwd[2, 3] = 1.0
    assert np.allclose(camera_to_body(fwd[None])[0][:3, 3], [1.0, 0.0, 0.0])


@pytest.mark.sumo
def test_fuse_recovers_after_losing_track_in_a_tunnel(tmp_path):
    """The vo loses track through the 700 m tunnel and re-initialises with a constant-velocity guess
    that misses the tunnel's bend by hundreds of metres; the fixes after the tunnel must win."""
    from mapfusion.formats import read_gps_csv, read_tum
    from mapfusion.metrics import associate

    sc = tmp_path / "s.toml"
    sc.write_text('name = "t"\nmap = "tunnel"\nseed = 3\nduration_s = 150.0\n[route]\nedges = ["1", "3"]\n'
                  '[gps]\nmode = "continuous"\n')
    assert runner.invoke(app, ["simulate", str(sc), "--out", str(tmp_path / "run")]).exit_code == 0
    run = tmp_path / "run"
    r = runner.invoke(app, ["fuse", "--map", "tunnel", "--odometry", str(run / "odometry.tum"),
                            "--gps", str(run / "gps.csv"), "--out", str(tmp_path / "e.tum")])
    assert r.exit_code == 0, r.output
    te, xe, _ = read_tum(tmp_path / "e.tum")
    tt, xt, _ = read_tum(run / "truth.tum")
    ia, ib = associate(te, tt)
    err = np.hypot(*(xe[ia, :2] - xt[ib, :2]).T)
    gps = read_gps_csv(run / "gps.csv")
    exit_t = gps.t_s[np.argmax(np.diff(gps.t_s)) + 1]  # the first fix after the tunnel
    late = te[ia] > exit_t + 15.0
    assert late.sum() > 20
    assert err[late].max() < 10.0, err[late].max()


@pytest.mark.sumo
def test_fuse_with_wheel_and_gyro_keeps_an_estimate_through_the_tunnel(tmp_path):
    """The same drive with the car's wheel speed and gyro (issue 18): simulate writes wheel.csv, and
    `fuse --wheel --imu` has an estimate at every frame inside the 700 m tunnel, where the VO alone has
    none, within 10 m of the truth there."""
    from mapfusion.formats import read_gps_csv, read_tum, read_wheel_csv
    from mapfusion.metrics import associate

    sc = tmp_path / "s.toml"
    sc.write_text('name = "t"\nmap = "tunnel"\nseed = 3\nduration_s = 150.0\n[route]\nedges = ["1", "3"]\n'
                  '[gps]\nmode = "continuous"\n[odometry]\nkind = "vo+wheel"\n')
    assert runner.invoke(app, ["simulate", str(sc), "--out", str(tmp_path / "run")]).exit_code == 0
    run = tmp_path / "run"
    tw, _ = read_wheel_csv(run / "wheel.csv")
    base = ["fuse", "--map", "tunnel", "--odometry", str(run / "odometry.tum"), "--gps", str(run / "gps.csv")]
    alone = runner.invoke(app, base + ["--out", str(tmp_path / "vo.tum")])
    wheel = runner.invoke(app, base + ["--wheel", str(run / "wheel.csv"), "--imu", str(run / "imu.csv"),
                                       "--out", str(tmp_path / "wheel.tum")])
    assert alone.exit_code == 0 and wheel.exit_code == 0, wheel.output
    assert "wheel + gyro" in wheel.stdout and "wheel + gyro" not in alone.stdout
    gps = read_gps_csv(run / "gps.csv")
    i = int(np.argmax(np.diff(gps.t_s)))
    t_in, t_out = gps.t_s[i] + 2.0, gps.t_s[i + 1] - 2.0  # inside the tunnel: no fix, no VO frame
    tt, xt, _ = read_tum(run / "truth.tum")
    assert abs(len(tw) - 50.0 * (tt[-1] - tt[0])) <= 2  # the car preset's 50 Hz over the whole drive
    inside = (tt > t_in) & (tt < t_out)
    assert inside.sum() > 100
    for name, want in (("vo.tum", 0.0), ("wheel.tum", 0.95)):
        te, xe, _ = read_tum(tmp_path / name)
        ia, ib = associate(te, tt[inside])
        assert len(ia) >= want * inside.sum() and (want or len(ia) == 0), (name, len(ia))
        if want:
            err = np.hypot(*(xe[ia, :2] - xt[inside][ib, :2]).T)
            assert err.max() < 10.0, err.max()


# ----------------------------------------------------------------------------- run, plot, demo
CONTRACT_FILES = ("scenario.toml", "truth.tum", "truth.csv", "odometry.tum", "gps.csv", "imu.csv",
                  "estimate_odometry.tum", "estimate_mapfusion.tum", "metrics.json", "plot.png")
METRIC_KEYS = ("scenario", "seed", "map", "weather", "odometry", "gps_mode", "route_length_m", "duration_s", "frames",
               "ate_odometry_m", "ate_mapfusion_m", "ate_reduction_m", "delocalized_odometry", "delocalized_mapfusion",
               "online_rmse_odometry_m", "online_rmse_mapfusion_m", "online_max_mapfusion_m",
               "tunnel_rmse_mapfusion_m", "match_rate", "map_priors", "fusion_frames_per_s")


def test_the_results_record_owns_the_contracts_keys():
    from mapfusion.harness.results import REQUIRED_KEYS, summarise

    assert set(REQUIRED_KEYS) == set(METRIC_KEYS)
    rows = [{"ate_odometry_m": 10.0, "ate_mapfusion_m": 2.0, "delocalized_odometry": False, "delocalized_mapfusion": False},
            {"ate_odometry_m": 30.0, "ate_mapfusion_m": 4.0, "delocalized_odometry": True, "delocalized_mapfusion": False},
            {"scenario": "x", "error": "boom"}]
    s = summarise(rows)
    assert (s.runs, s.failed, s.delocalized_odometry, s.delocalized_mapfusion) == (2, 1, 1, 0)
    assert (s.mean_odometry_m, s.mean_mapfusion_m) == (20.0, 3.0)
    # the paper's averages leave the de-localised runs out; the reduction needs both localised
    assert (s.paper_odometry_m, s.paper_mapfusion_m, s.paper_reduction_m) == (10.0, 3.0, 8.0)


@pytest.mark.sumo
def test_run_writes_every_contract_file(tmp_path):
    sc = tmp_path / "s.toml"
    sc.write_text('name = "r1"\nmap = "grid"\nseed = 2\nduration_s = 200.0\nmin_route_m = 1200.0\n'
                  '[weather]\nkind = "rain"\n[[tunnels]]\nstart_m = 400.0\nend_m = 450.0\n')
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "r2"\nmap = "grid"\n[route]\nedges = ["nope"]\n')
    out = tmp_path / "out"
    r = runner.invoke(app, ["run", str(sc), str(bad), "--out", str(out)])
    assert r.exit_code == 0, r.output
    for f in CONTRACT_FILES:
        assert (out / "r1" / f).stat().st_size > 0, f
    metrics = json.loads((out / "r1" / "metrics.json").read_text())
    for k in METRIC_KEYS:
        assert k in metrics, k
    assert metrics["lost_events"] == 0 and metrics["lost_s"] == 0.0  # the single-frame default never says lost
    for v in ("odometry", "mapfusion"):  # where each estimate ends: at most its worst error, at least 0
        assert 0.0 <= metrics[f"online_end_{v}_m"] <= metrics.get(f"online_max_{v}_m", math.inf), v
    counted = json.loads((out / "r1" / "fusion_events.json").read_text())["counters"]
    assert (metrics["road_fixes"], metrics["road_fixes_gated"]) == (counted["road_fixes"], counted["road_fixes_gated"])
    lines = (out / "results.jsonl").read_text().splitlines()
    rows = [json.loads(line) for line in lines]  # whole lines, valid JSON
    by = {row["scenario"]: row for row in rows}  # lines in the order the runs finished
    assert sorted(by) == ["r1", "r2"] and len(rows) == 2
    assert "error" in by["r2"] and "nope" in by["r2"]["error"]  # the failed run is recorded, the other kept
    assert "error" not in by["r1"]
    assert "odometry" in r.stdout and "+ Map-Fusion" in r.stdout and "reduction" in r.stdout
    from PIL import Image

    assert Image.open(out / "r1" / "plot.png").size == (1200, 1000)
    # mapfusion plot redraws it
    r2 = runner.invoke(app, ["plot", str(out / "r1"), "--out", str(tmp_path / "p.png")])
    assert r2.exit_code == 0 and Image.open(tmp_path / "p.png").size == (1200, 1000)


def test_bench_refuses_a_bad_engine_configuration_before_measuring(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[mapfusion]\nheading_prior_sigma_deg = -5.0\n")
    r = runner.invoke(app, ["bench", "--config", str(cfg)])
    assert r.exit_code == 2 and "heading_prior_sigma_deg" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.output


def test_bench_refuses_a_map_that_is_not_one_before_measuring(tmp_path):
    r = runner.invoke(app, ["bench", "--map", str(tmp_path / "nowhere.osm")])
    assert r.exit_code == 2 and "nowhere.osm" in r.stderr and "Traceback" not in r.output
    junk = tmp_path / "junk.osm"
    junk.write_text("not osm at all")
    r = runner.invoke(app, ["bench", "--map", str(junk)])
    assert r.exit_code == 2 and "junk.osm" in r.stderr and "Traceback" not in r.output
    assert len(r.stderr.strip().splitlines()) == 1


def test_plot_bad_input(tmp_path):
    r = runner.invoke(app, ["plot", str(tmp_path), "--out", str(tmp_path / "p.png")])
    assert r.exit_code == 2 and "not a run directory" in r.stderr


@pytest.mark.slow
@pytest.mark.sumo
def test_demo_runs_and_map_fusion_helps(tmp_path):
    r = runner.invoke(app, ["demo", "--out", str(tmp_path / "demo")])
    assert r.exit_code == 0, r.output
    m = json.loads((tmp_path / "demo" / "metrics.json").read_text())
    assert (tmp_path / "demo" / "plot.png").stat().st_size > 10000
    # the demo drive is chosen to show the method at work: the map must help there
    assert m["ate_mapfusion_m"] < m["ate_odometry_m"] and m["online_rmse_mapfusion_m"] < m["online_rmse_odometry_m"]


@pytest.mark.sumo
def test_run_skips_runs_whose_data_is_unavailable(tmp_path, monkeypatch):
    monkeypatch.delenv("NO_SUCH_DATA_VAR", raising=False)
    fam = tmp_path / "f.toml"
    fam.write_text('[family]\nname = "f"\n[family.axes]\nmap = ["grid", "${NO_SUCH_DATA_VAR}/x.osm"]\n'
                   '[base]\nduration_s = 150.0\nmin_route_m = 800.0\n')
    out = tmp_path / "out"
    r = runner.invoke(app, ["run", str(fam), "--out", str(out), "--no-plot"])
    assert r.exit_code == 0, r.output
    assert "skipped f-x-s1" in r.stderr and "NO_SUCH_DATA_VAR" in r.stderr
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert [row["scenario"] for row in rows] == ["f-grid-s1"]
    only = tmp_path / "only.toml"
    only.write_text('map = "${NO_SUCH_DATA_VAR}/x.osm"\n')
    r = runner.invoke(app, ["run", str(only), "--out", str(tmp_path / "o2")])
    assert r.exit_code == 2 and "NO_SUCH_DATA_VAR, which is not set" in r.stderr


def test_table_one_has_sequences_as_columns():
    from io import StringIO

    from rich.console import Console

    from mapfusion.harness.tables import table_one

    def row(seq, weather, seed, o, m, deloc_o=False):
        return {"scenario": f"kitti-{seq}-{weather}-vo-s{seed}", "recorded": f"/d/kitti/{seq}", "odometry": "vo",
                "weather": weather, "ate_odometry_m": o, "ate_mapfusion_m": m, "ate_reduction_m": o - m,
                "delocalized_odometry": deloc_o, "delocalized_mapfusion": False}

    rows = [row("00", "clear", 1, 2.0, 1.0), row("00", "clear", 2, 4.0, 3.0), row("05", "clear", 1, 30.0, 2.0, True),
            {"scenario": "kitti-05-rain-vo-s1", "recorded": "/d/kitti/05", "odometry": "vo", "weather": "rain",
             "error": "boom"}, row("00", "rain", 1, 9.0, 3.0)]
    buf = StringIO()
    Console(file=buf, width=200).print(table_one(rows, "t"))
    lines = {ln.split("│")[1].strip(): [c.strip() for c in ln.split("│")[2:-1]] for ln in buf.getvalue().splitlines()
             if ln.startswith("│")}
    assert lines["VO clear"] == ["3.00", "x", "3.00"]  # the mean over seeds; de-localised cells left out of Avg
    assert lines["VO clear + Map-Fusion"] == ["2.00", "2.00", "2.00"]
    assert lines["VO rain"] == ["9.00", "failed", "9.00"]
    assert "00" in buf.getvalue().splitlines()[2] and "05" in buf.getvalue().splitlines()[2]


@pytest.mark.parametrize("n,width,turned", [(3, 80, False), (40, 80, True), (40, 2000, False)])
def test_paper_table_turns_when_the_runs_do_not_fit(n, width, turned):
    from io import StringIO

    from rich.console import Console

    from mapfusion.harness.tables import paper_table

    rows = [{"scenario": f"fam-helsinki-vo-s{i}", "ate_odometry_m": 4.0 + i, "ate_mapfusion_m": 2.0,
             "ate_reduction_m": 2.0 + i, "delocalized_odometry": False, "delocalized_mapfusion": i == 1}
            for i in range(n)]
    buf = StringIO()
    Console(file=buf, width=width).print(paper_table(rows, "t", strip_prefix="fam-", width=width))
    text = buf.getvalue()
    assert all(len(ln) <= width for ln in text.splitlines())
    cells = {ln.split("│")[1].strip(): [c.strip() for c in ln.split("│")[2:-1]] for ln in text.splitlines()
             if ln.startswith("│")}
    kept_m = [2.0 for i in range(n) if i != 1]
    avg_o = sum(4.0 + i for i in range(n)) / n
    if turned:  # a row per run, every name whole, then the averages (de-localised runs left out)
        assert cells["helsinki-vo-s1"] == ["5.00", "x", "NA"]
        assert cells["helsinki-vo-s39"] == ["43.00", "2.00", "41.00"]
        assert cells["Avg"][:2] == [f"{avg_o:.2f}", f"{sum(kept_m) / len(kept_m):.2f}"]
    else:
        assert cells["odometry"][-1] == f"{avg_o:.2f}"
        assert cells["+ Map-Fusion"][1] == "x"


@pytest.mark.parametrize("name", ["../../escaped", "/abs/escaped", "a/b", ".hidden", "a b"])
@pytest.mark.parametrize("kind", ["scenario", "family"])
def test_a_name_never_escapes_out(tmp_path, name, kind):
    """Issue 19: a run's name names its directory under --out; a name that is not one safe path
    component is refused (exit 2, one line naming it) before anything is written."""
    if kind == "scenario":
        text = f'name = "{name}"\nmap = "grid"\nduration_s = 60.0\n'
    else:
        text = f'[family]\nname = "{name}"\nseeds = [1]\n[family.axes]\nmap = ["grid"]\n[base]\nduration_s = 60.0\n'
    (tmp_path / "work").mkdir()
    p = tmp_path / "work" / "s.toml"
    p.write_text(text)
    out = tmp_path / "work" / "out"
    before = sorted(tmp_path.rglob("*"))
    r = runner.invoke(app, ["run", str(p), "--out", str(out), "--no-plot"])
    assert r.exit_code == 2, r.output
    assert "name" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert sorted(tmp_path.rglob("*")) == before  # nothing written, inside --out or outside it


def test_json_output_is_strict(capsys):
    import math

    from mapfusion.harness.cli import _print_json

    _print_json({"a": math.inf, "b": [math.nan, 1.5], "c": {"d": -math.inf}, "e": np.float64(2.0)})
    out = json.loads(capsys.readouterr().out, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    assert out == {"a": None, "b": [None, 1.5], "c": {"d": None}, "e": 2.0}


@pytest.mark.sumo
@pytest.mark.parametrize("case,needle", [("odometry", "is also --odometry"), ("gps", "is also --gps"),
                                         ("dir", "is a directory"), ("missing", "no such directory"),
                                         ("same", "is also --out")])
def test_fuse_refuses_a_bad_output_before_the_work(sim_run, tmp_path, case, needle):
    """Issue 19: --out (or --smoothed) naming an input, a directory or a missing folder is refused with
    exit 2 and one line before the fusion runs, and no input is touched."""
    work = tmp_path / "w"
    work.mkdir()
    odo, gps = work / "odometry.tum", work / "gps.csv"
    odo.write_bytes((sim_run / "odometry.tum").read_bytes())
    gps.write_bytes((sim_run / "gps.csv").read_bytes())
    before = {p: p.read_bytes() for p in (odo, gps)}
    out, smoothed = {"odometry": (odo, None), "gps": (work / "e.tum", gps), "dir": (work, None),
                     "missing": (work / "no" / "e.tum", None), "same": (work / "e.tum", work / "e.tum")}[case]
    args = ["fuse", "--map", "grid", "--odometry", str(odo), "--gps", str(gps), "--out", str(out)]
    if smoothed is not None:
        args += ["--smoothed", str(smoothed)]
    r = runner.invoke(app, args)
    assert r.exit_code == 2, r.output
    assert needle in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert {p: p.read_bytes() for p in (odo, gps)} == before
    assert not (work / "e.tum").exists()


def test_evaluate_reports_kittis_metric_with_and_without_a_fitted_scale(tmp_path, capsys):
    from mapfusion.formats import write_tum, yaw_to_quaternion
    from mapfusion.harness.cli import main

    n = 1200  # 1,199 m straight, one frame a metre
    t = np.arange(n) * 0.1
    xyz = np.column_stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)])
    q = yaw_to_quaternion(np.zeros(n))
    write_tum(tmp_path / "truth.tum", t, xyz, q)
    write_tum(tmp_path / "est.tum", t, xyz * 1.02, q)
    out = []
    for extra in ([], ["--scale"]):
        assert main(["evaluate", "--truth", str(tmp_path / "truth.tum"), "--estimate", str(tmp_path / "est.tum"),
                     "--json", *extra]) == 0
        out.append(json.loads(capsys.readouterr().out))
    assert 2.0 <= out[0]["kitti_t_err_percent"] <= 2.0 * 1.01 and out[0]["kitti_scale"] == 1.0
    assert out[1]["kitti_t_err_percent"] < 1e-6 and abs(out[1]["kitti_scale"] - 1 / 1.02) < 1e-9
    assert out[0]["kitti_segments"] > 0 and out[0]["kitti_r_err_deg_per_100m"] < 1e-6
